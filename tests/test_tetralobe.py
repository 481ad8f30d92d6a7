"""The tetralobe clump (``lobe_count_<material>`` 4, torchdem.mixture.tetralobe_template).

- Geometry: four lobes of radius 0.5 - s at distance s from the centre, sqrt(8/3) s apart, so the
  clump just fits the sphere of its sieve size (bounding radius 0.5 d, as the trilobe's).
- Mass: with the lobes apart (s = 0.3, lobe radius 0.2, centres 0.49 apart) the volume is four
  spheres', 4 x 4/3 pi 0.2^3, and by the tetrahedron's symmetry the inertia tensor is isotropic,
  I = 4 v (2/5 r^2 + 2/3 s^2) per unit density (parallel axes: 2/3 s^2 is a lobe centre's squared
  distance off any axis, averaged), to 5e-5 (the quadrature with spheres off its axes: 2.2e-5
  measured); overlapping (s = 0.2574) it stays isotropic to 1e-6 of its trace.
- Keys: ``tetralobe_s0.2574[_k1.1500]`` round-trip and build on first use; the trilobe keys stay.
- ``lobe_count_sinter`` 4 reaches the DEM: four spheres per sinter body at the same spacing; 3.5 or a
  count for a sphere material without a spacing is refused by name.
"""
import math
from pathlib import Path

import numpy as np
import pytest

from torchdem.clumps import mass_properties
from torchdem.errors import ConfigError
from torchdem.mixture import TEMPLATES, lobe_shape, lobed_parameters, tetralobe_template, trilobe_template


@pytest.mark.parametrize("s", [0.15, 0.2574, 0.3])
def test_four_lobes_on_a_tetrahedron_fit_the_sieve_sphere(s):
    t = tetralobe_template(s)
    assert t.n_spheres == 4 and t.radii == pytest.approx(np.full(4, 0.5 - s))
    assert np.linalg.norm(t.offsets, axis=1) == pytest.approx(np.full(4, s))
    gaps = [np.linalg.norm(t.offsets[i] - t.offsets[j]) for i in range(4) for j in range(i + 1, 4)]
    assert gaps == pytest.approx([math.sqrt(8 / 3) * s] * 6)
    assert t.bounding_radius() == pytest.approx(0.5) == trilobe_template(s).bounding_radius()
    assert np.abs(np.linalg.svd(t.offsets - t.offsets.mean(0))[1]).min() > 0.1 * s   # not in any plane


def test_mass_properties_apart_are_four_spheres_and_isotropic_when_they_overlap():
    s, r = 0.3, 0.2
    p = mass_properties(tetralobe_template(s))
    v1 = 4 / 3 * math.pi * r ** 3
    assert p.volume == pytest.approx(4 * v1, rel=5e-5)                      # measured 2.2e-5 off
    assert p.centre == pytest.approx(np.zeros(3), abs=1e-7)
    # each axis: 2/5 v r^2 per sphere plus v times the squared distance off the axis (2/3 s^2 on average)
    assert p.inertia == pytest.approx(np.eye(3) * 4 * v1 * (0.4 * r ** 2 + 2 / 3 * s ** 2), rel=5e-5, abs=1e-12)
    q = mass_properties(tetralobe_template(0.2574))
    trace = np.trace(q.inertia)
    assert q.inertia == pytest.approx(np.eye(3) * trace / 3, abs=1e-6 * trace)
    assert q.volume < 4 * 4 / 3 * math.pi * (0.5 - 0.2574) ** 3            # the lobes overlap, counted once


def test_keys_round_trip_and_build_on_first_use():
    assert lobe_shape(4, 0.2574) == "tetralobe_s0.2574" and lobe_shape(4, 0.2574, 1.15) == "tetralobe_s0.2574_k1.1500"
    assert lobe_shape(3, 0.2574) == "trilobe_s0.2574"
    assert lobed_parameters("tetralobe_s0.2574_k1.1500") == (4, 0.2574, 1.15)
    assert lobed_parameters("sinter_trilobe") == (3, 0.15, 1.0) and lobed_parameters("sphere") is None
    assert TEMPLATES["tetralobe_s0.2574"].radii == pytest.approx(tetralobe_template(0.2574).radii)
    assert "tetralobe_s0.3500" not in TEMPLATES                               # outside (0, 0.3]
    with pytest.raises(ConfigError, match="lobe count = 5"):
        lobe_shape(5, 0.2)


CONF = str(Path(__file__).resolve().parents[1] / "conf")


def _mini_model():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from bo.cli.common import model_from

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        plain = OmegaConf.to_container(compose(config_name="screen", overrides=["+experiment=mini"]), resolve=True)
    return model_from(plain), plain["condition"]


def test_the_lobe_count_reaches_the_dem():
    model, condition = _mini_model()
    test = model.test_for(condition, [{"lobe_spacing_sinter": 0.2574},
                                      {"lobe_spacing_sinter": 0.2574, "lobe_count_sinter": 4}])
    shapes = [{m.name: m.shape for m in test.mixture_of(i).materials}["sinter"] for i in (0, 1)]
    assert shapes == ["trilobe_s0.2574", "tetralobe_s0.2574"]
    system, _, _ = test.build([0, 0], [0, 1])
    sinter = system.material_names.index("sinter")
    for b, lobes in enumerate((3, 4)):
        bodies = int((system.body_material[b] == sinter).sum())
        radii = system.sphere_radius[b][system.sphere_material[b] == sinter]
        assert bodies > 0 and radii.numel() == lobes * bodies


def test_bad_lobe_counts_are_refused_by_name():
    model, condition = _mini_model()
    with pytest.raises(ConfigError, match=r"lobe_count_sinter = 3\.5.*3 \(a flat trilobe\) or 4"):
        model.test_for(condition, [{"lobe_count_sinter": 3.5}])
    with pytest.raises(ConfigError, match="lobe_count_pellet = 4.*'sphere'.*lobe_spacing_pellet"):
        model.test_for(condition, [{"lobe_count_pellet": 4}])
