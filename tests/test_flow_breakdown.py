"""The model's breakdown of the draw-down flow (``torchdem.drawdown.flow_breakdown``), against
analytic load-cell records.

An upper box emptying as m(t) = M - a t - b t^2 / 2 flows at a + b t. The least-squares slope of a
quadratic sampled uniformly is its derivative at the centre of the samples in the window, and a Gaussian
filter (symmetric kernel) adds only a constant to a quadratic away from the record's ends, so the
rate over a window is a + b c exactly, c the mean time of its samples (to round-off; the 0.5-2.0 s window is > 3 filter
widths from both ends of a 0-4 s record).
"""
import numpy as np
import pytest

from kpi.loadcell import DischargeConfig
from torchdem.drawdown import FLOW_BREAKDOWN_KPIS, KPI_UNITS, flow_breakdown

T = np.arange(0.0, 4.0 + 1e-9, 0.02)  # 50 Hz


def emptying(mass: float, a: float, b: float) -> np.ndarray:
    return mass - a * T - 0.5 * b * T ** 2


def test_each_material_and_each_half_window_flow_at_their_analytic_rates():
    pellets = emptying(20.0, 4.0, 0.8)   # 4 + 0.8 t kg/s: the pellets speed up
    sinter = emptying(20.0, 6.0, -0.4)   # 6 - 0.4 t kg/s: the sinter slows
    got = flow_breakdown(T, pellets + sinter, pellets, DischargeConfig(), scale=2.0)
    assert set(got) == set(FLOW_BREAKDOWN_KPIS) and set(got) <= set(KPI_UNITS)
    def centre(t1, t2):  # 1.25 s is not a sample time: 0.5-1.25 s has its samples 0.50 .. 1.24 s
        return T[(T >= t1 - 1e-9) & (T <= t2 + 1e-9)].mean()

    centre, early, late = centre(0.5, 2.0), centre(0.5, 1.25), centre(1.25, 2.0)
    assert (centre, early, late) == pytest.approx((1.25, 0.87, 1.63))
    assert got["mass_flow_rate_pellet_full_kg_s"] == pytest.approx(2 * (4.0 + 0.8 * centre), rel=1e-9)
    assert got["mass_flow_rate_sinter_full_kg_s"] == pytest.approx(2 * (6.0 - 0.4 * centre), rel=1e-9)
    assert got["mass_flow_rate_early_full_kg_s"] == pytest.approx(2 * (10.0 + 0.4 * early), rel=1e-9)
    assert got["mass_flow_rate_late_full_kg_s"] == pytest.approx(2 * (10.0 + 0.4 * late), rel=1e-9)


def test_a_record_without_the_pellet_trace_gives_no_breakdown():
    total = emptying(40.0, 10.0, 0.0)
    pellets = np.full_like(T, np.nan)  # resumed from a checkpoint written before the trace was kept
    assert flow_breakdown(T, total, pellets, DischargeConfig()) == {}


def test_a_half_window_with_too_few_samples_is_left_out_and_the_rest_is_kept():
    coarse = np.arange(0.0, 1.0 + 1e-9, 0.1)  # 10 Hz, window 0.3-0.6 s: 4 samples, 2 in the early half
    pellets, sinter = 20.0 - 4.0 * coarse, 20.0 - 6.0 * coarse
    got = flow_breakdown(coarse, pellets + sinter, pellets, DischargeConfig(filter_sigma_s=0.0, fit_window_s=(0.3, 0.6)))
    assert "mass_flow_rate_early_full_kg_s" not in got
    assert got["mass_flow_rate_pellet_full_kg_s"] == pytest.approx(4.0)
    assert got["mass_flow_rate_sinter_full_kg_s"] == pytest.approx(6.0)
