"""Sinter clump shape: the lobe spacing of the three-sphere clump free (0 a sphere, 0.15 the
default sinter, 0.3 flat and angular; torchdem.mixture.trilobe_template), for every material
modelled as a trilobe. Prior: 0.05-0.3 of the sieve size.

On a periodic slice the prior starts higher: the minimum image needs the period above twice the
largest contact distance, 4 lobe radii of the largest particle, (0.5 - s) d_max each, so
s > 0.5 - period / (4 d_max); the prior keeps 5 % clear of that (0.12 on the paper's 4 cm slice
with 25 mm sinter). A slice too thin for any spacing up to 0.3 makes the mechanism unavailable.

The extended model rains its fill by the clumps' lobes (``RunSettings.fill_packing = "lobes"``):
packed by bounding spheres, a flat trilobe (0.3) takes five times its volume and the 40 kg fill
overflowed the fill column (2.3 m against 1.85 m on the slice)."""
import dataclasses

from torchdem.mechanisms import Mechanism
from torchdem.mixture import trilobe_parameters

LOW, HIGH = 0.05, 0.3
MARGIN = 0.95  # fraction of the period the largest contact distance may use, twice


def trilobe_materials(c) -> list[str]:
    """The context's materials whose shape is a trilobe clump (any lobe spacing and scale)."""
    return [m for m in c.materials if trilobe_parameters(c.shapes[m]) is not None]


def _spacing(shape: str) -> float:
    """Lobe spacing of a trilobe shape key (the default sinter trilobe: 0.15)."""
    return trilobe_parameters(shape)[0]


def _low(c, m) -> float:
    if c.period is None or m not in c.largest_size:
        return LOW
    return max(LOW, 0.5 - MARGIN * c.period / (4 * c.largest_size[m]))


def _unavailable(c):
    if not trilobe_materials(c):
        return "no material is a trilobe clump"
    tight = [m for m in trilobe_materials(c) if _low(c, m) >= HIGH]
    if tight:
        return (f"the periodic slice ({c.period:g} m) is too thin for trilobes of {tight} up to lobe spacing {HIGH} "
                "(widen geometry.slice_depth or use geometry=drawdown_full)")
    return None


MECHANISM = Mechanism(
    name="clump_shape",
    description="shape of the three-sphere clumps (lobe spacing) free",
    parameters=lambda c: {f"lobe_spacing_{m}": (round(_low(c, m), 4), HIGH) for m in trilobe_materials(c)},
    available=_unavailable,
    null=lambda c: {f"lobe_spacing_{m}": _spacing(c.shapes[m]) for m in trilobe_materials(c)},
    apply=lambda model: dataclasses.replace(
        model, settings=dataclasses.replace(model.settings, fill_packing="lobes")),
)
