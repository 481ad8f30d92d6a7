"""Where each shipped campaign stands: runs done and left per stage, the worker time spent, and the
worker time the rest of what is stored will take (``bo.campaign.progress``), per cost class
(geometry and particle shape).

    python scripts/campaign_status.py                       # every store of campaigns/manifest.json
    python scripts/campaign_status.py campaigns/table2/lab.sqlite --workers 2
    python scripts/campaign_status.py campaigns/table2/lab_round.sqlite --profile lab_round
    python scripts/campaign_status.py campaigns/table2/*.sqlite    # and what all of them cost together

With ``--profile NAME`` (and ``--override key=value ...``, as on ``torchdem-calibrate``'s command line)
it also sets the calibration's plan beside the store (``bo.calibration.plan``): the most runs of every
stage, those reached or not, what is done of them and how long the rest takes at the store's cost of
a run of each condition (``--costs-from STORE ...``: where the store has no run of a condition yet,
its runs in those stores of the same model).

Worker time is one-thread process time, as the campaigns run (``executor=dask``, one thread per
worker): divide by the number of workers for wall time. Stages not reached yet hold no rows and
are not in the estimate (the calibration's surrogate rounds, verification and validation) unless
``--profile`` gives the plan. Given several stores, it ends with a table of the DEM runs each made and
their worker time, and the sum: the cost of a body of work (a run adopted from another store, that
took another's result, or that came with a copy of another store, ``store_from``, counts in the store that
made it). Stores are only read.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bo.calibration.plan import campaign_plan, plan_progress
from bo.campaign.progress import StoreProgress, run_costs, store_progress
from torchdem.drawdown import JAM_FRACTION
from torchdem.errors import exit_on_bad_input

ROOT = Path(__file__).resolve().parents[1]


def _hours(seconds: float | None) -> str:
    return "?" if seconds is None else f"{seconds / 3600:.1f} h"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 60 else f"{seconds / 60:.1f} min"


def report(progress: StoreProgress, workers: int) -> str:
    lines = [f"## {progress.path}", ""]
    for stage, counts in progress.status.items():
        lines.append(f"- {stage}: " + ", ".join(f"{n} {state}" for state, n in sorted(counts.items())))
        keys = progress.batches.get(stage, {})
        if len(keys) > 1 and stage != "screening":  # earlier designs (surrogate.reuse_designs names them)
            lines += [f"  - batch {key}: " + ", ".join(f"{n} {state}" for state, n in sorted(c.items()))
                      for key, c in keys.items()]
    lines += ["", "| runs of | done | left | failed | worker time per run |", "| --- | ---: | ---: | ---: | ---: |"]
    for c in progress.classes:
        per_run = "-" if c.seconds_per_run is None else _duration(c.seconds_per_run)
        if c.borrowed:
            per_run = f"{c.bound} {per_run} (nearest class)"
        lines.append(f"| {c.label} | {c.done} | {c.remaining} | {c.failed} | {per_run} |")
    left, bound = progress.remaining_s, progress.remaining_bound
    lines += ["", f"Spent: {_hours(progress.spent_s)} of worker time. Left in the store: {progress.remaining_runs} "
                  f"runs, {bound + ' ' if bound else ''}{_hours(left)} of worker time"
                  + ("" if left is None else f", {bound or 'about'} {_hours(left / workers)} on {workers} workers")
                  + (" (classes without finished runs borrow their nearest class's figure)" if bound else "")
                  + ". Stages not reached yet are not counted."]
    if progress.copied_runs:
        lines.append(f"The store was copied from {progress.copied_from}: {progress.copied_runs} finished runs "
                     f"({_hours(progress.copied_s)}) came with the copy and are counted there, not in Spent.")
    d = progress.discharge
    if d.get("not ended") or d.get("ended"):
        lines += ["", f"Discharge of the done runs: {d['ended']} ended, {d['not ended']} stopped while the upper box still "
                      f"emptied (their lower box and photos are not the lab's end state: run.max_discharge_time_s)"
                  + (f", {d['not recorded']} made before runs recorded it" if d.get("not recorded") else "")
                  + (f"; {d['jammed']} jammed (less than {JAM_FRACTION:.0%} of the fill left the upper box: the grains "
                     f"arched over the slot)" if d.get("jammed") else "") + "."]
    return "\n".join(lines)


def totals_report(stores: list[str], workers: int) -> str:
    """The DEM runs each store made (done or failed, with a wall time of their own) and their worker
    time, and the sum over the stores."""
    lines = ["## All stores", "", "| store | DEM runs made | worker time |", "| --- | ---: | ---: |"]
    runs, seconds = 0, 0.0
    for store in stores:
        made = [c.seconds for c in run_costs(store) if c.seconds is not None and not c.copied]
        runs, seconds = runs + len(made), seconds + sum(made)
        lines.append(f"| {store} | {len(made)} | {_hours(sum(made))} |")
    lines += [f"| all {len(stores)} | {runs} | {_hours(seconds)} |", "",
              f"Together: {runs} DEM runs, {_hours(seconds)} of worker time, {_hours(seconds / workers)} on {workers} "
              "workers."]
    return "\n".join(lines)


_SOURCES = {"store": "", "costs_from": " (--costs-from)", "all conditions": " (all conditions)", "": ""}


def plan_report(profile: str, overrides: list[str], store: str, workers: int, costs_from: list[str]) -> str:
    """The plan of ``torchdem-calibrate profile=<profile> <overrides>`` beside ``store``."""
    from hydra import compose, initialize_config_dir

    from bo.cli.calibrate import calibration_settings_from
    from bo.cli.common import plain_config
    from torchdem.cli import CONF_DIR
    from torchdem.measured import load_measured

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=[f"profile={profile}", *overrides]))
    plan = campaign_plan(calibration_settings_from(plain), load_measured(plain.get("measured")))
    rows = plan_progress(plan, store, costs_from)
    lines = [f"Plan of profile={profile}{' ' + ' '.join(overrides) if overrides else ''}: {plan.text()}.", "",
             "| stage | condition | runs at most | done | left | worker time per run |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for r in rows:
        per_run = "?" if r.seconds_per_run is None else _duration(r.seconds_per_run)
        lines.append(f"| {r.stage} | {r.condition} | {r.planned} | {r.done} | {r.left} | "
                     f"{per_run}{_SOURCES[r.cost_source]} |")
    left = [r.seconds_left for r in rows if r.left]
    total = None if None in left else sum(left)
    borrowed = any(r.cost_source == "all conditions" and r.left for r in rows)
    lines += ["", f"Left of the plan: at most {sum(r.left for r in rows)} runs, "
                  + ("? h" if total is None else f"{_hours(total)} of worker time, {_hours(total / workers)} on "
                     f"{workers} workers")
                  + (" (a condition without finished runs takes the median of all of them)" if borrowed else "")
                  + ". The surrogate stage may stop before its budget."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="*", help="store files (default: those of campaigns/manifest.json)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes, for the wall-time figure")
    parser.add_argument("--profile", help="a calibration profile (conf/profile/): set its plan beside the store")
    parser.add_argument("--override", nargs="*", default=[], help="more overrides of that calibration, key=value")
    parser.add_argument("--costs-from", nargs="*", default=[],
                        help="stores of the same model whose runs give a condition's cost where the store has none")
    args = parser.parse_args()
    if args.workers < 1:
        raise SystemExit(f"--workers {args.workers}: allowed is an int >= 1")
    if args.profile and len(args.stores) != 1:
        raise SystemExit(f"--profile {args.profile}: give the one store of that campaign, not {len(args.stores)}")
    stores = args.stores or [str(ROOT / "campaigns" / s["store"])
                             for s in json.loads((ROOT / "campaigns" / "manifest.json").read_text())["stores"]]
    print("\n\n".join(report(store_progress(s), args.workers) for s in stores))
    if len(stores) > 1:
        print("\n" + totals_report(stores, args.workers))
    if args.profile:
        print("\n" + plan_report(args.profile, args.override, stores[0], args.workers, args.costs_from))


if __name__ == "__main__":
    exit_on_bad_input("campaign_status.py", main)
