"""Discovery's verdict rules on constructed scores (bo/discovery/pipeline.py, step 3):

- two candidates that both beat refitting the parameters and whose scores differ by less than
  the DEM noise of their difference are tied (no cause is named); a clear winner is not tied;
- a named cause reports the share of the calibrated model's chi^2 it removes on the held-out
  cells (computed by hand here), and is called partial, with the largest remaining cells, when
  the extended model still misses beyond noise.
"""
import math

import pytest

from bo.discovery.pipeline import Cell, Discrepancy, HypothesisScore, explained_share, tied_with
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
