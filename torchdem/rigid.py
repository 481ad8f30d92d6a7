"""Rigid-body kinematics with unit quaternions (w, x, y, z), batched over any leading axes.

Contract: pure functions; quaternions rotate body-frame vectors into the world frame;
angular momentum is kept in the world frame (constant for a free body, so a free clump
conserves it exactly), angular velocity is derived from it through the body-frame principal
inertia. Orientation advances by the exact rotation of the midpoint angular velocity
(second order; Omelyan-style midpoint, see Rozmanov & Kusalik 2010 for the family).
"""
from __future__ import annotations

import torch

Tensor = torch.Tensor


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b, ``[..., 4]``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack((
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ), -1)


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate ``v`` ``[..., 3]`` by unit quaternion ``q`` ``[..., 4]``: v + 2w(u x v) + 2u x (u x v)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def quat_rotate_inverse(q: Tensor, v: Tensor) -> Tensor:
    """Rotate ``v`` by the conjugate of ``q`` (world -> body)."""
    conj = torch.cat((q[..., :1], -q[..., 1:]), -1)
    return quat_rotate(conj, v)


def quat_from_rotation_vector(rv: Tensor) -> Tensor:
    """Unit quaternion of the rotation by angle |rv| about rv / |rv|, ``[..., 3] -> [..., 4]``."""
    angle = rv.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(half)/angle, with its series near zero.
    small = angle < 1e-8
    safe = torch.where(small, torch.ones_like(angle), angle)
    s = torch.where(small, 0.5 - angle * angle / 48.0, torch.sin(half) / safe)
    return torch.cat((torch.cos(half), rv * s), -1)


def angular_velocity(q: Tensor, angular_momentum: Tensor, inertia: Tensor) -> Tensor:
    """World angular velocity omega = R diag(1/I) R^T L. inertia: ``[..., 3]`` principal moments."""
    return quat_rotate(q, quat_rotate_inverse(q, angular_momentum) / inertia)


def advance_orientation(q: Tensor, angular_momentum: Tensor, inertia: Tensor, dt: float) -> Tensor:
    """Orientation after dt at fixed world angular momentum (midpoint rule), renormalised."""
    w0 = angular_velocity(q, angular_momentum, inertia)
    q_half = quat_mul(quat_from_rotation_vector(0.5 * dt * w0), q)
    w_half = angular_velocity(q_half, angular_momentum, inertia)
    q_new = quat_mul(quat_from_rotation_vector(dt * w_half), q)
    return q_new / q_new.norm(dim=-1, keepdim=True)
