"""What one parameter set gives on the calibration's own model: the runs a campaign would make at it,
their KPIs beside the measurement.

The model is the calibrate config's (Hydra overrides after ``--``, default ``profile=lab``), so a run
here is the run a campaign task of these parameters makes. Parameters not given keep the config's
values (``contact``, the mixture's densities, the extension's values). Each ``CONDITION:SEED`` runs
alone on one thread; with ``--json`` the rows are written as JSON too.

Usage::

    python scripts/run_parameter_set.py mu_s_pg=0.9 mu_s_sg=0.83 lobe_spacing_sinter=0.2679 \\
        --runs 50-50:0 50-50:1 -- profile=lab

``--images DIR`` keeps each run's front views (the photos its angles and segregation were measured
on), and ``--scenes DIR`` the spheres each photo shows, so another reading of them, or the photos
drawn again with shadows (``scripts/photo_readings.py``), needs no new run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from bo.cli.calibrate import calibration_model_for
from bo.screening.pipeline import measured_name
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.errors import ConfigError, exit_on_bad_input

KPIS = CALIBRATION_KPIS_DEM


def parse_parameters(items: list[str]) -> dict[str, float]:
    """``name=value`` items as a parameter set (names are checked by the model)."""
    params = {}
    for item in items:
        name, eq, value = item.partition("=")
        try:
            params[name] = float(value)
        except ValueError:
            raise ConfigError(f"parameter {item!r}: expected NAME=NUMBER, e.g. mu_s_pg=0.9") from None
        if not eq or not name:
            raise ConfigError(f"parameter {item!r}: expected NAME=NUMBER, e.g. mu_s_pg=0.9")
    return params


def save_images(images: dict, folder: Path, tag: str) -> None:
    """Writes a run's front views (``{"upper": BGR, "lower": BGR}``) as ``<view>_<tag>.png`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for view, image in images.items():
        path = folder / f"{view}_{tag}.png"
        if not cv2.imwrite(str(path), image):
            raise ConfigError(f"--images {folder}: could not write {path}")


def save_scenes(scenes: dict, folder: Path, condition: str, seed: int) -> None:
    """Writes each photo's spheres, view and crop box (``DrawDownResult.photo_scenes``) as
    ``<view>_<condition>_<seed>.npz`` in ``folder`` (read back by ``scripts/photo_readings.py``)."""
    folder.mkdir(parents=True, exist_ok=True)
    for view_name, scene in scenes.items():
        view, crop = scene["view"], scene["crop"]
        np.savez_compressed(folder / f"{view_name}_{condition}_{seed}.npz", centres=scene["centres"],
                            radii=scene["radii"], labels=scene["labels"], condition=condition, seed=seed,
                            view=np.array([view.x_min, view.x_max, view.z_min, view.z_max, view.metres_per_pixel]),
                            crop=np.array([crop.x0, crop.y0, crop.x1, crop.y1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("parameters", nargs="*", help="NAME=VALUE, e.g. mu_s_pg=0.9 lobe_spacing_sinter=0.2679")
    parser.add_argument("--runs", nargs="+", default=["50-50:0"], help="CONDITION:SEED, e.g. 50-50:0")
    parser.add_argument("--json", help="write the rows as JSON here too")
    parser.add_argument("--images", help="write each run's front views here (upper_/lower_<condition>_<seed>.png), "
                                         "for a measurement other than the KPIs' (kpi's command line reads them)")
    parser.add_argument("--scenes", help="write the spheres each photo shows here (upper_/lower_<condition>_<seed>.npz), "
                                         "to draw and measure the photos again (scripts/photo_readings.py)")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:cut])
    overrides = argv[cut + 1:] or ["profile=lab"]
    params = parse_parameters(args.parameters)
    torch.set_num_threads(1)
    _, model, measured = calibration_model_for(overrides)
    print(f"parameters: {params or 'the config values'}; model: {' '.join(overrides)}")
    rows = []
    for spec in args.runs:
        condition, _, seed = spec.partition(":")
        started = time.perf_counter()
        res = model.test_for(condition, [params]).run_members([(0, 0, int(seed or 0))])
        k = res.kpis[0]
        if args.images:
            save_images(res.images[0], Path(args.images), f"{condition}_{int(seed or 0)}")
        if args.scenes:
            save_scenes(res.photo_scenes[0], Path(args.scenes), condition, int(seed or 0))
        row = {"condition": condition, "seed": int(seed or 0), "wall_s": round(time.perf_counter() - started, 1),
               "kpis": k, "not_measured": res.errors[0]}
        rows.append(row)
        print(f"{condition} seed {row['seed']} ({row['wall_s']:.0f} s): "
              + ", ".join(f"{n} {k.get(n, float('nan')):.2f}" for n in KPIS)
              + f"; discharge ended {k.get('discharge_ended')}, jammed {k.get('discharge_jammed')}"
              + (f"; not measured: {row['not_measured']}" if row["not_measured"] else ""), flush=True)
    print("\n| condition | runs | " + " | ".join(KPIS) + " |")
    print("| --- | ---: |" + " ---: |" * len(KPIS))
    for condition in dict.fromkeys(r["condition"] for r in rows):
        mine = [r["kpis"] for r in rows if r["condition"] == condition]
        cells = [f"{np.nanmean([m.get(n, np.nan) for m in mine]):.2f}" for n in KPIS]
        print(f"| {condition} | {len(mine)} | " + " | ".join(cells) + " |")
        try:
            lab = measured.condition(condition).kpis
        except (KeyError, ConfigError):
            continue
        print("| measured | | " + " | ".join(f"{lab[measured_name(n)].mean:.2f}" if measured_name(n) in lab else ""
                                           for n in KPIS) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"parameters": params, "overrides": overrides, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    exit_on_bad_input("run_parameter_set.py", main)
