"""The README's examples work as written (tests/test_readme.py).

- Every ``python`` code block runs to the end in a fresh interpreter (slow: the mixture example
  simulates a small draw down test).
- Every command line of the ``bash`` blocks that calls a Hydra entry point composes with its
  overrides (``--cfg job``: Hydra checks every key and group and prints the config, no run);
  ``torchdem-kpi`` lines parse with its argument parser.
"""
from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = (REPO / "README.md").read_text()
HYDRA_APPS = {"torchdem-demo": "torchdem.cli", "torchdem-simulate": "torchdem.cli_simulate",
              "torchdem-screen": "bo.cli.screen", "torchdem-study": "bo.cli.study",
              "torchdem-calibrate": "bo.cli.calibrate", "torchdem-discover": "bo.cli.discover"}


def code_blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, re.S)


def command_lines() -> list[list[str]]:
    """Each command of the bash blocks as argv, comments and continuation lines handled."""
    commands = []
    for block in code_blocks("bash"):
        for line in block.replace("\\\n", " ").splitlines():
            argv = shlex.split(line, comments=True)
            if argv:
                argv[0] = argv[0].removeprefix(".venv/bin/")
                commands.append(argv)
    return commands


def test_readme_has_examples_of_every_command():
    names = {argv[0] for argv in command_lines()}
    assert {"make", "torchdem-simulate", "torchdem-kpi", "torchdem-screen", "torchdem-calibrate",
            "torchdem-discover"} <= names
    assert len(README.splitlines()) <= 250
    assert not re.search(r"\bsitting\b|this session", README, re.I)


@pytest.mark.parametrize("argv", [a for a in command_lines() if a[0] in HYDRA_APPS], ids=" ".join)
def test_readme_command_composes(argv):
    proc = subprocess.run([sys.executable, "-m", HYDRA_APPS[argv[0]], *argv[1:], "--cfg", "job"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.mark.parametrize("argv", [a for a in command_lines() if a[0] == "torchdem-kpi"], ids=" ".join)
def test_readme_kpi_command_parses(argv):
    from kpi.cli import build_parser

    args = build_parser().parse_args(argv[1:])
    assert callable(args.run)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(code_blocks("python"))))
def test_readme_python_example_runs(index, tmp_path):
    script = tmp_path / f"readme_{index}.py"
    script.write_text(code_blocks("python")[index])
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip()
