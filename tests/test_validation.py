"""Bad input is rejected up front with an error naming the value, the range and the source."""

import pytest
import torch

from conftest import F64, glass, steel
from torchdem.errors import ConfigError
from torchdem.materials import Material, interaction_table
from torchdem.simulation import GuardSettings
from torchdem.system import build_system
from torchdem.walls import WallSpec, box_walls, plane

PP = dict(mu_s=0.5, mu_r=0.05, restitution=0.5)


def _table(**override):
    pp = dict(PP, **override)
    return interaction_table([glass(), steel()], {("glass", "glass"): pp, ("glass", "steel"): PP},
                             source="conf/contact.yaml")


@pytest.mark.parametrize("key,value,range_text", [
    ("mu_s", -0.1, "[0.0, inf)"),
    ("mu_r", -1.0, "[0.0, inf)"),
    ("restitution", 0.0, "(0.0, 1.0]"),
    ("restitution", 1.2, "(0.0, 1.0]"),
    ("rolling_damping", -0.3, "[0.0, inf)"),
])
def test_bad_coefficients_name_value_range_and_source(key, value, range_text):
    with pytest.raises(ConfigError) as err:
        _table(**{key: value})
    msg = str(err.value)
    assert key in msg and repr(value) in msg and range_text in msg and "conf/contact.yaml[glass,glass]" in msg


def test_bad_material_properties():
    with pytest.raises(ConfigError, match=r"poisson_ratio = 0.7 .*\(-1, 0.5\)"):
        interaction_table([Material("x", 1e8, 0.7, 2500.0)], {("x", "x"): PP})
    with pytest.raises(ConfigError, match=r"shear_modulus = -1.0"):
        interaction_table([Material("x", -1.0, 0.2, 2500.0)], {("x", "x"): PP})


def test_per_member_values_must_match_batch():
    with pytest.raises(ConfigError, match=r"length B=3"):
        interaction_table([glass()], {("glass", "glass"): dict(PP, mu_s=[0.1, 0.2])}, batch=3)


def _spheres(**kw):
    pos = torch.tensor([[[0.0, 0.0, 0.01], [0.03, 0.0, 0.01]]], dtype=F64)
    args = dict(radius=torch.full((1, 2), 0.005, dtype=F64))
    args.update(kw)
    return build_system(pos, torch.zeros(1, 2, dtype=torch.long), [glass(), steel()], _table(), **args)


def test_time_step_above_rayleigh_limit_is_rejected():
    with pytest.raises(ConfigError, match=r"dt = 0.001 .*Rayleigh time step"):
        _spheres(dt=1e-3)
    with pytest.raises(ConfigError, match=r"time_step_fraction = 1.5"):
        _spheres(time_step_fraction=1.5)


def test_empty_system_is_rejected():
    with pytest.raises(ConfigError, match=r"empty"):
        build_system(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=torch.long), [glass()],
                     interaction_table([glass()], {("glass", "glass"): PP}), radius=torch.zeros(1, 0, dtype=F64))


def test_bad_radius_shape_and_material_id():
    with pytest.raises(ConfigError, match=r"radius/scale = -0.005"):
        _spheres(radius=torch.tensor([[0.005, -0.005]], dtype=F64))
    with pytest.raises(ConfigError, match=r"expected \(1, 2\)"):
        _spheres(radius=torch.full((1, 3), 0.005, dtype=F64))


def test_overlapping_walls_are_rejected():
    walls = box_walls("a", (0, 0, 0), (0.1, 0.1, 0.1), "steel") + [
        WallSpec("dup", (0.05, 0.05, 0.0), (0, 0, 1), (1, 0, 0), 0.02, 0.02, "steel")]
    with pytest.raises(ConfigError, match=r"'a_bottom' and 'dup' lie on top of each other"):
        _spheres(walls=walls)


def test_coplanar_but_disjoint_walls_are_fine():
    walls = [WallSpec("left", (-0.05, 0, 0), (0, 0, 1), (1, 0, 0), 0.02, 0.02, "steel"),
             WallSpec("right", (0.05, 0, 0), (0, 0, 1), (1, 0, 0), 0.02, 0.02, "steel")]
    _spheres(walls=walls)


def test_bad_wall_geometry_and_material():
    with pytest.raises(ConfigError, match=r"walls\[w\]: normal .* unit vector"):
        _spheres(walls=[WallSpec("w", (0, 0, 0), (0, 0, 2), (1, 0, 0), 1, 1, "steel")])
    with pytest.raises(ConfigError, match=r"half_u = 0"):
        _spheres(walls=[WallSpec("w", (0, 0, 0), (0, 0, 1), (1, 0, 0), 0, 1, "steel")])
    with pytest.raises(ConfigError, match=r"material 'wood' is unknown"):
        _spheres(walls=[plane("w", (0, 0, 0), (0, 0, 1), "wood")])


def test_undefined_interaction_pair_that_can_touch_is_rejected():
    table = interaction_table([glass(), steel()], {("glass", "glass"): PP})
    pos = torch.tensor([[[0.0, 0.0, 0.01]]], dtype=F64)
    with pytest.raises(ConfigError, match=r"pair \(glass, steel\) can touch"):
        build_system(pos, torch.zeros(1, 1, dtype=torch.long), [glass(), steel()], table,
                     radius=torch.full((1, 1), 0.005, dtype=F64), walls=[plane("floor", (0, 0, 0), (0, 0, 1), "steel")])


def test_guard_settings_are_validated():
    with pytest.raises(ConfigError, match=r"on_blowup = 'ignore'"):
        GuardSettings(on_blowup="ignore").validate()
