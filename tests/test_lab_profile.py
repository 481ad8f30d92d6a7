"""profile=lab: the lab calibration's config composes into checked settings and a model on the
lab geometry (mirror, half depth, fill by lobes, the four conditions of Table 2), within the
issue's budget of about 215 lab-geometry runs; ``surrogate.added`` parameters join the
selection with their own bounds, and bad ones are one-line errors naming the key."""
from types import SimpleNamespace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.calibration.pipeline import choose_parameters
from bo.cli.calibrate import calibration_model_from, calibration_settings_from
from bo.cli.common import plain_config
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_measured


def _plain(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose("calibrate", overrides=["profile=lab", *overrides]))


def test_lab_profile_composes_on_the_lab_geometry_within_budget():
    plain = _plain()
    s = calibration_settings_from(plain)
    model, _ = calibration_model_from(plain, load_measured())
    assert model.geometry.mirror and model.geometry.depth_scale == 0.5
    assert model.settings.fill_packing == "lobes"
    assert sorted(model.conditions) == ["25-75", "50-50", "50-50-reverse", "75-25"]
    assert "lobe_spacing_sinter" in s.screening.table.names
    screening_runs = (2 * (s.screening.table.k + 2) + 1) * len(s.screening.seeds)
    a = s.surrogate.adaptive
    total = screening_runs + a.budget * len(s.surrogate.seeds) + len(s.verification_seeds) \
        + 3 * len(s.validation_seeds)
    assert total <= 215, total
    # single runs with the pooled noise: the stop counts R^2 against the explainable variance
    assert a.target_basis == "explainable" and s.surrogate.noise == "pooled"
    # Eq. 7 over the paper's four KPIs, whatever the screening keeps (Table 2 also has the RSDs)
    assert s.objective_kpis == ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                                "mass_lower_box_full_kg")


def test_added_parameters_join_the_selection_with_their_bounds():
    plain = _plain()
    s = calibration_settings_from(plain).surrogate
    screening = SimpleNamespace(results=SimpleNamespace(levels=lambda: {"mu_s_pp": (0.3, 0.9)}, parameter_names=("mu_s_pp",)),
                                analysis=SimpleNamespace(selected_parameters=("mu_s_pp",)), proposal=None)
    names, bounds, note = choose_parameters(screening, s)
    assert names == ("mu_s_pp", "density_pellet", "density_sinter")
    np.testing.assert_allclose(bounds[:, 1:], [[3240.0, 3100.0], [3960.0, 3800.0]])
    assert "added by the config" in note
    with pytest.raises(ConfigError, match=r"surrogate: added.density_pellet"):
        calibration_settings_from(_plain("surrogate.added.density_pellet=[-1,3000]"))


def test_the_extension_stops_at_the_profiles_limits():
    """profile=lab's screening.limits: sliding friction at most 1 and the lobe spacing in
    [0.15, 0.3] whatever the Table-6 rule asks; a limit that does not hold the screened levels,
    or names a parameter not screened, is an error naming the key."""
    from bo.cli.common import screen_settings_from
    from bo.screening.bounds import PhysicalLimit

    s = calibration_settings_from(_plain()).screening
    assert s.physical_limits()["mu_s_pg"] == PhysicalLimit(0.0, 1.0)
    assert s.physical_limits()["lobe_spacing_sinter"] == PhysicalLimit(0.15, 0.3)
    with pytest.raises(ConfigError, match=r"screening: limits.lobe_spacing_sinter = \[0.2, 0.3\].*\[0.15, 0.3\]"):
        screen_settings_from(_plain("screening.limits.lobe_spacing_sinter=[0.2,0.3]"))
    with pytest.raises(ConfigError, match=r"limits.coh_pp .*limits of screened parameters"):
        screen_settings_from(_plain("+screening.limits.coh_pp=[0,1]"))
    with pytest.raises(ConfigError, match=r"limits.mu_s_pp .*low < high"):
        screen_settings_from(_plain("screening.limits.mu_s_pp=[1,0.5]"))
