"""Sinter clump size: every trilobe clump scaled by ``clump_scale_<material>`` (1: the clump just fits
the sphere of its sieve size, as built; torchdem.mixture.trilobe_template), at the same mass per sieve
class, so a larger scale means fewer, larger grains. Prior: 1.0-1.4.

Why it is a candidate: a sieve sorts a grain by the smallest square aperture it passes, and the trilobe
that fits the sphere of diameter d passes, standing along the aperture's diagonal, an aperture of only
(1 - 0.939 s) d (torchdem.mixture.trilobe_aperture): 0.76 d at the lab calibration's lobe spacing
0.257. So the model's sinter of the class d would be sieved into a class about a quarter finer, and
the clump that passes the aperture d itself is 1 / (1 - 0.939 s) larger: 1.16 at s = 0.15, 1.32 at
0.257, 1.39 at 0.3; the prior reaches 1.4. The size convention is not in the paper's text, and a
grain's size acts where the grains are few across: the slot (Beverloo's empty annulus, k d) and the
residue beside it.

The scale sets the lobes' radius and so the Rayleigh time step at ``time_step_fraction``, as the lobe
spacing does: the step grows with the scale where the sinter's lobes are the smallest spheres. On a
periodic slice the period must exceed twice the largest contact distance, 4 lobe radii of the largest
grain at the prior's top; a slice too thin for it makes the mechanism unavailable. The extended model
rains its fill by the clumps' lobes (``RunSettings.fill_packing = "lobes"``), as ``clump_shape`` does."""
import dataclasses

from torchdem.mechanisms import Mechanism
from torchdem.mechanisms.clump_shape import MARGIN, trilobe_materials
from torchdem.mixture import trilobe_parameters

LOW, HIGH = 1.0, 1.4


def _spacing(c, m) -> float:
    """The material's lobe spacing: the calibrated set's ``lobe_spacing_<m>`` where it has one, else its shape's."""
    return float(c.calibrated.get(f"lobe_spacing_{m}", trilobe_parameters(c.shapes[m])[0]))


def _unavailable(c):
    if not trilobe_materials(c):
        return "no material is a trilobe clump"
    if c.period is not None:
        tight = [m for m in trilobe_materials(c) if m in c.largest_size
                 and 4 * HIGH * (0.5 - _spacing(c, m)) * c.largest_size[m] > MARGIN * c.period]
        if tight:
            return (f"the periodic slice ({c.period:g} m) is too thin for trilobes of {tight} scaled by {HIGH} "
                    "(widen geometry.slice_depth or use geometry=drawdown_full)")
    return None


MECHANISM = Mechanism(
    name="clump_size",
    description="size of the three-sphere clumps against their sieve size free (sieve convention)",
    parameters=lambda c: {f"clump_scale_{m}": (LOW, HIGH) for m in trilobe_materials(c)},
    available=_unavailable,
    null=lambda c: {f"clump_scale_{m}": 1.0 for m in trilobe_materials(c)},
    apply=lambda model: dataclasses.replace(
        model, settings=dataclasses.replace(model.settings, fill_packing="lobes")),
)
