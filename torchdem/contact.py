"""Contact laws: pure functions of per-contact tensors.

Contract: every function takes ``[P]`` / ``[P, 3]`` tensors for P contacts and returns new
tensors; none reads global state or allocates per-contact Python objects, so the whole
force evaluation can be compiled or graph-captured. Forces are those acting on the *first*
body of the contact (sphere i, or the sphere of a sphere-wall contact); the unit normal ``n``
points from the first body towards the second, and ``v_rel`` is the velocity of the first
body's contact point relative to the second's. Overlap ``delta > 0`` means touching.

Hertz-Mindlin (no-slip), as in EDEM and LIGGGHTS ``model hertz tangential history``
(Tsuji et al. 1992; Di Renzo & Di Maio 2004):

    S_n = 2 E* sqrt(R* delta)         S_t = 8 G* sqrt(R* delta)
    F_n = 4/3 E* sqrt(R*) delta^(3/2) - 2 sqrt(5/6) beta sqrt(S_n m*) v_n
    F_t = -S_t xi - 2 sqrt(5/6) beta sqrt(S_t m*) v_t,   |S_t xi| <= mu_s |F_n|
    beta = ln(e) / sqrt(ln(e)^2 + pi^2)

The damped normal force may become slightly attractive at the end of a collision; this is
what makes the rebound restitution equal the input e exactly (LIGGGHTS ``limitForce off``).
When the tangential spring exceeds the Coulomb limit, the spring is rescaled to the limit
and the dashpot is dropped (sliding).

Rolling resistance, elastic-plastic spring-dashpot (EPSD, type C of Ai et al., Powder
Technol. 206 (2011) 269-282):

    M_r^k <- M_r^k - k_r omega_rt dt,    |M_r^k| <= mu_r R* |F_n|
    M_r^d = -eta_r 2 sqrt(I_r k_r) omega_rt   (only while the spring is below its limit)
    k_r = S_t R*^2      ("tangential", LIGGGHTS epsd2, Iwashita & Oda 1998)
        | 2.25 mu_r^2 R*^2 k_n with k_n = 4/3 E* sqrt(R* delta)  ("ai2011", LIGGGHTS epsd)

with omega_rt the relative angular velocity (first minus second body) projected onto the
tangent plane, so that torsion does not feed the rolling spring.
"""
from __future__ import annotations

import math

import torch

Tensor = torch.Tensor

SQRT_5_6 = math.sqrt(5.0 / 6.0)


def rotate_history(spring: Tensor, normal: Tensor) -> Tensor:
    """Project a history vector onto the current tangent plane, keeping its length.

    Contacts roll and the contact frame turns; the stored spring must stay tangential.
    """
    proj = spring - (spring * normal).sum(-1, keepdim=True) * normal
    old = spring.norm(dim=-1, keepdim=True)
    new = proj.norm(dim=-1, keepdim=True)
    scale = torch.where(new > 0, old / new.clamp_min(torch.finfo(spring.dtype).tiny), torch.zeros_like(new))
    return proj * scale


def hertz_mindlin(
    overlap: Tensor,
    normal: Tensor,
    v_rel: Tensor,
    tangential: Tensor,
    radius_eff: Tensor,
    mass_eff: Tensor,
    young_eff: Tensor,
    shear_eff: Tensor,
    beta: Tensor,
    mu_s: Tensor,
    dt: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Hertz-Mindlin normal and tangential force on the first body.

    Args:
        overlap: ``[P]`` delta, m (contacts with delta <= 0 produce zero force and history).
        normal: ``[P, 3]`` unit normal from first to second body.
        v_rel: ``[P, 3]`` relative contact-point velocity (first minus second), m/s.
        tangential: ``[P, 3]`` tangential spring displacement from the last step, m.
        radius_eff, mass_eff, young_eff, shear_eff, beta, mu_s: ``[P]`` per-contact constants.
        dt: time step, s.
    Returns:
        f_n: ``[P]`` normal force magnitude, N (> 0 repulsive; acts as ``-f_n * normal`` on
            the first body).
        force: ``[P, 3]`` total contact force on the first body, N.
        tangential: ``[P, 3]`` updated spring displacement, m.
        k_t: ``[P]`` tangential stiffness S_t, N/m (used by the rolling law).
    """
    touching = overlap > 0
    delta = overlap.clamp_min(0.0)
    v_n = (v_rel * normal).sum(-1)
    v_t = v_rel - v_n[:, None] * normal
    sqrt_rd = torch.sqrt(radius_eff * delta)
    k_n = 2.0 * young_eff * sqrt_rd
    k_t = 8.0 * shear_eff * sqrt_rd
    damp = -2.0 * SQRT_5_6 * beta
    f_n = (2.0 / 3.0) * k_n * delta + damp * torch.sqrt(k_n * mass_eff) * v_n
    f_n = torch.where(touching, f_n, torch.zeros_like(f_n))

    xi = rotate_history(tangential, normal) + v_t * dt
    xi = torch.where(touching[:, None], xi, torch.zeros_like(xi))
    f_spring = -k_t[:, None] * xi
    f_spring_mag = f_spring.norm(dim=-1)
    f_limit = mu_s * f_n.abs()
    sliding = f_spring_mag > f_limit
    ratio = torch.where(sliding, f_limit / f_spring_mag.clamp_min(torch.finfo(xi.dtype).tiny),
                        torch.ones_like(f_limit))
    xi = xi * ratio[:, None]
    f_damp = (damp * torch.sqrt(k_t * mass_eff))[:, None] * v_t
    f_t = torch.where(sliding[:, None], f_spring * ratio[:, None], f_spring - f_damp)
    force = -f_n[:, None] * normal + f_t
    return f_n, force, xi, k_t


def rolling_epsd(
    omega_rel: Tensor,
    normal: Tensor,
    rolling: Tensor,
    f_n: Tensor,
    k_t: Tensor,
    overlap: Tensor,
    radius_eff: Tensor,
    young_eff: Tensor,
    mu_r: Tensor,
    rolling_damping: Tensor,
    rolling_inertia: Tensor,
    dt: float,
    stiffness_model: str = "tangential",
) -> tuple[Tensor, Tensor]:
    """EPSD (type C) rolling-resistance torque on the first body.

    Args:
        omega_rel: ``[P, 3]`` angular velocity of the first body minus the second's, rad/s.
        normal: ``[P, 3]`` unit contact normal.
        rolling: ``[P, 3]`` spring torque from the last step, N m.
        f_n: ``[P]`` normal force from :func:`hertz_mindlin`, N. k_t: ``[P]`` S_t, N/m.
        overlap: ``[P]`` m. radius_eff: ``[P]`` R*, m. young_eff: ``[P]`` E*, Pa.
        mu_r, rolling_damping: ``[P]`` coefficient of rolling friction and damping ratio eta_r.
        rolling_inertia: ``[P]`` I_r, kg m^2. dt: s.
        stiffness_model: ``"tangential"`` (k_r = S_t R*^2) or ``"ai2011"`` (2.25 mu_r^2 R*^2 k_n).
    Returns:
        torque: ``[P, 3]`` rolling torque on the first body (the second gets the opposite), N m.
        rolling: ``[P, 3]`` updated spring torque, N m.
    """
    touching = overlap > 0
    w_t = omega_rel - (omega_rel * normal).sum(-1, keepdim=True) * normal
    r2 = radius_eff * radius_eff
    if stiffness_model == "tangential":
        k_r = k_t * r2
    elif stiffness_model == "ai2011":
        k_n = (4.0 / 3.0) * young_eff * torch.sqrt(radius_eff * overlap.clamp_min(0.0))
        k_r = 2.25 * mu_r * mu_r * r2 * k_n
    else:
        raise ValueError(f"stiffness_model = {stiffness_model!r}; expected 'tangential' or 'ai2011'")
    m_spring = rotate_history(rolling, normal) - (k_r * dt)[:, None] * w_t
    m_spring = torch.where(touching[:, None], m_spring, torch.zeros_like(m_spring))
    mag = m_spring.norm(dim=-1)
    limit = mu_r * radius_eff * f_n.abs()
    full = mag > limit
    ratio = torch.where(full, limit / mag.clamp_min(torch.finfo(mag.dtype).tiny), torch.ones_like(mag))
    m_spring = m_spring * ratio[:, None]
    c_r = rolling_damping * 2.0 * torch.sqrt(rolling_inertia * k_r)
    m_damp = torch.where(full[:, None], torch.zeros_like(w_t), -c_r[:, None] * w_t)
    return m_spring + m_damp, m_spring


def sjkr_contact_area(overlap: Tensor, distance: Tensor, radius_i: Tensor, radius_j: Tensor | None = None) -> Tensor:
    """Area of the contact circle of two overlapping spheres (or a sphere and a wall), m^2.

    Two spheres at centre distance d: the intersection circle of their surfaces has area
    ``pi / 4 (d - ri - rj)(d + ri - rj)(d - ri + rj)(d + ri + rj) / d^2`` (the LIGGGHTS ``sjkr``
    formula), about ``2 pi R* delta`` for small overlaps; a sphere at distance d from a wall:
    ``pi (r^2 - d^2)``. Zero where the bodies do not touch.
    """
    touching = overlap > 0
    if radius_j is None:
        area = math.pi * (radius_i * radius_i - distance * distance)
    else:
        d = distance.clamp_min(torch.finfo(distance.dtype).tiny)
        area = (-0.25 * math.pi * (d - radius_i - radius_j) * (d + radius_i - radius_j)
                * (d - radius_i + radius_j) * (d + radius_i + radius_j) / (d * d))
    return torch.where(touching, area.clamp_min(0.0), torch.zeros_like(area))


def sjkr_cohesion(area: Tensor, cohesion: Tensor) -> Tensor:
    """Simplified JKR cohesion (LIGGGHTS ``cohesion sjkr``; Johnson, Kendall, Roberts 1971): an
    attractive normal force ``k_c A`` with ``k_c`` the cohesion energy density (J/m^3 = N/m^2) and
    ``A`` the contact area (:func:`sjkr_contact_area`). Returns the force magnitude, N (>= 0),
    pulling the first body towards the second (``+f * normal`` on the first body). The Coulomb
    and rolling limits of :func:`hertz_mindlin` and :func:`rolling_epsd` use the repulsive Hertz
    force only."""
    return cohesion * area
