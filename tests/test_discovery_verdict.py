"""Discovery's verdict rules on constructed scores (bo/discovery/verdict.py, step 3 of bo/discovery/pipeline.py):

- two candidates that both beat refitting the parameters and whose scores differ by less than
  the DEM noise of their difference are tied (no cause is named); a clear winner is not tied;
- a named cause reports the share of the calibrated model's chi^2 it removes on the held-out
  cells (computed by hand here), and is called partial, with the largest remaining cells, when
  the extended model still misses beyond noise;
- the fit check: a fit consistent with its cells, or one whose GP mean misses with a certain GP,
  is resolved; one that misses because the GP's own uncertainty exceeds the data's is not (the
  chi^2 quantile computed by hand).
"""
import math

import numpy as np
import pytest

import dataclasses

from scipy import stats

from bo.discovery.verdict import (Cell, Discrepancy, HypothesisScore, explained_share, fit_check,
                                  prediction_astray, tied_with)
from bo.discovery.replicate_noise import ReplicateNoise


def _cell(condition, kpi, z, se=0.2, u=0.3):
    s = math.sqrt(se ** 2 + u ** 2)
    return Cell(condition, kpi, 10.0 + z * s, se, 3, 10.0, u, z, 100 * z * s / 10.0)


def _hyp(name, score, zs, gain_sd=1.0):
    cells = tuple(_cell(c, "k", z) for c, z in zip(("a", "b", "c"), zs))
    return HypothesisScore(name, name, ("x",), {"x": (0, 1)}, 1, {c.condition: c.z ** 2 for c in cells}, {}, {},
                           0.0, score, 10, held_out_cells=cells, gain_noise_sd=gain_sd)


def test_close_candidates_are_tied_and_a_clear_winner_is_not():
    reference = _hyp("parameters", 60.0, (4.0, 4.0, 4.0))
    best = _hyp("A", 10.0, (1.0, 1.5, 1.0))
    close = _hyp("B", 12.0, (1.2, 1.5, 1.1))
    far = _hyp("C", 40.0, (3.0, 3.0, 3.0))
    assert [h.name for h in tied_with(best, [best, close, far], reference, margin=4.0)] == ["B"]
    assert tied_with(best, [best, far], reference, margin=4.0) == []
    # a rival within the margin that does not itself beat the reference is not a tie
    weak = _hyp("D", 13.0, (1.2, 1.5, 1.1), gain_sd=30.0)
    assert tied_with(best, [best, weak], reference, margin=4.0) == []


def test_explained_share_and_partial_cause():
    before = Discrepancy(cells=tuple(_cell(c, "k", 5.0) for c in ("a", "b", "c")), chi2=75.0, dof=3, p_value=1e-15,
                         significant=True, noise=ReplicateNoise.of(["k"], []))
    full = _hyp("A", 3.0, (0.5, -0.5, 1.0))
    share, partial, remaining = explained_share(full, before, alpha=0.05)
    assert share == pytest.approx(1 - (0.25 + 0.25 + 1.0) / 75.0)
    assert not partial and remaining == ""
    half = _hyp("B", 40.0, (3.5, 3.5, 0.5))
    share, partial, remaining = explained_share(half, before, alpha=0.05)
    assert share == pytest.approx(1 - (12.25 + 12.25 + 0.25) / 75.0)
    assert partial and "on a" in remaining and "z +3.5" in remaining


def test_fit_check_flags_a_fit_left_uncertain_by_its_surrogate():
    h = _hyp("A", 10.0, (1.0, 1.0, 1.0))  # one parameter, 16 cells fitted: 15 degrees of freedom
    limit = stats.chi2.isf(0.05, 15)  # 25.0
    fits = lambda misfit, gp: dataclasses.replace(h, fit_misfit_chi2=misfit, fit_surrogate_chi2=gp,  # noqa: E731
                                                  fit_cells=16)
    assert fit_check(fits(10.0, 14.0), 0.05) == (True, "")          # reproduces its data (24 < 25)
    assert fit_check(fits(60.0, 3.0), 0.05) == (True, "")           # the hypothesis misses, the GP is sure
    assert fit_check(fits(limit - 16.6, 16.5), 0.05)[0] is True      # just consistent
    assert fit_check(fits(limit - 16.4, 16.5), 0.05)[0] is False     # just not, GP to blame
    resolved, why = fit_check(fits(30.0, 95.0), 0.05)                # the GP knows less than the data
    assert not resolved
    assert "expected chi^2 125.0 on 15 degrees of freedom" in why and "95.0 is the GP's own uncertainty" in why
    assert fit_check(fits(10.0, 17.0), 0.05)[0] is False             # 27 > 25 and 17 > 16 cells
    assert fit_check(dataclasses.replace(h, parameters=()), 0.05) == (True, "")  # nothing fitted


def test_a_left_out_fit_astray_is_flagged_beyond_noise_only():
    """prediction_astray: a DEM held-out chi^2 beyond the 99.9 % point of the noncentral chi^2 its
    GP predicts (4 cells, predicted 16.9: noncentrality 12.9, limit 48.7). Where the GP predicted
    right, z^2 sums drawn with that noncentrality are flagged in about 0.1 % of draws. A flag
    triggers the refinement; it does not block a verdict itself (fit_check)."""
    assert prediction_astray(67.4, 16.9, 4)      # the walls twin: the GP misjudged the point
    assert not prediction_astray(48.5, 16.9, 4) and prediction_astray(48.9, 16.9, 4)
    assert not prediction_astray(2.0, 60.0, 4)   # the DEM did better than predicted
    rng = np.random.default_rng(0)
    for predicted, k in ((4.0, 4), (16.9, 4), (60.0, 4), (12.0, 3)):
        offset = np.sqrt(max(predicted - k, 0.0) / k)  # equal offsets per cell: lambda = predicted - k
        draws = ((offset + rng.standard_normal((20000, k))) ** 2).sum(axis=1)
        flagged = np.mean([prediction_astray(d, predicted, k) for d in draws])
        assert flagged < 0.002, (predicted, k, flagged)
    # once refined, the held-out runs are the DEM's own evidence: an astray fit alone blocks nothing
    h = dataclasses.replace(_hyp("A", 10.0, (1.0, 1.0, 1.0)), fit_misfit_chi2=10.0, fit_surrogate_chi2=3.0,
                            fit_cells=16, astray={"50-50-reverse": (67.4, 16.9)})
    assert fit_check(h, 0.05) == (True, "")
