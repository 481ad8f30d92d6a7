"""A KPI's linear response over a campaign's runs (bo/screening/response.py, scripts/kpi_response.py).

- On runs drawn from a known plane plus Gaussian noise (sd 0.1), with every set run twice: each
  parameter's effect over its range comes back within 3 standard errors of the plane's, the
  residual sd and the pooled replicate sd within 25 % of 0.1, a parameter held constant is not
  fitted, and R^2 equals 1 - residual / total variance computed by hand.
- A KPI with no relation to the parameters gets R^2 near 0 and effects within 3 se of 0.
- Runs without the KPI are left out; too few runs for the fit raise ConfigError naming the count.
- The script reads a store written through the campaign API, leaves the jammed run out, prints the
  lab's CI count; ``store_runs`` keeps one stage's runs when asked.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.executor import EvalOutcome
from bo.campaign.store import CampaignStore
from bo.screening.response import kpi_response, store_runs
from torchdem.errors import ConfigError

REPO = Path(__file__).resolve().parent.parent
NOISE = 0.1


def _runs(n_sets: int = 60, seed: int = 0) -> list[tuple[dict, dict]]:
    rng = np.random.default_rng(seed)
    runs = []
    for _ in range(n_sets):
        a, b = rng.uniform(0.2, 0.8), rng.uniform(10.0, 20.0)
        for _ in range(2):
            plane = 1.0 + 2.0 * a - 0.05 * b
            runs.append(({"a": a, "b": b, "held": 3.0},
                         {"plane": plane + NOISE * rng.standard_normal(), "unrelated": rng.standard_normal()}))
    return runs


def test_a_known_plane_comes_back_with_its_noise():
    runs = _runs()
    fit = kpi_response(runs, "plane")
    assert fit.parameters == ("a", "b")  # "held" never varies
    a = np.array([p["a"] for p, _ in runs])
    b = np.array([p["b"] for p, _ in runs])
    expected = np.array([2.0 * (a.max() - a.min()), -0.05 * (b.max() - b.min())])
    assert np.all(np.abs(fit.effect - expected) < 3 * fit.effect_se)
    assert fit.residual_sd == pytest.approx(NOISE, rel=0.25)
    assert fit.replicate_sd == pytest.approx(NOISE, rel=0.25) and fit.replicate_dof == 60
    y = fit.values
    residual = fit.residual_sd ** 2 * (len(y) - 3)
    assert fit.r2 == pytest.approx(1 - residual / np.sum((y - y.mean()) ** 2), rel=1e-12)
    assert fit.r2 > 0.9


def test_noise_alone_explains_nothing():
    fit = kpi_response(_runs(), "unrelated")
    assert abs(fit.r2) < 0.1
    assert np.all(np.abs(fit.effect) < 3 * fit.effect_se)


def test_runs_without_the_kpi_are_left_out_and_too_few_are_refused():
    runs = _runs(n_sets=3)
    runs[0][1].pop("plane")
    assert len(kpi_response(runs, "plane").values) == 5
    with pytest.raises(ConfigError, match="my store: 2 runs with a finite 'plane' cannot fit 2 parameters"):
        kpi_response(runs[:3], "plane", "my store")
    with pytest.raises(ConfigError, match="no run has a finite 'missing'"):
        kpi_response(runs, "missing")


def test_the_script_reads_a_store_and_leaves_jammed_runs_out(tmp_path):
    path = tmp_path / "store.sqlite"
    store = CampaignStore(path, "hash")
    rows = [(0.1, 30.0, 0.0), (0.2, 31.0, 0.0), (0.3, 32.1, 0.0), (0.4, 32.9, 0.0), (0.5, 10.0, 1.0)]
    for knob, aor, jammed in rows:
        key = f"k{knob}"
        store.batch("initial", key, lambda: [{"knob": knob}], seeds=[0], conditions=["50-50"])
        store.record([(t, EvalOutcome.success({"angle_of_repose_deg": aor, "discharge_jammed": jammed}, 1.0))
                      for t in store.claim(10, stage="initial", batch_key=key)])
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "kpi_response.py"), str(path),
                          "--kpis", "angle_of_repose_deg"], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("4 runs that flowed at 50-50")
    # 29.47 +- 0.48 (Table 2) holds none of 30.0-32.9; the least-squares slope is 0.49 / 0.05 = 9.8 deg per unit, 2.94 over 0.1-0.4
    assert "| angle_of_repose_deg | 4 | 30 to 32.9 |" in out.stdout and "| 29.47 +- 0.48 | 0 |" in out.stdout
    assert "knob 0.1-0.4 +2.94" in out.stdout
    # a second stage's run joins the runs unless the stages name the first one only
    store.batch("verification", "o", lambda: [{"knob": 0.6}], seeds=[0], conditions=["50-50"])
    store.record([(t, EvalOutcome.success({"angle_of_repose_deg": 40.0, "discharge_jammed": 0.0}, 1.0))
                  for t in store.claim(10, stage="verification", batch_key="o")])
    assert len(store_runs([path], "50-50")) == 5 and len(store_runs([path], "75-25")) == 0
    assert sorted(p["knob"] for p, _ in store_runs([path], "50-50", ["initial"])) == [0.1, 0.2, 0.3, 0.4]
