"""Command-line entry point ``torchdem-kpi``: measure draw-down KPIs from files, print JSON.

Contract: three subcommands, each reading one file and printing one JSON object to stdout
whose keys carry their units (``_deg``, ``_kg``, ``_kg_s`` = kg/s, ``_s``, ``_px``)::

    torchdem-kpi angles IMAGE --kind repose|shear [--crop X0 Y0 X1 Y1] [--pixel-aspect R]
    torchdem-kpi segregation IMAGE [--crop X0 Y0 X1 Y1] [colour thresholds]
    torchdem-kpi loadcell FILE.csv --initial-mass KG [--gate-open S] [--fit-window S S]

Bad input (missing file, crop outside the image, no heap, broken CSV, ...) prints
``torchdem-kpi: error: <file>: <problem>`` to stderr and exits with status 2, like argparse's
own usage errors. argparse rather than Hydra keeps ``kpi`` usable without the simulator's
config tree; the CLI only turns arguments into the typed configs of the library modules.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from kpi.angles import SurfaceConfig, measure_surface_angle
from kpi.errors import KPIInputError
from kpi.io import CropBox, read_image, read_loadcell_csv
from kpi.loadcell import DischargeConfig, measure_discharge
from kpi.segregation import SegmentationConfig, measure_segregation

PROG = "torchdem-kpi"


def _crop_box(args: argparse.Namespace) -> CropBox | None:
    return None if args.crop is None else CropBox(*args.crop)


def _box_list(box: CropBox) -> list[int]:
    return [box.x0, box.y0, box.x1, box.y1]


def run_angles(args: argparse.Namespace) -> dict:
    config_fields = {}
    if args.background is not None:
        config_fields["background_bgr"] = tuple(args.background)
    if args.background_delta_e is not None:
        config_fields["background_delta_e"] = args.background_delta_e
    config = SurfaceConfig(**config_fields)
    image = read_image(args.image)
    result = measure_surface_angle(
        image, args.kind, crop_box=_crop_box(args), config=config, pixel_aspect=args.pixel_aspect, source=str(args.image)
    )
    return {
        "kpi": "angle_of_repose" if args.kind == "repose" else "shear_angle",
        "source": result.source,
        "angle_deg": result.angle_deg,
        "left_angle_deg": result.left_angle_deg,
        "right_angle_deg": result.right_angle_deg,
        "split_x_px": result.split_x_px,
        "crop_px": _box_list(result.crop_box),
        "pixel_aspect": result.pixel_aspect,
    }


def run_segregation(args: argparse.Namespace) -> dict:
    defaults = SegmentationConfig()
    config = SegmentationConfig(
        pellet_b_max=args.pellet_b_max,
        pellet_white_l_min=None if args.no_white_pellets else defaults.pellet_white_l_min,
        sinter_l_max=args.sinter_l_max,
        sinter_chroma_max=args.sinter_chroma_max,
        vertical_segregation_slices=args.vertical_slices,
        horizontal_segregation_slices=args.horizontal_slices,
        ddof=args.ddof,
        min_component_fraction=args.min_component_fraction,
    )
    image = read_image(args.image)
    result = measure_segregation(image, crop_box=_crop_box(args), config=config, source=str(args.image))

    def direction(slices) -> dict:
        return {
            "pellet_rsd": slices.pellet_rsd,
            "sinter_rsd": slices.sinter_rsd,
            "pellet_fraction": slices.pellet_fraction.tolist(),
            "sinter_fraction": slices.sinter_fraction.tolist(),
            "slice_bounds_px": [list(bounds) for bounds in slices.slice_bounds_px],
        }

    return {
        "kpi": "segregation",
        "source": result.source,
        "ddof": result.ddof,
        "heap_box_px": _box_list(result.heap_box),
        "vertical": direction(result.vertical),
        "horizontal": direction(result.horizontal),
    }


def run_loadcell(args: argparse.Namespace) -> dict:
    config = DischargeConfig(
        filter_sigma_s=args.filter_sigma,
        gate_open_s=args.gate_open,
        fit_window_s=tuple(args.fit_window),
        final_window_s=args.final_window,
    )
    signal = read_loadcell_csv(
        args.csv,
        time_column=args.time_column,
        mass_column=args.mass_column,
        required_until_s=config.fit_window_end_s,
    )
    result = measure_discharge(signal, args.initial_mass, config)
    return {
        "kpi": "discharge",
        "source": signal.source,
        "mass_flow_rate_kg_s": result.mass_flow_rate_kg_s,
        "lower_box_mass_kg": result.lower_box_mass_kg,
        "initial_mass_kg": result.initial_mass_kg,
        "final_upper_mass_kg": result.final_upper_mass_kg,
        "discharge_end_s": result.discharge_end_s,
        "discharge_duration_s": result.discharge_duration_s,
        "fit_window_s": list(result.fit_window_s),
        "filter_sigma_s": config.filter_sigma_s,
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description="Measure draw-down test KPIs from images and load-cell records.")
    commands = parser.add_subparsers(dest="command", required=True)

    crop_help = "region of interest in pixels, half-open: columns X0..X1-1, rows Y0..Y1-1 (default: whole image)"

    angles = commands.add_parser("angles", help="angle of repose (lower box) or shear angle (upper box)")
    angles.add_argument("image", help="PNG or JPEG photo or render")
    angles.add_argument("--kind", choices=("repose", "shear"), required=True,
                        help="repose: heap in the lower box; shear: funnel left in the upper box")
    angles.add_argument("--crop", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), help=crop_help)
    angles.add_argument("--pixel-aspect", type=float, default=1.0, help="pixel height / pixel width (default 1)")
    angles.add_argument("--background", type=int, nargs=3, metavar=("B", "G", "R"),
                        help="background colour to remove (default: the render green 0 255 0)")
    angles.add_argument("--background-delta-e", type=float,
                        help="fixed Delta E threshold between background and material (default: Otsu)")
    angles.set_defaults(run=run_angles)

    segregation = commands.add_parser("segregation", help="vertical and horizontal segregation RSD in the lower box")
    segregation.add_argument("image", help="PNG or JPEG photo or render")
    segregation.add_argument("--crop", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"), help=crop_help)
    defaults = SegmentationConfig()
    segregation.add_argument("--pellet-b-max", type=float, default=defaults.pellet_b_max,
                             help="blue pellet if b* <= this (default %(default)s)")
    segregation.add_argument("--no-white-pellets", action="store_true",
                             help="do not count bright neutral pixels as white-painted pellets")
    segregation.add_argument("--sinter-l-max", type=float, default=defaults.sinter_l_max,
                             help="sinter if L* <= this (default %(default)s)")
    segregation.add_argument("--sinter-chroma-max", type=float, default=defaults.sinter_chroma_max,
                             help="sinter if chroma <= this (default %(default)s)")
    segregation.add_argument("--vertical-slices", type=int, default=defaults.vertical_segregation_slices,
                             help="bands stacked top to bottom for vertical segregation (default %(default)s)")
    segregation.add_argument("--horizontal-slices", type=int, default=defaults.horizontal_segregation_slices,
                             help="strips side by side for horizontal segregation (default %(default)s)")
    segregation.add_argument("--ddof", type=int, default=defaults.ddof, choices=(0, 1),
                             help="1: sample standard deviation (default), 0: population")
    segregation.add_argument("--min-component-fraction", type=float, default=defaults.min_component_fraction,
                             help="regions smaller than this share of the largest are not part of the heap "
                                  "(default %(default)s; 0 keeps all)")
    segregation.set_defaults(run=run_segregation)

    loadcell = commands.add_parser("loadcell", help="mass flow rate and lower-box mass from the load-cell record")
    loadcell.add_argument("csv", help="CSV with a header row: time (s) and upper-box mass (kg)")
    loadcell.add_argument("--initial-mass", type=float, required=True, help="mass filled into the upper box, kg")
    discharge = DischargeConfig()
    loadcell.add_argument("--gate-open", type=float, default=discharge.gate_open_s,
                          help="time at which the gate opened, s (default %(default)s)")
    loadcell.add_argument("--fit-window", type=float, nargs=2, metavar=("START", "END"),
                          default=list(discharge.fit_window_s), help="fit window after the gate opens, s (default 0.5 2.0)")
    loadcell.add_argument("--filter-sigma", type=float, default=discharge.filter_sigma_s,
                          help="Gaussian filter standard deviation, s (default %(default)s)")
    loadcell.add_argument("--final-window", type=float, default=discharge.final_window_s,
                          help="tail of the record averaged for the final mass, s (default %(default)s)")
    loadcell.add_argument("--time-column", default="time_s", help="header of the time column (default %(default)s)")
    loadcell.add_argument("--mass-column", default="mass_kg", help="header of the mass column (default %(default)s)")
    loadcell.set_defaults(run=run_loadcell)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; returns the process exit status (0 ok, 2 bad input)."""
    args = build_parser().parse_args(argv)
    try:
        report = args.run(args)
    except KPIInputError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
