"""The gap between two KPIs of one test, the lab's against every run in one or more campaign stores
(``bo.discovery.gap``): by default how far the face the upper box keeps stands above the heap
poured into the lower box (shear angle - angle of repose). Can any run the model ever made produce
the lab's combination? The stores are only read, so it may be run beside a campaign.

    python scripts/gap_check.py campaigns/table2/*.sqlite
    python scripts/gap_check.py STORE --kpis mass_flow_rate_full_kg_s mass_lower_box_full_kg --data my_lab.json
    python scripts/gap_check.py campaigns/table2/discover_lab.sqlite --by-stage   # G per candidate
    python scripts/gap_check.py campaigns/table2/probe_tetralobe.sqlite --by-set   # G per probe set
"""
from __future__ import annotations

import argparse

from bo.discovery.gap import FACE_ABOVE_HEAP, format_gap, gap_check
from torchdem.measured import load_measured
from torchdem.errors import exit_on_bad_input


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stores", nargs="+", help="campaign stores (SQLite)")
    parser.add_argument("--kpis", nargs=2, default=list(FACE_ABOVE_HEAP), metavar=("A", "B"),
                        help="the gap A - B (default: shear_angle_deg angle_of_repose_deg)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    parser.add_argument("--by-stage", action="store_true", help="also G per store and stage")
    parser.add_argument("--by-set", action="store_true", help="also G per store, stage and batch (a probe's sets)")
    args = parser.parse_args()
    print(format_gap(gap_check(args.stores, load_measured(args.data), *args.kpis), by_stage=args.by_stage,
                     by_batch=args.by_set), end="")


if __name__ == "__main__":
    exit_on_bad_input("gap_check.py", main)
