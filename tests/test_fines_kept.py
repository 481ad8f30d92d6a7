"""The fines below the scalping cut kept as sieved (``fines_kept_<material>``,
torchdem/mechanisms/fines_kept.py):

- ``scalp_sieve`` with a share kept: each fine class keeps that share of its mass and only the rest
  joins the class at the cut; the mass fractions still sum to 1; share 0 is the plain scalp every
  shipped store ran, share 1 the sieve as measured.
- ``fines_kept_sinter`` reaches a run: the member's sinter has Table 1's 5.6-8 and 8-10 mm classes at
  that share, the particles drawn for it include grains under 10 mm (none at share 0), and the layers
  weigh what they weighed.
- Bad values name the parameter and its range; 0 is allowed (the candidate's null); a share where the
  runs scalp nothing is refused.
- The candidate's prior, null and availability: on the scalped lab model, not where nothing is scalped.
"""
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bo.cli.calibrate import calibration_model_from
from bo.cli.common import plain_config
from torchdem.errors import ConfigError
from torchdem.measured import load_measured
from torchdem.mechanisms import model_context, registry
from torchdem.mixture import SieveClass, sample_layers, scalp_sieve

CONF = str(Path(__file__).resolve().parents[1] / "conf")
TABLE1_SINTER = (SieveClass(0.0056, 0.008, 0.3637), SieveClass(0.008, 0.010, 0.2313), SieveClass(0.010, 0.0125, 0.1761),
                 SieveClass(0.0125, 0.016, 0.1345), SieveClass(0.016, 0.020, 0.0508),
                 SieveClass(0.020, 0.025, 0.0436))


def _lab_model(*overrides, profile="lab_box"):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=[f"profile={profile}", *overrides]))
    return calibration_model_from(plain, load_measured())[0]


@pytest.mark.parametrize("share", [0.0, 0.3, 1.0])
def test_a_share_of_each_fine_class_stays_and_the_rest_joins_the_class_at_the_cut(share):
    sieve = scalp_sieve(TABLE1_SINTER, 0.010, fines_kept=share)
    assert sum(c.mass_fraction for c in sieve) == pytest.approx(1.0, abs=1e-12)
    by_class = {(c.d_min, c.d_max): c.mass_fraction for c in sieve}
    if share == 0:
        assert sieve == scalp_sieve(TABLE1_SINTER, 0.010)  # what every shipped store ran
        assert min(by_class)[0] == 0.010
    else:
        assert by_class[(0.0056, 0.008)] == pytest.approx(share * 0.3637)
        assert by_class[(0.008, 0.010)] == pytest.approx(share * 0.2313)
    assert by_class[(0.010, 0.0125)] == pytest.approx(0.1761 + (1 - share) * (0.3637 + 0.2313))
    if share == 1:
        assert sieve == TABLE1_SINTER
    with pytest.raises(ConfigError, match=r"fines_kept.*1\.2.*\[0, 1\]"):
        scalp_sieve(TABLE1_SINTER, 0.010, fines_kept=1.2)


def test_the_share_reaches_a_members_sinter_and_keeps_the_layers_mass():
    model = _lab_model()
    assert model.settings.fines_cut == pytest.approx(0.010)
    test = model.test_for("50-50", [{"fines_kept_sinter": 0.0}, {"fines_kept_sinter": 0.5}, {"fines_kept_sinter": 1.0}])
    sinter = [{m.name: m for m in test.mixture_of(i).materials}["sinter"] for i in range(3)]
    assert min(c.d_min for c in sinter[0].sieve) == pytest.approx(0.010)
    half = {(round(c.d_min, 4)): c.mass_fraction for c in sinter[1].sieve}
    assert half[0.0056] == pytest.approx(0.5 * 0.3637) and half[0.008] == pytest.approx(0.5 * 0.2313)
    assert [(c.d_min, c.d_max) for c in sinter[2].sieve] == [(c.d_min, c.d_max) for c in TABLE1_SINTER]
    drawn = [sample_layers(test.mixture_of(i), model.geometry.depth_scale, seed=0) for i in range(3)]
    k = [m.name for m in test.mixture.materials].index("sinter")
    fine = [int(((d.material == k) & (d.diameter < 0.010)).sum()) for d in drawn]
    assert fine[0] == 0 and 0 < fine[1] < fine[2]
    masses = [float(d.mass.sum()) for d in drawn]
    np.testing.assert_allclose(masses, masses[0], rtol=0.01)  # the layers' targets, drawn to within a grain


def test_bad_shares_name_the_parameter_and_its_range():
    model = _lab_model()
    model.test_for("50-50", [{"fines_kept_sinter": 0.0}])  # the null is a value, not an error
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError, match=r"fines_kept_sinter.*\[0, 1\]"):
            model.test_for("50-50", [{"fines_kept_sinter": bad}])
    with pytest.raises(ConfigError, match="fines_kept_glass.*names no material"):
        model.test_for("50-50", [{"fines_kept_glass": 0.5}])
    kept = _lab_model(profile="lab_fines")  # nothing scalped: a share of the scalped fines means nothing
    with pytest.raises(ConfigError, match=r"fines_kept_sinter set a share .*sim.fines_cut_mm is null"):
        kept.test_for("50-50", [{"fines_kept_sinter": 0.5}])


def test_the_candidate_applies_where_fines_are_scalped_and_not_where_none_are():
    mechanism = registry()["fines_kept"]
    scalped = _lab_model()
    context = model_context(scalped, scalped.fixed)
    assert mechanism.available(context) is None
    # the pellets' sieve starts at the cut (10 mm): only the sinter has fines to keep
    assert mechanism.parameters(context) == {"fines_kept_sinter": (0.0, 1.0)}
    assert mechanism.null(context) == {"fines_kept_sinter": 0.0}
    kept = _lab_model(profile="lab_fines")
    assert "fines_cut_mm is null" in mechanism.available(model_context(kept, kept.fixed))
    coarse = _lab_model("sim.fines_cut_mm=5.6")
    assert "no material's sieve reaches below the fines cut (5.6 mm)" == mechanism.available(
        model_context(coarse, coarse.fixed))
