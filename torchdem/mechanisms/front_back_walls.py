"""Front and back walls with their own friction (a glass front for the photos, a steel back), and,
for a periodic slice, the walls themselves: the slice becomes bounded by them. Prior: sliding
friction of each material on these walls 0.1-1.0; rolling friction and restitution as on the
rest of the geometry.

On a slice the walls stand depth / slice_depth times closer together than in the lab's box (5x
for the default 0.04 m slice of the 0.20 m box), so they hold back that much more material per
unit of wall friction: the fitted friction is then an effective value of the slice, not the
walls' own. Score this candidate on the whole box (geometry=drawdown_full) or on the lab geometry
(drawdown_lab: the real front wall, and a mirror plane at mid-depth that stands for the back wall)
to read it as the walls' friction: the side walls, the floors and the slot's edges keep the
calibrated geometry friction (mu_s_pg, mu_s_sg), and the front and back take their own."""
import dataclasses

from torchdem.mechanisms import Mechanism
from torchdem.materials import Material


def _apply(model):
    settings = dataclasses.replace(model.settings, front_back_material=Material("front_back", 2e11, 0.3, 7800.0))
    geometry = dataclasses.replace(model.geometry, slice_walls=True) if model.geometry.is_slice else model.geometry
    return dataclasses.replace(model, settings=settings, geometry=geometry)


MECHANISM = Mechanism(
    name="front_back_walls",
    description="front and back walls present, with a sliding friction of their own",
    parameters=lambda c: {f"mu_s_{c.letters[m]}w": (0.1, 1.0) for m in c.materials},
    apply=_apply,
    null=lambda c: {f"mu_s_{c.letters[m]}w": float(c.calibrated[f"mu_s_{c.letters[m]}g"]) for m in c.materials
                    if f"mu_s_{c.letters[m]}g" in c.calibrated} or None,
)
