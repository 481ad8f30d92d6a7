"""Particle density calibrated per material instead of taken from the measured solid density.

The paper (section 3.6) rescales both densities by one heap-height ratio and then loses the
flow rate; a separate density per material lets mass-like KPIs move differently per mixture.
Prior: 70-130 % of the nominal density of each material."""
from torchdem.mechanisms import Mechanism

MECHANISM = Mechanism(
    name="density_per_material",
    description="particle density of each material free (not the measured solid density)",
    parameters=lambda c: {f"density_{m}": (0.7 * c.densities[m], 1.3 * c.densities[m]) for m in c.materials},
    null=lambda c: {f"density_{m}": float(c.densities[m]) for m in c.materials},
)
