"""Named parameter sets run on chosen conditions and seeds, kept in a campaign store: a designed probe
that resumes, instead of one-off runs.

A probe file (YAML) names the model (the calibrate config's Hydra overrides), the conditions, the seeds,
a ``base`` set and the sets to run, each as changes to the base. Every set is stored as the base with
its changes, under stage ``probe`` and its own name, so all sets name the same parameters and a set
differs from the base exactly where the file says. The runs are the runs a campaign task of these
parameters makes (same model, same store hash as ``torchdem-calibrate`` with these overrides). A rerun
with the same store runs only what is missing; a change of a set's values needs a new set name, while more
seeds or conditions for a set already run add only their runs (``CampaignStore.batch`` grows the set's batch).

    python scripts/probe_sets.py campaigns/table2/probe_contrast.yaml --workers 2
    python scripts/contrast_check.py campaigns/table2/probe_contrast.sqlite --by-set   # C per set

After the runs it prints each set's KPI means per condition and their relative errors against the
measured data (``--data``; default the paper's Table 2), with each set's largest error over the conditions
but ``--calibration-condition``.

Probe file::

    overrides: [profile=lab_box]
    store: campaigns/table2/probe_contrast.sqlite   # relative to the working directory
    conditions: [75-25, 25-75]
    seeds: [0, 1]
    base: {geometry_upper_width: 0.3431, fill_friction: 0.654}
    sets:
      base: {}
      pellets_less_elastic: {e_pp: 0.6}
    sets_seeds: {base: [0, 1, 2]}     # optional: set -> its own seeds
    sets_conditions: {base: [75-25]}  # optional: set -> its own conditions
    adopt: {set: base, store: campaigns/table2/lab_box.sqlite, stage: validation}   # optional

``adopt`` takes a set's runs from another store of the same model (a campaign's validation runs of the
base, say) instead of running them: the runs of that stage (or of a list of stages, e.g. ``[verification,
validation]`` for a calibrated set on every condition) whose parameters equal the set's on every
parameter they name (the others must be the model's own values: the file vouches for that), on the
set's seeds and conditions; of several runs of one seed and condition, the first stage's.

Sets of equal values share their runs (``CampaignStore``'s shared runs): a set ``verification`` with
the values of a set already run, on seeds 0-4 at one condition (``sets_seeds``, ``sets_conditions``),
runs only the seeds that set did not.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import yaml

from torchdem.errors import ConfigError, exit_on_bad_input, out_of_range

if TYPE_CHECKING:  # the store is imported where a probe runs, so the script's --help stays light
    from bo.campaign.store import CampaignStore

#: The store stage of a probe's runs.
STAGE = "probe"


def load_probe(path: str | Path) -> dict[str, Any]:
    """The probe file, checked: ``{"overrides", "store", "conditions", "seeds", "sets", "set_conditions",
    "adopt"}`` with ``sets`` name -> (full parameter set, its seeds), every set the base with its changes,
    and ``set_conditions`` name -> its conditions (the file's ``conditions`` unless ``sets_conditions``
    names the set)."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the probe file ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from None
    source = str(path)
    if not isinstance(raw, Mapping):
        raise out_of_range("probe file", type(raw).__name__, "a mapping with overrides, store, conditions, seeds, "
                           "base and sets", source)
    missing = [k for k in ("store", "conditions", "seeds", "sets") if k not in raw]
    if missing:
        raise ConfigError(f"{source}: missing {missing}; a probe file needs store, conditions, seeds and sets")
    overrides = raw.get("overrides") or []
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise out_of_range("overrides", overrides, "a list of Hydra overrides, e.g. [profile=lab_box]", source)
    conditions = raw["conditions"]
    if not isinstance(conditions, list) or not conditions or not all(isinstance(c, str) for c in conditions):
        raise out_of_range("conditions", conditions, "a non-empty list of condition names, e.g. [75-25, 25-75]",
                           source)

    def seed_list(value, key: str) -> list[int]:
        if (not isinstance(value, list) or not value or len(set(value)) != len(value)
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value)):
            raise out_of_range(key, value, "a non-empty list of distinct integers >= 0", source)
        return list(value)

    seeds = seed_list(raw["seeds"], "seeds")
    base = _parameters(raw.get("base") or {}, "base", source)
    sets_raw = raw["sets"]
    if not isinstance(sets_raw, Mapping) or not sets_raw:
        raise out_of_range("sets", sets_raw, "a mapping of set names to parameter changes ({} for the base itself)",
                           source)
    changes = {str(name): _parameters(v or {}, f"sets.{name}", source) for name, v in sets_raw.items()}
    names = sorted(set(base).union(*changes.values()))
    if not names:
        raise ConfigError(f"{source}: no parameter is named in base or sets; name at least one (the base's values "
                          "of the ones the sets change)")
    unbased = sorted(set(names) - set(base))
    if unbased:
        raise ConfigError(f"{source}: {unbased} are changed by a set but have no base value; give every parameter "
                          "a set changes its base value under base, so that all sets name the same parameters")
    per_set = raw.get("sets_seeds") or {}
    if not isinstance(per_set, Mapping) or set(per_set) - set(changes):
        raise out_of_range("sets_seeds", per_set, f"a mapping of some of the sets {sorted(changes)} to seed lists",
                           source)
    sets = {name: ({**base, **c}, seed_list(per_set[name], f"sets_seeds.{name}") if name in per_set else seeds)
            for name, c in changes.items()}
    own_conditions = raw.get("sets_conditions") or {}
    if not isinstance(own_conditions, Mapping) or set(own_conditions) - set(changes) or not all(
            isinstance(v, list) and v and len(set(v)) == len(v) and all(isinstance(c, str) for c in v)
            for v in own_conditions.values()):
        raise out_of_range("sets_conditions", own_conditions, f"a mapping of some of the sets {sorted(changes)} to "
                           "non-empty lists of distinct condition names", source)
    set_conditions = {name: list(own_conditions.get(name, conditions)) for name in changes}
    adopt = raw.get("adopt")
    if adopt is not None and (not isinstance(adopt, Mapping) or set(adopt) != {"set", "store", "stage"}
                              or adopt["set"] not in sets):
        raise out_of_range("adopt", adopt, f"a mapping with set (one of {sorted(sets)}), store and stage", source)
    if adopt is not None:
        stages = [adopt["stage"]] if isinstance(adopt["stage"], str) else adopt["stage"]
        if (not isinstance(stages, list) or not stages or len(set(map(str, stages))) != len(stages)
                or not all(isinstance(s, str) and s for s in stages)):
            raise out_of_range("adopt.stage", adopt["stage"], "a stage name or a non-empty list of distinct stage "
                               "names, e.g. [verification, validation]", source)
        adopt = {**adopt, "stage": list(stages)}
    return {"overrides": list(overrides), "store": str(raw["store"]), "conditions": list(conditions),
            "seeds": seeds, "sets": sets, "set_conditions": set_conditions, "adopt": dict(adopt) if adopt else None}


def conditions_of(probe: Mapping[str, Any], name: str) -> list[str]:
    """The conditions set ``name`` runs on (``sets_conditions``, else the probe's ``conditions``)."""
    return list(probe.get("set_conditions", {}).get(name, probe["conditions"]))


def _parameters(value, key: str, source: str) -> dict[str, float]:
    if not isinstance(value, Mapping):
        raise out_of_range(key, value, "a mapping of parameter names to numbers", source)
    out = {}
    for name, v in value.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise out_of_range(f"{key}.{name}", v, "a finite number", source)
        out[str(name)] = float(v)
    return out


def run_probe(probe: Mapping[str, Any], workers: int, echo=print) -> CampaignStore:
    """Every set's missing runs, in the probe's store; returns the store."""
    from bo.campaign.executor import run_pending
    from bo.cli.calibrate import calibration_model_for
    from bo.cli.common import (MODEL_KEYS, ExecutorSettings, check_builds, checkpoint_dir_for, executor_from,
                               open_store)

    plain, model, _ = calibration_model_for(probe["overrides"])
    named = dict.fromkeys(c for name in probe["sets"] for c in conditions_of(probe, name))
    unknown = [c for c in named if c not in model.conditions]
    if unknown:
        raise out_of_range("conditions", unknown, f"conditions of the model {sorted(model.conditions)}", "probe file")
    for name, (params, _) in probe["sets"].items():  # the model builds every set before any run is made
        check_builds(model, conditions_of(probe, name)[0], params, f"probe file: set {name!r} ({params})")
    path = Path(probe["store"])
    store = open_store(path, plain, MODEL_KEYS + ("measured",), extra_stages=(STAGE,))
    for name, (params, seeds) in probe["sets"].items():
        store.batch(STAGE, name, lambda p=params: [p], seeds=seeds, conditions=conditions_of(probe, name))
    if probe.get("adopt"):
        echo(adopt_runs(store, probe))
    counts = store.counts(STAGE)
    echo(f"probe: store {path}, {len(probe['sets'])} sets on {list(named)}; "
         + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    settings = ExecutorSettings(kind="dask" if workers > 1 else "inprocess", batch_size=1, n_workers=workers)
    with executor_from(settings, model, checkpoints=checkpoint_dir_for(path)) as executor:
        summary = run_pending(store, executor, STAGE)
    echo(f"probe: {summary}")
    return store


def adopt_runs(store, probe: Mapping[str, Any]) -> str:
    """Complete the ``adopt`` set's tasks with the matching done runs of the other store (module
    docstring); returns a line saying how many."""
    from bo.campaign.progress import check_same_model, done_records

    spec = probe["adopt"]
    params, seeds = probe["sets"][spec["set"]]
    source = Path(spec["store"])
    check_same_model(source, store.model_hashes, "probe file: adopt")  # read only: a shipped store is not written
    runs = [r for stage in spec["stage"] for r in done_records(source, stage, "probe file: adopt")]
    runs = [r for r in runs if r.seed in seeds and r.condition in conditions_of(probe, spec["set"]) and r.params
            and all(n in params and math.isclose(v, params[n], rel_tol=1e-12, abs_tol=0.0)
                    for n, v in r.params.items())]
    taken = {}
    for r in runs:  # one run per seed and condition
        taken.setdefault((r.seed, r.condition), r)
    n = store.adopt(STAGE, spec["set"], list(taken.values()), str(spec["store"]))
    return (f"probe: set {spec['set']!r}: {n} runs taken from {spec['store']} ({', '.join(spec['stage'])}), "
            f"{len(taken)} matched")


def summary_table(store, probe: Mapping[str, Any], kpis) -> str:
    """Markdown: per set and condition, the runs that flowed and their KPI means (sd)."""
    from kpi.loadcell import discharge_jammed

    lines = ["| set | condition | runs (jammed) | " + " | ".join(kpis) + " |",
             "| --- | --- | ---: |" + " ---: |" * len(kpis)]
    for name in probe["sets"]:
        done = store.records(STAGE, batch_key=name, status="done")
        for condition in conditions_of(probe, name):
            recs = [r for r in done if r.condition == condition and r.kpis]
            flowed = [r.kpis for r in recs if not discharge_jammed(r.kpis)]
            cells = []
            for k in kpis:
                v = np.array([f.get(k, math.nan) for f in flowed], dtype=float)
                cells.append("-" if not len(v) else f"{np.nanmean(v):.2f}" + (f" ({np.nanstd(v, ddof=1):.2f})"
                                                                                 if len(v) > 1 else ""))
            lines.append(f"| {name} | {condition} | {len(flowed)} ({len(recs) - len(flowed)}) | " + " | ".join(cells)
                         + " |")
    return "\n".join(lines) + "\n"


def standard_error_pct(a) -> float:
    """The standard error of a :class:`~bo.calibration.pipeline.KPIAgreement`'s relative error, in % of
    the lab's mean: the replicates' sd / sqrt(n) (NaN for one run). Whether a mean error past a threshold
    (the paper's 7.23 %) is more than the runs' scatter."""
    return 100.0 * a.dem_std / math.sqrt(a.n) / abs(a.measured_mean) if a.n > 1 else math.nan


def error_table(store, probe: Mapping[str, Any], kpis, measured, calibration_condition: str | None = None) -> str:
    """Markdown: per set and condition, each KPI's mean relative error against the measured data, in %
    (``*``: the mean lies outside the lab's 95 % CI), over the runs that flowed (the calibration's
    :func:`bo.calibration.pipeline.agreement`), and per set the largest |error| over its conditions but
    ``calibration_condition``: how far a set is from validating, as the paper's Table A.6 reports it, and
    the conditions where its discharge jammed (the runs column counts those that flowed). The largest
    error carries its standard error over the runs (``+7.9 +- 1.5 %``) where a condition has two or more."""
    from bo.calibration.pipeline import JAMMED, agreement

    columns = list(kpis) + [JAMMED]
    lines = ["| set | condition | runs | " + " | ".join(kpis) + " | largest error |",
             "| --- | --- | ---: |" + " ---: |" * (len(kpis) + 1)]
    for name in probe["sets"]:
        done = store.records(STAGE, batch_key=name, status="done")
        rows, worst, jams = [], None, []
        for condition in conditions_of(probe, name):
            runs = np.array([[r.kpis.get(k, math.nan) for k in columns] for r in done
                             if r.condition == condition and r.kpis], dtype=float).reshape(-1, len(columns))
            lab = measured.condition(condition).kpis if condition in measured.names else {}
            found = {a.kpi: a for a in agreement(runs, columns, lab) if a.n}
            cells = [f"{found[k].relative_error_pct:+.1f}" + ("" if found[k].within_ci else "*") if k in found
                     else "-" for k in kpis]
            for a in found.values():
                if condition != calibration_condition and (worst is None or abs(a.relative_error_pct)
                                                           > abs(worst[0])):
                    worst = (a.relative_error_pct, f"{condition} {a.kpi}", standard_error_pct(a))
            jammed = int((runs[:, -1] == 1).sum())
            if jammed:  # a set that jams on a condition cannot validate, whatever its flowing runs' errors
                jams.append(f"{condition} {jammed} of {len(runs)}")
            rows.append(f"| {name} | {condition} | {len(runs) - jammed} | " + " | ".join(cells) + " |")
        largest = [] if worst is None else [f"{worst[0]:+.1f}" + ("" if math.isnan(worst[2]) else f" +- {worst[2]:.1f}")
                                            + f" % ({worst[1]})"]
        last = " ".join(largest + ([f"jammed: {', '.join(jams)}"] if jams else []))
        rows = [r + " |" for r in rows[:-1]] + [rows[-1] + (f" {last} |" if last else " |")]
        lines += rows
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("probe", help="the probe file (YAML)")
    parser.add_argument("--workers", type=int, default=1, help="one-thread worker processes (default 1)")
    parser.add_argument("--store", help="the store, instead of the probe file's")
    parser.add_argument("--data", default=None, help="measured-data JSON for the errors (default: the paper's Table 2)")
    parser.add_argument("--calibration-condition", default=None,
                        help="a condition left out of each set's largest error (the one calibrated on, e.g. 50-50)")
    args = parser.parse_args()
    if args.workers < 1:
        raise out_of_range("--workers", args.workers, "an integer >= 1", "probe_sets.py")
    probe = load_probe(args.probe)
    if args.store:
        probe["store"] = args.store
    store = run_probe(probe, args.workers)
    from torchdem.drawdown import CALIBRATION_KPIS_DEM
    print(summary_table(store, probe, CALIBRATION_KPIS_DEM), end="")
    from torchdem.measured import load_measured
    print("\nRelative error against the measured data, % (* outside its 95 % CI):\n")
    print(error_table(store, probe, CALIBRATION_KPIS_DEM, load_measured(args.data), args.calibration_condition),
          end="")


if __name__ == "__main__":
    exit_on_bad_input("probe_sets.py", main)
