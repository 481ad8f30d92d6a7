"""Shadows in the draw down's photos (``run.photo_shadow_depth_m``, ``RunSettings.photo_shadow_depth``).

- The setting is read from the run block, refused below or at 0 with the key named, and hashed as
  absent while null, so the stores written before it keep their hash.
- The same small draw down (same seed, same trajectory) photographed with and without shadows: the
  shadowed photo holds shadow pixels where the flat one shows grains behind the front layer; the
  angles and masses, which take every grain as material, are the same to the last bit; the
  segregation, which counts the shadow as sinter, changes.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bo.cli.common import config_hash
from kpi.colors import SHADOW_BGR
from torchdem.config import run_settings_from
from torchdem.errors import ConfigError

from test_drawdown import small_drawdown

SIM = {"time_step_fraction": 0.15, "dtype": "float64", "compile": False,
       "guards": {"check_every": 200, "max_speed": 50.0, "energy_tolerance": 0.05, "on_blowup": "raise"}}
RUN = {"fill_time_s": 0.8, "discharge_time_s": 4.0, "loadcell_rate_hz": 50, "rolling_damping": 0.3,
       "metres_per_pixel": 0.001, "rsd_component": "sinter", "loose_fraction": 0.3}


def test_the_setting_is_read_checked_and_hashed_as_absent_while_null():
    assert run_settings_from(SIM, RUN).photo_shadow_depth is None
    assert run_settings_from(SIM, {**RUN, "photo_shadow_depth_m": 0.01}).photo_shadow_depth == 0.01
    with pytest.raises(ConfigError, match=r"run\.photo_shadow_depth_m.*> 0 m behind the front layer, or null"):
        run_settings_from(SIM, {**RUN, "photo_shadow_depth_m": 0.0})
    assert config_hash({"run": {**RUN, "photo_shadow_depth_m": None}}) == config_hash({"run": RUN})
    assert config_hash({"run": {**RUN, "photo_shadow_depth_m": 0.01}}) != config_hash({"run": RUN})


def test_shadows_change_the_segregation_and_nothing_else():
    base = small_drawdown()
    short = dataclasses.replace(base.settings, discharge_time=0.6, flow_window=(0.1, 0.3), final_window=0.2)
    flat = base.__class__(base.mixture, base.geometry, settings=short).run(replicates=1, seeds=[5])
    shaded_test = base.__class__(base.mixture, base.geometry,
                                 settings=dataclasses.replace(short, photo_shadow_depth=0.006))
    shaded = shaded_test.run(replicates=1, seeds=[5])
    shadow = (shaded.images[0]["lower"] == SHADOW_BGR).all(-1)
    assert shadow.sum() > 100 and not (flat.images[0]["lower"] == SHADOW_BGR).all(-1).any()
    for kpi in ("angle_of_repose_deg", "shear_angle_deg", "mass_lower_box_kg", "mass_flow_rate_kg_s"):
        assert shaded.kpis[0][kpi] == flat.kpis[0][kpi], kpi
    assert shaded.kpis[0]["segregation_rsd_horizontal"] != flat.kpis[0]["segregation_rsd_horizontal"]
    assert np.array_equal(shaded.images[0]["lower"][~shadow], flat.images[0]["lower"][~shadow])
