"""Numerical studies before calibration: time step and reduced shear modulus (paper section 3.2.4)."""
