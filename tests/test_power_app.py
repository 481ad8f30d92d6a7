"""scripts/discovery_power.py: the effects of conf/power.yaml against each mechanism's prior, and
bad values as one-line config errors naming the key (the study itself: test_discovery_power.py)."""
import importlib.util
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from bo.cli.calibrate import calibration_model_from
from bo.cli.common import plain_config
from bo.discovery.power import NULL, PowerRow
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_measured
from torchdem.mechanisms import get, model_context

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "discovery_power.py"
spec = importlib.util.spec_from_file_location("discovery_power", SCRIPT)
app = importlib.util.module_from_spec(spec)
spec.loader.exec_module(app)


def _context(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("power", overrides=list(overrides)))
    data = plain.get("data") or plain.get("measured")
    model, _ = calibration_model_from({**plain, "measured": data}, load_measured(data))
    return plain, model_context(model, model.fixed)


def test_effects_step_from_null_towards_the_prior_end():
    plain, context = _context()
    effects = app.effects_from(plain, context)
    cohesion = [e for e in effects if e.mechanism == "cohesion"]
    top = get("cohesion").parameters(context)["coh_pp"][1]
    assert [e.values["coh_pp"] for e in cohesion] == pytest.approx([0.25 * top, 0.5 * top, top])
    assert [e.fraction for e in cohesion] == pytest.approx([0.25, 0.5, 1.0])
    density = [e for e in effects if e.mechanism == "density_per_material"]
    low = get("density_per_material").parameters(context)["density_pellet"][0]
    assert density[-1].values["density_pellet"] == pytest.approx(low)


@pytest.mark.parametrize("override, key", [
    ("power.effects.cohesion.steps=[1.5]", "power.effects.cohesion.steps"),
    ("power.effects.cohesion.toward=up", "power.effects.cohesion.toward"),
    ("+power.effects.cohesion.values=[{coh_pp:1e9,coh_ss:0.0}]", "power.effects.cohesion.values[0].coh_pp"),
    ("power.mechanisms=[gravity]", "power.mechanisms"),
])
def test_bad_effects_name_the_key(override, key):
    plain, context = _context(override)
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        app.effects_from(plain, context)


def test_a_bad_reanalyse_flag_is_refused_before_the_store_is_opened(tmp_path):
    plain, _ = _context("power.reanalyse=maybe", f"store={tmp_path / 'p.sqlite'}")
    with pytest.raises(ConfigError, match="power.reanalyse"):
        app.run(plain, tmp_path / "out")
    assert not (tmp_path / "p.sqlite").exists()


def test_report_table_and_figure(tmp_path):
    rate = lambda k, n: (k / n, max(0.0, k / n - 0.2), min(1.0, k / n + 0.2))  # noqa: E731
    rows = [PowerRow(NULL, "none", 0.0, 30, 2, 0, 1, rate(2, 30), rate(0, 30), rate(1, 30), {"cohesion": 1}),
            PowerRow("cohesion", "coh_pp 5000", 0.5, 10, 9, 8, 1, rate(9, 10), rate(8, 10), rate(1, 10), {"x": 1})]
    from bo.discovery.power import power_summary
    files = app.write_power_report(rows, power_summary(rows), tmp_path, {"dem_runs_computed": 5, "dem_runs_used": 9,
                                                                         "wall_time_s": 1.0})
    text = files["md"].read_text()
    assert "| cohesion | coh_pp 5000 | 0.50 | 10 | 90 % (70-100) | 80 % (60-100) |" in text
    assert "cohesion: named right in 80 % (60-100) at coh_pp 5000" in text
    assert files["png"].stat().st_size > 1000
