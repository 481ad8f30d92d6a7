"""Tests for bo/report/plots.py: the figures carry the analysis numbers, and the PNG files are real
images of the expected size.

The data drawn are checked on the returned ``Figure`` objects (error-bar heights, bar heights,
band limits), so a figure that looks plausible but plots the wrong numbers fails.
"""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from bo.design.dsd import definitive_screening_design, paper_parameter_table
from bo.report.plots import (
    screening_vs_measured_figure,
    time_step_figure,
    variance_shares_figure,
    write_screening_vs_measured_plot,
    write_time_step_plot,
    write_variance_shares_plot,
)
from bo.screening.stepwise import ScreeningResults
from bo.studies.timestep import choose_time_step
from bo.screening.variance import decompose_variance
from torchdem.errors import ConfigError
from torchdem.measured import load_measured

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DPI = 40  # small images keep the test fast; the size check uses the same value
KPIS = ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_kg_s")
MEASURED = load_measured().condition("50-50").kpis


@pytest.fixture(scope="module")
def time_step_choice():
    rng = np.random.default_rng(0)
    values = np.array([30.0, 42.0, 10.3]) + rng.normal(0, 0.2, (4, 5, 3))
    return choose_time_step((0.05, 0.1, 0.15, 0.2), values, KPIS)


@pytest.fixture(scope="module")
def decomposition():
    rng = np.random.default_rng(1)
    values = rng.normal(size=(29, 5, 2)) + rng.normal(size=(29, 1, 2)) * [3.0, 0.3]
    return decompose_variance(values, ["mass_lower_box_kg", "segregation_rsd_vertical"])


@pytest.fixture(scope="module")
def screening():
    coded = definitive_screening_design(12, 2)
    rng = np.random.default_rng(2)
    values = np.array([29.0, 38.0, 11.0]) + coded[:, :3, None].transpose(0, 2, 1) \
        + rng.normal(0, 0.3, (29, 4, 3))
    return ScreeningResults.from_parameter_table(paper_parameter_table(), coded, (1, 2, 3, 4),
                                                 KPIS, values)


def check_png(path, figure_size_in, dpi=DPI):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    image = imread(path)
    # constrained layout keeps the canvas size: pixels = inches x dpi
    assert image.shape[:2] == (round(figure_size_in[1] * dpi), round(figure_size_in[0] * dpi))
    assert image[..., :3].std() > 0.05  # not a blank canvas


def test_time_step_figure_shows_mean_and_std(time_step_choice, tmp_path):
    fig = time_step_figure(time_step_choice)
    assert len(fig.axes) == 3
    for j, ax in enumerate(fig.axes):
        assert ax.get_ylabel() == KPIS[j]
        container = ax.containers[0]
        x, y = container.lines[0].get_data()
        np.testing.assert_allclose(x, [5, 10, 15, 20])
        np.testing.assert_allclose(y, time_step_choice.mean[:, j])
        segments = container.lines[2][0].get_segments()
        np.testing.assert_allclose([s[1, 1] - s[0, 1] for s in segments],
                                   2 * time_step_choice.std[:, j])
        chosen = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert chosen[0].get_xdata()[0] == pytest.approx(100 * time_step_choice.chosen_fraction)
    path = write_time_step_plot(time_step_choice, tmp_path / "fig9.png", dpi=DPI)
    check_png(path, fig.get_size_inches())


def test_variance_figure_stacks_the_shares(decomposition, tmp_path):
    fig = variance_shares_figure(decomposition)
    (ax,) = fig.axes
    parameter_bars, stochastic_bars = ax.containers
    np.testing.assert_allclose([b.get_height() for b in parameter_bars],
                               decomposition.parameter_percent)
    np.testing.assert_allclose([b.get_height() for b in stochastic_bars],
                               decomposition.stochastic_percent)
    np.testing.assert_allclose([b.get_y() for b in stochastic_bars],
                               decomposition.parameter_percent)
    labels = [t.get_text() for t in ax.get_xticklabels()]
    assert labels == ["mass_lower_box_kg", "segregation_rsd_vertical\n(excluded)"]
    path = write_variance_shares_plot(decomposition, tmp_path / "fig10.png", dpi=DPI)
    check_png(path, fig.get_size_inches())


def test_screening_figure_shows_runs_and_measured_band(screening, tmp_path):
    fig = screening_vs_measured_figure(screening, MEASURED)
    assert len(fig.axes) == 3
    for j, ax in enumerate(fig.axes):
        kpi = KPIS[j]
        replicates, means, measured_line = ax.get_lines()
        assert replicates.get_ydata().size == 29 * 4
        np.testing.assert_allclose(means.get_ydata(), screening.run_means(kpi))
        assert measured_line.get_ydata()[0] == MEASURED[kpi].mean
        (band,) = ax.patches
        corners = band.get_transform().transform(band.get_path().vertices)
        data_y = ax.transData.inverted().transform(corners)[:, 1]
        assert data_y.min() == pytest.approx(MEASURED[kpi].mean - MEASURED[kpi].ci95)
        assert data_y.max() == pytest.approx(MEASURED[kpi].mean + MEASURED[kpi].ci95)
    path = write_screening_vs_measured_plot(screening, MEASURED, tmp_path / "fig11.png", dpi=DPI)
    check_png(path, fig.get_size_inches())


def test_bad_paths_and_kpis_are_rejected(decomposition, screening, tmp_path):
    with pytest.raises(ConfigError, match=r"path = '.*fig10.jpg' is not allowed; expected .*\.png"):
        write_variance_shares_plot(decomposition, tmp_path / "fig10.jpg")
    with pytest.raises(ConfigError, match="does not exist"):
        write_variance_shares_plot(decomposition, tmp_path / "missing" / "fig10.png")
    with pytest.raises(ConfigError, match=r"KPIs \['flow'\] are not allowed"):
        screening_vs_measured_figure(screening, MEASURED, kpis=["flow"])
    no_flow = {k: v for k, v in MEASURED.items() if k != "mass_flow_rate_kg_s"}
    with pytest.raises(ConfigError, match="measured data lack KPI 'mass_flow_rate_kg_s'"):
        screening_vs_measured_figure(screening, no_flow, kpis=KPIS)
