"""The upper box's residue per unit slope, R = (fill - lower box) / tan(shear angle), of the lab and
of every run in one or more campaign stores (``bo.discovery.residue``), and a least-squares fit of
R on the run parameters per condition: does any calibration parameter move the one combination of
shear angle and lower-box mass that the box's geometry and the bulk density fix? The stores are
only read, so it may be run beside a campaign.

    python scripts/residue_check.py campaigns/table2/lab.sqlite campaigns/table2/discover_lab.sqlite
    python scripts/residue_check.py STORE --data my_lab.json
    python scripts/residue_check.py campaigns/table2/discover_lab.sqlite --by-stage   # R per candidate
"""
from __future__ import annotations

import argparse

from bo.discovery.residue import format_residue, residue_check
from torchdem.measured import load_measured
from torchdem.errors import exit_on_bad_input


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="+", help="campaign stores (SQLite)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    parser.add_argument("--by-stage", action="store_true", help="also R per stage (a discovery's candidates)")
    args = parser.parse_args()
    print(format_residue(residue_check(args.stores, load_measured(args.data)), by_stage=args.by_stage), end="")


if __name__ == "__main__":
    exit_on_bad_input("residue_check.py", main)
