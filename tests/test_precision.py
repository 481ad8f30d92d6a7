"""The float32-against-float64 equivalence study (bo/studies/precision.py, torchdem-study study=precision).

- The TOST power formula agrees with the rate at which TOST passes on simulated equal-mean data
  (4,000 simulated studies: within 3 binomial standard errors).
- The verdict: equal means with enough runs are "equivalent"; means a margin and a half apart
  with enough runs are "not equivalent"; too few runs for the scatter are "undecided" and the
  report names the seeds needed.
- A precision is a condition variant (``50-50|dtype=float32``) that round-trips.
- The app runs end to end on the mini box and writes its verdict.
"""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from statsmodels.stats.weightstats import ttost_ind

from bo.studies.precision import precision_verdict, seeds_for_power, tost_power
from torchdem.drawdown import RunSettings
from torchdem.errors import ConfigError
from torchdem.model import split_condition, variant

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("n, margin", [(10, 0.9), (20, 0.8), (40, 0.5)])
def test_power_formula_matches_simulated_tost(n, margin):
    rng = np.random.default_rng(7)
    reps = 4000
    passed = 0
    for _ in range(reps):
        a, b = rng.normal(0.0, 1.0, n), rng.normal(0.0, 1.0, n)
        p, _, _ = ttost_ind(b, a, -margin, margin, usevar="unequal")
        passed += p < 0.05
    rate = passed / reps
    expected = tost_power(1.0, margin, n)
    se = math.sqrt(max(expected * (1 - expected), 1e-4) / reps)
    assert abs(rate - expected) < 3 * se + 0.01, (rate, expected)


def test_seeds_for_power_is_the_smallest_n_reaching_it():
    n = seeds_for_power(1.0, 0.5, power=0.8, minimum=2)
    assert tost_power(1.0, 0.5, n) >= 0.8 > tost_power(1.0, 0.5, n - 1)
    assert seeds_for_power(0.1, 0.5, minimum=10) == 10  # never below the floor


def test_verdicts():
    rng = np.random.default_rng(3)
    names = ["same", "shifted", "noisy"]
    a = np.stack([rng.normal(10, 0.2, 40), rng.normal(5, 0.2, 40), rng.normal(1, 3.0, 40)], 1)
    b = np.stack([rng.normal(10, 0.2, 40), rng.normal(5.75, 0.2, 40), rng.normal(1, 3.0, 40)], 1)
    v = precision_verdict(a, b, names, {"same": 0.5, "shifted": 0.5, "noisy": 0.5})
    verdicts = {r.kpi: r.verdict for r in v.rows}
    assert verdicts == {"same": "equivalent", "shifted": "not equivalent", "noisy": "undecided"}
    noisy = next(r for r in v.rows if r.kpi == "noisy")
    assert noisy.seeds_needed > 40 and tost_power(noisy.sd, 0.5, noisy.seeds_needed) >= 0.8
    assert v.failing == ("shifted",) and not v.equivalent
    assert "NOT equivalent" in v.to_text()
    v2 = precision_verdict(a, b, names, {"same": 0.5})
    assert v2.equivalent and set(v2.skipped) == {"shifted", "noisy"}


def test_bad_shapes_and_levels_are_named():
    with pytest.raises(ConfigError, match=r"\[runs, 2\]"):
        precision_verdict(np.zeros((5, 3)), np.zeros((5, 2)), ["a", "b"], {})
    with pytest.raises(ConfigError, match="alpha"):
        precision_verdict(np.zeros((5, 1)), np.zeros((5, 1)), ["a"], {"a": 1.0}, alpha=0.7)


def test_precision_is_a_condition_variant():
    name = variant("50-50", dtype="float32")
    assert name == "50-50|dtype=float32"
    base, settings = split_condition(name, RunSettings())
    assert base == "50-50" and settings.dtype == "float32"
    with pytest.raises(ConfigError, match="float16"):
        split_condition("50-50|dtype=float16", RunSettings())


@pytest.mark.slow
def test_precision_study_app_runs_on_the_mini_box(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "bo.cli.study", "study=precision", "replicates=2",
                           "run.fill_time_s=0.1", "run.discharge_time_s=0.3", "run.flow_window_s=[0.02,0.15]",
                           "run.final_window_s=0.05", f"hydra.run.dir={out}"], cwd=REPO, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads((out / "precision.json").read_text())
    assert doc["labels"] == ["float64", "float32"] and doc["conditions"] == ["50-50|dtype=float64",
                                                                              "50-50|dtype=float32"]
    # (0.3 s of discharge leaves few bodies at rest for the photo's angle of repose)
    assert {r["kpi"] for r in doc["rows"]} >= {"shear_angle_deg", "mass_lower_box_full_kg"}
    assert "Verdict:" in (out / "precision.md").read_text()
