"""Simulation state: frozen dataclasses of tensors, every one with a leading ensemble axis B.

Contract:
- :class:`Bodies` is the dynamic state of the rigid bodies (a pellet is a one-sphere body, a
  sinter particle a three-sphere clump). Shapes use B (ensemble members) and Nb (bodies per
  member; members are padded to the same Nb with ``active = False``).
- :class:`PairContacts` and :class:`WallContacts` are the Verlet (skin) neighbour lists with
  their contact history (tangential and rolling springs) and the per-contact constants that
  do not change between rebuilds. Contacts are indexed by *flat* indices: sphere ``s`` of
  member ``b`` is ``b * Ns + s``; body ``k`` of member ``b`` is ``b * Nb + k``. A contact always
  joins two spheres of the same member, so members never interact.
- :class:`State` bundles them with the step counter. A step returns a new State; nothing
  is mutated in place that a caller may still hold.

Units are SI throughout: metres, seconds, kilograms, newtons, radians.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import torch

Tensor = torch.Tensor


class _Replaceable:
    def set(self, **changes):
        """Return a copy with the given fields replaced (what ``dataclasses.replace`` returns for
        these plain frozen dataclasses: no ``__post_init__``, no cached properties), without
        re-running ``__init__``: a step replaces fields ~8 times, and ``dataclasses.replace``
        cost 3 % of a slice run."""
        names = _field_names(type(self))
        unknown = set(changes) - names
        if unknown:
            raise TypeError(f"{type(self).__name__}.set: unknown field(s) {sorted(unknown)}")
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new


@functools.lru_cache(maxsize=None)
def _field_names(cls: type) -> frozenset[str]:
    return frozenset(f.name for f in dataclasses.fields(cls))


@dataclass(frozen=True)
class Bodies(_Replaceable):
    """Rigid-body state.

    Attributes:
        position: ``[B, Nb, 3]`` centre of mass, m.
        velocity: ``[B, Nb, 3]`` m/s (at the half step between the two kicks of a step it is
            the half-step velocity; between steps it is the full-step velocity).
        orientation: ``[B, Nb, 4]`` unit quaternion (w, x, y, z) rotating the body frame into
            the world frame.
        angular_momentum: ``[B, Nb, 3]`` world frame, kg m^2/s.
        force: ``[B, Nb, 3]`` total force of the last evaluation, N.
        torque: ``[B, Nb, 3]`` total torque about the centre of mass, world frame, N m.
        active: ``[B, Nb]`` bool; inactive bodies (padding, removed, lost) do not move or touch.
    """

    position: Tensor
    velocity: Tensor
    orientation: Tensor
    angular_momentum: Tensor
    force: Tensor
    torque: Tensor
    active: Tensor


@dataclass(frozen=True)
class PairContacts(_Replaceable):
    """Sphere-sphere neighbour list (pairs closer than the sum of radii plus the skin).

    Attributes (P pairs):
        i, j: ``[P]`` flat sphere indices, i < j, same member.
        body_i, body_j: ``[P]`` flat body indices of the two spheres.
        key: ``[P]`` int64 ``i * S + j`` (S = B * Ns), sorted ascending; used to carry history.
        tangential: ``[P, 3]`` Mindlin tangential spring displacement, m (history).
        rolling: ``[P, 3]`` EPSD rolling spring torque, N m (history).
        radius_i, radius_j: ``[P]`` sphere radii, m.
        radius_eff: ``[P]`` R* = Ri Rj / (Ri + Rj), m. mass_eff: ``[P]`` m* of the two bodies, kg.
        young_eff, shear_eff: ``[P]`` E*, G*, Pa. beta: ``[P]`` damping factor from e.
        mu_s, mu_r, rolling_damping: ``[P]`` interaction coefficients.
        rolling_inertia: ``[P]`` I_r of the EPSD damping, kg m^2.
        cohesion: ``[P]`` SJKR cohesion energy density, J/m^3.

    The per-pair constants (radius_i ... cohesion) are None in a list built for the C++ kernels,
    which look them up per sphere (``System.pair_lookup``); ``integrate.with_pair_values`` fills them.
    """

    i: Tensor
    j: Tensor
    body_i: Tensor
    body_j: Tensor
    key: Tensor
    tangential: Tensor
    rolling: Tensor
    radius_i: Tensor | None
    radius_j: Tensor | None
    radius_eff: Tensor | None
    mass_eff: Tensor | None
    young_eff: Tensor | None
    shear_eff: Tensor | None
    beta: Tensor | None
    mu_s: Tensor | None
    mu_r: Tensor | None
    rolling_damping: Tensor | None
    rolling_inertia: Tensor | None
    cohesion: Tensor | None

    @property
    def n(self) -> int:
        return self.i.shape[0]


@dataclass(frozen=True)
class WallContacts(_Replaceable):
    """Sphere-wall neighbour list, same conventions as :class:`PairContacts`.

    Attributes (Q pairs):
        sphere: ``[Q]`` flat sphere index. body: ``[Q]`` flat body index. wall: ``[Q]`` wall index.
        key: ``[Q]`` int64 ``sphere * W + wall``, sorted ascending.
        tangential: ``[Q, 3]`` m. rolling: ``[Q, 3]`` N m.
        radius: ``[Q]`` sphere radius = R*, m. mass_eff: ``[Q]`` body mass, kg.
        young_eff, shear_eff, beta, mu_s, mu_r, rolling_damping, rolling_inertia, cohesion: ``[Q]``.
    """

    sphere: Tensor
    body: Tensor
    wall: Tensor
    key: Tensor
    tangential: Tensor
    rolling: Tensor
    radius: Tensor
    mass_eff: Tensor
    young_eff: Tensor
    shear_eff: Tensor
    beta: Tensor
    mu_s: Tensor
    mu_r: Tensor
    rolling_damping: Tensor
    rolling_inertia: Tensor
    cohesion: Tensor

    @property
    def n(self) -> int:
        return self.sphere.shape[0]


@dataclass(frozen=True)
class State(_Replaceable):
    """Everything that changes during a run.

    Attributes:
        bodies: rigid-body state.
        pairs, walls: neighbour lists with contact history.
        reference: ``[B * Ns, 3]`` sphere positions at which the lists were last searched for each
            sphere (a partial rebuild searches only the spheres that moved), m.
        wall_shift: ``[W, 3]`` wall displacement when the lists were last built, m.
        wall_active: ``[W]`` bool, which walls were present when the lists were last built.
        step: number of steps taken since t = 0 (time: ``System.time_of(step)``).
        rebuilds: number of neighbour-list rebuilds so far.
        lost: ``[B]`` int64, bodies deactivated because they left the domain, per member.
        body_id: ``[B, Nb]`` int64, the body's index when the system was built: slot k of
            member m holds body ``body_id[m, k]``. The identity until the bodies are reordered
            in space (:mod:`torchdem.reorder`); outputs name bodies by it.
        sphere_id: ``[B, Ns]`` int64, the same for spheres.
    """

    bodies: Bodies
    pairs: PairContacts
    walls: WallContacts
    reference: Tensor
    wall_shift: Tensor
    wall_active: Tensor
    step: int
    rebuilds: int
    lost: Tensor
    body_id: Tensor
    sphere_id: Tensor


def to_dict(obj) -> dict:
    """Nested plain dict of a state dataclass (for torch.save with weights_only loading)."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        out[f.name] = to_dict(v) if dataclasses.is_dataclass(v) else v
    return out


def state_from_dict(d: dict) -> State:
    """Inverse of :func:`to_dict` for :class:`State` (a state saved before ``body_id`` and
    ``sphere_id`` existed gets the identity order)."""
    bodies = Bodies(**d["bodies"])
    rest = {k: v for k, v in d.items() if k not in ("bodies", "pairs", "walls")}
    B, Nb = bodies.active.shape
    if "body_id" not in rest:
        rest["body_id"] = torch.arange(Nb, device=bodies.active.device).expand(B, Nb).clone()
    if "sphere_id" not in rest:
        Ns = rest["reference"].shape[0] // B
        rest["sphere_id"] = torch.arange(Ns, device=bodies.active.device).expand(B, Ns).clone()
    return State(bodies=bodies, pairs=PairContacts(**d["pairs"]), walls=WallContacts(**d["walls"]), **rest)
