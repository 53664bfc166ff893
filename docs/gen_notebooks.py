"""Put the notebooks of ``notebooks/`` into the site at build time (mkdocs-gen-files), as ``notebooks/*.ipynb``.

mkdocs-jupyter renders them as stored, outputs included, without running them (``execute: false`` in
``mkdocs.yml``); the test suite executes them (``tests/test_notebooks.py``). Copying at build time keeps one copy of
each notebook in the repository.
"""

from __future__ import annotations

import pathlib

import mkdocs_gen_files

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"

for path in sorted(NOTEBOOKS.glob("*.ipynb")):
    with mkdocs_gen_files.open(f"notebooks/{path.name}", "wb") as f:
        f.write(path.read_bytes())
    mkdocs_gen_files.set_edit_path(f"notebooks/{path.name}", f"../notebooks/{path.name}")
