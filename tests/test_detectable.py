"""The smallest detectable effect and what to measure next (bo/discovery/detectable.py), against
answers computed directly:

- one cell, shift a t: the chi^2_1 test is |Z + sqrt(lambda)| > 1.96, so the power is
  Phi(sqrt(lambda) - 1.96) + Phi(-sqrt(lambda) - 1.96), and 80 % needs sqrt(lambda) = 2.8016;
  the smallest t is 2.8016 sigma / a;
- the known-answer model (tests/_calibration_model.py) is linear in the density factor, so its
  flow-rate shift is exact in t and the smallest detectable density change follows from the
  non-centrality lambda* of 80 % power: t* = sqrt(lambda* / sum (slope / sigma)^2);
- doubling the lab repeats or the DEM replicates, or adding a KPI, raises the power, and the
  ranking puts the largest gain first.
"""
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize, stats

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _calibration_model as km  # noqa: E402

from bo.discovery.detectable import (CellUncertainty, detection_power, distinguishing_power, smallest_detectable,
                                    what_separates, what_to_measure_next)
from torchdem.errors import ConfigError


def test_one_cell_power_and_smallest_effect_match_the_normal_formula():
    sigma, a = 0.5, 3.0
    for t in (0.1, 0.3, 0.6):
        root = a * t / sigma
        expected = stats.norm.cdf(root - 1.959964) + stats.norm.cdf(-root - 1.959964)
        assert detection_power([a * t], [sigma]) == pytest.approx(expected, rel=1e-6)
    root80 = optimize.brentq(lambda r: stats.norm.cdf(r - 1.959964) + stats.norm.cdf(-r - 1.959964) - 0.8, 0, 10)
    assert root80 == pytest.approx(2.8016, abs=1e-3)
    assert smallest_detectable(lambda t: [a * t], [sigma]) == pytest.approx(root80 * sigma / a, rel=1e-4)
    assert smallest_detectable(lambda t: [0.1 * t], [sigma]) is None  # never reaches 80 % within [0, 1]
    assert detection_power([0.0], [sigma]) == pytest.approx(0.05)


def _density_shift(t):
    """Known model: flow and mass shifts of particles (1 - 0.3 t) x nominal density, per condition."""
    out = {}
    for c in ("50-50", "75-25", "25-75"):
        base = km.known_kpis(km.TRUE, 0, c, noise=False)
        rho = {f"density_{m}": (1 - 0.3 * t) * v for m, v in km.NOMINAL_DENSITY.items()}
        now = km.known_kpis({**km.TRUE, **rho}, 0, c, noise=False)
        for k in ("mass_flow_rate_full_kg_s", "max_heap_height_m", "angle_of_repose_deg"):
            out[(c, k)] = now[k] - base[k]
    return out


def test_smallest_detectable_density_change_on_the_known_model():
    cells = [CellUncertainty(c, "mass_flow_rate_full_kg_s", se=0.05, u=0.12, dem_replicates=3, lab_repeats=5)
             for c in ("50-50", "75-25", "25-75")]
    keys = [(c.condition, c.kpi) for c in cells]
    sigma = np.array([c.sigma for c in cells])
    slope = np.array([_density_shift(1.0)[k] for k in keys])  # linear in t
    np.testing.assert_allclose([_density_shift(0.5)[k] for k in keys], 0.5 * slope, rtol=1e-9)
    critical = stats.chi2.isf(0.05, 3)
    lam = optimize.brentq(lambda x: stats.ncx2.sf(critical, 3, x) - 0.8, 1e-6, 100)
    expected = math.sqrt(lam / np.sum((slope / sigma) ** 2))
    got = smallest_detectable(lambda t: [_density_shift(t)[k] for k in keys], sigma)
    assert got == pytest.approx(expected, rel=1e-4)
    # the angle of repose does not see density in this model: no KPI of it adds power
    ranked = what_to_measure_next(cells, _density_shift, reference=0.05,
                                  new_kpis={"max_heap_height_m": (0.0005, 0.001), "angle_of_repose_deg": (0.1, 0.3)})
    names = [a.name for a in ranked]
    power = {a.name: a.power for a in ranked}
    assert names[-1] in ("as is", "kpi:angle_of_repose_deg")
    assert power["lab_repeats"] > power["as is"] and power["dem_replicates"] > power["as is"]
    assert power["kpi:max_heap_height_m"] > power["as is"]
    assert power["kpi:angle_of_repose_deg"] < power["as is"]  # a dead cell only adds degrees of freedom
    assert [a.power for a in ranked] == sorted((a.power for a in ranked), reverse=True)
    smallest = {a.name: a.smallest for a in ranked}
    assert smallest["as is"] == pytest.approx(expected, rel=1e-4)
    assert smallest["lab_repeats"] < smallest["as is"]


def test_detectability_from_store_script_against_a_direct_computation(tmp_path):
    """scripts/detectability_from_store.py on a store of two parameter sets (3 runs each, known
    KPI values, one unmeasured KPI in one run) prints the shift, the pooled replicate sd and the
    power that detection_power gives for them with Table 2's 50-50 uncertainties."""
    import json
    import sqlite3
    import subprocess

    from torchdem.measured import load_measured

    kpis = ["angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg"]
    null = np.array([[29.0, 40.0, 10.0, 32.0], [29.5, 41.0, 10.2, 32.2], [30.0, 42.0, 10.4, 32.4]])
    effect = null + np.array([0.0, -3.0, 0.4, 0.6])
    store = tmp_path / "two_sets.sqlite"
    con = sqlite3.connect(store)
    con.execute("CREATE TABLE evaluations (params TEXT, kpis TEXT, status TEXT, condition TEXT)")
    cond = "50-50|mirror=True|slice_depth=0.1"
    for value, rows in ((0.9, null), (0.3, effect)):
        for r in rows:
            con.execute("INSERT INTO evaluations VALUES (?, ?, 'done', ?)",
                        (json.dumps({"mu_s_pg": value}), json.dumps(dict(zip(kpis, r.tolist()))), cond))
    con.execute("INSERT INTO evaluations VALUES (?, ?, 'done', ?)",  # the heap edge not measured: left out
                (json.dumps({"mu_s_pg": 0.3}), json.dumps({**dict(zip(kpis, [math.nan] * 4)), "angle_of_repose_deg": None}),
                 cond))
    con.execute("INSERT INTO evaluations VALUES (?, ?, 'failed', ?)", (json.dumps({"mu_s_pg": 0.3}), "{}", cond))
    con.commit()
    script = Path(__file__).resolve().parents[1] / "scripts" / "detectability_from_store.py"
    out = subprocess.run([sys.executable, str(script), "--store", str(store), "--condition", cond, "--parameter",
                          "mu_s_pg", "--null", "0.9", "--effect", "0.3", "--dem-replicates", "3"],
                         capture_output=True, text=True, check=True).stdout
    c = load_measured("hadi2025_pellet_sinter.json").condition("50-50")
    u = np.array([c.standard_uncertainty(k)[0] for k in
                  ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s", "mass_lower_box_kg")])
    sd = null.std(0, ddof=1)  # both sets have the same scatter
    shift = np.array([0.0, -3.0, 0.4, 0.6])
    power = detection_power(shift, np.sqrt(sd ** 2 / 3 + u ** 2))
    assert f"power {power:.3f}" in out
    assert "shift   -3.000" in out and f"DEM replicate sd {sd[1]:6.3f}" in out


def test_detectability_from_store_script_compares_the_shift_of_two_geometries(tmp_path):
    """With two conditions the script prints, per KPI, the second geometry's shift against the
    first's: their ratio where the first stands out of its noise, and their difference in
    standard errors of the two shifts."""
    import json
    import sqlite3
    import subprocess

    kpis = ["angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg"]
    null = np.array([[29.0, 40.0, 10.0, 32.0], [29.5, 41.0, 10.2, 32.2], [30.0, 42.0, 10.4, 32.4]])
    shifts = {"50-50|mirror=True|slice_depth=0.1": np.array([0.0, -4.0, 0.5, 0.6]),
              "50-50|mirror=False|slice_depth=0.04": np.array([0.3, -6.0, 0.5, 1.8])}
    store = tmp_path / "geometries.sqlite"
    con = sqlite3.connect(store)
    con.execute("CREATE TABLE evaluations (params TEXT, kpis TEXT, status TEXT, condition TEXT)")
    for cond, shift in shifts.items():
        for value, rows in ((0.0, null), (13333.0, null + shift)):
            for r in rows:
                con.execute("INSERT INTO evaluations VALUES (?, ?, 'done', ?)",
                            (json.dumps({"coh_pp": value}), json.dumps(dict(zip(kpis, r.tolist()))), cond))
    con.commit()
    script = Path(__file__).resolve().parents[1] / "scripts" / "detectability_from_store.py"
    out = subprocess.run([sys.executable, str(script), "--store", str(store), "--condition", *shifts,
                          "--parameter", "coh_pp", "--null", "0", "--effect", "13333"],
                         capture_output=True, text=True, check=True).stdout
    se = null.std(0, ddof=1) * math.sqrt(2 / 3)  # each shift's standard error: equal scatter, 3 + 3 runs
    lines = {line.split()[0]: line for line in out.split("against 50-50|mirror=True|slice_depth=0.1:")[1].splitlines()
             if line.strip()}
    assert "ratio      -," in lines["angle_of_repose_deg"]  # no ratio: the reference shift is 0
    assert "ratio  +1.50," in lines["shear_angle_deg"]
    assert f"difference {-2.0 / math.hypot(se[1], se[1]):+5.1f} se" in lines["shear_angle_deg"]
    assert "ratio  +1.00, difference  +0.0 se" in lines["mass_flow_rate_full_kg_s"]
    assert f"ratio  +3.00, difference {1.2 / math.hypot(se[3], se[3]):+5.1f} se" in lines["mass_lower_box_full_kg"]


def test_distinguishing_power_against_closed_forms():
    """Two cells of sigma 1. A mechanism along the other's direction (any sign or size) cannot be
    told from it: power alpha. Orthogonal shifts: the whole true shift is lack of fit, lambda =
    |a|^2 on one degree of freedom, whose power is P(|Z + sqrt(lambda)| > z_{0.975}). At 45 degrees
    half of |a|^2 remains."""
    sigma = [1.0, 1.0]
    assert distinguishing_power([3.0, 1.0], [-6.0, -2.0], sigma) == pytest.approx(0.05)
    z = stats.norm.isf(0.025)
    for lam in (1.0, 4.0, 9.0):
        expected = stats.norm.sf(z - math.sqrt(lam)) + stats.norm.cdf(-z - math.sqrt(lam))
        assert distinguishing_power([math.sqrt(lam), 0.0], [0.0, 5.0], sigma) == pytest.approx(expected, rel=1e-6)
    half = stats.ncx2.sf(stats.chi2.isf(0.05, 1), 1, 8.0)
    assert distinguishing_power([4.0, 0.0], [1.0, 1.0], sigma) == pytest.approx(half, rel=1e-6)
    # sigma weighs the cells: a difference in a precise cell counts more than the same in a noisy one
    assert distinguishing_power([1.0, 2.0], [1.0, 0.0], [1.0, 0.5]) > distinguishing_power([2.0, 1.0], [0.0, 1.0],
                                                                                          [1.0, 0.5])
    with pytest.raises(ConfigError, match="distinguishing_power"):
        distinguishing_power([1.0], [1.0], [1.0])


def test_detectability_from_store_script_sets_another_mechanism_beside_and_picks_the_closest_null(tmp_path):
    """A store of three sets: the reference, cohesion, and a lower wall friction that also sits at
    coh_pp = 0. The cohesion shift is taken against the reference (the null set closest to the
    cohesion set), and a wall-friction shift along the same line (twice as large, opposite sign)
    cannot be told from it: cosine -1, power alpha. One along another line can."""
    import json
    import sqlite3
    import subprocess

    kpis = ["angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg"]
    base = np.array([[29.0, 40.0, 10.0, 32.0], [29.5, 41.0, 10.2, 32.2], [30.0, 42.0, 10.4, 32.4]])
    cohesion = np.array([0.8, 3.0, -0.2, -0.5])
    cond = "50-50|mirror=True|slice_depth=0.1"
    script = Path(__file__).resolve().parents[1] / "scripts" / "detectability_from_store.py"

    def run(wall_shift):
        store = tmp_path / f"mechanisms{wall_shift[0]}.sqlite"
        con = sqlite3.connect(store)
        con.execute("CREATE TABLE evaluations (params TEXT, kpis TEXT, status TEXT, condition TEXT)")
        for params, rows in (({"coh_pp": 0.0, "mu_s_pg": 0.9}, base), ({"coh_pp": 13333.0, "mu_s_pg": 0.9}, base + cohesion),
                             ({"coh_pp": 0.0, "mu_s_pg": 0.3}, base + wall_shift)):
            for r in rows:
                con.execute("INSERT INTO evaluations VALUES (?, ?, 'done', ?)",
                            (json.dumps(params), json.dumps(dict(zip(kpis, r.tolist()))), cond))
        con.commit()
        return subprocess.run([sys.executable, str(script), "--store", str(store), "--condition", cond, "--parameter",
                               "coh_pp", "--null", "0", "--effect", "13333", "--dem-replicates", "3",
                               "--versus", "mu_s_pg", "0.9", "0.3"], capture_output=True, text=True, check=True).stdout

    out = run(-2.0 * cohesion)
    assert "(3 and 3 runs)" in out and "shift   +3.000" in out  # against the reference set, not the wall set
    assert "cosine of the two shifts in units of sigma -1.000; power to reject it at its best magnitude 0.050" in out
    out = run(np.array([0.0, -3.0, 0.6, 0.7]))
    power = float(out.rsplit("best magnitude ", 1)[1].split()[0])
    from torchdem.measured import load_measured
    c = load_measured("hadi2025_pellet_sinter.json").condition("50-50")
    u = np.array([c.standard_uncertainty(k)[0] for k in
                  ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s", "mass_lower_box_kg")])
    sigma = np.sqrt(base.std(0, ddof=1) ** 2 / 3 + u ** 2)
    assert power == pytest.approx(distinguishing_power(cohesion, [0.0, -3.0, 0.6, 0.7], sigma), abs=6e-4)


def test_distinguishing_power_against_a_rival_of_several_bounded_directions():
    """Three cells of sigma 1. A rival free along e1 and e2 absorbs those components of the true
    shift (3, 4, 2): the lack of fit is the third, lambda = 4 on 3 - 2 = 1 degree of freedom. Held
    to magnitudes in [0, 1], it can absorb only 1 of the 3 along e1: lambda = 2^2 + 2^2 = 8. A rival
    with as many free directions as cells leaves no degree of freedom: power alpha."""
    sigma = [1.0, 1.0, 1.0]
    power = lambda lam, dof: stats.ncx2.sf(stats.chi2.isf(0.05, dof), dof, lam)  # noqa: E731
    rival = [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]
    assert distinguishing_power([3.0, 4.0, 2.0], rival, sigma) == pytest.approx(power(4.0, 1), rel=1e-6)
    bounded = distinguishing_power([3.0, 4.0, 2.0], rival, sigma, bounds=[(0.0, 1.0), (0.0, 2.0)])
    assert bounded == pytest.approx(power(8.0, 1), rel=1e-5)
    # a direction the rival cannot take with the sign it needs: the whole component stays
    assert distinguishing_power([-3.0, 0.0, 0.0], [[1.0, 0.0, 0.0]], sigma, bounds=[(0.0, 1.0)]) \
        == pytest.approx(power(9.0, 2), rel=1e-5)
    # a rival that does not move the cells (all-zero direction) keeps every degree of freedom
    assert distinguishing_power([2.0, 0.0, 0.0], [[0.0, 0.0, 0.0]], sigma) == pytest.approx(power(4.0, 3), rel=1e-6)
    assert distinguishing_power([3.0, 4.0, 2.0], np.eye(3), sigma) == pytest.approx(0.05)
    with pytest.raises(ConfigError, match="one \\(low <= high\\) bound per direction"):
        distinguishing_power([3.0, 4.0, 2.0], rival, sigma, bounds=[(0.0, 1.0)])


def test_what_separates_ranks_the_addition_that_tells_two_mechanisms_apart():
    """Two mechanisms that move the flow rate alike on two conditions; only the mechanism under
    test moves a KPI the lab does not report (the heap height). As they are, the cells cannot tell
    the two apart (power alpha); the heap height can: the rival absorbs the flow cells (c = t / 2,
    inside its range) and leaves the two heap cells, lambda = 2 (h t / s)^2 on 4 - 1 = 3 degrees of
    freedom. More replicates of the same cells change nothing."""
    cells = [CellUncertainty(c, "flow", se=0.05, u=0.1, dem_replicates=3, lab_repeats=5) for c in ("A", "B")]

    def shift(t):
        return {("A", "flow"): -0.5 * t, ("B", "flow"): -0.3 * t, ("A", "heap"): 0.004 * t, ("B", "heap"): 0.004 * t}

    rival = [{("A", "flow"): -1.0, ("B", "flow"): -0.6, ("A", "heap"): 0.0, ("B", "heap"): 0.0}]
    ranked = what_separates(cells, shift, rival, [(0.0, 1.0)], new_kpis={"heap": (0.001, 0.001)})
    by = {a.name: a for a in ranked}
    assert ranked[0].name == "kpi:heap"
    for name in ("as is", "lab_repeats", "dem_replicates"):
        assert by[name].power == pytest.approx(0.05) and by[name].smallest is None
    sigma = [c.sigma for c in cells] + [math.hypot(0.001, 0.001)] * 2
    direct = lambda t: distinguishing_power([-0.5 * t, -0.3 * t, 0.004 * t, 0.004 * t],  # noqa: E731
                                            [[-1.0, -0.6, 0.0, 0.0]], sigma, bounds=[(0.0, 1.0)])
    assert by["kpi:heap"].power == pytest.approx(direct(1.0), rel=1e-6)
    lam = 2 * (0.004 / math.hypot(0.001, 0.001)) ** 2
    assert direct(1.0) == pytest.approx(stats.ncx2.sf(stats.chi2.isf(0.05, 3), 3, lam), rel=1e-5)
    t80 = optimize.brentq(lambda t: direct(t) - 0.8, 1e-3, 1.0)
    assert by["kpi:heap"].smallest == pytest.approx(t80, rel=1e-4)
    # a rival that does not predict the new KPI drops that addition rather than guess it
    partial = what_separates(cells, shift, [{("A", "flow"): -1.0, ("B", "flow"): -0.6}], [(0.0, 1.0)],
                             new_kpis={"heap": (0.001, 0.001)})
    assert "kpi:heap" not in {a.name for a in partial}
