"""The code's form: ruff's lint rules and its formatting (pyproject.toml, ``[tool.ruff]``) hold over the repository,
at the ruff version of constraints.txt (the formatter's style can change between ruff's minor releases); benchmarks/
holds what its report runs, and uses the package through its public names."""

import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["ruff check", "ruff format --check"])
def test_ruff(command):
    result = subprocess.run([sys.executable, "-m", "ruff", *command, "."], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr  # the files and rules it names


def _report_benchmarks() -> set[str]:
    """The scripts that ``benchmarks/report.py`` runs (its ``BENCHMARKS``) as ``FOLDER/NAME``, read from its source."""
    tree = ast.parse((ROOT / "benchmarks" / "report.py").read_text())
    return {
        f"{node.args[1].value}/{node.args[0].value}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and getattr(node.func, "id", None) == "Benchmark"
        and len(node.args) > 1
        and all(isinstance(a, ast.Constant) for a in node.args[:2])
    }


def test_every_benchmark_is_run_by_the_report_or_kept_with_the_experiments():
    """benchmarks/speed, gradients and training hold what ``report.py`` runs (docs/benchmarks.md's tables), the
    workers of those (``_*.py``) and the original's runner; the runs that chose a setting live in
    benchmarks/experiments/ and the scores against real data, which need a clone of their repository, in
    benchmarks/validation/. Nothing else sits in benchmarks/ but the report and what the scripts share."""
    benchmarks = ROOT / "benchmarks"
    assert {p.name for p in benchmarks.glob("*.py")} == {"report.py", "common.py"}
    measured = {
        f"{p.parent.name}/{p.stem}"
        for folder in ("speed", "gradients", "training")
        for p in (benchmarks / folder).glob("*.py")
        if not p.stem.startswith("_") and p.stem != "original"
    }
    assert measured == _report_benchmarks()
    assert sorted(p.name for p in (benchmarks / "experiments").glob("*.py"))
    assert sorted(p.name for p in (benchmarks / "validation").glob("*.py"))


def _private_uses(source: str) -> list[str]:
    """The package's private names that a script imports or reads off a module it imported from the package."""
    tree = ast.parse(source)
    modules, found = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxdrones"):
            modules |= {a.asname or a.name for a in node.names}
            found += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
        elif isinstance(node, ast.Import):
            modules |= {(a.asname or a.name).split(".")[0] for a in node.names if a.name.startswith("jaxdrones")}
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in modules:
                found.append(ast.unparse(node))
    return found


def test_benchmarks_use_the_package_through_its_public_names():
    scripts = sorted((ROOT / "benchmarks").rglob("*.py"))
    uses = {str(p.relative_to(ROOT)): _private_uses(p.read_text()) for p in scripts}
    assert {path: names for path, names in uses.items() if names} == {}
    assert _private_uses("from jaxdrones.training.run import _x\nimport jaxdrones.cameras as c\nc._images") == [
        "jaxdrones.training.run._x",
        "c._images",
    ]
