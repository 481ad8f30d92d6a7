"""Raining a fill by the clumps' lobes (``run.fill_packing = lobes``).

- The top of the clump-shape prior (lobe spacing 0.3, flat sinter) fills the CPU slice's
  column at the paper's 40 kg: packed by bounding spheres it overflows (2.3 m against the
  1.85 m allowed), packed by lobes it fits, with no two spheres of different bodies closer than
  the fill's clearance (0.2 mm) and every sphere inside the box walls, measured on the built
  DEM system's spheres (so the fill placed the lobes where the DEM puts them).
- The clump_shape extension switches the model to lobe packing; a bad ``run.fill_packing`` is a
  one-line error naming the key.
"""
import dataclasses

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree

from bo.cli.common import model_from, plain_config
from torchdem.cli import CONF_DIR
from torchdem.config import run_settings_from
from torchdem.errors import ConfigError
from torchdem.integrate import sphere_positions
from torchdem.mechanisms import with_extension

GAP = 0.0002


def _plain(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose("study", overrides=["study=precision", "study_profile=precision", *overrides]))


def test_flat_sinter_fills_the_slice_by_lobes_without_overlaps():
    model = model_from(_plain())
    flat = [{"lobe_spacing_sinter": 0.3}]
    with pytest.raises(ConfigError, match="loose stack reaches"):
        model.test_for("50-50", flat).build([0], [0])
    lobes = dataclasses.replace(model, settings=dataclasses.replace(model.settings, fill_packing="lobes"))
    system, state, (n,) = lobes.test_for("50-50", flat).build([0], [0])
    assert n > 5000
    x = sphere_positions(system, state.bodies).numpy()
    r = system.sphere_radius[0].numpy()
    body = system.sphere_body[0].numpy()
    g = model.geometry
    assert float((x[:, 2] + r).max()) < g.upper_bottom_z + 3 * g.upper_height
    assert float((x[:, 2] - r).min()) >= g.upper_bottom_z - 1e-12
    assert float((np.abs(x[:, 0]) + r).max()) <= g.upper_width / 2 + 1e-12
    pairs = cKDTree(x, boxsize=None).query_pairs(2 * float(r.max()) + GAP, output_type="ndarray")
    # the slice is periodic along y: compare minimum images
    d = x[pairs[:, 0]] - x[pairs[:, 1]]
    d[:, 1] -= g.slice_depth * np.round(d[:, 1] / g.slice_depth)
    other = body[pairs[:, 0]] != body[pairs[:, 1]]
    gap = np.linalg.norm(d, axis=1) - r[pairs[:, 0]] - r[pairs[:, 1]]
    assert gap[other].min() >= GAP * (1 - 1e-9)


def test_clump_shape_extension_packs_by_lobes_and_bad_packing_is_refused():
    plain = _plain()
    model = model_from(plain)
    assert model.settings.fill_packing == "bounding"
    from torchdem.config import extension_from
    extended = with_extension(model, *extension_from({"name": "clump_shape", "values": {"lobe_spacing_sinter": 0.2}}))
    assert extended.settings.fill_packing == "lobes"
    with pytest.raises(ConfigError, match=r"run: fill_packing = 'spheres'"):
        run_settings_from(plain["sim"], {**plain["run"], "fill_packing": "spheres"})
