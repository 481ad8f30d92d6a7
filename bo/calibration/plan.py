"""How many DEM runs a calibration campaign makes at most, stage by stage, and what is left of them.

Contract
--------
``campaign_plan(settings, measured)`` reads a ``CalibrationSettings`` (``bo.calibration.pipeline``)
and the measured data, and returns a ``CampaignPlan``: per stage and condition, the most DEM runs
the campaign can make there. Only the surrogate stage can stop short of its figure (its rounds
end when the cross-validated R^2 reaches the target); every other figure is exact:

- screening: the definitive screening design's runs (``2 m + 1`` points for ``m`` real and fake
  factors, ``m`` even) times its replicate seeds, on the calibrated condition;
- surrogate: ``budget`` points times the surrogate's seeds, on the calibrated condition and again
  on each of ``objective_conditions`` and ``jam_conditions`` (the screening's reused points are not
  run again);
- verification: its seeds, twice with ``fresh_verification`` (on the calibrated condition; the
  stored verification runs on each of ``objective_conditions`` too);
- density: its seeds again, where the measured data carry a heap height and the check is on;
- validation: its seeds on each validation condition.

``plan_progress(plan, path, costs_from=())`` sets the plan beside a campaign store (read only):
per stage and condition, the runs done and the worker time the rest will take at the median cost
of that condition's finished runs in the store (``bo.campaign.progress.run_costs``). Where the
condition has none yet, the figure comes from its runs in the stores ``costs_from`` (runs of the
same model elsewhere: a probe of the same geometry and particles), else from the median over all
conditions of the store; ``PlannedRow.cost_source`` says which. A pellet-rich fill empties in half
the time of 50-50, so the last is a rough figure. A campaign resumes from its store, so this is
how long the rest of it takes, before the stages not reached have rows. A store seeded with another
campaign's (``store_from``) counts as done only the runs that are this campaign's: the screening's,
its own surrogate batches' (not the ``reuse_designs`` it reads as data) and the checks made after
them.

``python scripts/campaign_status.py STORE --profile NAME`` prints both.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from statistics import median
from typing import Mapping, Sequence

from bo.campaign.progress import open_read_only, run_costs
from bo.campaign.store import reused_from
from bo.design.dsd import definitive_screening_design
from torchdem.measured import MeasuredData

__all__ = ["StagePlan", "CampaignPlan", "PlannedRow", "campaign_plan", "plan_progress"]

#: The store stages of each plan stage (the surrogate's rounds are ``round-1``, ``round-2``, ...).
STORE_STAGES = {"screening": ("screening",), "surrogate": ("initial", "round-"), "verification": ("verification",),
                "density": ("density",), "validation": ("validation",)}


@dataclass(frozen=True)
class StagePlan:
    """The most runs one stage makes.

    Attributes:
        stage: ``screening``, ``surrogate``, ``verification``, ``density`` or ``validation``.
        runs: condition -> the most runs there (conditions in the order the stage runs them).
        what: how the figure is made, for people ("9 points x 2 seeds").
        exact: whether the stage always makes that many (only the surrogate can stop short).
    """

    stage: str
    runs: Mapping[str, int]
    what: str
    exact: bool = True

    @property
    def total(self) -> int:
        return sum(self.runs.values())


@dataclass(frozen=True)
class CampaignPlan:
    """The stages of a calibration campaign with their most runs; stages that run nothing are left out.
    ``earlier_designs``: the batch keys of the earlier campaigns' surrogate designs it reads as data
    (``surrogate.reuse_designs``), whose runs are not its own."""

    stages: tuple[StagePlan, ...]
    earlier_designs: tuple[str, ...] = ()

    @property
    def total(self) -> int:
        return sum(s.total for s in self.stages)

    def text(self) -> str:
        """One line: ``at most 74 DEM runs: screening 18 (9 points x 2 seeds on 50-50), ...``."""
        return f"at most {self.total} DEM runs: " + ", ".join(
            f"{s.stage} {'' if s.exact else 'at most '}{s.total} ({s.what})" for s in self.stages)


def _n(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _conditions(names) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def campaign_plan(settings, measured: MeasuredData) -> CampaignPlan:
    """The most DEM runs of each stage of a campaign of ``settings`` (a ``CalibrationSettings``) on
    ``measured``; see the module docstring."""
    from bo.calibration.pipeline import HEAP_HEIGHT_KPI, validation_conditions

    settings = settings.validate()
    condition, stages = settings.condition, []
    sc = settings.screening
    points = definitive_screening_design(sc.table.k, int(sc.n_fake)).shape[0]
    stages.append(StagePlan("screening", {condition: points * len(sc.seeds)},
                            f"{_n(points, 'point')} x {_n(len(sc.seeds), 'seed')} on {condition}"))
    s = settings.surrogate
    budget = s.adaptive.budget
    where = tuple(dict.fromkeys((condition, *settings.objective_conditions, *s.jam_conditions)))
    stages.append(StagePlan("surrogate", {c: budget * len(s.seeds) for c in where},
                            f"{_n(budget, 'point')} x {_n(len(s.seeds), 'seed')} on {_conditions(where)}", exact=False))
    n_ver = len(settings.verification_seeds)
    times = 2 if settings.fresh_verification else 1
    fitted = settings.objective_conditions
    stages.append(StagePlan("verification", {condition: n_ver * times, **{c: n_ver for c in fitted}},
                            _n(n_ver, "seed") + (f" on {_conditions((condition, *fitted))}" if fitted else "")
                            + (f", and again on this machine{f' on {condition}' if fitted else ''}"
                               if times == 2 else "")))
    if settings.density_recalibration and HEAP_HEIGHT_KPI in measured.condition(condition).kpis:
        stages.append(StagePlan("density", {condition: n_ver}, f"{_n(n_ver, 'seed')} at the rescaled densities"))
    validation = validation_conditions(settings, measured)
    if validation:
        n_val = len(settings.validation_seeds)
        stages.append(StagePlan("validation", {c: n_val for c in validation},
                                f"{_n(n_val, 'seed')} on each of {_conditions(validation)}"))
    return CampaignPlan(tuple(stages), tuple(s.reuse_designs))


@dataclass(frozen=True)
class PlannedRow:
    """One stage and condition of a plan beside a store.

    Attributes:
        stage, condition: as in ``StagePlan``. planned: the most runs there. done: the stage's
            finished rows of that condition in the store that are the campaign's own (see
            ``plan_progress``), those that took the result of the same run elsewhere in the stage
            included. left: ``max(planned - done, 0)``.
        seconds_per_run: median worker seconds of a finished run of the condition (any stage); None:
            no finished run anywhere.
        cost_source: where ``seconds_per_run`` comes from: ``"store"`` (the condition's runs in the
            store), ``"costs_from"`` (its runs in the other stores), ``"all conditions"`` (every
            finished run of the store) or ``""`` (None).
        exact: the plan's ``exact`` for the stage.
    """

    stage: str
    condition: str
    planned: int
    done: int
    left: int
    seconds_per_run: float | None
    cost_source: str
    exact: bool

    @property
    def seconds_left(self) -> float | None:
        return None if self.seconds_per_run is None else self.left * self.seconds_per_run


def _seconds_by_condition(runs) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for run in runs:
        if run.state == "done" and run.seconds is not None:
            out.setdefault(run.condition, []).append(run.seconds)
    return out


def _own_done(plan: CampaignPlan, path: str | Path) -> list[tuple[str, str]]:
    """``(plan stage, condition)`` of every finished row of the store at ``path`` that is the campaign's
    own. A store seeded with another campaign's (``store_from``) holds that campaign's surrogate
    design and checks too: the designs the plan reads as data (``earlier_designs``) are not its
    surrogate's runs, and a verification, density or validation batch made before the campaign's
    own surrogate batches ended is the check of another calibrated set. A row that took the result of
    another own row (the store's shared runs, ``reused:<task id>``) is one run with it."""
    conn = open_read_only(Path(path), "plan_progress")
    try:
        rows = conn.execute("SELECT e.task_id, e.stage, e.batch_key, e.condition, e.claimed_by, b.created_at "
                            "FROM evaluations e JOIN batches b ON e.stage = b.stage AND e.batch_key = b.batch_key "
                            "WHERE e.status = 'done' ORDER BY e.task_id").fetchall()
    finally:
        conn.close()
    staged = [(task_id, next((p for p, prefixes in STORE_STAGES.items() if stage.startswith(prefixes)), None), key,
               condition, owner, created) for task_id, stage, key, condition, owner, created in rows]
    surrogate = [created for _, stage, key, *_, created in staged if stage == "surrogate"
                 and key not in plan.earlier_designs]
    after = max(surrogate, default=float("inf"))
    own = [(task_id, stage, condition, owner) for task_id, stage, key, condition, owner, created in staged
           if stage == "screening" or (stage == "surrogate" and key not in plan.earlier_designs)
           or (stage in ("verification", "density", "validation") and created > after)]
    ids = {task_id for task_id, *_ in own}
    return [(stage, condition) for _, stage, condition, owner in own
            if reused_from(owner) not in ids]


def plan_progress(plan: CampaignPlan, path: str | Path,
                  costs_from: Sequence[str | Path] = ()) -> tuple[PlannedRow, ...]:
    """The plan's stages and conditions with what the store at ``path`` holds of them; see the
    module docstring for ``costs_from``."""
    runs = run_costs(path)
    done: dict[tuple[str, str], int] = {}
    for stage, condition in _own_done(plan, path):
        done[stage, condition] = done.get((stage, condition), 0) + 1
    own = _seconds_by_condition(runs)
    elsewhere: dict[str, list[float]] = {}
    for other in costs_from:
        for condition, seconds in _seconds_by_condition(run_costs(other)).items():
            elsewhere.setdefault(condition, []).extend(seconds)
    every = [c for v in own.values() for c in v]
    rows = []
    for s in plan.stages:
        for condition, planned in s.runs.items():
            if own.get(condition):
                per_run, source = median(own[condition]), "store"
            elif elsewhere.get(condition):
                per_run, source = median(elsewhere[condition]), "costs_from"
            elif every:
                per_run, source = median(every), "all conditions"
            else:
                per_run, source = None, ""
            n = done.get((s.stage, condition), 0)
            rows.append(PlannedRow(s.stage, condition, planned, n, max(planned - n, 0), per_run, source, s.exact))
    return tuple(rows)
