"""``scripts/flow_layers.py``: each condition's flow broken down by material and half window, and its
difference from a reference condition, from the KPIs a store keeps (synthetic records here; the
breakdown's own values are tested in tests/test_flow_breakdown.py)."""
import importlib.util
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "flow_layers.py"
_spec = importlib.util.spec_from_file_location("flow_layers", SCRIPT)
flow_layers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(flow_layers)


def run(condition, pellets, sinter, early, late, seed=0, params=None, batch_key="base", **extra):
    kpis = {"mass_flow_rate_full_kg_s": pellets + sinter, "mass_flow_rate_pellet_full_kg_s": pellets,
            "mass_flow_rate_sinter_full_kg_s": sinter, "mass_flow_rate_early_full_kg_s": early,
            "mass_flow_rate_late_full_kg_s": late, "mass_lower_box_full_kg": 32.0, "discharge_jammed": 0.0}
    return SimpleNamespace(condition=condition, seed=seed, params=params or {"eta_r": 0.3}, batch_key=batch_key,
                           kpis={**kpis, **extra})


def test_the_difference_from_the_reference_is_split_by_material_with_its_standard_error():
    records = [run("50-50", 6.0, 4.0, 10.5, 9.5), run("50-50", 6.2, 4.0, 10.7, 9.7, seed=1),
               run("50-50", 6.2, 4.0, 10.7, 9.7, seed=1),  # the same run under a second set: once
               run("50-50-reverse", 5.0, 6.0, 9.5, 12.5), run("50-50-reverse", 5.2, 6.0, 9.7, 12.7, seed=1),
               run("50-50-reverse", 1.0, 1.0, 1.0, 1.0, discharge_jammed=1.0),  # arched: left out
               SimpleNamespace(condition="75-25", seed=0, params={}, kpis={"mass_flow_rate_full_kg_s": 9.0}),  # no breakdown
               run("25-75", 5.0, 5.0, 10.0, 10.0, mass_flow_rate_late_full_kg_s=None)]  # NaN, as stored
    runs = flow_layers.runs_by_condition(records)
    assert sorted(runs) == ["50-50", "50-50-reverse"] and len(runs["50-50"]) == len(runs["50-50-reverse"]) == 2
    table = flow_layers.format_flow(runs, "50-50")
    assert "| 50-50-reverse | 2 | 11.10 | 5.10 | 6.00 | 0.46 | 0.50 | 9.60 | 12.60 |" in table
    # +1.00 kg/s: -1.00 of pellets and +2.00 of sinter; variance 0.02 in each condition's pellets (two runs
    # 0.2 apart): se = sqrt(0.02 / 2 + 0.02 / 2) = 0.14
    assert "| 50-50-reverse | +1.00 +- 0.14 | -1.00 +- 0.14 | +2.00 +- 0.00 | -1.00 +- 0.14 | +3.00 +- 0.14 |" in table


def test_by_set_each_set_of_values_gets_its_own_difference_named_by_the_sets_that_share_it():
    round_ = {"lobe_spacing_sinter": 0.15}
    records = [run("50-50", 4.0, 6.0, 10.0, 10.0, batch_key="base"),
               run("50-50-reverse", 7.0, 4.0, 11.0, 11.0, batch_key="base"),
               run("50-50", 4.0, 6.5, 10.5, 10.5, params=round_, batch_key="round"),
               run("50-50", 4.0, 6.5, 10.5, 10.5, params=round_, batch_key="round_4_seeds"),  # shared: once
               run("50-50", 4.2, 6.5, 10.7, 10.7, seed=1, params=round_, batch_key="round_4_seeds"),
               run("50-50-reverse", 7.0, 3.7, 10.7, 10.7, params=round_, batch_key="round")]
    sets = flow_layers.runs_by_set(records)
    assert list(sets) == ["base", "round / round_4_seeds"]
    assert len(sets["round / round_4_seeds"]["50-50"]) == 2
    # each set's reverse against its own 50-50: +1.00 at the base, 10.7 - 10.6 = +0.10 at the round set
    assert "| 50-50-reverse | +1.00 | +3.00 | -2.00 | +1.00 | +1.00 |" in flow_layers.format_flow(sets["base"])
    assert "| 50-50-reverse | +0.10 | +2.90 | -2.80 | +0.10 | +0.10 |" in flow_layers.format_flow(
        sets["round / round_4_seeds"])


@pytest.mark.parametrize("condition, share", [("75-25", 0.75), ("50-50-reverse", 0.5), ("pellets", np.nan)])
def test_the_fill_share_is_read_from_the_condition_name(condition, share):
    assert flow_layers.fill_pellet_share(condition) == pytest.approx(share, nan_ok=True)


def test_runs_without_the_breakdown_say_so_and_a_missing_store_is_named(tmp_path):
    assert "no runs with the flow breakdown" in flow_layers.format_flow({})
    missing = tmp_path / "none.sqlite"
    done = subprocess.run([sys.executable, str(SCRIPT), str(missing)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode != 0 and str(missing) in done.stderr and "Traceback" not in done.stderr
