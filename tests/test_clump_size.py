"""The sinter clump's size against its sieve size (``clump_scale_<material>``,
torchdem/mechanisms/clump_size.py).

- A trilobe of unit scale passes a square sieve aperture of (1 - (2 - 3 / (2 sqrt 2)) s) d, no smaller
  (standing along the aperture's diagonal): searched over
  100,000 random orientations and polished by Nelder-Mead, the smallest square that holds the
  clump's projection (a union of disks) is that side to 1e-3 d, and no orientation beats it by more
  than round-off. Edge on (the plate's narrowest width, 1 - s / 2) it needs more.
- A scale k multiplies every length: bounding radius k / 2, volume k^3 (the quadrature's 1e-5), the
  square it passes edge on k (1 - s / 2). Scale 1 keeps the shape key every shipped store hashes.
- ``clump_scale_sinter`` reaches the DEM: the member's sinter lobes are k times those of the unscaled
  member of the same seed and sieve diameters, and the same mass is made of fewer grains.
- Bad values name the parameter and its range; a scale on a material that is no trilobe is refused.
- The mechanism's prior, null and availability on a periodic slice.
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from torchdem.clumps import mass_properties
from torchdem.errors import ConfigError
from torchdem.mechanisms import apply_extension, registry
from torchdem.mixture import TEMPLATES, trilobe_aperture, trilobe_parameters, trilobe_shape, trilobe_template


def _square_side(template, rotation: Rotation) -> np.ndarray:
    """Side of the smallest axis-aligned square holding the projection of the rotated clump on the x-y
    plane (the sieve's plane): the disks of its spheres, at their projected centres."""
    centres = np.einsum("rij,kj->rki", rotation.as_matrix().reshape(-1, 3, 3), template.offsets)
    r = template.radii
    wx = (centres[..., 0] + r).max(1) - (centres[..., 0] - r).min(1)
    wy = (centres[..., 1] + r).max(1) - (centres[..., 1] - r).min(1)
    return np.maximum(wx, wy)


@pytest.mark.parametrize("spacing", [0.15, 0.2574, 0.3])
def test_a_trilobe_passes_the_square_aperture_it_is_said_to_and_no_smaller(spacing):
    t = trilobe_template(spacing)
    rotations = Rotation.random(100_000, random_state=1)
    sides = _square_side(t, rotations)
    best = np.argsort(sides)[:5]
    polished = [minimize(lambda v: float(_square_side(t, Rotation.from_rotvec([v]))[0]),
                         rotations[int(i)].as_rotvec(), method="Nelder-Mead",
                         options={"xatol": 1e-7, "fatol": 1e-9}).fun for i in best]
    aperture = trilobe_aperture(spacing)
    assert min(polished) == pytest.approx(aperture, abs=1e-3)
    assert min(min(polished), sides.min()) >= aperture - 1e-9  # no orientation passes a smaller aperture
    edge_on = _square_side(t, Rotation.from_euler("x", [90.0], degrees=True))[0]  # plate vertical, one lobe up
    assert edge_on == pytest.approx(1 - spacing / 2, abs=1e-12) and edge_on > aperture + 0.05 * spacing


def test_a_scale_multiplies_every_length_and_scale_one_keeps_the_key():
    s, k = 0.2574, 1.15
    plain, scaled = trilobe_template(s), trilobe_template(s, k)
    assert plain.bounding_radius() == pytest.approx(0.5) and scaled.bounding_radius() == pytest.approx(0.5 * k)
    assert mass_properties(scaled).volume == pytest.approx(k ** 3 * mass_properties(plain).volume, rel=1e-5)
    edge_on = Rotation.from_euler("x", [90.0], degrees=True)
    assert _square_side(scaled, edge_on)[0] == pytest.approx(k * _square_side(plain, edge_on)[0], abs=1e-12)
    assert trilobe_shape(s) == "trilobe_s0.2574" and trilobe_shape(s, 1.0) == "trilobe_s0.2574"
    assert trilobe_shape(s, k) == "trilobe_s0.2574_k1.1500"
    assert TEMPLATES[trilobe_shape(s, k)].radii == pytest.approx(scaled.radii)
    assert trilobe_parameters("trilobe_s0.2574_k1.1500") == (0.2574, 1.15)
    assert trilobe_parameters("sinter_trilobe") == (0.15, 1.0) and trilobe_parameters("sphere") is None
    assert "trilobe_s0.2574_k2.5000" not in TEMPLATES  # outside (0.5, 2]


CONF = str(Path(__file__).resolve().parents[1] / "conf")


def _plain(config_name, overrides):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return OmegaConf.to_container(compose(config_name=config_name, overrides=overrides), resolve=True)


def _mini_model():
    from bo.cli.common import model_from

    plain = _plain("screen", ["+experiment=mini"])
    return model_from(plain), plain["condition"]


def test_the_clump_scale_reaches_the_dem():
    model, condition = _mini_model()
    k = 1.2
    test = model.test_for(condition, [{}, {"clump_scale_sinter": k}])
    shapes = [{m.name: m.shape for m in test.mixture_of(i).materials}["sinter"] for i in (0, 1)]
    assert shapes == ["sinter_trilobe", "trilobe_s0.1500_k1.2000"]
    system, _, _ = test.build([0, 0], [0, 1])
    sinter = system.material_names.index("sinter")
    material = test.mixture_of(0).materials[sinter]
    d_min, d_max = min(c.d_min for c in material.sieve), max(c.d_max for c in material.sieve)
    lobe = 0.5 - 0.15  # the default sinter's lobe radius, of the sieve diameter
    bodies = []
    for b, scale in enumerate((1.0, k)):
        radii = system.sphere_radius[b][system.sphere_material[b] == sinter].double().cpu().numpy()
        bodies.append(int((system.body_material[b] == sinter).sum()))
        assert radii.size == 3 * bodies[-1]
        assert radii.min() >= scale * lobe * d_min * (1 - 1e-6) and radii.max() <= scale * lobe * d_max * (1 + 1e-6)
        # and spread over the class: the largest grains of the scaled member are larger than any unscaled one
        assert radii.max() > scale * lobe * (d_min + 0.8 * (d_max - d_min))
    # the same sinter mass in about 1 / k^3 as many grains (a fill of ~100 grains: within 15 %)
    assert bodies[1] == pytest.approx(bodies[0] / k ** 3, rel=0.15)


def test_bad_clump_scales_are_refused_by_name():
    model, condition = _mini_model()
    with pytest.raises(ConfigError, match=r"clump_scale_sinter = 2\.5.*\(0\.5, 2\]"):
        model.test_for(condition, [{"clump_scale_sinter": 2.5}])
    with pytest.raises(ConfigError, match="clump_scale_pellet.*'sphere'"):
        model.test_for(condition, [{"clump_scale_pellet": 1.1}])


def test_the_mechanism_prior_null_and_its_fit_on_a_periodic_slice():
    from bo.cli.calibrate import calibration_model_from
    from bo.discovery.pipeline import model_context
    from torchdem.measured import load_measured

    plain = _plain("discover", ["profile=paper", "calibration=paper"])
    model, _ = calibration_model_from({**plain, "measured": "hadi2025_pellet_sinter.json"},
                                      load_measured("hadi2025_pellet_sinter.json"))
    context = model_context(model, model.fixed)
    size = registry()["clump_size"]
    assert size.parameters(context) == {"clump_scale_sinter": (1.0, 1.4)}
    assert size.null(context) == {"clump_scale_sinter": 1.0}
    # the paper's 4 cm slice: 4 lobe radii of the largest sinter (25 mm) at scale 1.4 need
    # 4 x 1.4 x (0.5 - s) x 0.025 <= 0.95 x 0.04: s = 0.15 does not fit, the lab's 0.257 does
    assert context.period == pytest.approx(0.04)
    assert "too thin" in size.available(dataclasses.replace(context, calibrated={**context.calibrated,
                                                                                "lobe_spacing_sinter": 0.15}))
    flat = dataclasses.replace(context, calibrated={**context.calibrated, "lobe_spacing_sinter": 0.2574})
    assert size.available(flat) is None
    extended = apply_extension(model, "clump_size", {"clump_scale_sinter": 1.4}, flat)
    assert extended.settings.fill_packing == "lobes"
    assert size.available(dataclasses.replace(context, shapes={"pellet": "sphere", "sinter": "sphere"})) \
        == "no material is a trilobe clump"
