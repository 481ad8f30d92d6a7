"""``scripts/probe_sets.py``: named parameter sets in a campaign store, on the calibration's own model
(the mini box of ``profile=smoke`` here).

- Each set is stored as the base with its changes, so every set names the same parameters; the changes
  reach the DEM (the slippery set's fill empties further, as in tests/test_run_parameter_set.py).
- A rerun runs nothing, a set given more seeds runs only those; ``adopt`` takes a set's runs from another store of the same model instead of
  running them, and refuses a store of another model; ``contrast_check --by-set`` names each set by
  what it changes.
- A bad probe file names the key, the value and what is allowed.
"""
import importlib.util
import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from torchdem.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "probe_sets.py"
_spec = importlib.util.spec_from_file_location("probe_sets", SCRIPT)
probe_sets = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(probe_sets)


def _write(tmp_path, name, **doc) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc))
    return path


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=ROOT)


def _rows(store: Path) -> list[tuple]:
    conn = sqlite3.connect(store)
    try:
        return conn.execute("SELECT batch_key, params, condition, seed, status, kpis, claimed_by FROM evaluations "
                            "ORDER BY task_id").fetchall()
    finally:
        conn.close()


@pytest.mark.xdist_group("probe_sets")
def test_sets_run_once_reach_the_dem_and_can_be_adopted(tmp_path):
    store = tmp_path / "probe.sqlite"
    probe = _write(tmp_path, "probe.yaml", overrides=["profile=smoke"], store=str(store), conditions=["50-50"],
                   seeds=[0], base={"mu_s_pp": 0.9, "mu_s_ss": 0.9},
                   sets={"base": {}, "slippery": {"mu_s_pp": 0.1, "mu_s_ss": 0.1}})
    out = _run(probe)
    assert out.returncode == 0, out.stderr
    assert "n_done=2" in out.stdout and "| slippery | 50-50 | 1 (0) |" in out.stdout
    rows = {r[0]: r for r in _rows(store)}
    assert json.loads(rows["base"][1]) == {"mu_s_pp": 0.9, "mu_s_ss": 0.9}
    # the errors against Table 2's 50-50 (angle of repose 29.47 deg), each set's largest over its conditions
    aor = json.loads(rows["base"][5])["angle_of_repose_deg"]
    (line,) = [x for x in out.stdout.splitlines() if x.startswith("| base | 50-50 | 1 | ")]
    error = 100 * (aor - 29.47) / 29.47
    assert line.split("|")[4].strip().rstrip("*") == f"{error:+.1f}"
    assert line.split("|")[4].strip().endswith("*") == (abs(aor - 29.47) > 0.48)
    cells = [float(c.strip().rstrip("*")) for c in line.split("|")[4:8]]
    assert line.split("|")[8].strip().startswith(f"{max(cells, key=abs):+.1f} % (50-50 ")
    assert json.loads(rows["slippery"][1]) == {"mu_s_pp": 0.1, "mu_s_ss": 0.1}
    lower = {k: json.loads(r[5])["mass_lower_box_kg"] for k, r in rows.items()}
    assert lower["slippery"] > lower["base"] + 0.02  # 0.715 against 0.672 kg at seed 0

    again = _run(probe, "--calibration-condition", "50-50")  # the store has every run: nothing runs
    assert again.returncode == 0, again.stderr
    assert "done 2" in again.stdout and "n_done=0" in again.stdout
    (line,) = [x for x in again.stdout.splitlines() if x.startswith("| base | 50-50 | 1 | ")]
    assert line.endswith("| |")  # the calibration's condition is not in a set's largest error

    # a second probe takes the base's run from the first store instead of running it
    second = tmp_path / "second.sqlite"
    adopting = _write(tmp_path, "adopt.yaml", overrides=["profile=smoke"], store=str(second), conditions=["50-50"],
                      seeds=[0], base={"mu_s_pp": 0.9, "mu_s_ss": 0.9}, sets={"base": {}},
                      adopt={"set": "base", "store": str(store), "stage": ["validation", "probe"]})
    before = store.read_bytes()
    out = _run(adopting)
    assert out.returncode == 0, out.stderr
    assert "1 runs taken from" in out.stdout and "(validation, probe)" in out.stdout and "n_done=0" in out.stdout
    assert store.read_bytes() == before  # the source is only read
    (row,) = _rows(second)
    assert row[4] == "done" and row[6].startswith("imported:") and json.loads(row[5]) == json.loads(rows["base"][5])

    # a store of another model (a shorter time step) is refused with both hashes
    other = _write(tmp_path, "other.yaml", overrides=["profile=smoke", "sim.time_step_fraction=0.1"],
                   store=str(tmp_path / "third.sqlite"), conditions=["50-50"], seeds=[0],
                   base={"mu_s_pp": 0.9, "mu_s_ss": 0.9}, sets={"base": {}},
                   adopt={"set": "base", "store": str(store), "stage": "probe"})
    out = _run(other)
    assert out.returncode != 0 and "its runs are of another model" in out.stderr and "Traceback" not in out.stderr
    # the Verlet skin is an execution setting, not the model: a probe at another skin takes the same run
    skinned = _write(tmp_path, "skin.yaml", overrides=["profile=smoke", "sim.skin_fraction=0.3"],
                     store=str(tmp_path / "fourth.sqlite"), conditions=["50-50"], seeds=[0],
                     base={"mu_s_pp": 0.9, "mu_s_ss": 0.9}, sets={"base": {}},
                     adopt={"set": "base", "store": str(store), "stage": ["validation", "probe"]})
    out = _run(skinned)
    assert out.returncode == 0, out.stderr
    assert "1 runs taken from" in out.stdout and "n_done=0" in out.stdout

    # contrast_check names each set by what it changes (one condition here: no contrast, but the labels)
    from bo.discovery.contrast import ContrastSet, set_labels
    sets = [ContrastSet(str(store), "probe", json.loads(rows[k][1]), {}, {}) for k in ("base", "slippery")]
    assert set_labels(sets) == ["mu_s_pp=0.9, mu_s_ss=0.9", "mu_s_pp=0.1, mu_s_ss=0.1"]


@pytest.mark.xdist_group("probe_sets")
def test_a_set_of_equal_values_on_its_own_seeds_and_conditions_runs_only_what_is_new(tmp_path):
    """A verification of a probed set (its values on more seeds, at one condition) reuses the probe's run of
    the seed they share (the store's shared runs) and runs the others only."""
    store = tmp_path / "probe.sqlite"
    values = {"mu_s_pp": 0.5, "mu_s_ss": 0.6}
    probe = _write(tmp_path, "probe.yaml", overrides=["profile=smoke"], store=str(store), conditions=["50-50"],
                   seeds=[0], base=values, sets={"found": {}, "verification": {}},
                   sets_seeds={"verification": [0, 1]}, sets_conditions={"verification": ["50-50"]})
    out = _run(probe)
    assert out.returncode == 0, out.stderr
    assert "n_done=2" in out.stdout  # found's seed 0 and verification's seed 1; verification's seed 0 is found's
    rows = _rows(store)
    assert [(r[0], r[3]) for r in rows] == [("found", 0), ("verification", 0), ("verification", 1)]
    assert rows[1][6] == "reused:1" and rows[1][5] == rows[0][5]
    assert "| verification | 50-50 | 2 (0) |" in out.stdout
    loaded = probe_sets.load_probe(probe)
    assert probe_sets.conditions_of(loaded, "verification") == ["50-50"] == probe_sets.conditions_of(loaded, "found")

    # the set run, given a seed more: its set grows and only the new seed runs
    probe = _write(tmp_path, "probe.yaml", overrides=["profile=smoke"], store=str(store), conditions=["50-50"],
                   seeds=[0], base=values, sets={"found": {}, "verification": {}},
                   sets_seeds={"verification": [0, 1, 2]}, sets_conditions={"verification": ["50-50"]})
    out = _run(probe)
    assert out.returncode == 0, out.stderr
    assert "n_done=1" in out.stdout and "| verification | 50-50 | 3 (0) |" in out.stdout
    assert _rows(store)[:3] == rows and [(r[0], r[3]) for r in _rows(store)[3:]] == [("verification", 2)]


def test_labels_name_where_a_set_leaves_the_common_values():
    from bo.discovery.contrast import ContrastSet, set_labels
    base = {"a": 1.0, "b": 2.0, "c": 3.0}
    sets = [ContrastSet("s", "probe", p, {}, {}) for p in (base, {**base, "a": 0.5}, {**base, "b": 9.0})]
    sets.append(ContrastSet("t", "validation", base, {}, {}))
    assert set_labels(sets) == ["(common)", "a=0.5", "b=9", "(only set)"]


@pytest.mark.parametrize("doc, message", [
    ({"store": "s", "conditions": ["50-50"], "seeds": [0]}, r"missing \['sets'\]"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0, 0], "sets": {"x": {}}, "base": {"e_pp": 0.5}},
     "seeds = \\[0, 0\\] is not allowed; expected a non-empty list of distinct integers >= 0"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": 0.5}, "sets": {"x": {"mu_r_pp": 0.2}}},
     r"\['mu_r_pp'\] are changed by a set but have no base value"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": "high"}, "sets": {"x": {}}},
     "base.e_pp = 'high' is not allowed; expected a finite number"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": 0.5}, "sets": {"x": {}},
      "adopt": {"set": "y", "store": "t", "stage": "validation"}}, "adopt = .* a mapping with set \\(one of \\['x'\\]\\)"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": 0.5}, "sets": {"x": {}},
      "adopt": {"set": "x", "store": "t", "stage": ["validation", "validation"]}},
     r"adopt.stage = \['validation', 'validation'\] is not allowed; expected a stage name or a non-empty list"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": 0.5}, "sets": {"x": {}},
      "sets_conditions": {"x": []}}, r"sets_conditions = .* non-empty lists of distinct condition names"),
    ({"store": "s", "conditions": ["50-50"], "seeds": [0], "base": {"e_pp": 0.5}, "sets": {"x": {}},
      "sets_conditions": {"y": ["50-50"]}}, r"sets_conditions = .* some of the sets \['x'\]"),
])
def test_a_bad_probe_file_names_the_key_and_what_is_allowed(tmp_path, doc, message):
    path = _write(tmp_path, "bad.yaml", **doc)
    with pytest.raises(ConfigError, match=message):
        probe_sets.load_probe(path)
    with pytest.raises(ConfigError, match="cannot read the probe file"):
        probe_sets.load_probe(tmp_path / "missing.yaml")


@pytest.mark.parametrize("overrides, sets, message", [
    (["profile=smoke"], {"x": {"mu_s_zz": 0.5}}, r"probe file: set 'x' \(\{'mu_s_zz': 0.5\}\): contact: mu_s_zz names "
                                                 r"unknown material letter\(s\) in 'zz'"),
    (["profile=smoke"], {"x": {"mu_s_pp": -0.5}}, r"probe file: set 'x' .*: mu_s = -0.5 is not allowed"),
    (["profile=nonexistent"], {"x": {"mu_s_pp": 0.5}}, r"overrides \['profile=nonexistent'\]: .*Could not find "
                                                       r"'profile/nonexistent'"),
])
def test_a_probe_the_model_cannot_run_stops_before_its_store_is_made(tmp_path, overrides, sets, message):
    """A set the model refuses (a parameter it does not know, a value out of its range) or overrides
    Hydra cannot compose: one ConfigError before the store exists, not a stored failure per run."""
    store = tmp_path / "never.sqlite"
    probe = probe_sets.load_probe(_write(tmp_path, "probe.yaml", overrides=overrides, store=str(store),
                                         conditions=["50-50"], seeds=[0], base=sets["x"], sets={"x": {}}))
    with pytest.raises(ConfigError, match=message):
        probe_sets.run_probe(probe, workers=1, echo=lambda s: None)
    assert not store.exists()


def test_the_error_table_leaves_jammed_runs_out_and_names_where_a_set_jammed():
    """Errors over the runs that flowed (Table 2: 75-25 angle of repose 28.55 +- 0.65 deg, flow 10.29 +- 0.10
    kg/s); a jammed run is counted apart and named in the set's last column, since it cannot validate."""
    from types import SimpleNamespace
    from torchdem.measured import load_measured

    kpis = ("angle_of_repose_deg", "mass_flow_rate_full_kg_s")
    runs = [SimpleNamespace(condition="75-25", kpis={"angle_of_repose_deg": 28.55 * 1.02,
                                                     "mass_flow_rate_full_kg_s": 10.29 * 0.95, "discharge_jammed": 0.0}),
            SimpleNamespace(condition="25-75", kpis={"angle_of_repose_deg": 0.0, "mass_flow_rate_full_kg_s": 0.0,
                                                     "discharge_jammed": 1.0})]
    store = SimpleNamespace(records=lambda stage, batch_key, status: runs)
    probe = {"sets": {"s": ({}, [0])}, "conditions": ["75-25", "25-75"]}
    lines = probe_sets.error_table(store, probe, kpis, load_measured()).splitlines()
    assert lines[2] == "| s | 75-25 | 1 | +2.0 | -5.0* | |"
    assert lines[3] == "| s | 25-75 | 0 | - | - | -5.0 % (75-25 mass_flow_rate_full_kg_s) jammed: 25-75 1 of 1 |"


def test_the_largest_error_carries_its_standard_error_over_the_runs():
    """Two 75-25 runs at 5 % and 3 % under Table 2's flow (10.29 kg/s): the mean error is -4.0 % and its
    standard error sd / sqrt(2) = 1.0 % of the lab's mean, so a miss past a threshold reads against the
    runs' scatter."""
    from types import SimpleNamespace
    from torchdem.measured import load_measured

    kpis = ("angle_of_repose_deg", "mass_flow_rate_full_kg_s")
    runs = [SimpleNamespace(condition="75-25", kpis={"angle_of_repose_deg": 28.55 * 1.02,
                                                     "mass_flow_rate_full_kg_s": 10.29 * f, "discharge_jammed": 0.0})
            for f in (0.95, 0.97)]
    store = SimpleNamespace(records=lambda stage, batch_key, status: runs)
    probe = {"sets": {"s": ({}, [0, 1])}, "conditions": ["75-25"]}
    (line,) = probe_sets.error_table(store, probe, kpis, load_measured()).splitlines()[2:]
    assert line == "| s | 75-25 | 2 | +2.0 | -4.0* | -4.0 +- 1.0 % (75-25 mass_flow_rate_full_kg_s) |"
