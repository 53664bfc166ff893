"""Time to install jaxdrones into a fresh virtual environment, per Python interpreter, wheels only.

Each run creates a new venv with the interpreter given, upgrades nothing, and times
``pip install --only-binary=:all: [-c constraints.txt] .[EXTRAS] [jax==VERSION]`` from this checkout (so a
dependency without a wheel for that Python fails the run instead of compiling; ``--source`` lets pip build one from
source, e.g. pybullet on Python 3.12), then ``import jaxdrones`` in it.
pip's own cache is used as the machine has it: on a machine that installed these packages before, downloads are
faster than on a new one.

    python benchmarks/speed/install.py                                          # python3.11 and python3.12 if found
    python benchmarks/speed/install.py --python python3.12 --jax 0.11.2
    python benchmarks/speed/install.py --python python3.11 --extras pybullet --constraints
    python benchmarks/speed/install.py --python python3.12 --extras pybullet --source

Prints one line per run; ``--out`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def find_python(version: str) -> str | None:
    """``pythonX.Y`` on PATH if it runs, else pyenv's newest X.Y.*; None if neither."""
    name = f"python{version}"
    path = shutil.which(name)
    if path and subprocess.run([path, "--version"], capture_output=True).returncode == 0:
        return path
    root = (
        subprocess.run(["pyenv", "root"], capture_output=True, text=True).stdout.strip()
        if shutil.which("pyenv")
        else ""
    )
    versions = sorted(
        (v for v in os.listdir(os.path.join(root, "versions")) if v.startswith(version + "."))
        if root and os.path.isdir(os.path.join(root, "versions"))
        else [],
        key=lambda v: tuple(int(p) for p in v.split(".") if p.isdigit()),
    )
    return os.path.join(root, "versions", versions[-1], "bin", name) if versions else None


def install(python: str, extras: str, jax: str | None, constraints: bool, source: bool = False) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        venv = os.path.join(tmp, "venv")
        subprocess.run([python, "-m", "venv", venv], check=True)
        pip = [os.path.join(venv, "bin", "python"), "-m", "pip", "install", "-q"]
        pip += [] if source else ["--only-binary=:all:"]
        pip += ["-c", os.path.join(ROOT, "constraints.txt")] if constraints else []
        pip += [f".[{extras}]" if extras else "."] + ([f"jax=={jax}"] if jax else [])
        start = time.perf_counter()
        result = subprocess.run(pip, cwd=ROOT, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        versions = (
            subprocess.run(
                [
                    os.path.join(venv, "bin", "python"),
                    "-c",
                    "import sys, jax, jaxdrones; print(sys.version.split()[0], jax.__version__)",
                ],
                capture_output=True,
                text=True,
            )
            if result.returncode == 0
            else None
        )
        return {
            "python": python,
            "extras": extras,
            "jax_asked": jax,
            "constraints": constraints,
            "source": source,
            "ok": result.returncode == 0 and versions.returncode == 0,
            "install_s": round(seconds, 1),
            "python_version": versions.stdout.split()[0] if versions and versions.stdout else None,
            "jax": versions.stdout.split()[1] if versions and versions.stdout else None,
            "error": None if result.returncode == 0 else result.stderr.strip().splitlines()[-1:],
        }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--python", action="append", help="interpreter (repeatable; default python3.11, 3.12)")
    parser.add_argument("--extras", default="", help="extras to install, e.g. pybullet or test")
    parser.add_argument("--jax", help="a jax version to install with it (default: what pip chooses)")
    parser.add_argument("--constraints", action="store_true", help="install with -c constraints.txt")
    parser.add_argument("--source", action="store_true", help="let pip build packages without a wheel from source")
    parser.add_argument("--out", help="JSON output path")
    args = parser.parse_args(argv)
    pythons = args.python or [p for p in (find_python("3.11"), find_python("3.12")) if p]
    results = []
    for python in pythons:
        result = install(python, args.extras, args.jax, args.constraints, args.source)
        results.append(result)
        print(
            f"{result['python_version'] or python}: pip install {'.[' + args.extras + ']' if args.extras else '.'}"
            f"{' (source builds allowed)' if args.source else ''}"
            f"{' jax==' + args.jax if args.jax else ''}: {'ok' if result['ok'] else 'FAILED'} in "
            f"{result['install_s']} s, jax {result['jax']}" + (f" ({result['error']})" if result["error"] else ""),
            flush=True,
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
    return 0 if all(r["ok"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
