"""Mixtures, sieve sampling, geometry and the rained fill.

- Sampled layers reach their target mass (within one particle) and reproduce the sieve
  analysis: the drawn mass fraction per sieve class is within 3 percentage points of the
  paper's Table 1 for a fill of several thousand particles.
- Layer masses follow the mixture: 50-50 in four alternating layers is 10 kg per layer;
  three materials and arbitrary sequences work; bad mixtures are rejected by name.
- The sinter template reproduces the paper's time step (15% Rayleigh of its smallest sphere
  = 5.91e-6 s) and fits its sieve diameter.
- The rained fill has no overlapping bounding spheres (periodic images included) and keeps
  the layers in order.
"""
import math

import numpy as np
import pytest

from torchdem.errors import ConfigError
from torchdem.fill import rain_positions
from torchdem.geometry import DrawDownGeometry
from torchdem.materials import rayleigh_time_step
from torchdem.measured import load_materials
from torchdem.mixture import Mixture, ParticleMaterial, SieveClass, sample_layers, sieve_from_table


def _materials():
    t = load_materials()
    pellet = ParticleMaterial("pellet", "sphere", sieve_from_table(t["pellet"]["sieve_size_distribution"]),
                              3602.4, label="pellet")
    sinter = ParticleMaterial("sinter", "sinter_trilobe", sieve_from_table(t["sinter"]["sieve_size_distribution"]),
                              3449.0, label="sinter")
    return pellet, sinter


def test_layer_masses_follow_fractions_and_sequence():
    pellet, sinter = _materials()
    mix = Mixture("m", (pellet, sinter), (0.5, 0.5), ("pellet", "sinter", "pellet", "sinter"), 40.0).validate()
    assert mix.layer_masses() == [(0, 10.0), (1, 10.0), (0, 10.0), (1, 10.0)]
    mix = Mixture("m", (pellet, sinter), (0.75, 0.25), ("sinter", "pellet", "sinter", "pellet"), 40.0).validate()
    assert mix.layer_masses(0.5) == [(1, 2.5), (0, 7.5), (1, 2.5), (0, 7.5)]
    third = ParticleMaterial("coke", "sphere", (SieveClass(0.02, 0.03, 1.0),), 1100.0)
    mix = Mixture("m3", (pellet, sinter, third), (0.4, 0.4, 0.2), ("pellet", "coke", "sinter"), 10.0).validate()
    assert [k for k, _ in mix.layer_masses()] == [0, 2, 1]
    assert math.isclose(sum(m for _, m in mix.layer_masses()), 10.0)


def test_sampled_fill_matches_sieve_analysis_and_target_mass():
    pellet, sinter = _materials()
    mix = Mixture("m", (pellet, sinter), (0.5, 0.5), ("pellet", "sinter"), 40.0).validate()
    s = sample_layers(mix, 0.25, seed=4)
    for k, mat in enumerate((pellet, sinter)):
        sel = s.material == k
        assert abs(s.mass[sel].sum() - 5.0) < s.mass[sel].max()
        for c in mat.sieve:
            inside = sel & (s.diameter >= c.d_min) & (s.diameter < c.d_max)
            assert abs(s.mass[inside].sum() / s.mass[sel].sum() - c.mass_fraction) < 0.03, (mat.name, c)
    again = sample_layers(mix, 0.25, seed=4)
    assert np.array_equal(again.diameter, s.diameter)


def test_sinter_template_reproduces_paper_time_step_and_fits_sieve():
    _, sinter = _materials()
    dt = 0.15 * rayleigh_time_step(sinter.smallest_sphere_radius, 3449.0, 1e8, 0.25)
    assert abs(dt - 5.91e-6) / 5.91e-6 < 0.01
    assert math.isclose(2 * sinter.template.bounding_radius(), 1.0, rel_tol=1e-12)


@pytest.mark.parametrize("bad,match", [
    (dict(mass_fractions=(0.6, 0.6)), r"mass_fractions"),
    (dict(layering=("pellet", "coke")), r"layering\[1\] = 'coke'"),
    (dict(layering=("pellet",)), r"'sinter' has mass fraction 0.5 but no layer"),
    (dict(total_mass=-1.0), r"total_mass = -1.0"),
])
def test_bad_mixtures_are_rejected(bad, match):
    pellet, sinter = _materials()
    args = dict(name="m", materials=(pellet, sinter), mass_fractions=(0.5, 0.5), layering=("pellet", "sinter"),
                total_mass=40.0)
    args.update(bad)
    with pytest.raises(ConfigError, match=match):
        Mixture(**args).validate("conf/mixture/test.yaml")


def test_bad_sieve_is_rejected():
    bad = ParticleMaterial("x", "sphere", (SieveClass(0.01, 0.008, 1.0),), 3000.0)
    with pytest.raises(ConfigError, match=r"0 < d_min < d_max"):
        bad.validate("conf/mixture")


def test_a_render_label_the_renderer_does_not_know_is_refused():
    """A label such as 'Pellet' would draw the material as sinter, so the segregation KPI (the
    pellet-coloured pixels) would silently miss it: refused, with the labels the renderer knows."""
    bad = ParticleMaterial("x", "sphere", (SieveClass(0.01, 0.012, 1.0),), 3000.0, label="Pellet")
    with pytest.raises(ConfigError, match=r"conf/mixture\[x\]: label = 'Pellet' is not allowed; expected a render "
                                          r"label of 'pellet' \(white/blue\), 'sinter' \(dark grey\), ''"):
        bad.validate("conf/mixture")
    for label in ("pellet", "sinter", ""):
        ParticleMaterial("x", "sphere", (SieveClass(0.01, 0.012, 1.0),), 3000.0, label=label).validate("conf/mixture")


def test_geometry_validation_and_walls():
    g = DrawDownGeometry().validate()
    names = [w.name for w in g.walls("steel", 0.5)]
    assert "gate" in names and "upper_front" in names
    s = DrawDownGeometry(slice_depth=0.04).validate()
    assert s.periodic == (False, True, False) and math.isclose(s.depth_scale, 0.2)
    assert "upper_front" not in [w.name for w in s.walls("steel", 0.5)]
    with pytest.raises(ConfigError, match=r"outlet_width = 0.5"):
        DrawDownGeometry(outlet_width=0.5).validate()
    with pytest.raises(ConfigError, match=r"slice_depth = 0.3"):
        DrawDownGeometry(slice_depth=0.3).validate()


def test_rained_fill_has_no_overlaps_and_ordered_layers():
    rng = np.random.default_rng(0)
    n = 400
    radius = rng.uniform(0.003, 0.008, n)
    layer = np.repeat(np.arange(4), n // 4)
    g = DrawDownGeometry(upper_width=0.2, slice_depth=0.04, upper_height=1.0)
    fill = rain_positions(radius, layer, 4 / 3 * np.pi * radius ** 3, g, seed=1)
    p = fill.position
    d = p[:, None, :] - p[None, :, :]
    d[..., 1] -= 0.04 * np.round(d[..., 1] / 0.04)
    dist = np.linalg.norm(d, axis=-1) + np.eye(n)
    assert (dist >= radius[:, None] + radius[None, :] - 1e-12).all()
    assert (np.abs(p[:, 0]) + radius <= 0.1 + 1e-12).all() and (p[:, 2] - radius >= g.upper_bottom_z).all()
    for k in range(2):  # every particle of layer k lies below every particle of layer k + 2
        assert p[layer == k, 2].max() < p[layer == k + 2, 2].min()
    assert np.all(np.diff(fill.layer_tops) > 0)


def test_a_fill_that_would_overflow_is_rained_denser_and_one_that_fits_is_unchanged():
    """rain_to_fit: a fill that fits at the loose fraction is rain_positions' fill, bit for bit; one
    whose loose stack would rise above max_top is placed at the first denser fraction (0.025
    steps) that fits, as rain_positions places it there, without overlaps; above the densest
    fraction's stack it fails, naming the fractions tried."""
    from torchdem.fill import FillOverflowError, rain_to_fit

    rng = np.random.default_rng(2)
    n = 1200
    radius = rng.uniform(0.003, 0.008, n)
    layer = np.repeat(np.arange(2), n // 2)
    volume = 4 / 3 * np.pi * radius ** 3
    g = DrawDownGeometry(upper_width=0.2, slice_depth=0.04, upper_height=1.0)
    tops = {f: rain_positions(radius, layer, volume, g, seed=3, loose_fraction=f, max_top=10.0).top
            for f in (0.3, 0.325, 0.35, 0.375)}
    assert tops[0.3] > tops[0.325] > tops[0.35] > tops[0.375]
    fill, used = rain_to_fit(radius, layer, volume, g, 3, 0.3, max_top=10.0)
    assert used == 0.3 and np.array_equal(fill.position, rain_positions(radius, layer, volume, g, 3, 0.3,
                                                                        max_top=10.0).position)
    fill, used = rain_to_fit(radius, layer, volume, g, 3, 0.3, max_top=(tops[0.3] + tops[0.325]) / 2)
    assert used == 0.325 and fill.top == tops[0.325]
    limit = (tops[0.35] + tops[0.375]) / 2  # only the densest fraction fits
    fill, used = rain_to_fit(radius, layer, volume, g, 3, 0.3, max_top=limit)
    assert used == 0.375 and fill.top == tops[0.375] <= limit
    p = fill.position
    d = p[:, None, :] - p[None, :, :]
    d[..., 1] -= 0.04 * np.round(d[..., 1] / 0.04)
    assert (np.linalg.norm(d, axis=-1) + np.eye(n) >= radius[:, None] + radius[None, :] - 1e-12).all()
    with pytest.raises(FillOverflowError, match=r"above the allowed z.*loose fractions 0.3 to 0.375 tried"):
        rain_to_fit(radius, layer, volume, g, 3, 0.3, max_top=tops[0.375] - 0.001)
