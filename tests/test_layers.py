"""The import rule between the three packages (docs/architecture.md): data flows one way.

- ``kpi`` imports neither ``torchdem`` nor ``bo``: a lab user measures photos and load-cell files
  with ``kpi`` alone.
- ``torchdem`` (engine, draw down model, model extensions) never imports ``bo``.
- ``bo`` may import both.

Every import statement counts, at module level or inside a function, so a lazy import cannot hide
a back-arrow. The rule is checked on the source, so it needs no import to run.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

FORBIDDEN = {"kpi": {"torchdem", "bo"}, "torchdem": {"bo"}}


def imported_packages(path: Path) -> list[tuple[int, str]]:
    """(line, top-level package) of every absolute import in a source file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_only_downstream(package):
    files = sorted((REPO / package).rglob("*.py"))
    assert files, f"no sources under {package}/"
    bad = [f"{f.relative_to(REPO)}:{line} imports {top}" for f in files for line, top in imported_packages(f)
           if top in FORBIDDEN[package]]
    assert not bad, "import rule broken:\n" + "\n".join(bad)


def test_checker_sees_lazy_imports(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("import os\n\ndef f():\n    from bo.campaign import store\n    import kpi.angles\n")
    assert imported_packages(source) == [(1, "os"), (4, "bo"), (5, "kpi")]
