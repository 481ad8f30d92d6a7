"""The CV R^2 a surrogate can reach on single DEM runs: the noise ceiling of each KPI and of Eq. 7.

A held-out run carries its own DEM noise, which no surrogate predicts, so even the noise-free
objective scores only ``1 - noise variance / variance across the design`` in cross-validation
(``bo.surrogate.gp.r2_ceiling``). This prints that ceiling from a campaign store: the spread of the
KPIs over the done runs of one stage, the noise pooled from every group of replicate runs (same
point, condition and batch) in the noise store (default: the same store).

    python scripts/noise_ceiling.py campaigns/table2/lab_4s.sqlite --noise-from campaigns/geometry_lab.sqlite \
        --noise-batch mirror=True     # the lab geometry's replicates of the geometry study

If the Eq. 7 ceiling is below the surrogate's ``target_r2``, the paper's rule on the total variance
can only stop at the budget; ``surrogate.target_basis=explainable`` counts R^2 against the ceiling.
Runs whose discharge jammed are left out of both. Stores are only read.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from bo.calibration.pipeline import pooled_replicate_covariance
from bo.campaign.progress import open_read_only
from bo.screening.pipeline import measured_name
from bo.surrogate.gp import objective_noise_variance, r2_ceiling
from bo.surrogate.objective import ObjectiveSpec
from kpi.loadcell import discharge_jammed
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import ConfigError, exit_on_bad_input
from torchdem.measured import load_measured

KPIS = CALIBRATION_KPIS_DEM


def _rows(path: Path, sql: str, args: tuple = ()) -> list:
    conn = open_read_only(path, "noise_ceiling")
    try:
        return conn.execute(sql, args).fetchall()
    finally:
        conn.close()


def _kpi_row(values: dict, kpis) -> list[float] | None:
    """The run's KPIs, or None if one is missing or its discharge jammed (a box that did not flow
    measured no KPI: its zeros are no sample of the spread nor of the noise)."""
    if discharge_jammed(values):
        return None
    row = [values.get(k) for k in kpis]
    return None if any(v is None or not np.isfinite(v) for v in row) else [float(v) for v in row]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store", type=Path, help="campaign store whose runs give the spread")
    ap.add_argument("--noise-from", type=Path, default=None, help="store whose replicate groups give the noise")
    ap.add_argument("--noise-batch", default="", help="only replicate groups whose batch key contains this")
    ap.add_argument("--stage", default="screening", help="stage whose done runs give the spread")
    ap.add_argument("--condition", default="50-50")
    ap.add_argument("--kpis", nargs="+", default=list(KPIS))
    args = ap.parse_args(argv)
    kpis = tuple(args.kpis)

    done = [json.loads(text or "null") or {} for (text,) in _rows(
        args.store, "SELECT kpis FROM evaluations WHERE status = 'done' AND stage = ? AND condition = ?",
        (args.stage, args.condition))]
    spread = [r for values in done if (r := _kpi_row(values, kpis)) is not None]
    jammed = sum(map(discharge_jammed, done))
    if len(spread) < 3:
        raise ConfigError(f"{args.store}: {len(spread)} done runs of stage {args.stage!r} at {args.condition} with "
                          f"every KPI of {list(kpis)}; the spread needs at least 3")
    groups: dict[tuple, list] = defaultdict(list)
    noise_store = args.noise_from or args.store
    for stage, key, point, cond, text in _rows(noise_store, "SELECT stage, batch_key, point_index, condition, kpis "
                                               "FROM evaluations WHERE status = 'done'"):
        if args.noise_batch in key and (r := _kpi_row(json.loads(text or "null") or {}, kpis)) is not None:
            groups[(stage, key, point, cond)].append(r)
    if not groups:
        raise ConfigError(f"{noise_store}: no done runs with every KPI of {list(kpis)} in a batch key containing "
                          f"{args.noise_batch!r}")
    width = max(len(g) for g in groups.values())
    reps = np.full((len(groups), width, len(kpis)), np.nan)
    for i, g in enumerate(groups.values()):
        reps[i, :len(g)] = g
    cov, dof = pooled_replicate_covariance(reps)
    Y = np.asarray(spread)
    measured = load_measured(None).condition(args.condition).kpis
    spec = ObjectiveSpec(kpis, tuple(measured[measured_name(k)].mean for k in kpis), source="noise_ceiling")
    print(f"spread: {len(Y)} runs of {args.stage} at {args.condition} in {args.store}"
          + (f" ({jammed} that jammed left out)" if jammed else ""))
    print(f"noise: one run's scatter pooled over {dof} degrees of freedom in {noise_store}"
          + (f" (batches with {args.noise_batch!r})" if args.noise_batch else "") + "\n")
    print("| KPI | sd across runs | sd of one run | ceiling |\n| --- | ---: | ---: | ---: |")
    for j, k in enumerate(kpis):
        print(f"| {k} | {Y[:, j].std():.3g} | {np.sqrt(cov[j, j]):.3g} | {1 - cov[j, j] / Y[:, j].var():.3f} |")
    actual = spec(Y)
    noise = objective_noise_variance(Y, np.tile(np.diag(cov), (len(Y), 1)), spec, "per_kpi")
    print(f"| Eq. 7 (equal weights) | {actual.std():.3g} | {np.sqrt(noise.mean()):.3g} | "
          f"{r2_ceiling(actual, noise):.3f} |")


if __name__ == "__main__":
    exit_on_bad_input("noise_ceiling.py", main)
