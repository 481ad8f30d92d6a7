"""Each checking stage of a campaign store against the measured data: per stage, batch and condition, the mean
of every measured KPI over the finished runs, its relative error and whether it stands inside the lab's 95 % CI.
What a calibration's report prints at its end, read while the campaign still runs (the store is only read).

    python scripts/stage_kpis.py campaigns/table2/lab_split.sqlite
    python scripts/stage_kpis.py STORE --stages round-1 --data my_lab.json

Runs that jammed (``discharge_jammed`` 1) are counted apart and left out of the means: their
box did not flow, so their KPIs measure no discharge. A batch that came with a copied store
(``bo.campaign.store.copy_store``) is marked with the store it was made in.
"""
from __future__ import annotations

import argparse
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bo.calibration.pipeline import JAMMED, KPIAgreement, agreement
from bo.campaign.progress import copied_from, done_records, open_read_only
from bo.screening.pipeline import measured_for, measured_name
from torchdem.measured import MeasuredData, load_measured
from torchdem.errors import exit_on_bad_input

CHECKS = ("verification", "validation")


@dataclass(frozen=True)
class StageKPIs:
    """One stage's runs of one batch on one condition.

    Attributes:
        stage, batch_key, condition: which runs.
        copied_from: the store the batch was made in, if it came with a copy of it, else None.
        runs: finished runs that flowed (``jammed``: those left out).
        agreement: per KPI the condition measured, in the measured data's order, the DEM's mean and sd over the
            runs that flowed against the lab (``bo.calibration.pipeline.agreement``, as the campaign's report;
            a reduced box's ``<x>_full_<unit>`` stands for the lab's ``<x>_<unit>``).
    """

    stage: str
    batch_key: str
    condition: str
    copied_from: str | None
    runs: int
    agreement: tuple[KPIAgreement, ...]

    @property
    def jammed(self) -> int:
        """Runs left out of the means because their discharge jammed."""
        return self.agreement[0].jammed if self.agreement else 0

    @property
    def means(self) -> dict[str, float]:
        return {a.kpi: a.dem_mean for a in self.agreement}

    @property
    def sds(self) -> dict[str, float]:
        return {a.kpi: a.dem_std for a in self.agreement}


def stage_kpis(store: str | Path, measured: MeasuredData, stages=CHECKS) -> list[StageKPIs]:
    """The checking stages' KPIs of ``store`` against ``measured`` (module docstring), in the store's task order."""
    path = Path(store)
    conn = open_read_only(path, "stage_kpis")
    try:
        source, last = copied_from(conn)
    finally:
        conn.close()
    conditions = {c.name: c for c in measured.conditions}
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    copied: dict[tuple[str, str, str], bool] = {}
    for r in done_records(path, None, "stage_kpis"):
        if r.stage in stages and r.condition in conditions:
            key = (r.stage, r.batch_key, r.condition)
            groups[key].append({n: math.nan if v is None else float(v) for n, v in (r.kpis or {}).items()})
            copied[key] = r.task_id <= last
    out = []
    for key, runs in groups.items():
        lab = conditions[key[2]].kpis
        kpis = sorted(measured_for(list(dict.fromkeys(n for k in runs for n in k)), lab),
                      key=lambda n: list(lab).index(measured_name(n))) + [JAMMED]   # the measured data's order
        replicates = np.array([[k.get(n, math.nan) for n in kpis] for k in runs])
        agreed = agreement(replicates, kpis, lab)
        flowed = len(runs) - (agreed[0].jammed if agreed else 0)
        out.append(StageKPIs(*key, source if copied[key] else None, flowed, agreed))
    return out


def format_stage_kpis(rows: list[StageKPIs]) -> str:
    """Markdown: a table per stage and batch, a row per condition and a cell per KPI: the mean, its relative
    error against the measured mean and * where it stands outside the measured 95 % CI."""
    lines: list[str] = []
    for stage, batch in dict.fromkeys((r.stage, r.batch_key) for r in rows):
        block = [r for r in rows if (r.stage, r.batch_key) == (stage, batch)]
        kpis = list(dict.fromkeys(a.kpi for r in block for a in r.agreement))
        origin = f" (came with the copy of {block[0].copied_from})" if block[0].copied_from else ""
        lines += [f"## {stage}, batch {batch}{origin}", "",
                  "Mean over the runs that flowed (relative error against the lab; * outside the lab's 95 % CI).", "",
                  "| condition | runs | jammed | " + " | ".join(kpis) + " |",
                  "| --- | ---: | ---: | " + " | ".join("---:" for _ in kpis) + " |"]
        for r in block:
            by_kpi = {a.kpi: a for a in r.agreement}
            cells = [f"{a.dem_mean:.2f} ({a.relative_error_pct:+.1f} %{'' if a.within_ci else '*'})"
                     if (a := by_kpi.get(n)) is not None and math.isfinite(a.dem_mean) else "-" for n in kpis]
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
    print(format_stage_kpis(stage_kpis(args.store, measured, tuple(args.stages))), end="")


if __name__ == "__main__":
    exit_on_bad_input("stage_kpis.py", main)
