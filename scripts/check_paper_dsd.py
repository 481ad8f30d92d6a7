"""Compare the paper's DSD (Table A.1) with ours for 12 factors and 2 fake factors.

Prints ``bo.design.dsd.check_dsd`` reports for both coded designs. The paper's design is read from
``bo/data/tableA1_paper_dsd.json`` and coded against Table 4 (``bo/data/table4_dsd_levels.json``)
by nearest level. Usage: ``python scripts/check_paper_dsd.py``.
"""
from __future__ import annotations

from bo.design.dsd import check_dsd, code_design, definitive_screening_design, paper_design, \
    paper_parameter_table
from torchdem.errors import exit_on_bad_input


def main() -> None:
    table = paper_parameter_table()
    paper = check_dsd(code_design(paper_design(), table))
    ours = check_dsd(definitive_screening_design(table.k, n_fake=2))
    print(paper.to_text("Paper, Table A.1 (coded against Table 4)", table.names))
    print()
    print(ours.to_text(f"Ours, definitive_screening_design({table.k}, n_fake=2)", table.names))


if __name__ == "__main__":
    exit_on_bad_input("check_paper_dsd.py", main)
