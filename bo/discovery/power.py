"""How often does discovery find a hidden effect, name the right cause, or cry wolf? A power study.

Contract
--------
For every mechanism of the registry (``torchdem.mechanisms``) and for the null (no mechanism), a
power study makes twin "lab" data with the DEM itself: the baseline model with the mechanism
switched on at an effect size (:class:`Effect`: the mechanism's parameter values, in its own
units) run on every measured condition with ``lab_replicates`` fresh seeds per "lab"
(:func:`twin_measurement`; lab r of an effect uses seeds ``lab_seed + r * lab_replicates + k``,
the same for every effect of a mechanism: common random numbers). Discovery then runs from the
true baseline on each twin (``bo.discovery.pipeline.run_discovery``) and the outcome is one
:class:`TwinOutcome`: was the discrepancy significant, which cause was named.

Each lab also gets its own seeds for discovery's discrepancy and held-out runs
(``discovery_seed + r * len(settings.seeds) + k``): a user's discovery draws its DEM runs afresh,
and with one set of baseline runs shared by every twin the twins' p-values are not independent
nor uniform under the null (on the known-answer model all 40 null p-values exceeded 0.35: the
shared runs' own error is a common offset that the twins' scatter is measured around).

Everything goes through one campaign store, so a study resumes, and it is affordable because
the store shares runs within a stage (``bo.campaign.store``, "Shared runs"): every hypothesis's
design is the same for every twin and runs once, and lab r's discrepancy runs serve every
effect's lab r; only the held-out runs (fitted to each twin) and the twins themselves are new. A twin's outcome is an artifact (``power/<mechanism>/<effect index>/<lab>``), so a finished
twin is not re-analysed either. Outcome artifacts are keyed by the verdict rules they were reached
with (``bo.discovery.pipeline.VERDICT_RULES``; rules 1 under ``power/<mechanism>/...``, later
ones under ``power/rules<k>/<mechanism>/...``): a study under new rules analyses every twin again,
reusing every DEM run whose parameters are unchanged, and keeps the old outcomes for the
before-and-after.

:func:`tabulate` counts per mechanism and effect: detection (the discrepancy is significant),
right cause (the mechanism itself is named), wrong cause (another mechanism is named), no cause,
each with its Wilson 95 % interval (``statsmodels.stats.proportion.proportion_confint``); for
the null, the false-alarm rate is the share of twins with any cause named. :func:`power_summary`
states per mechanism the smallest studied effect at which the right cause is named in at least
80 % of the labs (None: not reached in the studied range) and the misattribution there.

Twin data carry ``replicates`` (the lab repeats), so discovery's measured uncertainty is
``ci95 / t(0.975, n - 1)``, as for real data that state it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import stats
from statsmodels.stats.proportion import proportion_confint

from bo.campaign.executor import Executor, run_pending
from bo.campaign.store import CampaignStore
from torchdem.errors import ConfigError, out_of_range
from torchdem.mechanisms import apply_extension, get, model_context
from torchdem.measured import Condition, KPIValue, MeasuredData
from torchdem.model import DrawDownModel

__all__ = ["NULL", "LAB_KPIS", "twin_kpis", "Effect", "TwinOutcome", "PowerRow", "power_stages", "twin_measurement",
           "run_power_study", "reanalyse", "ReadOnlyExecutor", "RunsNeeded", "tabulate", "power_summary", "wilson"]

#: Name of the no-mechanism twins.
NULL = "null"
#: DEM KPI -> measured KPI name of the twin data (full-box masses compare with the lab's masses).
LAB_KPIS = {"angle_of_repose_deg": ("angle_of_repose_deg", "deg"), "shear_angle_deg": ("shear_angle_deg", "deg"),
            "mass_flow_rate_full_kg_s": ("mass_flow_rate_kg_s", "kg/s"),
            "mass_lower_box_full_kg": ("mass_lower_box_kg", "kg"), "max_heap_height_m": ("max_heap_height_m", "m"),
            "segregation_rsd_vertical": ("segregation_rsd_vertical", "1"),
            "segregation_rsd_horizontal": ("segregation_rsd_horizontal", "1")}


def power_stages(mechanisms: Sequence[str]) -> tuple[str, ...]:
    """Store stages of the twins (besides ``discovery_stages``)."""
    return (f"twin-{NULL}", *(f"twin-{m}" for m in mechanisms))


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson 95 % interval of k successes in n trials ((nan, nan) for n = 0). It holds k / n:
    at k = 0 the closed form's lower end rounds to a few 1e-17 above 0."""
    if n == 0:
        return math.nan, math.nan
    lo, hi = proportion_confint(k, n, alpha=0.05, method="wilson")
    return min(float(lo), k / n), max(float(hi), k / n)


@dataclass(frozen=True)
class Effect:
    """One effect size of one mechanism: its parameter values (own units) and, for the report,
    the first value as a fraction of that parameter's prior range."""

    mechanism: str
    values: Mapping[str, float]
    fraction: float = math.nan

    @property
    def label(self) -> str:
        return ", ".join(f"{k} {v:g}" for k, v in self.values.items()) or "none"


@dataclass(frozen=True)
class TwinOutcome:
    """Discovery on one twin: discrepancy p-value and chi^2, significant or not, the cause named
    (None: none), every hypothesis's score, the candidates tied and those whose fit was unresolved
    (empty for outcomes of rules 1, which did not record them) and those not run on their held-out
    conditions because by their own GPs they could not be named (recorded from rules 5)."""

    mechanism: str
    effect_index: int
    lab: int
    p_value: float
    chi2: float
    significant: bool
    cause: str | None
    scores: Mapping[str, float] = field(default_factory=dict)
    tied: tuple[str, ...] = ()
    unresolved: tuple[str, ...] = ()
    pruned: tuple[str, ...] = ()


@dataclass(frozen=True)
class PowerRow:
    """Rates of one mechanism at one effect size (null: ``mechanism == "null"``), with Wilson 95 %
    intervals ``(low, high)``; ``tied`` and ``unresolved``: twins where no cause was named because
    candidates tied or a candidate's fit was unresolved (recorded from verdict rules 2)."""

    mechanism: str
    effect: str
    fraction: float
    n: int
    detected: int
    right: int
    wrong: int
    detection: tuple[float, float, float]
    right_rate: tuple[float, float, float]
    wrong_rate: tuple[float, float, float]
    wrong_causes: Mapping[str, int]
    tied: int = 0
    unresolved: int = 0


def _hash(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def lab_seeds(lab: int, replicates: int, base: int) -> list[int]:
    """Seeds of lab ``lab`` (see the module docstring)."""
    return [base + lab * replicates + k for k in range(replicates)]


def twin_kpis(values: Mapping[str, Sequence[float]]) -> dict[str, KPIValue]:
    """Lab KPIs of a twin condition: DEM KPI -> its replicate values (finite ones), to measured
    name -> mean and 95 % CI half-width ``t(0.975, n - 1) s / sqrt(n)``; KPIs with fewer than two
    values are left out."""
    out = {}
    for k, v in values.items():
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v)]
        if v.size < 2:
            continue
        lab_name, unit = LAB_KPIS[k]
        half = float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / math.sqrt(v.size))
        out[lab_name] = KPIValue(float(v.mean()), half, unit)
    return out


def twin_measurement(store: CampaignStore, executor_for: Callable[[DrawDownModel], Executor], model: DrawDownModel,
                     baseline: Mapping[str, float], template: MeasuredData, effect: Effect | None,
                     seeds: Sequence[int], kpis: Sequence[str]) -> MeasuredData:
    """Twin data of one lab: the baseline model with ``effect`` switched on (None: the null) run on
    every condition of ``template`` with ``seeds``; means and ``t(0.975, n - 1) s / sqrt(n)`` per KPI."""
    if len(seeds) < 2:
        raise out_of_range("lab_replicates", len(seeds), "an int >= 2 (the twin's CI needs a spread)", "power study")
    unknown = [k for k in kpis if k not in LAB_KPIS]
    if unknown:
        raise out_of_range("kpis", list(kpis), f"KPIs with a lab counterpart {sorted(LAB_KPIS)}", "power study")
    name = NULL if effect is None else effect.mechanism
    truth = model
    point = dict(baseline)
    if effect is not None:
        truth = apply_extension(model, effect.mechanism, effect.values, model_context(model, baseline),
                                source=f"power study: {effect.mechanism}")
        point.update({k: float(v) for k, v in effect.values.items()})
    stage = f"twin-{name}"
    conditions = list(template.names)
    key = f"{_hash(sorted(point.items()))}/seeds={_hash(list(seeds))}"
    store.batch(stage, key, lambda: [point], seeds=list(seeds), conditions=conditions)
    with executor_for(truth) as executor:
        run_pending(store, executor, stage)
    values: dict[tuple[str, str], list[float]] = {}
    for rec in store.records(stage, batch_key=key, status="done"):
        for k in kpis:
            v = (rec.kpis or {}).get(k, math.nan)
            if math.isfinite(v):
                values.setdefault((rec.condition, k), []).append(v)
    out = []
    for c in template.conditions:
        measured = twin_kpis({k: values.get((c.name, k), []) for k in kpis})
        if not measured:
            raise ConfigError(f"power study: twin {name} lab seeds {list(seeds)}: no KPI of condition {c.name!r} "
                              f"was measured twice; see the store's stage {stage!r}")
        out.append(Condition(name=c.name, pellet_mass_fraction=c.pellet_mass_fraction, layering=c.layering,
                             fill_mass_kg=c.fill_mass_kg, kpis=measured, mixture=c.mixture,
                             description=f"twin: {name} {effect.label if effect else ''} seeds {list(seeds)}",
                             replicates=len(seeds)))
    return MeasuredData(source=f"power-study twin ({name})", conditions=tuple(out))


def outcome_artifact(name: str, index: int, lab: int, rules: int) -> str:
    """Store artifact of one twin's outcome under verdict rules ``rules``."""
    return f"power/{name}/{index}/{lab}" if rules == 1 else f"power/rules{rules}/{name}/{index}/{lab}"


def _jobs(effects: Sequence[Effect], labs: int, null_labs: int) -> list[tuple[str, int, Effect | None, int]]:
    """``(mechanism, effect index, effect, lab)`` of every twin, the null's first."""
    if labs < 1 or null_labs < 0:
        raise out_of_range("(labs, null_labs)", (labs, null_labs), "labs >= 1, null_labs >= 0", "power study")
    jobs = [(NULL, 0, None, r) for r in range(null_labs)]
    for i, e in enumerate(effects):
        get(e.mechanism, "power study")
        jobs += [(e.mechanism, i, e, r) for r in range(labs)]
    return jobs


def _analyse(store: CampaignStore, executor_for: Callable[[DrawDownModel], Executor], model: DrawDownModel,
             baseline: Mapping[str, float], template: MeasuredData, settings, name: str, index: int,
             effect: Effect | None, lab: int, lab_replicates: int, lab_seed: int, discovery_seed: int) -> dict:
    """One twin made (or read) and analysed: its outcome as the store keeps it."""
    from bo.discovery.pipeline import run_discovery

    seeds = lab_seeds(lab, lab_replicates, lab_seed)
    twin = twin_measurement(store, executor_for, model, baseline, template, effect, seeds, list(settings.kpis))
    own = dataclasses.replace(settings, seeds=tuple(lab_seeds(lab, len(settings.seeds), discovery_seed)))
    result = run_discovery(store, executor_for, model, baseline, twin, own, echo=lambda s: None)
    d = result.discrepancy
    return {"mechanism": name, "effect_index": index, "lab": lab, "p_value": float(d.p_value),
            "chi2": float(d.chi2), "significant": bool(d.significant), "cause": result.cause,
            "scores": {h.name: (float(h.score) if math.isfinite(h.score) else None) for h in result.hypotheses},
            "tied": list(result.tied), "unresolved": list(result.unresolved),
            "pruned": [h.name for h in result.hypotheses if h.pruned]}


class RunsNeeded(Exception):
    """A re-analysis asked for DEM runs its store does not hold."""


class ReadOnlyExecutor(Executor):
    """Runs nothing: any task raises :class:`RunsNeeded` (a re-analysis that may only read the store)."""

    def __init__(self):
        super().__init__(lambda tasks: [], 1)

    @property
    def parallelism(self) -> int:
        return 1

    def run(self, tasks):
        raise RunsNeeded(f"{len(tasks)} DEM runs not in the store")


#: The outcome fields a re-analysis compares (``p_value`` and ``chi2`` follow from the scores).
COMPARED = ("significant", "cause", "scores", "tied", "unresolved")


def reanalyse(store: CampaignStore, model: DrawDownModel, baseline: Mapping[str, float], template: MeasuredData,
              effects: Sequence[Effect], settings, *, labs: int, null_labs: int, lab_replicates: int,
              lab_seed: int, discovery_seed: int = 500_000, echo: Callable[[str], None] = print) -> list[dict]:
    """Every twin with a stored outcome under the rules ``settings`` apply, analysed again with this
    code from the runs the store holds, on a copy of it (``store`` is not written): per twin
    ``status`` "same" (every field of :data:`COMPARED` equal to the last digit), "different"
    (``changed``: the fields and both values) or "needs runs" (``runs``: those of the batches it had
    asked for when it stopped at the first; the copy is taken again so that these unrun batches do
    not stand in for the next twin's).
    Twins without a stored outcome are left out. Shows whether the shipped outcomes follow from the
    shipped runs on this machine."""
    import tempfile
    from pathlib import Path

    from bo.campaign.store import copy_store
    from bo.discovery.pipeline import rules_of

    rules = rules_of(settings)
    executor_for = lambda m: ReadOnlyExecutor()  # noqa: E731
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="reanalyse-") as tmp:
        copies = itertools.count()

        def fresh() -> CampaignStore:  # a file of its own: no connection to an earlier copy sees it
            copy = Path(tmp) / f"{next(copies)}-{store.path.name}"
            copy_store(store.path, copy)
            return CampaignStore(copy, store.config_hash, extra_stages=store.extra_stages,
                                 allow_config_mismatch=store.stored_config_hash != store.config_hash)

        def unrun(s: CampaignStore) -> int:
            c = s.counts()
            return c["pending"] + c["running"]

        work = fresh()
        base = unrun(work)
        jobs = _jobs(effects, labs, null_labs)
        for n, (name, index, effect, lab) in enumerate(jobs):
            stored = store.get_artifact(outcome_artifact(name, index, lab, rules), None)
            if stored is None:
                continue
            row = {"mechanism": name, "effect_index": index, "lab": lab}
            try:
                found = _analyse(work, executor_for, model, baseline, template, settings, name, index, effect, lab,
                                 lab_replicates, lab_seed, discovery_seed)
            except RunsNeeded:
                row.update(status="needs runs", runs=unrun(work) - base)
                work = fresh()
            else:
                changed = {k: [stored.get(k), found.get(k)] for k in COMPARED if stored.get(k) != found.get(k)}
                row.update(status="different" if changed else "same", changed=changed)
            rows.append(row)
            echo(f"[{n + 1}/{len(jobs)}] {name} effect {index} lab {lab}: {row['status']}"
                 + (f" ({row['runs']} runs)" if "runs" in row else "")
                 + (f" ({', '.join(row['changed'])})" if row.get("changed") else ""))
    return rows


def run_power_study(store: CampaignStore, executor_for: Callable[[DrawDownModel], Executor], model: DrawDownModel,
                    baseline: Mapping[str, float], template: MeasuredData, effects: Sequence[Effect],
                    settings, *, labs: int, null_labs: int, lab_replicates: int, lab_seed: int,
                    discovery_seed: int = 500_000, echo: Callable[[str], None] = print,
                    rules: int | None = None) -> list[TwinOutcome]:
    """Twins and discovery for the null (``null_labs`` labs) and every effect (``labs`` labs each),
    resuming from the store's artifacts; returns every outcome (null first). ``rules`` (default the
    rules ``settings`` apply, ``bo.discovery.pipeline.rules_of``) other than those only reads the
    outcomes the store holds."""
    from bo.discovery.pipeline import VERDICT_RULES, rules_of

    current = rules_of(settings)
    rules = current if rules is None else rules
    if isinstance(rules, bool) or not isinstance(rules, int) or not 1 <= rules <= VERDICT_RULES:
        raise out_of_range("power.rules", rules, f"an int in [1, {VERDICT_RULES}] (the verdict rules' versions)",
                           "power study")

    jobs = _jobs(effects, labs, null_labs)
    outcomes = []
    for n, (name, index, effect, lab) in enumerate(jobs):
        artifact = outcome_artifact(name, index, lab, rules)
        found = store.get_artifact(artifact, None)
        if found is None and rules != current:
            raise ConfigError(f"power study: the store {store.path} holds no outcome of {name} effect {index} lab {lab} "
                              f"under verdict rules {rules}; only the rules these settings apply ({current}) can "
                              f"analyse a twin")
        if found is None:
            found = _analyse(store, executor_for, model, baseline, template, settings, name, index, effect, lab,
                             lab_replicates, lab_seed, discovery_seed)
            store.put_artifact(artifact, found)
        outcome = TwinOutcome(**{**found, "scores": {k: (math.inf if v is None else v)
                                                      for k, v in found["scores"].items()},
                                 "tied": tuple(found.get("tied", ())),
                                 "unresolved": tuple(found.get("unresolved", ())),
                                 "pruned": tuple(found.get("pruned", ()))})
        outcomes.append(outcome)
        echo(f"[{n + 1}/{len(jobs)}] {name} effect {index} lab {lab}: p = {outcome.p_value:.3g}, "
             f"cause {outcome.cause}")
    return outcomes


def tabulate(outcomes: Sequence[TwinOutcome], effects: Sequence[Effect]) -> list[PowerRow]:
    """Rates per mechanism and effect (see the module docstring); the null row first."""
    groups: dict[tuple[str, int], list[TwinOutcome]] = {}
    for o in outcomes:
        groups.setdefault((o.mechanism, o.effect_index), []).append(o)
    rows = []
    for (name, index), group in sorted(groups.items(), key=lambda kv: (kv[0][0] != NULL, kv[0][0], kv[0][1])):
        n = len(group)
        detected = sum(o.significant for o in group)
        named = [o.cause for o in group if o.cause is not None]
        right = sum(c == name for c in named) if name != NULL else 0
        wrong_causes: dict[str, int] = {}
        for c in named:
            if c != name:
                wrong_causes[c] = wrong_causes.get(c, 0) + 1
        wrong = sum(wrong_causes.values())
        effect = effects[index] if name != NULL else None
        rate = lambda k: (k / n, *wilson(k, n))  # noqa: E731
        rows.append(PowerRow(mechanism=name, effect=effect.label if effect else "none",
                             fraction=effect.fraction if effect else 0.0, n=n, detected=detected, right=right,
                             wrong=wrong, detection=rate(detected), right_rate=rate(right), wrong_rate=rate(wrong),
                             wrong_causes=wrong_causes, tied=sum(bool(o.tied) for o in group if o.cause is None),
                             unresolved=sum(bool(o.unresolved) and not o.tied for o in group if o.cause is None)))
    return rows


def power_summary(rows: Sequence[PowerRow], target: float = 0.8) -> dict[str, dict]:
    """Per mechanism: the smallest studied effect named right in >= ``target`` of the labs, with
    its misattribution; for the null, the false-alarm rate (any cause named)."""
    out: dict[str, dict] = {}
    for r in rows:
        if r.mechanism == NULL:
            out[NULL] = {"false_alarm": r.wrong_rate, "detection": r.detection, "n": r.n}
            continue
        entry = out.setdefault(r.mechanism, {"reached": None, "studied": []})
        entry["studied"].append({"effect": r.effect, "fraction": r.fraction, "right": r.right_rate,
                                 "wrong": r.wrong_rate, "detection": r.detection, "n": r.n})
    for name, entry in out.items():
        if name == NULL:
            continue
        hits = [s for s in sorted(entry["studied"], key=lambda s: s["fraction"]) if s["right"][0] >= target]
        entry["reached"] = hits[0] if hits else None
    return out


def rows_to_json(rows: Sequence[PowerRow]) -> list[dict]:
    return [asdict(r) for r in rows]
