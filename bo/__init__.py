"""Calibration and discovery on top of torchdem: designs, screening, surrogates, campaigns, reports."""
