"""Where each shipped campaign stands: runs done and left per stage, the worker time spent, and the
worker time the rest of what is stored will take (``bo.campaign.progress``), per cost class
(geometry and particle shape).

    python scripts/campaign_status.py                       # every store of campaigns/manifest.json
    python scripts/campaign_status.py campaigns/table2/lab.sqlite --workers 2

Worker time is one-thread process time, as the campaigns run (``executor=dask``, one thread per
worker): divide by the number of workers for wall time. Stages not reached yet hold no rows and
are not in the estimate (the calibration's surrogate rounds, verification and validation).
Stores are only read.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from bo.campaign.progress import StoreProgress, store_progress
from torchdem.drawdown import JAM_FRACTION

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
    d = progress.discharge
    if d.get("not ended") or d.get("ended"):
        lines += ["", f"Discharge of the done runs: {d['ended']} ended, {d['not ended']} stopped while the upper box still "
                      f"emptied (their lower box and photos are not the lab's end state: run.max_discharge_time_s)"
                  + (f", {d['not recorded']} made before runs recorded it" if d.get("not recorded") else "")
                  + (f"; {d['jammed']} jammed (less than {JAM_FRACTION:.0%} of the fill left the upper box: the grains "
                     f"arched over the slot)" if d.get("jammed") else "") + "."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="*", help="store files (default: those of campaigns/manifest.json)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes, for the wall-time figure")
    args = parser.parse_args()
    if args.workers < 1:
        raise SystemExit(f"--workers {args.workers}: allowed is an int >= 1")
    stores = args.stores or [str(ROOT / "campaigns" / s["store"])
                             for s in json.loads((ROOT / "campaigns" / "manifest.json").read_text())["stores"]]
    print("\n\n".join(report(store_progress(s), args.workers) for s in stores))


if __name__ == "__main__":
    main()
