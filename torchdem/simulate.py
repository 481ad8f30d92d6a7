"""Run draw down tests and write what the lab would get: KPIs, load-cell files, photos.

Contract: :func:`simulate_drawdown` runs ``test`` for the given seeds as one batched ensemble
and writes into ``output_dir``:

* ``kpis.json``: ``units`` (every KPI's unit), ``scaling`` (how slice values are scaled to
  the full box), ``members`` (per replicate: seed, KPIs, KPIs that could not be measured with
  the reason, mass bookkeeping), ``summary`` (per KPI: mean, sample std, n) and ``run``
  (particles, steps, time step, wall time, particle-steps per second);
* ``loadcell_<seed>.csv``: the 50 Hz upper-box mass since the gate opened, in the CSV format
  ``torchdem-kpi`` and :func:`kpi.io.read_loadcell_csv` read (slice mass, kg);
* ``upper_<seed>.png`` / ``lower_<seed>.png``: front views in the lab photos' colours;
* ``vtk/`` frames if asked; ``checkpoint.pt`` while running (an interrupted run started again
  in the same directory resumes from it).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from kpi.io import write_image, write_loadcell_csv
from kpi.loadcell import LoadCellSignal
from torchdem.drawdown import KPI_UNITS, DrawDownResult, DrawDownTest


def summarise(result: DrawDownResult) -> dict[str, dict[str, float]]:
    """Per KPI: mean, sample standard deviation (ddof 1; 0 for one value) and the number of
    members where it was measured."""
    out = {}
    for name in KPI_UNITS:
        values = result.kpi_table(name)
        values = values[np.isfinite(values)]
        if values.size:
            out[name] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
                         "n": int(values.size)}
    return out


def simulate_drawdown(test: DrawDownTest, seeds: Sequence[int], output_dir: str | Path, device="cpu",
                      images: bool = True, vtk_interval_s: float | None = None, checkpoint_every_s: float = 0.5,
                      progress: Callable[[float, float], None] | None = None) -> dict:
    """Run and write (see the module docstring); returns the ``kpis.json`` content."""
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    vtk = (out / "vtk", vtk_interval_s) if vtk_interval_s else None
    result = test.run(replicates=len(seeds), seeds=list(seeds), device=device, progress=progress, vtk=vtk,
                      checkpoint=out / "checkpoint.pt", checkpoint_every=checkpoint_every_s)
    g = test.geometry
    members = []
    for k, (_, replicate, seed) in enumerate(result.members):
        t, m = result.loadcell[k]
        write_loadcell_csv(out / f"loadcell_{seed}.csv", LoadCellSignal(t, m, source="simulation"))
        if images and result.images[k]:  # a member isolated by the blow-up guard has no images
            write_image(out / f"upper_{seed}.png", result.images[k]["upper"])
            write_image(out / f"lower_{seed}.png", result.images[k]["lower"])
        members.append({"seed": seed, "replicate": replicate, "kpis": result.kpis[k], "not_measured": result.errors[k],
                        "mass_balance_kg": result.conservation[k]})
    steps = int(result.steps)
    bodies = [int(n) for n in result.particles]
    report = {
        "mixture": test.mixture.name,
        "units": dict(KPI_UNITS),
        "scaling": ("full box (no scaling)" if not g.is_slice else
                    f"slice of {g.slice_depth} m of a {g.depth} m deep box: *_full_* = slice value x "
                    f"{g.depth / g.slice_depth:g} (mass, mass in the lower box, mass flow rate); "
                    "angles, RSD and heights are not scaled"),
        "members": members,
        "summary": summarise(result),
        "run": {"bodies_per_member": bodies, "spheres_per_member": result.spheres, "steps": steps,
                "dt_s": result.dt, "wall_time_s": result.wall_time_s, "fill_time_s": result.build_time_s,
                "particle_steps_per_s": len(bodies) * result.spheres * steps
                / max(result.wall_time_s - result.build_time_s, 1e-9),
                "simulated_time_s": test.total_time},
    }
    (out / "kpis.json").write_text(json.dumps(report, indent=2, default=_json_default))
    return report


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"cannot write {type(x).__name__} to JSON")


def format_summary(report: dict) -> str:
    """A short human-readable table of the summary."""
    lines = [f"{report['mixture']}: {len(report['members'])} member(s), "
             f"{report['run']['bodies_per_member'][0]} bodies, {report['run']['steps']} steps, "
             f"{report['run']['wall_time_s']:.1f} s wall"]
    for name, s in report["summary"].items():
        unit = report["units"][name]
        spread = f" +/- {s['std']:.4g}" if s["n"] > 1 else ""
        lines.append(f"  {name:28s} {s['mean']:.4g}{spread} {unit}" + ("" if math.isfinite(s["mean"]) else " (!)"))
    return "\n".join(lines)
