"""Front and back walls with their own friction (a glass front for the photos, a steel back), and,
for a periodic slice, the walls themselves: the slice becomes bounded by them. Prior: sliding
friction of each material on these walls 0.1-1.0; rolling friction and restitution as on the
rest of the geometry."""
import dataclasses

from bo.mechanisms import Mechanism
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
)
