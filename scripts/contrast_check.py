"""The change of each KPI between two conditions at one parameter set, C = KPI(a) - KPI(b), of the lab
and at every parameter set that one or more campaign stores ran on both (``bo.discovery.contrast``):
does any parameter or candidate a campaign varied give the lab's C? The stores are only read, so it
may be run beside a campaign.

    python scripts/contrast_check.py campaigns/table2/*.sqlite --by-stage       # 25-75 less 75-25
    python scripts/contrast_check.py campaigns/table2/probe_contrast.sqlite --by-set    # every set's C
    python scripts/contrast_check.py STORE --between 50-50 75-25 --data my_lab.json
    python scripts/contrast_check.py campaigns/table2/lab_priors.sqlite --between 75-25 50-50 --regress \
        --at campaigns/table2/calibration_lab_priors.json
    python scripts/contrast_check.py campaigns/table2/lab_round.sqlite --between 50-50-reverse 50-50 --across-stages
"""
from __future__ import annotations

import argparse

from bo.calibration.document import calibrated_parameters
from bo.discovery.contrast import contrast_check, format_contrast
from torchdem.errors import exit_on_bad_input
from torchdem.measured import load_measured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="+", help="campaign stores (SQLite)")
    parser.add_argument("--between", nargs=2, default=["25-75", "75-25"], metavar=("A", "B"),
                        help="the two conditions, C = KPI(A) - KPI(B) (default 25-75 75-25)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    parser.add_argument("--by-stage", action="store_true", help="also the mean C per stage (a discovery's candidates)")
    parser.add_argument("--by-set", action="store_true", help="also every set's C, named by what it changes")
    parser.add_argument("--across-stages", action="store_true",
                        help="pair a parameter set's runs across the stages of its store (a calibrated set's "
                             "verification with its validation)")
    parser.add_argument("--regress", action="store_true",
                        help="also each KPI's C fitted on the parameters the sets vary (one campaign's store)")
    parser.add_argument("--at", default=None, metavar="CALIBRATION_JSON",
                        help="with --regress: also the fit's C at this calibration.json's calibrated set")
    args = parser.parse_args()
    check = contrast_check(args.stores, load_measured(args.data), *args.between, across_stages=args.across_stages)
    at = calibrated_parameters(args.at, "--at", held=True) if args.at else None
    print(format_contrast(check, by_stage=args.by_stage, by_set=args.by_set, regress=args.regress, at=at), end="")


if __name__ == "__main__":
    exit_on_bad_input("contrast_check.py", main)
