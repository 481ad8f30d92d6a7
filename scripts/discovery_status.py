"""Where a discovery campaign stands, from its store alone (``bo.discovery.status``): each
candidate's design span per condition beside the measurement, its mean shift and a least-squares
plane of each KPI on its parameters over the design points, and its held-out runs' z and chi^2
beside the calibrated set's, before ``torchdem-discover`` has scored the candidates. The store is
only read, so it may be run beside the campaign.

    python scripts/discovery_status.py campaigns/table2/discover_4s.sqlite
    python scripts/discovery_status.py STORE --data my_lab.json --kpis shear_angle_deg mass_flow_rate_full_kg_s
"""
from __future__ import annotations

import argparse

from bo.discovery.status import discovery_status, format_status
from torchdem.drawdown import CALIBRATION_KPIS_DEM
from torchdem.measured import load_measured
from torchdem.errors import exit_on_bad_input

KPIS = CALIBRATION_KPIS_DEM


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("store", help="the discovery's campaign store (SQLite)")
    parser.add_argument("--data", default=None, help="measured-data JSON (default: the paper's Table 2)")
    parser.add_argument("--kpis", nargs="+", default=list(KPIS), help="DEM KPIs compared (default: the four of Eq. 7)")
    args = parser.parse_args()
    measured = load_measured(args.data)
    print(format_status(discovery_status(args.store, measured, args.kpis), measured), end="")


if __name__ == "__main__":
    exit_on_bad_input("discovery_status.py", main)
