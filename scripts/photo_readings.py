"""The segregation of runs' lower-box photos drawn again with shadows of several depths and read four
ways, beside the lab's: does the photo, rather than the physics, make a misfit?

A lab photo is lit through the glass, so the grains it shows through the gaps of the front layer lie
in shadow, and a threshold on dark grey counts that shadow as sinter. ``torchdem.render``'s
``shadow_depth`` paints what lies deeper than that behind the front layer near black. Each scene
(``scripts/run_parameter_set.py --scenes DIR``: the spheres a photo showed, its view and crop box) is
drawn again at every depth and measured with ``kpi.segregation``, as the run measured it. Four
readings of the paper's text: the sinter's or the pellet's RSD, and the slicing as ``kpi`` reads it
("vertical": 3 bands stacked, "horizontal": 6 strips side by side) or swapped (3 strips, 6 bands).

    python scripts/photo_readings.py DIR/lower_*.npz --shadow-depths 0 0.008 0.012 0.016
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from kpi.errors import KPIInputError
from kpi.io import CropBox
from kpi.segregation import SegmentationConfig, measure_segregation
from torchdem.errors import ConfigError, exit_on_bad_input
from torchdem.measured import load_measured
from torchdem.render import View, render_front

READINGS = (("as kpi reads it", SegmentationConfig()),
            ("slicing swapped", SegmentationConfig(vertical_segregation_slices=6, horizontal_segregation_slices=3)))


def load_scene(path: Path) -> dict:
    """A scene written by ``run_parameter_set.py --scenes``; a file without its arrays is refused by name."""
    try:
        with np.load(path) as f:
            scene = {k: f[k] for k in ("centres", "radii", "labels", "view", "crop", "condition", "seed")}
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError(f"{path}: not a photo scene of run_parameter_set.py --scenes ({exc})") from None
    return scene


def readings(scene: dict, shadow_depth: float | None) -> dict[str, float]:
    """``{"<reading>, <component>, <V|H>": RSD}`` of the scene drawn with ``shadow_depth`` (None: none)."""
    v = scene["view"]
    view = View(*map(float, v[:4]), metres_per_pixel=float(v[4]))
    image = render_front(scene["centres"], scene["radii"], scene["labels"], view, shadow_depth=shadow_depth)
    crop = CropBox(*map(int, scene["crop"]))
    out = {}
    for name, config in READINGS:
        try:
            seg = measure_segregation(image, crop_box=crop, config=config)
        except KPIInputError:
            continue
        # swapped: the "vertical" figure is the strips' (config.horizontal), the "horizontal" the bands'
        vertical, horizontal = (seg.vertical, seg.horizontal) if name == "as kpi reads it" else (seg.horizontal,
                                                                                                 seg.vertical)
        for component in ("sinter", "pellet"):
            out[f"{name}, {component}, V"] = getattr(vertical, f"{component}_rsd")
            out[f"{name}, {component}, H"] = getattr(horizontal, f"{component}_rsd")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", help="lower-box scenes (lower_<condition>_<seed>.npz)")
    parser.add_argument("--shadow-depths", nargs="+", type=float, default=[0.0, 0.008, 0.012, 0.016],
                        help="m behind the front layer; 0: no shadow (default 0 0.008 0.012 0.016)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    args = parser.parse_args()
    if any(not (math.isfinite(d) and d >= 0) for d in args.shadow_depths):
        parser.error(f"--shadow-depths {args.shadow_depths}: expected depths >= 0 m (0: no shadow)")
    measured = load_measured(args.data)
    keys = [f"{r}, {c}, {d}" for r, _ in READINGS for c in ("sinter", "pellet") for d in ("V", "H")]
    print("| condition | seed | shadow depth, mm | " + " | ".join(keys) + " |")
    print("| --- | ---: | ---: |" + " ---: |" * len(keys))
    for path in args.scenes:
        scene = load_scene(Path(path))
        condition = str(scene["condition"])
        try:
            lab = measured.condition(condition).kpis
            v, h = lab.get("segregation_rsd_vertical"), lab.get("segregation_rsd_horizontal")
            if v is not None and h is not None:
                print(f"| {condition} | lab | | " + " | ".join(f"{v.mean:.3f}" if k.endswith("V") else f"{h.mean:.3f}"
                                                              for k in keys) + " |")
        except ConfigError:
            pass
        for depth in args.shadow_depths:
            values = readings(scene, depth or None)
            print(f"| {condition} | {int(scene['seed'])} | {depth * 1000:g} | "
                  + " | ".join(f"{values[k]:.3f}" if k in values else "-" for k in keys) + " |")


if __name__ == "__main__":
    exit_on_bad_input("photo_readings.py", main)
