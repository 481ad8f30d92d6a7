"""Cohesion between particles (moisture, fines): SJKR, an attractive normal force k_c A at every
particle-particle contact (torchdem.contact.sjkr_cohesion), k_c per pure material pair, the unlike
pair the average. Prior: 0 to 1 % of the particle-particle E*, which at the overlaps of a gravity
flow (delta/R ~ 1e-3) makes cohesion up to ~1.5 times the Hertz force of a contact."""
from torchdem.mechanisms import Mechanism

MECHANISM = Mechanism(
    name="cohesion",
    description="cohesion between particles (SJKR cohesion energy density per material pair)",
    parameters=lambda c: {f"coh_{c.letters[m]}{c.letters[m]}": (0.0, 0.01 * c.young_eff) for m in c.materials},
    null=lambda c: {f"coh_{c.letters[m]}{c.letters[m]}": 0.0 for m in c.materials},
)
