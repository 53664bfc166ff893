"""Write the API reference at build time: one page per public module of ``jaxdrones`` (mkdocs-gen-files).

The package is walked on disk, so a module added or moved into a subpackage gets its page at the next build
without editing this file or ``mkdocs.yml``. Skipped:

- private modules and packages (a name part starting with ``_``, e.g. ``jaxdrones._xla``) and ``__main__``;
- a module that only re-exports another under an old import path (a file whose module, once imported, is another
  module: ``sys.modules`` aliases), so that each object is documented once, under its public home.

``jaxdrones.compat`` (gym-pybullet-drones' API) is documented too: it builds cleanly under ``--strict``.

The navigation is written to ``reference/SUMMARY.md`` for mkdocs-literate-nav.
"""

from __future__ import annotations

import importlib
import pathlib

import mkdocs_gen_files

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = "jaxdrones"


def module_name(path: pathlib.Path) -> str:
    """The dotted name of the module in ``path`` (a ``.py`` file under the package)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_public(name: str) -> bool:
    """Whether ``name`` is a public module: no part starting with ``_`` (which also leaves out ``__main__``)."""
    return not any(p.startswith("_") for p in name.split("."))


def is_alias(name: str) -> bool:
    """Whether importing ``name`` gives another module (an old import path kept as an alias)."""
    try:
        return importlib.import_module(name).__name__ != name
    except ImportError:  # an optional dependency missing: document it from its source
        return False


def public_modules() -> list[str]:
    """Every public module of the package, sorted, packages before their modules."""
    names = {module_name(p) for p in (ROOT / PACKAGE).rglob("*.py")}
    return sorted((n for n in names if is_public(n) and not is_alias(n)), key=lambda n: n.split("."))


def main() -> None:
    nav = mkdocs_gen_files.Nav()
    for name in public_modules():
        parts = tuple(name.split("."))
        doc_path = (
            pathlib.Path(*parts, "index.md")
            if (ROOT / pathlib.Path(*parts)).is_dir()
            else pathlib.Path(*parts).with_suffix(".md")
        )
        nav[parts] = doc_path.as_posix()
        with mkdocs_gen_files.open(pathlib.Path("reference", doc_path), "w") as f:
            f.write(f"# `{name}`\n\n::: {name}\n")
    with mkdocs_gen_files.open("reference/SUMMARY.md", "w") as f:
        f.writelines(nav.build_literate_nav())


main()
