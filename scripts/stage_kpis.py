"""Each checking stage of a campaign store against the measured data: per stage, batch and condition, the mean
of every measured KPI over the finished runs, its relative error and whether it stands inside the lab's 95 % CI.
What a calibration's report prints at its end, read while the campaign still runs (the store is only read).

    python scripts/stage_kpis.py campaigns/table2/lab_split.sqlite
    python scripts/stage_kpis.py STORE --stages round-1 --data my_lab.json

Runs that jammed (``kpi.loadcell.discharge_jammed``) are counted apart and left out of the means: their
box did not flow, so their KPIs measure no discharge. A batch that came with a copied store
(``bo.campaign.store.copy_store``) is marked with the store it was made in.
"""
from __future__ import annotations

import argparse
import math
import statistics
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from bo.campaign.progress import copied_from, done_records, open_read_only
from bo.screening.pipeline import measured_for, measured_name
from kpi.loadcell import discharge_jammed
from torchdem.measured import MeasuredData, load_measured

CHECKS = ("verification", "validation")


@dataclass(frozen=True)
class StageKPIs:
    """One stage's runs of one batch on one condition.

    Attributes:
        stage, batch_key, condition: which runs.
        copied_from: the store the batch was made in, if it came with a copy of it, else None.
        runs: finished runs that flowed; jammed: finished runs that jammed (left out of the means).
        means, sds: KPI (the DEM's name) -> mean and sample sd over ``runs`` (sd NaN below 2 runs), for the KPIs
            the condition measured (``bo.screening.pipeline.measured_for``: a reduced box's ``<x>_full_<unit>``
            for the lab's ``<x>_<unit>``).
    """

    stage: str
    batch_key: str
    condition: str
    copied_from: str | None
    runs: int
    jammed: int
    means: dict[str, float]
    sds: dict[str, float]


def stage_kpis(store: str | Path, measured: MeasuredData, stages=CHECKS) -> list[StageKPIs]:
    """The checking stages' KPI means of ``store`` (module docstring), in the store's task order."""
    path = Path(store)
    conn = open_read_only(path, "stage_kpis")
    try:
        source, last = copied_from(conn)
    finally:
        conn.close()
    conditions = {c.name: c for c in measured.conditions}
    groups: dict[tuple[str, str, str], list] = defaultdict(list)
    copied: dict[tuple[str, str, str], bool] = {}
    for r in done_records(path, None, "stage_kpis"):
        if r.stage not in stages or r.condition not in conditions:
            continue
        key = (r.stage, r.batch_key, r.condition)
        groups[key].append({n: math.nan if v is None else float(v) for n, v in (r.kpis or {}).items()})
        copied[key] = r.task_id <= last
    out = []
    for key, runs in groups.items():
        flowed = [k for k in runs if not discharge_jammed(k)]
        lab = conditions[key[2]].kpis
        kpis = sorted(measured_for(list(dict.fromkeys(n for k in flowed for n in k)), lab),
                      key=lambda n: list(lab).index(measured_name(n)))      # in the measured data's order
        values = {n: [k[n] for k in flowed if math.isfinite(k.get(n, math.nan))] for n in kpis}
        out.append(StageKPIs(*key, source if copied[key] else None, len(flowed), len(runs) - len(flowed),
                             {n: statistics.fmean(v) if v else math.nan for n, v in values.items()},
                             {n: statistics.stdev(v) if len(v) > 1 else math.nan for n, v in values.items()}))
    return out


def format_stage_kpis(rows: list[StageKPIs], measured: MeasuredData) -> str:
    """Markdown: a table per stage and batch, a row per condition and a cell per KPI: the mean, its relative
    error against the measured mean and * where it stands outside the measured 95 % CI."""
    conditions = {c.name: c for c in measured.conditions}
    lines: list[str] = []
    for stage, batch in dict.fromkeys((r.stage, r.batch_key) for r in rows):
        block = [r for r in rows if (r.stage, r.batch_key) == (stage, batch)]
        kpis = list(dict.fromkeys(n for r in block for n in r.means))
        origin = f" (came with the copy of {block[0].copied_from})" if block[0].copied_from else ""
        lines += [f"## {stage}, batch {batch}{origin}", "",
                  "Mean over the runs that flowed (relative error against the lab; * outside the lab's 95 % CI).", "",
                  "| condition | runs | jammed | " + " | ".join(kpis) + " |",
                  "| --- | ---: | ---: | " + " | ".join("---:" for _ in kpis) + " |"]
        for r in block:
            cells = []
            for n in kpis:
                lab = measured_for([n], conditions[r.condition].kpis).get(n)
                mean = r.means.get(n, math.nan)
                if lab is None or not math.isfinite(mean):
                    cells.append("-" if not math.isfinite(mean) else f"{mean:.2f}")
                    continue
                error = 100.0 * (mean / lab.mean - 1.0) if lab.mean else math.nan
                outside = "*" if abs(mean - lab.mean) > lab.ci95 else ""
                cells.append(f"{mean:.2f} ({error:+.1f} %{outside})")
            lines.append(f"| {r.condition} | {r.runs} | {r.jammed} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines) if lines else "No finished runs of these stages on the measured conditions.\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store", help="a campaign store (SQLite)")
    parser.add_argument("--stages", nargs="+", default=list(CHECKS),
                        help="the stages to read (default: verification validation)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    args = parser.parse_args(argv)
    measured = load_measured(args.data)
    print(format_stage_kpis(stage_kpis(args.store, measured, tuple(args.stages)), measured), end="")


if __name__ == "__main__":
    main()
