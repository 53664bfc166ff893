"""The code's form: ruff's lint rules and its formatting (pyproject.toml, ``[tool.ruff]``) hold over the repository,
at the ruff version of constraints.txt (the formatter's style can change between ruff's minor releases)."""

import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["ruff check", "ruff format --check"])
def test_ruff(command):
    result = subprocess.run([sys.executable, "-m", "ruff", *command, "."], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr  # the files and rules it names
