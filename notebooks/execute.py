"""Run the notebooks from top to bottom in this interpreter and save each with its outputs, in place.

    python notebooks/execute.py                          # every notebook (each trains to a solved result)
    python notebooks/execute.py 03_gradients.ipynb       # the notebooks named (file names or paths)

The docs site (mkdocs.yml: ``execute: false``) and GitHub show the notebooks as saved, so after changing one, run it
here and commit it with its outputs. The kernel runs this interpreter (a kernelspec in a temporary ``JUPYTER_PATH``;
``tests/test_notebooks.py`` runs the notebooks the same way, with `execute`) in a temporary working folder, so that
nothing a notebook writes is left in the checkout. The saved notebook keeps its own kernelspec ("python3"), and no
execution timestamps (smaller diffs); timings printed by the notebooks do change from run to run.

Raises ``nbclient.exceptions.CellExecutionError`` (naming the cell) when a cell fails; that notebook is not saved.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import re
import sys
import tempfile
import time

import nbclient
import nbformat

HERE = pathlib.Path(__file__).resolve().parent
NOTEBOOKS = sorted(HERE.glob("*.ipynb"))
KERNEL_NAME = "jaxdrones-notebooks-python"
TIMEOUT_S = 3600  # per cell: the default training budgets take minutes on a CPU
#: A verdict on a result: `jaxdrones.training.evaluation.result_line`'s, or a notebook's own outside a task.
VERDICT = re.compile(r"\b(not solved|solved): ")


@contextlib.contextmanager
def kernel_for_this_interpreter():
    """Yield the name of a kernelspec that starts ``sys.executable``, found first through a temporary JUPYTER_PATH
    (restored after)."""
    with tempfile.TemporaryDirectory() as tmp:
        spec_dir = pathlib.Path(tmp) / "kernels" / KERNEL_NAME
        spec_dir.mkdir(parents=True)
        spec = {
            "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
            "display_name": "Python (jaxdrones notebooks)",
            "language": "python",
        }
        (spec_dir / "kernel.json").write_text(json.dumps(spec))
        previous = os.environ.get("JUPYTER_PATH")
        os.environ["JUPYTER_PATH"] = tmp
        try:
            yield KERNEL_NAME
        finally:
            if previous is None:
                del os.environ["JUPYTER_PATH"]
            else:
                os.environ["JUPYTER_PATH"] = previous


def execute(
    nb: nbformat.NotebookNode, kernel_name: str, workdir: str | os.PathLike, timeout_s: int = TIMEOUT_S
) -> nbformat.NotebookNode:
    """Run ``nb`` (in place) from top to bottom with the kernel ``kernel_name``, in the folder ``workdir``, keeping
    its kernelspec metadata and recording no timestamps. The kernel inherits this process's environment.

    Raises:
        nbclient.exceptions.CellExecutionError: a cell raised (the error names the cell).
    """
    kernelspec = nb.metadata.get("kernelspec")
    nbclient.NotebookClient(
        nb,
        timeout=timeout_s,
        kernel_name=kernel_name,
        record_timing=False,
        resources={"metadata": {"path": str(workdir)}},
    ).execute()
    if kernelspec is not None:
        nb.metadata["kernelspec"] = kernelspec
    return nb


def output_text(nb: nbformat.NotebookNode) -> str:
    """The text of every stream and plain-text output of ``nb``, in order."""
    parts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if out.output_type == "stream":
                parts.append(out.text)
            elif "data" in out and "text/plain" in out.data:
                parts.append(out.data["text/plain"])
    return "\n".join(parts)


def verdicts(text: str) -> list[tuple[str, str]]:
    """``(verdict, line)`` for every line of ``text`` (`output_text`) with a verdict (``"solved"`` or ``"not
    solved"``)."""
    return [(m.group(1), line) for line in text.splitlines() for m in VERDICT.finditer(line)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", help="notebook file names or paths (default: every notebook here)")
    args = parser.parse_args(argv)
    paths = [pathlib.Path(n) if pathlib.Path(n).exists() else HERE / n for n in args.notebooks] or NOTEBOOKS
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        parser.error(f"no such notebook: {', '.join(missing)}")
    with kernel_for_this_interpreter() as kernel_name:
        for path in paths:
            nb = nbformat.read(path, as_version=4)
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as workdir:
                execute(nb, kernel_name, workdir)
            nbformat.write(nb, path)
            print(
                f"{path.name}: ran in {time.perf_counter() - start:.0f} s, saved ({path.stat().st_size:,} bytes)",
                flush=True,
            )
            for _, line in verdicts(output_text(nb)):
                print(f"  {line}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
