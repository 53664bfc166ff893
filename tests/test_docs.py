"""The documentation site: it builds with ``--strict``, its API reference has a page for every public module, its
Python examples run as written, and the notebooks it renders are stored with their outputs.

Which code blocks of ``docs/*.md`` run (the README's are ``tests/test_readme.py``'s): every block fenced
```` ```python ```` runs as written, in a fresh namespace, in the test process. A block that needs pybullet or torch
gets that marker, by the README's rule (`markers`: ``backend="pybullet"`` or ``stable_baselines3`` in its code). A
block that cannot run in the suite (minutes of computation, hardware, ROS) is fenced with another language tag,
```` ```py-norun ```` for Python: the site shows it and nothing runs it. Such blocks are kept few
(`test_few_blocks_left_unrun`: at most `MAX_NORUN`), and each says beside it why it does not run.

The site is built with ``mkdocs build --strict`` into a temporary folder, once per module and worker: 9 s of CPU,
11-25 s of wall time on 2 cores shared with other jobs, so the tests that read it are marked slow. Material's and
properdocs' notices are silenced by the variables mkdocs.yml names.
"""

from __future__ import annotations

import os
import pathlib
import pkgutil
import re
import subprocess
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
MAX_NORUN = 3  # docs blocks fenced so as not to run (py-norun)
QUIET = {"NO_MKDOCS_2_WARNING": "1", "DISABLE_MKDOCS_2_WARNING": "true"}  # mkdocs.yml: the theme's notices


def blocks(tag: str) -> list[tuple[str, str]]:
    """``(page:index, code)`` of every block fenced ```` ```tag ```` in ``docs/*.md``, dedented."""
    found = []
    for page in sorted(DOCS.glob("*.md")):
        pattern = rf"^( *)```{re.escape(tag)}\n(.*?)^\1```"
        for i, (indent, code) in enumerate(re.findall(pattern, page.read_text(), flags=re.DOTALL | re.MULTILINE)):
            code = "".join(line[len(indent) :] for line in code.splitlines(keepends=True))
            found.append((f"{page.name}:{i}", code))
    return found


def markers(code: str) -> list:
    """The markers of the optional packages that an example uses (as tests/test_readme.py's)."""
    return [pytest.mark.pybullet] * ('backend="pybullet"' in code) + [pytest.mark.torch] * ("stable_baselines3" in code)


def public_modules() -> list[str]:
    """Every public module of jaxdrones, found by importing the package's subpackages (pkgutil), independently of
    docs/gen_ref.py: no private part, and not an old import path that imports as another module."""
    import importlib

    import jaxdrones

    names = ["jaxdrones"]
    for info in pkgutil.walk_packages(jaxdrones.__path__, "jaxdrones.", onerror=lambda name: None):
        parts = info.name.split(".")
        if any(p.startswith("_") for p in parts):
            continue
        try:
            if importlib.import_module(info.name).__name__ != info.name:
                continue  # an alias of a module documented under its new path
        except ImportError:  # an optional dependency missing (rclpy): documented from its source
            pass
        names.append(info.name)
    return names


def package_version() -> str:
    """The version pyproject.toml declares: its ``project.version``, or the attribute its setuptools table names."""
    import importlib
    import tomllib

    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    if "version" in pyproject["project"]:
        return pyproject["project"]["version"]
    module, _, name = pyproject["tool"]["setuptools"]["dynamic"]["version"]["attr"].rpartition(".")
    return getattr(importlib.import_module(module), name)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site built by ``mkdocs build --strict``: (completed process, output folder, seconds)."""
    out = tmp_path_factory.mktemp("site")
    t0 = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        check=False,
        cwd=ROOT,
        env={**os.environ, **QUIET},
        capture_output=True,
        text=True,
        timeout=600,
    )
    return result, out, time.perf_counter() - t0


@pytest.mark.slow
def test_site_builds_strict(site):
    result, out, seconds = site
    print(f"mkdocs build --strict: {seconds:.1f} s")
    assert result.returncode == 0, result.stderr[-4000:]
    assert (out / "index.html").is_file()
    # nbconvert's lab template (mkdocs-jupyter renders the notebooks with it) writes no alt text for a PNG output and
    # logs this for every figure; nothing in a notebook can supply one. Any other warning fails the test.
    warnings = [
        line for line in result.stderr.splitlines() if "WARNING" in line and "Alternative text is missing" not in line
    ]
    assert not warnings, result.stderr[-4000:]


@pytest.mark.slow
def test_api_reference_covers_every_public_module(site):
    result, out, _ = site
    assert result.returncode == 0, result.stderr[-4000:]
    modules = public_modules()
    assert {"jaxdrones", "jaxdrones.sim", "jaxdrones.envs", "jaxdrones.training", "jaxdrones.compat"} <= set(modules)
    missing = []
    for name in modules:
        page = out / "reference" / pathlib.Path(*name.split(".")) / "index.html"
        if not page.is_file() or f'id="{name}"' not in page.read_text():
            missing.append(name)
    assert not missing, f"modules without an API reference page: {missing}"


@pytest.mark.slow
def test_changelog_page_includes_changelog(site):
    result, out, _ = site
    assert result.returncode == 0, result.stderr[-4000:]
    version = package_version()
    assert f"## {version}" in (ROOT / "CHANGELOG.md").read_text()
    html = (out / "changelog" / "index.html").read_text()
    assert "Unreleased" in html and version in html


def test_readme_links_resolve():
    """The README's relative links (to the guides under docs/, CHANGELOG.md) point at files that exist, so that they
    work on GitHub; `mkdocs build --strict` checks the links between the pages."""
    links = re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", (ROOT / "README.md").read_text())
    assert any(link.startswith("docs/") for link in links)
    missing = [link for link in links if not (ROOT / link).is_file()]
    assert not missing, f"README links to missing files: {missing}"


def heading_slugs(page: pathlib.Path) -> set[str]:
    """The anchors of a Markdown page's headings, as the docs site makes them (Python-Markdown's ``toc`` slugify)."""
    import unicodedata

    slugs = set()
    for heading in re.findall(r"^#+ (.+)$", page.read_text(), flags=re.M):
        text = unicodedata.normalize("NFKD", heading).encode("ascii", "ignore").decode()
        slugs.add(re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text).strip().lower()))
    return slugs


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_links_resolve(path):
    """A notebook's relative links point at files that exist, and at headings of theirs that exist (GitHub and the
    docs site show the notebooks as stored)."""
    import nbformat

    notebook = nbformat.read(path, as_version=4)
    text = "\n".join(cell.source for cell in notebook.cells if cell.cell_type == "markdown")
    dead = []
    for target, anchor in re.findall(r"\]\(([^)#:]+)(?:#([^)]*))?\)", text):
        page = (path.parent / target).resolve()
        if not page.is_file() or (anchor and anchor not in heading_slugs(page)):
            dead.append(f"{target}#{anchor}" if anchor else target)
    assert not dead, f"{path.name} links to missing files or headings: {dead}"


def test_docs_have_examples():
    assert len(blocks("python")) >= 10


def test_few_blocks_left_unrun():
    assert len(blocks("py-norun")) <= MAX_NORUN


#: A training budget of a page's example and what the suite runs instead: the example is checked to run as written,
#: not to learn (docs/adapters.md's SB3 run: 300,000 steps, 62 s of the suite on 2 cores; the page's learning figures
#: come from benchmarks/training/sb3_hover.py).
SHORTER_BUDGETS = {".learn(300_000)": ".learn(8_192)"}


def test_shorter_budgets_stand_in_the_docs():
    """Each budget the suite shortens is still on a page (else the page's example runs at its full budget)."""
    code = " ".join(c for _, c in blocks("python"))
    assert all(budget in code for budget in SHORTER_BUDGETS)


def readme_blocks() -> set[str]:
    """The README's Python blocks, whitespace-normalised: tests/test_readme.py runs them, so a page that shows one
    again is not run twice."""
    readme = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    return {" ".join(code.split()) for code in readme}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=markers(c), id=n)
        for n, c in blocks("python")
        if " ".join(c.split()) not in readme_blocks()
    ],
)
def test_docs_example_runs(name, capsys, users_rank_promotion):
    code = dict(blocks("python"))[name]
    for budget, short in SHORTER_BUDGETS.items():  # the code as written, with a shorter training
        code = code.replace(budget, short)
    exec(compile(code, f"docs/{name} (python block)", "exec"), {})
    if "print(touched)" in code:  # the PyBullet backend's collision report
        assert capsys.readouterr().out.strip() == "[2 0]"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_stored_with_outputs(path):
    """The site renders the notebooks as stored (mkdocs.yml: ``execute: false``), so each must hold its outputs."""
    import nbformat

    notebook = nbformat.read(path, as_version=4)
    outputs = [cell for cell in notebook.cells if cell.cell_type == "code" and cell.get("outputs")]
    assert outputs, f"{path.name} is stored without outputs: run it and save it with them"


def test_the_virtual_environments_the_docs_make_are_ignored_by_git():
    """Every folder that a ``python -m venv FOLDER`` of the README, the docs or .ci/run creates is one git ignores,
    so that a user who follows them commits none of it."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    texts = [ROOT / "README.md", ROOT / ".ci" / "run", *sorted(DOCS.glob("*.md"))]
    folders = {m for path in texts for m in re.findall(r"python3? -m venv (\.?[\w./-]+)", path.read_text())}
    assert ".venv-rllib" in folders  # docs/adapters.md's RLlib workflow
    for folder in sorted(folders):
        probe = f"{folder.rstrip('/')}/bin/python"
        result = subprocess.run(["git", "check-ignore", "-q", probe], cwd=ROOT, capture_output=True)
        assert result.returncode == 0, f"{folder} (a virtual environment the docs create) is not ignored by git"
