"""Sinter clump shape: the lobe spacing of the three-sphere clump free (0 a sphere, 0.15 the
default sinter, 0.3 flat and angular; torchdem.mixture.trilobe_template), for every material
modelled as a trilobe. Prior: 0.05-0.3 of the sieve size."""
from bo.mechanisms import Mechanism


def _trilobes(c):
    return [m for m in c.materials if c.shapes[m] == "sinter_trilobe" or c.shapes[m].startswith("trilobe_s")]


MECHANISM = Mechanism(
    name="clump_shape",
    description="shape of the three-sphere clumps (lobe spacing) free",
    parameters=lambda c: {f"lobe_spacing_{m}": (0.05, 0.3) for m in _trilobes(c)},
    available=lambda c: None if _trilobes(c) else "no material is a trilobe clump",
)
