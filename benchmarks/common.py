"""What the benchmarks share: where results go, the machine's description, the JSON report, timing of repeated
calls, and crazyflow's virtual environment.

The scripts of ``benchmarks/speed``, ``gradients``, ``training``, ``validation`` and ``experiments`` import it
after putting ``benchmarks/`` on ``sys.path`` (each is run as ``python benchmarks/FOLDER/NAME.py``).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
#: Every benchmark's default output folder.
RESULTS = os.path.join(HERE, "results")
CRAZYFLOW = "crazyflow==0.4.0"
#: crazyflow's own virtual environment, created on first use by the benchmarks that compare with it.
CRAZYFLOW_VENV = os.path.join(HERE, ".venv-crazyflow")


def configure_devices(requested: int | None) -> str:
    """Set XLA_FLAGS for one CPU device per core (must run before jax is imported); returns what was used."""
    flags = os.environ.get("XLA_FLAGS", "")
    if requested is not None:
        flags = " ".join(f for f in flags.split() if not f.startswith("--xla_force_host_platform_device_count"))
        flags += f" --xla_force_host_platform_device_count={requested}"
    elif "xla_force_host_platform_device_count" not in flags:
        flags += f" --xla_force_host_platform_device_count={len(os.sched_getaffinity(0))}"
    os.environ["XLA_FLAGS"] = flags.strip()
    return os.environ["XLA_FLAGS"]


def machine_info(jax) -> dict:
    cpu_model = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu_model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=os.path.dirname(os.path.abspath(__file__)),
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    import jaxlib

    return {
        "cpu_count": os.cpu_count(),
        "cpus_available": len(os.sched_getaffinity(0)),
        "cpu_model": cpu_model,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "git_commit": commit,
    }


def write_report(path: str, benchmark: str, info: dict, settings: dict, results: list, **extra) -> None:
    """Write a benchmark's JSON report (name, date, machine, load, settings, results) to ``path``."""
    report = {
        "benchmark": benchmark,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": info,
        **extra,
        "loadavg_end": os.getloadavg(),
        "settings": settings,
        "results": results,
    }
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(report, f, indent=2)
    print(f"wrote {path}")


def timed(run, repeats: int) -> tuple[float, float]:
    """Best and median wall time of ``run()`` over ``repeats`` calls, after one warm-up call."""
    run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times)


def timed_together(runs: dict, repeats: int) -> dict:
    """Best and median wall time of each of ``runs`` (name → callable), timed in turn within each of ``repeats``
    rounds after one warm-up call each, so that a change of the machine's load reaches every run alike."""
    for run in runs.values():
        run()
    times = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    return {name: (min(t), statistics.median(t)) for name, t in times.items()}


def crazyflow_python(venv: str) -> tuple[str | None, str]:
    """The Python of a virtual environment with crazyflow 0.4.0, created and installed when missing.

    Returns:
        (path to its python or None, what was done or why it failed).
    """
    python = os.path.join(venv, "bin", "python")
    version = _crazyflow_version(python)
    if version == CRAZYFLOW.split("==")[1]:
        return python, f"reused {venv} (crazyflow {version})"
    print(f"installing {CRAZYFLOW} into {venv} ...", flush=True)
    try:
        if not os.path.exists(python):
            subprocess.run(
                [sys.executable, "-m", "venv", venv], check=True, capture_output=True, text=True, timeout=300
            )
        pip = subprocess.run(
            [python, "-m", "pip", "install", "--disable-pip-version-check", CRAZYFLOW],
            check=False,
            capture_output=True,
            text=True,
            timeout=1800,
        )
    except (OSError, subprocess.SubprocessError) as e:
        return None, f"could not create {venv}: {e}"
    if pip.returncode != 0:
        tail = " | ".join((pip.stdout + pip.stderr).strip().splitlines()[-5:])
        return None, f"pip install {CRAZYFLOW} failed (exit {pip.returncode}): {tail}"
    version = _crazyflow_version(python)
    if version is None:
        return None, f"pip installed {CRAZYFLOW} into {venv} but it does not import"
    return python, f"installed {CRAZYFLOW} into {venv}"


def _crazyflow_version(python: str) -> str | None:
    if not os.path.exists(python):
        return None
    probe = subprocess.run(
        [python, "-c", "import importlib.metadata as m, crazyflow; print(m.version('crazyflow'))"],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = probe.stdout.strip().splitlines()  # crazyflow prints import messages first
    return lines[-1] if probe.returncode == 0 and lines else None
