"""The power study's bookkeeping on the known-answer model (tests/_calibration_model.py).

- Null twins: the calibrated discrepancy test detects in about alpha = 5 % of the labs (the
  observed rate's Wilson 95 % interval over 40 labs contains 0.05), the p-values are uniform
  (KS), and no more causes are named than the interval of a 5 % false-alarm rate allows.
- A strong hidden effect (particle densities x 0.8, inside the density_per_material prior) is
  detected and named right in every lab.
- Design runs are reused, not repeated: each hypothesis's design is run once for all twins, and
  lab r's discrepancy runs once for the null and the effect (40 labs, 46 twins).
- A finished twin is not analysed again (artifacts, keyed by the verdict rules: outcomes of older
  rules are only read), and Wilson intervals match statsmodels.
"""
from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _calibration_model as km  # noqa: E402
from test_discovery import KPIS, _known_model  # noqa: E402

from bo.campaign.executor import InProcessExecutor
from bo.campaign.store import CampaignStore
from bo.discovery.pipeline import VERDICT_RULES, DiscoverySettings, discovery_stages
from bo.discovery.power import (NULL, Effect, outcome_artifact, power_stages, power_summary, run_power_study, tabulate,
                                wilson)
from torchdem.errors import ConfigError
from torchdem.measured import load_measured

CANDIDATES = ("density_per_material", "cohesion")


def _settings():
    return DiscoverySettings(kpis=KPIS, seeds=(0, 1, 2), fit_seeds=(0, 1), candidates=CANDIDATES)


def _study(tmp_path, null_labs, labs, effects, rules=None):
    model = _known_model()
    template = load_measured().subset(["50-50", "75-25", "25-75"], "test")
    store = CampaignStore(tmp_path / "power.sqlite", "known",
                          extra_stages=discovery_stages() + power_stages(CANDIDATES))
    calls = []

    def executor_for(m):
        def batch(tasks):
            calls.append(len(tasks))
            return km.known_batch(tasks)
        return InProcessExecutor(batch, batch_size=64)

    baseline = {**model.fixed, **km.TRUE}
    settings = _settings()
    out = run_power_study(store, executor_for, model, baseline, template, effects, settings, labs=labs,
                          null_labs=null_labs, lab_replicates=5, lab_seed=1000, echo=lambda s: None, rules=rules)
    return store, out, calls


def test_power_study_recovers_the_null_rate_names_a_strong_effect_and_reuses_design_runs(tmp_path):
    rho = km.NOMINAL_DENSITY
    strong = Effect("density_per_material", {f"density_{m}": 0.8 * v for m, v in rho.items()}, fraction=(0.8 - 0.7) / 0.6)
    store, outcomes, calls = _study(tmp_path, null_labs=40, labs=6, effects=[strong])
    rows = tabulate(outcomes, [strong])
    null, effect = rows
    assert null.mechanism == NULL and null.n == 40 and effect.n == 6
    lo, hi = null.detection[1:]
    assert lo <= 0.05 <= hi, null
    # each lab draws its own discovery runs, so the null p-values are uniform (KS 0.40 measured;
    # with one set of baseline runs shared by every twin all 40 exceeded 0.35)
    from scipy import stats
    assert stats.kstest([o.p_value for o in outcomes if o.mechanism == NULL], "uniform").pvalue > 0.05
    assert null.wrong_rate[1] <= 0.05 <= null.wrong_rate[2] or null.wrong == 0
    assert effect.detected == 6 and effect.right == 6 and effect.wrong == 0
    summary = power_summary(rows)
    assert summary["density_per_material"]["reached"]["effect"] == strong.label
    # lab r's discrepancy runs (3 conditions x 3 seeds of its own) serve lab r of every effect
    assert store.counts("discrepancy", computed_only=True)["done"] == 40 * 9
    assert store.counts("discrepancy")["done"] == 40 * 9  # lab r asks for the same batch every time
    # each hypothesis's design ran once although every significant twin fitted it
    designs = {r.batch_key for r in store.records("discovery-cohesion") if r.batch_key.startswith("lhs/")}
    assert len(designs) == 1
    # twins: 46 labs x 3 conditions x 5 seeds, every one computed
    twins = store.counts("twin-null", computed_only=True)["done"] + store.counts(
        "twin-density_per_material", computed_only=True)["done"]
    assert twins == 46 * 3 * 5
    # a rerun analyses nothing again and evaluates nothing
    n_calls = len(calls)
    _, again, _ = _study(tmp_path, null_labs=40, labs=6, effects=[strong])
    assert again == outcomes and len(calls) == n_calls
    # outcomes are keyed by the verdict rules the settings apply (4: pruning is off by default):
    # those of other rules are read, never made or mixed
    assert store.get_artifact(outcome_artifact(NULL, 0, 0, 4), None) is not None
    assert store.get_artifact(outcome_artifact(NULL, 0, 0, VERDICT_RULES), None) is None
    assert store.get_artifact(outcome_artifact(NULL, 0, 0, 1), None) is None
    with pytest.raises(ConfigError, match=r"holds no outcome of null effect 0 lab 0 under verdict rules 1"):
        _study(tmp_path, null_labs=40, labs=6, effects=[strong], rules=1)
    with pytest.raises(ConfigError, match=r"power.rules"):
        _study(tmp_path, null_labs=40, labs=6, effects=[strong], rules=VERDICT_RULES + 1)
    # without pruning a discovery applies rules 4 whole (the held-out runs before a refinement too)
    from bo.discovery.pipeline import rules_of

    assert rules_of(DiscoverySettings(kpis=("shear_angle_deg",), prune_probability=0.01)) == VERDICT_RULES == 5
    assert rules_of(DiscoverySettings(kpis=("shear_angle_deg",))) == 4  # pruning is off by default
    assert sum(r.tied + r.unresolved for r in rows) <= sum(r.n - r.right - r.wrong for r in rows)


def test_a_reanalysis_reads_the_store_only_and_says_which_outcomes_follow(tmp_path):
    """``power.reanalyse``: every stored twin analysed again on a copy of the store with an executor
    that runs nothing. Straight after the study every outcome follows; an outcome edited in the
    store is reported with the field that differs; a discovery that would need runs the store does
    not hold (other discovery seeds) is counted, and the store itself is left as it was."""
    from bo.discovery.power import reanalyse

    rho = km.NOMINAL_DENSITY
    strong = Effect("density_per_material", {f"density_{m}": 0.8 * v for m, v in rho.items()}, fraction=(0.8 - 0.7) / 0.6)
    store, outcomes, calls = _study(tmp_path, null_labs=2, labs=2, effects=[strong])
    model, template = _known_model(), load_measured().subset(["50-50", "75-25", "25-75"], "test")
    baseline = {**model.fixed, **km.TRUE}
    again = functools.partial(reanalyse, store, model, baseline, template, [strong], labs=2, null_labs=2,
                              lab_replicates=5, lab_seed=1000, echo=lambda s: None)
    rows = again(_settings())
    assert [(r["mechanism"], r["lab"], r["status"]) for r in rows] == [
        (NULL, 0, "same"), (NULL, 1, "same"), ("density_per_material", 0, "same"), ("density_per_material", 1, "same")]
    name = outcome_artifact("density_per_material", 0, 1, 4)  # the rules of the default settings
    edited = {**store.get_artifact(name), "cause": "cohesion"}
    store.put_artifact(name, edited)
    rows = again(_settings())
    assert rows[3]["status"] == "different" and rows[3]["changed"] == {"cause": ["cohesion", "density_per_material"]}
    before = len(store.records())
    rows = again(_settings(), discovery_seed=7)
    assert {r["status"] for r in rows} == {"needs runs"} and all(r["runs"] == 9 for r in rows)  # 3 conditions x 3
    assert len(store.records()) == before and store.get_artifact(name) == edited


def test_wilson_interval():
    from statsmodels.stats.proportion import proportion_confint
    assert wilson(3, 40) == pytest.approx(proportion_confint(3, 40, method="wilson"))
    lo, hi = wilson(0, 30)
    assert lo == pytest.approx(0.0, abs=1e-12) and hi == pytest.approx(0.1135, abs=1e-3)
    # the interval holds the rate itself (the closed form's ends round past it at n = 7, 9, 14, ...),
    # so the power plot's error bars are never negative
    for n in range(1, 40):
        for k in (0, n):
            lo, hi = wilson(k, n)
            assert lo <= k / n <= hi
