"""Which material carries the model's flow, per condition: the flow over the fit window broken down by
material and by half window (``torchdem.drawdown.FLOW_BREAKDOWN_KPIS``, kept with every run since they
were added), and how a condition's flow differs from a reference condition's, material by material.

    python scripts/flow_layers.py campaigns/table2/probe_flow_layers.sqlite
    python scripts/flow_layers.py STORE... --reference 50-50 --stage probe
    python scripts/flow_layers.py campaigns/table2/probe_paper_set_reverse.sqlite --by-set

The lab weighs the whole upper box on one load cell, so it cannot split its flow; the model can. The
question it answers: where the reverse layering (sinter at the bottom) flows faster than 50-50, is the
extra flow sinter or pellets, and does it come early or late in the window? The stores are only read,
so it may be run beside a campaign. Runs without the breakdown (older runs) and jammed runs are left out.
"""
from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path
from typing import Iterable

import numpy as np

from bo.campaign.progress import done_records
from kpi.loadcell import discharge_jammed
from torchdem.drawdown import FLOW_BREAKDOWN_KPIS
from torchdem.errors import exit_on_bad_input

TOTAL = "mass_flow_rate_full_kg_s"
PELLET, SINTER, EARLY, LATE = FLOW_BREAKDOWN_KPIS
COLUMNS = (TOTAL, PELLET, SINTER, EARLY, LATE)
HEADER = ("flow", "pellets", "sinter", "pellet share", "fill's share", "early half", "late half")


def fill_pellet_share(condition: str) -> float:
    """The pellets' mass share of a condition's fill from its name (``75-25``: 0.75; NaN if unnamed)."""
    m = re.match(r"^(\d+(?:\.\d+)?)-(\d+(?:\.\d+)?)", condition)
    return float(m.group(1)) / (float(m.group(1)) + float(m.group(2))) if m else float("nan")


def runs_by_condition(records: Iterable) -> dict[str, np.ndarray]:
    """Condition -> ``[runs, 5]`` (flow, pellets, sinter, early half, late half) kg/s of the runs that
    kept the breakdown and did not jam; a run stored under several sets (shared runs: equal parameters,
    seed and condition) counts once."""
    rows: dict[str, list[list[float]]] = defaultdict(list)
    seen = set()
    for r in records:
        key = (r.condition, r.seed, tuple(sorted(r.params.items())))
        if key in seen:
            continue
        seen.add(key)
        k = r.kpis or {}
        values = [np.nan if k.get(c) is None else float(k[c]) for c in COLUMNS]  # a store keeps NaN as null
        if discharge_jammed(k) or not np.isfinite(values).all():
            continue
        rows[r.condition].append(values)
    return {c: np.array(v) for c, v in rows.items()}


def runs_by_set(records: Iterable) -> dict[str, dict[str, np.ndarray]]:
    """Set -> :func:`runs_by_condition` of its runs, a set being one set of parameter values, named by the
    batch keys its runs were stored under (a probe's set names, ``table8 / table8_4_seeds`` where two sets
    of equal values share their runs), in the order the store first ran them."""
    groups: dict[tuple, list] = defaultdict(list)
    names: dict[tuple, list[str]] = defaultdict(list)
    for r in records:
        key = tuple(sorted(r.params.items()))
        groups[key].append(r)
        if r.batch_key not in names[key]:
            names[key].append(r.batch_key)
    return {" / ".join(names[key]): runs_by_condition(group) for key, group in groups.items()}


def _line(name: str, n: int, v: np.ndarray, share_of_fill: float) -> str:
    flow, pel, sin, early, late = v
    return (f"| {name} | {n} | {flow:.2f} | {pel:.2f} | {sin:.2f} | {pel / flow:.2f} | {share_of_fill:.2f} | "
            f"{early:.2f} | {late:.2f} |")


def format_flow(runs: dict[str, np.ndarray], reference: str | None = "50-50") -> str:
    """A table of each condition's mean breakdown (kg/s of the whole box), and each condition's
    difference from ``reference`` with its standard error (pooled over both conditions' runs)."""
    if not runs:
        return "no runs with the flow breakdown (runs made before it was kept, or none finished)\n"
    out = ["| condition | runs | " + " | ".join(HEADER) + " |", "| --- | ---: |" + " ---: |" * len(HEADER)]
    for c in sorted(runs):
        out.append(_line(c, len(runs[c]), runs[c].mean(0), fill_pellet_share(c)))
    if reference in runs:
        ref = runs[reference]
        out += ["", f"difference from {reference} (kg/s; +- one standard error where both have >= 2 runs)", "",
                "| condition | flow | pellets | sinter | early half | late half |",
                "| --- | ---: | ---: | ---: | ---: | ---: |"]
        for c in sorted(runs):
            if c == reference:
                continue
            d = runs[c].mean(0) - ref.mean(0)
            if len(runs[c]) > 1 and len(ref) > 1:
                se = np.sqrt(runs[c].var(0, ddof=1) / len(runs[c]) + ref.var(0, ddof=1) / len(ref))
                cells = [f"{a:+.2f} +- {b:.2f}" for a, b in zip(d, se)]
            else:
                cells = [f"{a:+.2f}" for a in d]
            out.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="+", help="campaign stores (SQLite)")
    parser.add_argument("--reference", default="50-50", help="the condition the others are set against")
    parser.add_argument("--stage", default=None, help="only this stage's runs (default: every stage)")
    parser.add_argument("--by-set", action="store_true",
                        help="one table per parameter set (a probe's sets), instead of pooling a condition's runs")
    args = parser.parse_args()
    records = [r for s in args.stores for r in done_records(Path(s), args.stage, "flow_layers: store")]
    if not args.by_set:
        print(format_flow(runs_by_condition(records), args.reference), end="")
        return
    for name, runs in runs_by_set(records).items():
        print(f"### {name}\n\n{format_flow(runs, args.reference)}")


if __name__ == "__main__":
    exit_on_bad_input("flow_layers.py", main)
