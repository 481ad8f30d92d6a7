"""The discrepancy test of discovery is calibrated: under the null its p-values are uniform.

Simulated null studies (no DEM: the known answer is built in): 4 conditions x 4 KPIs, a lab that
repeats every test n = 5 times and reports Student-t 95 % half-widths (as labs and the twin data
do), a DEM run 3 times per cell with its scatter pooled over the 4 conditions (8 degrees of
freedom per KPI), lab and DEM means equal. 600 studies.

- The calibrated test (u = ci95 / t(0.975, 4), each z mapped through its Welch-Satterthwaite
  Student-t to a chi^2_1 value): a Kolmogorov-Smirnov test does not reject uniform p-values
  (p > 0.01), and the false-alarm rate at alpha = 0.05 lies within 0.05 +- 3 binomial standard
  errors.
- The old test (u = ci95 / 1.96, z taken as normal) is not uniform on the same studies (KS
  p < 1e-3): the lab variance it assumes is 2x too large while the estimated variances' heavy
  tails go unmodelled.
- The measured-data format carries the number of lab repeats; ``standard_uncertainty`` follows it.
"""
import dataclasses
import math

import numpy as np
import pytest
from scipy import stats

from bo.discovery.verdict import chi2_equivalent, discrepancy_of, welch_dof
from bo.discovery.replicate_noise import ReplicateNoise
from torchdem.measured import MeasuredDataError, load_measured

CONDITIONS = ["a", "b", "c", "d"]
KPIS = ["k1", "k2", "k3", "k4"]
LAB_N, DEM_R = 5, 3


def _null_study(rng):
    truth = rng.uniform(5, 50, size=(4, 4))
    lab_sd = rng.uniform(0.5, 2.0, size=(4, 4))
    dem_sd = rng.uniform(0.5, 2.0, size=4)  # a property of the KPI, the same in every condition
    lab_x = truth[..., None] + lab_sd[..., None] * rng.standard_normal((4, 4, LAB_N))
    lab_mean = lab_x.mean(-1)
    half = stats.t.ppf(0.975, LAB_N - 1) * lab_x.std(-1, ddof=1) / math.sqrt(LAB_N)
    reps = truth[:, None, :] + dem_sd[None, None, :] * rng.standard_normal((4, DEM_R, 4))  # [C, r, K]
    return lab_mean, half, reps


def _p_values(n_studies=600, seed=11):
    rng = np.random.default_rng(seed)
    new, old, old_chi2 = [], [], []
    for _ in range(n_studies):
        lab_mean, half, reps = _null_study(rng)
        noise = ReplicateNoise.of(KPIS, [reps])
        t975 = stats.t.ppf(0.975, LAB_N - 1)
        lab = {(c, k): (lab_mean[i, j], half[i, j] / t975, LAB_N - 1.0)
               for i, c in enumerate(CONDITIONS) for j, k in enumerate(KPIS)}
        new.append(discrepancy_of(reps, CONDITIONS, KPIS, lab, noise, 0.05).p_value)
        lab_old = {key: (m, half[CONDITIONS.index(key[0]), KPIS.index(key[1])] / 1.96, math.inf)
                   for key, (m, _, _) in lab.items()}
        d_old = discrepancy_of(reps, CONDITIONS, KPIS, lab_old, noise, 0.05)
        old.append(float(stats.chi2.sf(d_old.chi2, d_old.dof)))
        old_chi2.append(d_old.chi2)
    return np.array(new), np.array(old), np.array(old_chi2)


@pytest.fixture(scope="module")
def p_values():
    return _p_values()


def test_calibrated_p_values_are_uniform_under_the_null(p_values):
    new, _, _ = p_values
    assert stats.kstest(new, "uniform").pvalue > 0.01
    rate = float((new < 0.05).mean())
    assert abs(rate - 0.05) < 3 * math.sqrt(0.05 * 0.95 / new.size), rate


def test_the_large_sample_reading_of_t_half_widths_is_miscalibrated(p_values):
    _, old, _ = p_values
    assert stats.kstest(old, "uniform").pvalue < 1e-3


def test_welch_dof_and_chi2_equivalent():
    assert welch_dof(1.0, 8, 0.0, 4) == pytest.approx(8)
    assert welch_dof(0.0, 8, 1.0, 4) == pytest.approx(4)
    assert welch_dof(1.0, 10, 1.0, 10) == pytest.approx(20)
    assert welch_dof(1.0, math.inf, 1.0, math.inf) == math.inf
    assert chi2_equivalent(2.0, math.inf) == pytest.approx(4.0)
    # a t of 4 dof at its 97.5 % point maps to the normal's 97.5 % point
    assert chi2_equivalent(stats.t.ppf(0.975, 4), 4) == pytest.approx(1.959964 ** 2, rel=1e-5)


def test_measured_data_carry_lab_repeats():
    data = load_measured("torchdem/data/mini_box_twin.json")
    c = data.condition(data.names[0])
    assert c.replicates == 5
    u, dof = c.standard_uncertainty("angle_of_repose_deg")
    assert dof == 4 and u == pytest.approx(c.kpis["angle_of_repose_deg"].ci95 / stats.t.ppf(0.975, 4))
    paper = load_measured(None).condition("50-50")
    assert paper.replicates is None
    assert paper.standard_uncertainty("angle_of_repose_deg") == (pytest.approx(0.48 / 1.959964), math.inf)
    assert dataclasses.replace(paper, replicates=3).to_dict()["replicates"] == 3
    with pytest.raises(MeasuredDataError, match="replicates"):
        dataclasses.replace(paper, replicates=1)
