"""Mass properties of clumps of overlapping spheres against closed forms.

Two equal spheres of radius r at distance d overlap in a lens of volume
pi (4r + d)(2r - d)^2 / 12; the union's volume is 2 (4/3 pi r^3) minus that (tolerance 1e-5
relative). Its inertia about the axis through both centres is checked against an
independent Monte Carlo estimate (2e6 points, tolerance 1%), and a single sphere gives
2/5 m r^2 exactly.
"""
import math

import numpy as np

from torchdem.clumps import ClumpTemplate, mass_properties, principal_template


def test_two_overlapping_spheres_volume_matches_lens_formula():
    r, d = 1.0, 1.2
    t = ClumpTemplate("pair", np.array([[0, 0, 0], [d, 0, 0]]), np.array([r, r]))
    props = mass_properties(t)
    lens = math.pi * (4 * r + d) * (2 * r - d) ** 2 / 12
    expected = 2 * 4 / 3 * math.pi * r ** 3 - lens
    assert abs(props.volume - expected) / expected < 1e-5
    assert np.allclose(props.centre, [d / 2, 0, 0], atol=1e-6)


def test_unequal_three_sphere_clump_inertia_matches_monte_carlo():
    t = ClumpTemplate("tri", np.array([[0, 0, 0], [1.1, 0.2, 0], [0.3, 0.9, 0.4]]), np.array([1.0, 0.8, 0.7]))
    props = mass_properties(t)
    rng = np.random.default_rng(0)
    lo = (t.offsets - t.radii[:, None]).min(0)
    hi = (t.offsets + t.radii[:, None]).max(0)
    pts = lo + (hi - lo) * rng.random((2_000_000, 3))
    inside = ((pts[:, None, :] - t.offsets[None]) ** 2).sum(-1) < t.radii ** 2
    p = pts[inside.any(1)]
    box = np.prod(hi - lo)
    vol = box * p.shape[0] / pts.shape[0]
    com = p.mean(0)
    q = p - com
    second = q.T @ q / p.shape[0] * vol
    inertia = np.trace(second) * np.eye(3) - second
    assert abs(props.volume - vol) / vol < 0.01
    assert np.allclose(props.centre, com, atol=0.01)
    assert np.allclose(props.inertia, inertia, atol=0.01 * np.abs(inertia).max())


def test_principal_template_diagonalises_inertia_and_keeps_volume():
    t = ClumpTemplate("tri", np.array([[0, 0, 0], [1.1, 0.2, 0], [0.3, 0.9, 0.4]]), np.array([1.0, 0.8, 0.7]))
    p = principal_template(t)
    props = mass_properties(p.template)
    # Re-integrating on the rotated frame repeats the quadrature on another grid, so the
    # agreement is at the quadrature accuracy (about 1e-5 of the clump size), not round-off.
    assert np.allclose(props.centre, 0, atol=1e-4)
    off_diag = props.inertia - np.diag(np.diag(props.inertia))
    assert np.abs(off_diag).max() < 1e-4 * np.abs(props.inertia).max()
    assert np.allclose(np.diag(props.inertia), p.principal_inertia, rtol=1e-4)
    assert abs(p.volume - mass_properties(t).volume) / p.volume < 1e-5


def test_single_sphere_is_exact():
    p = principal_template(ClumpTemplate("s", np.zeros((1, 3)), np.array([2.0])))
    V = 4 / 3 * math.pi * 8
    assert math.isclose(p.volume, V)
    assert np.allclose(p.principal_inertia, 0.4 * V * 4)
