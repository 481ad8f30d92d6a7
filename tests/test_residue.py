"""The upper box's residue per unit slope (bo/discovery/residue.py, scripts/residue_check.py).

- Analytic: straight wedges of bulk density rho_b on the ledges a = (W - b) / 2 of a box of depth L
  leave rho_b a^2 L tan(theta) in the upper box, so R = (fill - lower) / tan(theta) returns
  rho_b a^2 L at every angle (rel 1e-12), and the lab's R and its first-order 95 % half-width
  are recomputed by hand from Table 2's 50-50 cell.
- Bad input names the value and its range.
- From a store written through the campaign API: R of each finished run (jammed runs left out), and
  a fit of R on the run parameters that recovers a known slope per standard deviation within
  3 standard errors, gives a parameter without effect a slope within 3 standard errors of 0, and
  leaves out a parameter set in fewer than half the runs.
"""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.campaign.executor import EvalOutcome
from bo.campaign.store import CampaignStore
from bo.discovery.residue import (format_residue, lab_residue, residue_check, residue_per_slope,
                                  wedge_residue_per_slope)
from torchdem.errors import ConfigError
from torchdem.measured import Condition, KPIValue, MeasuredData, load_measured

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("theta", [20.0, 37.85, 42.51, 60.0])
def test_straight_wedges_give_rho_a2_l_at_every_angle(theta):
    w, b, depth, rho, fill = 0.35, 0.065, 0.2, 2050.0, 40.0
    a = (w - b) / 2
    lower = fill - rho * a * a * depth * math.tan(math.radians(theta))
    expected = wedge_residue_per_slope(w, b, depth, rho)
    assert expected == pytest.approx(rho * 0.1425 ** 2 * 0.2, rel=1e-12)
    assert residue_per_slope(fill, lower, theta) == pytest.approx(expected, rel=1e-12)


def test_arrays_and_the_labs_residue_with_its_half_width():
    r = residue_per_slope(np.array([40.0, 40.0]), np.array([32.0, 30.0]), np.array([45.0, 45.0]))
    assert r == pytest.approx([8.0, 10.0], rel=1e-12)
    lab = lab_residue(load_measured())  # the paper's Table 2
    theta, d_theta, lower, d_lower = 42.51, 1.62, 32.32, 0.55
    t = math.tan(math.radians(theta))
    value = (40.0 - lower) / t
    half = math.hypot(d_lower / t, value / (t * math.cos(math.radians(theta)) ** 2) * math.radians(d_theta))
    assert lab["50-50"] == pytest.approx((value, half), rel=1e-12)
    assert set(lab) == {"50-50", "75-25", "25-75", "50-50-reverse"}


@pytest.mark.parametrize("args, word", [((40.0, 32.0, 0.0), "shear angle = 0.0 deg; expected in (0, 90)"),
                                        ((40.0, 32.0, 90.0), "shear angle"),
                                        ((40.0, 32.0, math.nan), "shear angle"),
                                        ((40.0, 41.0, 40.0),
                                         "lower box mass = 41.0 kg; expected in [0, fill mass 40.0]"),
                                        ((0.0, 0.0, 40.0), "fill mass = 0.0 kg")])
def test_bad_input_names_the_value_and_its_range(args, word):
    with pytest.raises(ConfigError, match="my.json") as err:
        residue_per_slope(*args, source="my.json")
    assert word in str(err.value)
    with pytest.raises(ConfigError, match="outlet width = 0.4 m"):
        wedge_residue_per_slope(0.35, 0.4, 0.2, 2000.0)


def _measured() -> MeasuredData:
    kpis = {"shear_angle_deg": KPIValue(45.0, 1.0, "deg"), "mass_lower_box_kg": KPIValue(32.0, 0.5, "kg")}
    return MeasuredData(source="test lab", conditions=(
        Condition(name="A", pellet_mass_fraction=0.5, layering=("pellet", "sinter"), fill_mass_kg=40.0,
                  kpis=kpis, replicates=5),))


def _store(tmp_path, n=40, slope=0.4, seed=3) -> tuple[Path, list[float]]:
    """``n`` runs at condition A whose R is 9 + slope * (density's z) + noise 0.05; ``knob`` has no
    effect; ``extra`` is set in 5 runs only; one more run jammed."""
    rng = np.random.default_rng(seed)
    density = rng.uniform(3200.0, 4000.0, n)
    knob = rng.uniform(0.0, 1.0, n)
    z = (density - density.mean()) / density.std()
    r = 9.0 + slope * z + rng.normal(0.0, 0.05, n)
    theta = rng.uniform(30.0, 44.0, n)
    lower = [40.0 - r[i] * math.tan(math.radians(theta[i])) for i in range(n)]
    path = tmp_path / "store.sqlite"
    store = CampaignStore(path, "hash")

    def run(stage, rows, extra):  # one batch of runs ``rows`` (indices; None: a run that jammed)
        points = [{"density": float(density[i]), "knob": float(knob[i]), **({"extra": 1.0 + i} if extra else {})}
                  if i is not None else {"density": 3600.0, "knob": 0.5} for i in rows]
        store.batch(stage, "b", lambda: points, seeds=[0], conditions=["A"])

        def kpis(i):
            if i is None:  # arched over the slot: nothing discharged
                return {"shear_angle_deg": 0.0, "mass_lower_box_full_kg": 0.5, "fill_mass_full_kg": 40.0,
                        "discharge_jammed": 1.0}
            return {"shear_angle_deg": float(theta[i]), "mass_lower_box_full_kg": lower[i],
                    "fill_mass_full_kg": 40.0, "discharge_jammed": 0.0}

        index = {float(density[i]): i for i in rows if i is not None}
        store.record([(t, EvalOutcome.success(kpis(index.get(t.params["density"])), 1.0))
                      for t in store.claim(100, stage=stage, batch_key="b")])

    run("screening", list(range(5)), extra=True)
    run("initial", list(range(5, n)) + [None], extra=False)
    return path, [float(v) for v in r]


def test_a_store_gives_each_runs_residue_and_the_fit_finds_what_moves_it(tmp_path):
    path, r = _store(tmp_path)
    before = path.read_bytes()
    check = residue_check([path], _measured())
    assert path.read_bytes() == before  # only read
    assert sorted(check.model("A")) == pytest.approx(sorted(r), rel=1e-9)  # the jammed run left out
    (fit,) = check.fits
    assert fit.condition == "A" and fit.runs == 40 and set(fit.slopes) == {"density", "knob"}  # not "extra"
    slope, se, _ = fit.slopes["density"]
    assert abs(slope - 0.4) < 3 * se and se < 0.02
    knob, knob_se, _ = fit.slopes["knob"]
    assert abs(knob) < 3 * knob_se
    assert fit.r2 > 0.95
    lab = (40.0 - 32.0) / math.tan(math.radians(45.0))
    assert check.ledge_factor("A") == pytest.approx(math.sqrt(lab / np.mean(r)), rel=1e-9)
    text = format_residue(check)
    assert "| A | 8.00 +- " in text and f"| 40 | {np.mean(r):.2f} (" in text
    assert f"| density | {slope:+.3f} ({se:.3f}) |" in text


def test_r_per_stage_groups_the_runs_as_stored(tmp_path):
    path, r = _store(tmp_path, n=12)
    check = residue_check([path], _measured())
    groups = check.by_stage()
    assert list(groups) == [("screening", "A"), ("initial", "A")]  # the jammed run left out of "initial"
    assert groups[("screening", "A")] == pytest.approx(r[:5], rel=1e-9)
    assert groups[("initial", "A")] == pytest.approx(r[5:], rel=1e-9)
    text = format_residue(check, by_stage=True)
    assert f"| screening | {np.mean(r[:5]):.2f} ({np.std(r[:5], ddof=1):.2f}, 5) |" in text
    assert f"| initial | {np.mean(r[5:]):.2f} ({np.std(r[5:], ddof=1):.2f}, 7) |" in text
    assert "R per stage" not in format_residue(check)
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "residue_check.py"), str(path), "--by-stage"],
                         capture_output=True, text=True, cwd=REPO, check=True).stdout
    assert "| stage | A |" in out and "| initial |" in out


def test_too_few_runs_give_no_fit(tmp_path):
    path, _ = _store(tmp_path, n=8)
    check = residue_check([path], _measured())
    assert len(check.model("A")) == 8 and check.fits == ()


def test_script_prints_the_table(tmp_path):
    path, _ = _store(tmp_path, n=12)
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "residue_check.py"), str(path)],
                         capture_output=True, text=True, cwd=REPO, check=True).stdout
    assert out.startswith("## Residue per unit slope") and "| 50-50 | 8.38 +- 0.77 | 0 |" in out
