"""The status of a discovery campaign read from its store (bo/discovery/status.py,
scripts/discovery_status.py): a store written through the campaign API with known KPI values;
the design spans, the pooled noise, the held-out z and chi^2 and the calibrated set's chi^2 are
recomputed here by hand; the store is not written. Runs whose discharge jammed are counted and
left out of every figure; a refinement batch's points are points of their own."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.executor import EvalOutcome
from bo.campaign.store import CampaignStore
from bo.discovery.pipeline import discovery_stages
from bo.discovery.status import discovery_status, format_status
from torchdem.measured import Condition, KPIValue, MeasuredData

REPO = Path(__file__).resolve().parent.parent
KPIS = ("shear_angle_deg", "mass_flow_rate_full_kg_s")
LAB = {"A": (40.0, 1.0, 10.0, 0.3), "B": (38.0, 1.2, 10.5, 0.4)}  # shear mean, ci95, flow mean, ci95
CALIBRATED = {"mu_s_pp": 0.5}


def _measured() -> MeasuredData:
    conditions = []
    for name, (shear, ci_shear, flow, ci_flow) in LAB.items():
        conditions.append(Condition(name=name, pellet_mass_fraction=0.5, layering=("pellet", "sinter"), fill_mass_kg=40.0,
                                    kpis={"shear_angle_deg": KPIValue(shear, ci_shear, "deg"),
                                          "mass_flow_rate_kg_s": KPIValue(flow, ci_flow, "kg/s")},
                                    replicates=5))
    return MeasuredData(source="test lab", conditions=tuple(conditions))


def _run(store: CampaignStore, stage: str, key: str, points, seeds, conditions, values) -> None:
    """Store a batch and record ``values(params, seed, condition) -> {kpi: value}`` for each task."""
    store.batch(stage, key, lambda: [dict(p) for p in points], seeds=list(seeds), conditions=list(conditions))
    tasks = store.claim(100, stage=stage, batch_key=key)
    store.record([(t, EvalOutcome.success(values(t.params, t.seed, t.condition), 1.0)) for t in tasks])


def _store(tmp_path) -> Path:
    path = tmp_path / "discover.sqlite"
    store = CampaignStore(path, "hash", extra_stages=discovery_stages(["knob"]))
    base = {("A", 0): (35.0, 9.0), ("A", 1): (36.0, 9.2), ("A", 2): (37.0, 8.8),
            ("B", 0): (37.5, 10.0), ("B", 1): (38.5, 10.4)}
    for c in ("A", "B"):
        seeds = [s for cc, s in base if cc == c]
        _run(store, "discrepancy", f"calibrated/{c}", [CALIBRATED], seeds, [c],
             lambda p, s, cc: dict(zip(KPIS, base[(cc, s)])))
    # the design: two points, one run each; the KPIs follow the knob (flow at B left unmeasured at one point)
    design = [{**CALIBRATED, "knob": 1.0}, {**CALIBRATED, "knob": 3.0}]
    _run(store, "discovery-knob", "lhs/1", design, [0], ["A", "B"],
         lambda p, s, c: {"shear_angle_deg": 30.0 + p["knob"] + (c == "B"),
                          "mass_flow_rate_full_kg_s": 9.0 + p["knob"] if not (c == "B" and p["knob"] == 3.0)
                          else math.nan})
    held = {0: (39.0, 9.9), 1: (40.0, 10.3)}
    _run(store, "discovery-knob", "held-out/A/1", [{**CALIBRATED, "knob": 2.5}], [0, 1], ["A"],
         lambda p, s, c: dict(zip(KPIS, held[s])))

    return path


def test_status_recomputes_spans_noise_and_held_out_chi2_by_hand(tmp_path):
    path = _store(tmp_path)
    before = path.read_bytes()
    measured = _measured()
    status = discovery_status(path, measured, KPIS)
    assert path.read_bytes() == before  # only read
    assert status.counts["discrepancy"] == {"done": 5} and status.counts["discovery-knob"] == {"done": 6}
    spans = {(d.candidate, d.condition): d for d in status.designs}
    assert [d.condition for d in status.designs] == ["A", "B"]
    assert spans[("knob", "A")].runs == 2 and spans[("knob", "A")].spans == {"shear_angle_deg": (31.0, 33.0),
                                                                             "mass_flow_rate_full_kg_s": (10.0, 12.0)}
    assert spans[("knob", "B")].spans["mass_flow_rate_full_kg_s"] == (10.0, 10.0)  # the NaN run left out
    # pooled replicate variance over the calibrated set's groups (A: 3 runs, B: 2) and the held-out group (2)
    groups = {"shear_angle_deg": [[35.0, 36.0, 37.0], [37.5, 38.5], [39.0, 40.0]],
              "mass_flow_rate_full_kg_s": [[9.0, 9.2, 8.8], [10.0, 10.4], [9.9, 10.3]]}
    var = {k: sum(((np.array(g) - np.mean(g)) ** 2).sum() for g in v) / sum(len(g) - 1 for g in v)
           for k, v in groups.items()}
    for k in KPIS:
        assert status.noise.variance(k) == pytest.approx(var[k], rel=1e-12)
    t975 = 2.7764451051977987  # Student t, 4 degrees of freedom: the lab's 5 repeats

    def z(mean, n, lab_mean, ci, k):
        return (mean - lab_mean) / math.sqrt(var[k] / n + (ci / t975) ** 2)

    (h,) = status.held_out
    assert h.candidate == "knob" and h.condition == "A" and h.parameters == {"knob": 2.5} and h.runs == 2
    zs = [z(39.5, 2, 40.0, 1.0, "shear_angle_deg"), z(10.1, 2, 10.0, 0.3, "mass_flow_rate_full_kg_s")]
    assert [c.z for c in h.cells] == pytest.approx(zs, rel=1e-10)
    assert h.chi2 == pytest.approx(sum(x * x for x in zs), rel=1e-10)
    base = [z(36.0, 3, 40.0, 1.0, "shear_angle_deg"), z(9.0, 3, 10.0, 0.3, "mass_flow_rate_full_kg_s")]
    assert h.baseline_chi2 == pytest.approx(sum(x * x for x in base), rel=1e-10)
    assert h.chi2 < h.baseline_chi2  # the knob predicts A far better than the calibrated set
    # the design's mean shift: A's shear points 31, 33 (sd sqrt 2) against the calibrated set's 36 (3 runs)
    shift, se = spans[("knob", "A")].shifts["shear_angle_deg"]
    assert shift == pytest.approx(32.0 - 36.0, abs=1e-12)
    assert se == pytest.approx(math.sqrt(2.0 / 2 + var["shear_angle_deg"] / 3), rel=1e-12)
    # B's flow has one design point left: no shift
    assert "mass_flow_rate_full_kg_s" not in spans[("knob", "B")].shifts
    assert spans[("knob", "B")].shifts["shear_angle_deg"][0] == pytest.approx(33.0 - 38.0, abs=1e-12)
    text = format_status(status, measured)
    assert f"| A | -4 ({se:.2g}) |" in text and "| B | -5 (" in text
    assert "| A | knob 2.5 | 2 |" in text and "31-33 (40)" in text and "| B | 38 (" in text


JAMMED = {"shear_angle_deg": 0.0, "mass_flow_rate_full_kg_s": 0.0, "discharge_jammed": 1.0}


def test_jammed_runs_are_counted_and_left_out_and_refined_points_kept_apart(tmp_path):
    path = _store(tmp_path)
    measured = _measured()
    before = discovery_status(path, measured, KPIS)
    store = CampaignStore(path, "hash", extra_stages=discovery_stages(["knob"]))
    _run(store, "discrepancy", "calibrated/A/more", [CALIBRATED], [7], ["A"], lambda p, s, c: JAMMED)
    # a refinement batch: its point 0 is another point than the design's point 0; one of its runs jammed
    _run(store, "discovery-knob", "refine/1", [{**CALIBRATED, "knob": 5.0}], [0, 1], ["A"],
         lambda p, s, c: JAMMED if s == 1 else {"shear_angle_deg": 35.0, "mass_flow_rate_full_kg_s": 14.0})
    _run(store, "discovery-knob", "held-out/B/1", [{**CALIBRATED, "knob": 2.0}], [0], ["B"], lambda p, s, c: JAMMED)
    status = discovery_status(path, measured, KPIS)
    assert status.baseline_jammed == {"A": 1}
    assert status.baseline == before.baseline and status.noise == before.noise  # the jammed runs change nothing
    spans = {(d.candidate, d.condition): d for d in status.designs}
    a = spans[("knob", "A")]
    assert a.jammed == 1 and a.runs == 3  # design points 1 and 3 (one run each) and the refined point 5 (one)
    assert a.spans["shear_angle_deg"] == (31.0, 35.0) and a.spans["mass_flow_rate_full_kg_s"] == (10.0, 14.0)
    held = {(h.candidate, h.condition): h for h in status.held_out}
    assert held[("knob", "B")].runs == 0 and held[("knob", "B")].jammed == 1
    assert held[("knob", "B")].parameters == {"knob": 2.0}
    assert all(not math.isfinite(c.z) for c in held[("knob", "B")].cells)
    text = format_status(status, measured)
    assert "| A | 3 (+1 jammed) |" in text and "calibrated set whose discharge jammed, left out: A 1" in text


def test_the_design_plane_recovers_each_parameters_slope(tmp_path):
    """Five design points on two knobs: the shear angle is a known plane plus a residual; the flow is
    measured at three points only, one fewer than a plane of two knobs and an intercept needs."""
    path = _store(tmp_path)
    store = CampaignStore(path, "hash", extra_stages=discovery_stages(["two"]))
    knobs = [(0.1, 0.9), (0.4, 0.2), (0.6, 0.7), (0.9, 0.4), (0.3, 0.5)]
    residual = [0.3, -0.2, 0.0, -0.4, 0.3]
    design = [{**CALIBRATED, "a": a, "b": b} for a, b in knobs]
    shear = {(a, b): 35.0 + 2.0 * a - 4.0 * b + r for (a, b), r in zip(knobs, residual)}
    _run(store, "discovery-two", "lhs/2", design, [0], ["A"],
         lambda p, s, c: {"shear_angle_deg": shear[(p["a"], p["b"])],
                          "mass_flow_rate_full_kg_s": 10.0 if p["a"] < 0.5 else math.nan})
    status = discovery_status(path, _measured(), KPIS)
    (d,) = [d for d in status.designs if d.candidate == "two"]
    X = np.array([[1.0, a, b] for a, b in knobs])
    y = np.array([shear[k] for k in knobs])
    inverse = np.linalg.inv(X.T @ X)  # the normal equations, by hand
    beta = inverse @ X.T @ y
    s2 = float(((y - X @ beta) ** 2).sum()) / (len(y) - 3)
    assert set(d.slopes) == {"shear_angle_deg"}  # the flow's 3 points leave no degree of freedom
    for i, name in enumerate(("a", "b"), start=1):
        slope, se = d.slopes["shear_angle_deg"][name]
        assert slope == pytest.approx(beta[i], rel=1e-10) and se == pytest.approx(math.sqrt(s2 * inverse[i, i]), rel=1e-8)
    assert d.plane_sd["shear_angle_deg"] == pytest.approx(math.sqrt(s2), rel=1e-10)
    assert abs(d.slopes["shear_angle_deg"]["a"][0] - 2.0) < 3 * d.slopes["shear_angle_deg"]["a"][1]
    # the knob store's designs have two points: no plane, and mu_s_pp, the same at every point, is no slope
    assert all(not k.slopes for k in status.designs if k.candidate == "knob")
    text = format_status(status, _measured())
    slope_a, se_a = d.slopes["shear_angle_deg"]["a"]
    assert f"| A | a | {slope_a:+.3g} ({se_a:.2g}) | - |" in text and "| A | residual sd |" in text


def test_script_prints_the_status_and_names_a_missing_store(tmp_path):
    path = _store(tmp_path)
    data = tmp_path / "lab.json"
    _measured().save(data)
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "discovery_status.py"), str(path), "--data", str(data),
                           "--kpis", *KPIS], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "### knob" in proc.stdout and "calibrated set's chi^2" in proc.stdout
    missing = subprocess.run([sys.executable, str(REPO / "scripts" / "discovery_status.py"), str(tmp_path / "no.sqlite")],
                             capture_output=True, text=True, timeout=120)
    assert missing.returncode != 0 and "no.sqlite" in missing.stderr and "does not exist" in missing.stderr
