"""Rerun the benchmarks of ``benchmarks/`` and regenerate their tables (``REPORT.md``) and plots (PNG) in one folder.

Each benchmark runs as its own subprocess (``python benchmarks/FOLDER/NAME.py ...``, a fresh JAX each time), writing its
JSON into the output folder; this script then reads the JSON and writes ``REPORT.md`` there: per benchmark the command,
its settings, the device, JAX version, CPU and machine load (``os.getloadavg()`` before and after it, and what the
benchmark recorded itself), its tables in the README's style and its plots. A benchmark that fails (or runs past
``--timeout``) is reported as failed with the last lines of its stderr, and the others still run. Every benchmark's
stdout and stderr are kept in ``logs/``; ``report_runs.json`` records each run (command, status, wall time, load), so
that ``--render-only`` can rebuild the report from the JSON already there, and a later ``--only NAME`` run replaces that
benchmark's section and keeps the others (each section gives its own date).

The device is JAX's default, as in the benchmarks themselves: a GPU when one is installed (``--cpu`` forces the CPU
with ``JAX_PLATFORMS=cpu``). A short probe process asks JAX which backend it gets, and the grids are sized for it:

============== =================================================== =========================================
benchmark      CPU (default run)                                   GPU (default run)
============== =================================================== =========================================
throughput     worlds 1, 64, 1024, 16384 × drones 1, 4             worlds 1 ... 2**22 × drones 1, 4
envs           its defaults: 1, 64, 1024, 4096 (native also        1 ... 2**20 worlds, each env at every size
               16384), crazyflow
gradients      its defaults: T 10, 100, 1000 × W 1, 1024, 16384    T 10, 100, 1000 × W 1 ... 65536
backends       its defaults (PyBullet is CPU only)                 the same
cameras        worlds 1, 64, 1024, 4096 × primitives 4, 16, 64,    worlds 1 ... 65536, the same scenes
               PyBullet's TinyRenderer and EGL at 16 worlds
train_algos    hover, ppo, brax_ppo, apg, shac at each trainer's   the same
               own budget, empty and warm compilation cache
sysid_noise    seeds 0, 1, 2                                       the same
============== =================================================== =========================================

On a GPU, ``envs`` and ``gradients`` run with ``XLA_PYTHON_CLIENT_PREALLOCATE=false``: each starts crazyflow's
worker, a second JAX process on the same GPU, while it holds its own arrays, and JAX's default of taking 75 % of the
GPU's memory at start would leave the worker too little.

The default run is the benchmarks that finish in minutes each on a 2-core CPU (throughput, envs, gradients, backends,
cameras, encoders, table2, firmware_loop, train_algos, sysid_noise; about an hour in all there, most of it train_algos'
eight training runs and the gradients at 1000 steps × 16384 worlds). The others run only when named (``--only NAME``) or
with ``--all``:

- ``multi_agent``: teams up to 256 drones (CPU; 1024 on a GPU) with MAPPO updates timed, tens of minutes on a CPU;
- ``downwash_policies``: trains MAPPO on ``crossing`` twice (3 M env steps each by default);
- ``sb3_hover``: Stable-Baselines3's PPO for 200 k steps, about 10 minutes, and needs torch and SB3 (the ``sb3``
  extra);
- ``jaxmarl_ippo``: JaxMARL's IPPO for 10 M steps, needs a JaxMARL checkout (``--jaxmarl-baselines
  PATH/baselines/IPPO``); skipped without one;
- the scripts behind docs/benchmarks.md's other tables, each shown as it prints it: ``suite`` (every task at its
  recipe, three seeds: hours on a CPU), ``first_run`` (the quick start's first and warm run), ``train_cost`` (a
  trained policy's operations per trainer and profile), ``gradient_profile`` and ``gradient_layers`` (where a
  gradient's time goes), ``run_memory`` (the memory of mapped runs against the estimate ``jaxdrones train`` checks),
  ``interrupt`` (a Ctrl-C at given seconds into ``jaxdrones train hover --overwrite``: what the run folder then
  holds), ``install`` (a fresh install, per Python; it downloads wheels).

These live in ``benchmarks/speed`` (throughput, memory, install and first-run time), ``benchmarks/gradients`` and
``benchmarks/training`` (time to solve, the suite, the runs' cost and safety), each with the workers of its scripts
(``_crazyflow_*.py``) and, in ``speed``, ``original.py`` (the original gym-pybullet-drones beside them, ``table2
--original``); what they share (the machine's description, the JSON report, timing) is ``benchmarks/common.py``. The
runs that chose a setting of the package, cited by docs/experiments.md and the guides, are in
``benchmarks/experiments/``, each run on its own. The model against real Crazyflie data (a thrust stand, Neural-Swarm's
flights: docs/validation.md) is in ``benchmarks/validation/``, each script run on a clone of the data's repository.

``--quick`` runs the same benchmarks on small grids, a smoke run of minutes rather than a measurement, and writes to
``benchmarks/results/quick`` unless ``--out`` says otherwise, so that it never replaces a full report. crazyflow's
comparison needs its own virtual environment (``benchmarks/.venv-crazyflow``, created by ``speed/envs.py`` with pip);
the quick run skips it when it does not exist yet.

Usage::

    python benchmarks/report.py                               # the default run, into benchmarks/results
    python benchmarks/report.py --quick --only throughput envs
    python benchmarks/report.py --only gradients              # rerun one, keep the other sections
    python benchmarks/report.py --all --skip jaxmarl_ippo
    python benchmarks/report.py --render-only                 # rebuild REPORT.md and the plots from the JSON
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable

from common import CRAZYFLOW_VENV, RESULTS

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


# -- the benchmarks ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Context:
    """What a benchmark's command line depends on."""

    quick: bool
    gpu: bool
    out: str
    crazyflow_ready: bool
    jaxmarl_baselines: str | None


@dataclasses.dataclass(frozen=True)
class Benchmark:
    """One script of ``benchmarks/``: how to run it and where its results go.

    Attributes:
        name: the script's name without ``.py``.
        folder: the folder of ``benchmarks/`` that holds it (what it measures: speed, gradients or training).
        default: part of the default run.
        args: its command-line arguments for a context, or a string saying why it cannot run.
        output: the JSON file it writes (None: its printed output is the result, kept in the run record).
        gpu_env: environment variables added when the device is a GPU.
    """

    name: str
    folder: str
    default: bool
    args: Callable[[Context], list[str] | str]
    output: Callable[[Context], str | None]
    gpu_env: dict = dataclasses.field(default_factory=dict)


def _crazyflow(ctx: Context) -> list[str]:
    """The quick run measures crazyflow only where its venv already exists (creating it takes minutes of pip)."""
    return ["--no-crazyflow"] if ctx.quick and not ctx.crazyflow_ready else []


def throughput_args(ctx: Context) -> list[str]:
    if ctx.quick:
        worlds = (1, 1024, 65536, 1048576) if ctx.gpu else (1, 1024)
        return ["--worlds", *map(str, worlds), "--drones", "1", "4", "--repeats", "3"]
    worlds = (1, 64, 1024, 16384, 131072, 2**20, 2**22) if ctx.gpu else (1, 64, 1024, 16384)
    return ["--worlds", *map(str, worlds), "--drones", "1", "4"]


def envs_args(ctx: Context) -> list[str]:
    if ctx.quick:
        return ["--quick", *(["--sizes", "1", "1024", "65536"] if ctx.gpu else []), *_crazyflow(ctx)]
    return ["--sizes", "1", "64", "1024", "16384", "131072", str(2**20)] if ctx.gpu else []


def gradients_args(ctx: Context) -> list[str]:
    if ctx.quick:
        return ["--quick", *_crazyflow(ctx)]
    return ["--worlds", "1", "1024", "16384", "65536"] if ctx.gpu else []


def cameras_args(ctx: Context) -> list[str]:
    if ctx.quick:
        return ["--worlds", "1", "1024", *(["65536"] if ctx.gpu else []), "--primitives", "16", "--repeats", "3"]
    worlds = ("1", "64", "1024", "16384", "65536") if ctx.gpu else ("1", "64", "1024", "4096")
    return ["--worlds", *worlds, "--primitives", "4", "16", "64"]


def train_algos_args(ctx: Context) -> list[str]:
    if ctx.quick:
        return ["--algos", "ppo", "apg", "--budgets", "100000", "--env-repeats", "2"]
    return ["--budgets", "default"]


def multi_agent_args(ctx: Context) -> list[str]:
    if ctx.quick:
        return ["--drones", "2", "8", "--agents", "256", "--no-mappo", "--repeats", "2"]
    return (
        ["--drones", "2", "8", "64", "256", "1024", "--agents", "65536"]
        if ctx.gpu
        else ["--drones", "2", "8", "64", "256"]
    )


def jaxmarl_args(ctx: Context) -> list[str] | str:
    if not ctx.jaxmarl_baselines:
        return "needs a JaxMARL checkout: --jaxmarl-baselines PATH/baselines/IPPO"
    # The quick run uses another seed than the README's (30), whose JSON in benchmarks/results it would replace.
    return [
        "--baselines",
        ctx.jaxmarl_baselines,
        "--task",
        "leader_follower",
        "--action-type",
        "one_d_rpm",
        *(["--seed", "0", "--steps", "1e5"] if ctx.quick else ["--seed", "30"]),
    ]


def _json(name: str) -> Callable[[Context], str]:
    return lambda ctx: os.path.join(ctx.out, name)


NO_PREALLOCATION = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
BENCHMARKS = {
    b.name: b
    for b in (
        Benchmark(
            "throughput",
            "speed",
            True,
            lambda ctx: throughput_args(ctx) + ["--out", _json("throughput.json")(ctx)],
            _json("throughput.json"),
        ),
        Benchmark(
            "envs",
            "speed",
            True,
            lambda ctx: envs_args(ctx) + ["--out", _json("envs.json")(ctx)],
            _json("envs.json"),
            NO_PREALLOCATION,
        ),
        Benchmark(
            "gradients",
            "gradients",
            True,
            lambda ctx: gradients_args(ctx) + ["--out", _json("gradients.json")(ctx)],
            _json("gradients.json"),
            NO_PREALLOCATION,
        ),
        Benchmark(
            "backends",
            "speed",
            True,
            lambda ctx: (
                (["--quick", "--drones", "1", "10"] if ctx.quick else []) + ["--out", _json("backends.json")(ctx)]
            ),
            _json("backends.json"),
        ),
        Benchmark(
            "cameras",
            "speed",
            True,
            lambda ctx: cameras_args(ctx) + ["--out", _json("cameras.json")(ctx)],
            _json("cameras.json"),
            NO_PREALLOCATION,
        ),
        Benchmark(
            "encoders",
            "gradients",
            True,
            lambda ctx: (
                (["--batch", "1024", "--repeats", "3"] if ctx.quick else []) + ["--out", _json("encoders.json")(ctx)]
            ),
            _json("encoders.json"),
        ),
        Benchmark(
            "table2",
            "speed",
            True,
            lambda ctx: (
                (["--seconds", "1", "--repeats", "1"] if ctx.quick else []) + ["--out", _json("table2.json")(ctx)]
            ),
            _json("table2.json"),
        ),
        Benchmark(
            "train_algos",
            "training",
            True,
            lambda ctx: train_algos_args(ctx) + ["--out", _json("train_algos_hover.json")(ctx)],
            _json("train_algos_hover.json"),
        ),
        Benchmark(
            "sysid_noise",
            "gradients",
            True,
            lambda ctx: ["--seeds", "0"] if ctx.quick else ["--seeds", "0", "1", "2"],
            lambda ctx: None,
        ),
        Benchmark(
            "firmware_loop",
            "speed",
            True,
            lambda ctx: (
                (["--worlds", "1024", "--ticks", "200", "--repeats", "3"] if ctx.quick else [])
                + ["--out", _json("firmware_loop.json")(ctx)]
            ),
            _json("firmware_loop.json"),
        ),
        Benchmark(
            "multi_agent",
            "speed",
            False,
            lambda ctx: multi_agent_args(ctx) + ["--out", _json("multi_agent.json")(ctx)],
            _json("multi_agent.json"),
        ),
        Benchmark(
            "downwash_policies",
            "training",
            False,
            lambda ctx: (
                (["--steps", "200000"] if ctx.quick else []) + ["--out", os.path.join(ctx.out, "downwash_policies")]
            ),
            _json(os.path.join("downwash_policies", "downwash_policies.json")),
        ),
        Benchmark(
            "sb3_hover",
            "training",
            False,
            lambda ctx: (
                ["--action-type", "one_d_rpm", "--out", _json("sb3_hover.json")(ctx)]
                + (
                    ["--steps", "8192", "--eval-episodes", "2"]
                    if ctx.quick
                    else ["--steps", "200000", "--eval-every", "49152"]
                )
            ),
            _json("sb3_hover.json"),
        ),
        Benchmark("jaxmarl_ippo", "training", False, jaxmarl_args, _json("jaxmarl_ippo.json")),
        # docs/benchmarks.md's other tables: each script prints its own, which the report shows as printed.
        Benchmark(
            "suite",
            "training",
            False,
            lambda ctx: (["--tasks", "hover", "--seeds", "0"] if ctx.quick else []) + ["--out", _json("suite")(ctx)],
            lambda ctx: None,
        ),
        Benchmark(
            "first_run",
            "speed",
            False,
            lambda ctx: (
                (["--rounds", "1"] if ctx.quick else ["--rounds", "3", "--warm", "2"])
                + ["--out", _json("first_run.json")(ctx)]
            ),
            lambda ctx: None,
        ),
        Benchmark("train_cost", "training", False, lambda ctx: ["--no-train"] if ctx.quick else [], lambda ctx: None),
        Benchmark(
            "gradient_profile",
            "gradients",
            False,
            lambda ctx: ["--worlds", "64", "--horizon", "10", "--repeats", "2"] if ctx.quick else [],
            lambda ctx: None,
        ),
        Benchmark(
            "gradient_layers",
            "gradients",
            False,
            lambda ctx: (
                (["--worlds", "64", "--horizon", "10", "--repeats", "2"] if ctx.quick else [])
                + ["--out", _json("gradient_layers.json")(ctx)]
            ),
            lambda ctx: None,
        ),
        Benchmark(
            "run_memory",
            "speed",
            False,
            lambda ctx: ["--tasks", "hover", "--extra", "8"] if ctx.quick else [],
            lambda ctx: None,
        ),
        Benchmark(
            "interrupt", "training", False, lambda ctx: ["--at", "1", "3"] if ctx.quick else [], lambda ctx: None
        ),
        Benchmark(
            "install",
            "speed",
            False,
            lambda ctx: ["--python", sys.executable, "--out", _json("install.json")(ctx)],
            lambda ctx: None,
        ),
    )
}


# -- running -------------------------------------------------------------------------------------------------------


PROBE = """
import json
import jaxdrones  # XLA's flags, as the benchmarks get them
import jax, jaxlib
devices = jax.devices()
stats = devices[0].memory_stats() or {}
print("PROBE " + json.dumps({"jax": jax.__version__, "jaxlib": jaxlib.__version__, "backend": jax.default_backend(),
                             "devices": [str(d) for d in devices], "device_kind": devices[0].device_kind,
                             "device_memory_gb": stats.get("bytes_limit", 0) / 2**30 or None}))
"""


def probe(env: dict) -> dict:
    """JAX's version, backend and devices as a benchmark process sees them (a short process of its own, so that this
    one never holds the device), with the host's CPU and the git commit."""
    info = {
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_available": len(os.sched_getaffinity(0)),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "git_commit": _git_commit(),
    }
    try:
        proc = subprocess.run(
            [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=600, cwd=ROOT, check=False
        )
        line = next((x for x in proc.stdout.splitlines() if x.startswith("PROBE ")), None)
        if line is None:
            return info | {"backend": "unknown", "probe_error": " | ".join(proc.stderr.strip().splitlines()[-3:])}
        return info | json.loads(line[6:])
    except (OSError, subprocess.SubprocessError) as err:
        return info | {"backend": "unknown", "probe_error": str(err)}


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def _git_commit() -> str | None:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=10,
            check=True,
        ).stdout.strip()
        return commit + ("+modified" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def run_benchmark(bench: Benchmark, ctx: Context, env: dict, timeout: float) -> dict:
    """Run one benchmark as a subprocess, echoing its stdout; the record of the run."""
    args = bench.args(ctx)
    record = {"name": bench.name, "date": _now(), "loadavg_before": list(os.getloadavg())}
    if isinstance(args, str):
        print(f"== {bench.name}: skipped, {args}", flush=True)
        return record | {"status": "skipped", "reason": args, "loadavg_after": record["loadavg_before"]}
    command = [sys.executable, os.path.join(HERE, bench.folder, f"{bench.name}.py"), *args]
    extra = bench.gpu_env if ctx.gpu else {}
    shown = [os.path.relpath(a, ROOT) if os.path.isabs(a) and a.startswith(ROOT + os.sep) else a for a in args]
    record |= {
        "command": "python " + shlex.join([os.path.relpath(command[1], ROOT), *shown]),
        "env": extra,
        "output": bench.output(ctx),
    }
    logs = os.path.join(ctx.out, "logs")
    os.makedirs(logs, exist_ok=True)
    stdout_path, stderr_path = (os.path.join(logs, f"{bench.name}.{k}.txt") for k in ("stdout", "stderr"))
    print(f"== {bench.name}: {record['command']}", flush=True)
    start = time.perf_counter()
    timed_out = threading.Event()
    with open(stdout_path, "w") as out, open(stderr_path, "w") as err:
        proc = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            cwd=ROOT,
            env=env | extra | {"PYTHONUNBUFFERED": "1"},
            start_new_session=True,
        )
        timer = threading.Timer(timeout, _stop, (proc, timed_out))
        timer.start()
        try:
            for line in proc.stdout:
                out.write(line)
                print(f"  {line}", end="", flush=True)
            proc.wait()
        except KeyboardInterrupt:
            _stop(proc, timed_out)
            raise
        finally:
            timer.cancel()
    record |= {
        "wall_s": time.perf_counter() - start,
        "loadavg_after": list(os.getloadavg()),
        "returncode": proc.returncode,
        "stdout_log": os.path.relpath(stdout_path, ctx.out),
        "stderr_log": os.path.relpath(stderr_path, ctx.out),
    }
    with open(stderr_path) as f:
        stderr = f.read().strip().splitlines()
    ok = proc.returncode == 0 and not timed_out.is_set()
    if ok and bench.name == "jaxmarl_ippo":
        _save_last_json_line(stdout_path, record["output"])
    if ok and record["output"] is None:  # a benchmark whose printed output is its result
        with open(stdout_path) as f:
            record["stdout"] = f.read()
    elif ok and not _fresh(record["output"], start_time=time.time() - record["wall_s"]):
        ok, stderr = False, stderr + [f"(it exited 0 but did not write {record['output']})"]
    record["status"] = "ok" if ok else ("timed out" if timed_out.is_set() else "failed")
    if not ok:
        record["stderr_tail"] = stderr[-25:] + (
            [f"(stopped after --timeout {timeout:g} s)"] if timed_out.is_set() else []
        )
        with open(stdout_path) as f:
            record["stdout_tail"] = f.read().strip().splitlines()[-10:]
    print(
        f"== {bench.name}: {record['status']} in {record['wall_s']:.0f} s, load "
        f"{record['loadavg_before'][0]:.2f} -> {record['loadavg_after'][0]:.2f}",
        flush=True,
    )
    if not ok:
        print("\n".join(f"   | {line}" for line in stderr[-10:]), flush=True)
    return record


def _stop(proc: subprocess.Popen, flag: threading.Event) -> None:
    """End the benchmark's process group (the benchmark and the workers it started), TERM first, then KILL."""
    flag.set()
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=20)
            return
        except subprocess.TimeoutExpired:
            continue


def _fresh(path: str, start_time: float) -> bool:
    return os.path.exists(path) and os.path.getmtime(path) >= start_time - 1


def _save_last_json_line(stdout_path: str, path: str) -> None:
    """jaxmarl_ippo.py prints its result as one JSON line (and writes it to a fixed path in benchmarks/results)."""
    with open(stdout_path) as f:
        lines = [line for line in f if line.startswith("{")]
    if lines:
        with open(path, "w") as f:
            f.write(lines[-1])


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


# -- formatting ----------------------------------------------------------------------------------------------------


def table(header: list[str], rows: list[list], align: str | None = None) -> str:
    """A markdown table; ``align`` gives ``l`` or ``r`` per column (default: the first left, the others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"]
    lines += ["| " + " | ".join("–" if c is None else str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def num(x, digits: int = 0) -> str | None:
    """``1,234,567`` (or with ``digits`` decimals); None for a missing or non-finite value."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return None
    return f"{x:,.{digits}f}"


def sig(x, digits: int = 3) -> str | None:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return None
    return f"{x:.{digits}g}"


def load_text(load) -> str:
    return "–" if not load else ", ".join(f"{v:.2f}" for v in load)


def settings_text(settings: dict) -> str:
    items = [
        f"`{k}`={json.dumps(v) if not isinstance(v, str) else v}"
        for k, v in settings.items()
        if v not in (None, [], {}) and len(json.dumps(v)) < 200
    ]
    return "; ".join(items)


def machine_text(m: dict) -> str:
    """One line of what a benchmark's JSON says about its machine (`throughput.machine_info`)."""
    parts = []
    if m.get("backend"):
        parts.append(
            f"backend {m['backend']} ({', '.join(m.get('devices', [])[:4])}"
            f"{', ...' if len(m.get('devices', [])) > 4 else ''})"
        )
    if m.get("jax"):
        parts.append(f"jax {m['jax']}" + (f" (jaxlib {m['jaxlib']})" if m.get("jaxlib") else ""))
    if m.get("cpu_model"):
        parts.append(f"{m['cpu_model']}, {m.get('cpus_available', m.get('cpu_count'))} cores")
    if m.get("xla_flags"):
        parts.append(f"XLA_FLAGS=`{m['xla_flags']}`")
    if m.get("git_commit"):
        parts.append(f"commit {m['git_commit'][:12]}")
    return "; ".join(parts)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out: str, name: str) -> str:
    fig.tight_layout()
    fig.savefig(os.path.join(out, name), dpi=110)
    _plt().close(fig)
    return f"![{name}]({name})"


# -- sections ------------------------------------------------------------------------------------------------------


def render_throughput(data: dict, out: str) -> str:
    rows = data["results"]
    combos = sorted({(r["drones"], r["effects"]) for r in rows})
    by = {(r["worlds"], r["drones"], r["effects"]): r for r in rows}
    worlds = sorted({r["worlds"] for r in rows})
    pivot = table(
        ["worlds"] + [f"{d} drone{'s' * (d > 1)}, effects {e}" for d, e in combos],
        [
            [num(w)] + [num(by[(w, d, e)]["median_drone_steps_per_s"]) if (w, d, e) in by else None for d, e in combos]
            for w in worlds
        ],
    )
    detail = table(
        [
            "worlds",
            "drones",
            "effects",
            "devices",
            "steps × substeps",
            "compile s",
            "best",
            "median",
            "state MB",
            "XLA temp MB",
            "RSS peak MB",
            "load",
        ],
        [
            [
                num(r["worlds"]),
                r["drones"],
                r["effects"],
                r.get("devices"),
                f"{r['control_steps']} × {r['substeps']}",
                num(r.get("compile_s"), 2),
                num(r["best_drone_steps_per_s"]),
                num(r["median_drone_steps_per_s"]),
                num(r.get("state_mb"), 2),
                num(r.get("xla_temp_mb"), 2),
                num(r.get("rss_peak_mb")),
                num(r.get("loadavg_1min"), 2),
            ]
            for r in sorted(rows, key=lambda r: (r["worlds"], r["drones"], r["effects"]))
        ],
    )
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for d, e in combos:
        pts = sorted(
            (r["worlds"], r["median_drone_steps_per_s"]) for r in rows if (r["drones"], r["effects"]) == (d, e)
        )
        ax.loglog(*zip(*pts, strict=True), "o-" if e == "on" else "s--", label=f"{d} drone(s), effects {e}")
    ax.set(xlabel="worlds", ylabel="drone-steps/s (median)", title="JAX physics core throughput")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    plot = _save(fig, out, "throughput.png")
    return (
        f"Median drone-steps/s (one drone-step: one {rows[0].get('integrator', '')} physics substep of one "
        f"drone):\n\n{pivot}\n\nAll measurements (drone-steps/s, best and median of the timed calls):\n\n"
        f"{detail}\n\n{plot}"
    )


ENV_LABELS = {"vector": "jaxdrones vector env", "native": "jaxdrones JAX-native", "crazyflow": "crazyflow vector env"}


def render_envs(data: dict, out: str) -> str:
    rows = data["results"]
    envs = [e for e in ENV_LABELS if any(r["env"] == e for r in rows)]
    by = {(r["env"], r["worlds"]): r for r in rows}
    sizes = sorted({r["worlds"] for r in rows})
    median = table(
        ["worlds"] + [ENV_LABELS[e] for e in envs],
        [[num(n)] + [num(by[(e, n)]["median_env_steps_per_s"]) if (e, n) in by else None for e in envs] for n in sizes],
    )
    first = table(
        ["worlds"] + [f"{ENV_LABELS[e]}: {'compile' if e == 'native' else 'first call'} s" for e in envs] + ["load"],
        [
            [num(n)]
            + [
                num(by[(e, n)].get("compile_s", by[(e, n)].get("first_call_s")), 2) if (e, n) in by else None
                for e in envs
            ]
            + [num(max(by[(e, n)].get("loadavg_1min", 0) for e in envs if (e, n) in by), 2)]
            for n in sizes
        ],
    )
    crazyflow = data.get("crazyflow") or {}
    if not crazyflow.get("requested", True):
        note = "crazyflow: not requested (`--no-crazyflow`)."
    elif crazyflow.get("error"):
        where = " at every size" if crazyflow.get("measured") else ""
        note = f"crazyflow: **not measured**{where}: {crazyflow['error']}"
    else:
        setup = crazyflow.get("setup_in_worker") or {}
        note = (
            f"crazyflow: {setup.get('env_id')} (crazyflow {setup.get('crazyflow')}, jax {setup.get('jax')}), "
            f"{setup.get('control')} control, {setup.get('dynamics')} model, {setup.get('sim_freq')} Hz physics "
            f"({setup.get('substeps')} substeps per step)."
        )
    ctrl_freq = data["settings"].get("ctrl_freq", 30)
    sections = [
        (
            f"Median env-steps/s (one env-step: one {ctrl_freq} Hz control step of one "
            f"world of hover, random actions):\n\n{median}\n\n{note}\n\nCompile (JAX-native) or first-call "
            f"(vector envs) time:\n\n{first}"
        )
    ]
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for e in envs:
        pts = sorted((r["worlds"], r["median_env_steps_per_s"]) for r in rows if r["env"] == e)
        ax.loglog(*zip(*pts, strict=True), "o-", label=ENV_LABELS[e])
    ax.set(xlabel="worlds", ylabel="env-steps/s (median)", title="env-steps/s by implementation")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    sections.append(_save(fig, out, "envs.png"))
    return "\n\n".join(sections)


def _timed_measures(rows: list[dict]) -> list[str]:
    """The timed calls of gradients.py's rows (dicts with a time ``s``), forward first, in their order of appearance."""
    names = []
    for r in rows:
        names += [k for k, v in r.items() if isinstance(v, dict) and "s" in v and k not in names]
    return sorted(names, key=lambda k: k != "forward")


def _gradient_label(r: dict) -> str:
    parts = [r.get("sim", "?")]
    if r.get("caller"):
        parts.append(str(r["caller"]))
    if "remat" in r and r.get("sim") != "crazyflow":
        parts.append(f"remat={r['remat']}")
    return ", ".join(parts)


def render_gradients(data: dict, out: str) -> str:
    rows = data["results"]
    measures = _timed_measures(rows)
    grads = [m for m in measures if m != "forward"]
    body = []
    for r in sorted(rows, key=lambda r: (r.get("horizon", 0), r.get("worlds", 0), _gradient_label(r))):
        forward = (r.get("forward") or {}).get("s")
        cells = []
        for m in measures:
            s = (r.get(m) or {}).get("s")
            ratio = r.get("ratio_" + m.removeprefix("grad_"), s / forward if s and forward else None)
            ratio = f" ({ratio:.1f}×)" if ratio and m != "forward" else ""
            cells.append(None if s is None else f"{1e3 * s:.2f}{ratio}")
        temps = [(r.get(m) or {}).get("temp_bytes") for m in grads]
        temps = [t for t in temps if t is not None]
        body.append(
            [r.get("horizon"), num(r.get("worlds")), _gradient_label(r)]
            + cells
            + [num(max(temps) / 2**20, 1) if temps else None]
        )
    main = table(
        ["T", "W", "simulator, caller"]
        + [f"{m} ms" + (" (÷ forward)" if m != "forward" else "") for m in measures]
        + ["largest temp MiB"],
        body,
        "rrl" + "r" * (len(measures) + 1),
    )
    crazyflow = data.get("crazyflow") or {}
    note = ""
    if crazyflow.get("requested") is False:
        note = "crazyflow: not requested (`--no-crazyflow`)."
    elif crazyflow.get("error"):
        note = f"crazyflow: **not measured**: {crazyflow['error']}"
    plot = _gradient_plot(rows, grads, out) if grads else ""
    return (
        f"Forward and gradient times (medians of the timed calls) and the gradient's cost in forward passes (the "
        f"median over rounds of one call of each, in turn); memory is XLA's temporary buffers of the compiled "
        f"call:\n\n{main}\n\n{note}\n\n{plot}"
    )


def _gradient_plot(rows: list[dict], grads: list[str], out: str) -> str:
    plt = _plt()
    horizons = sorted({r["horizon"] for r in rows if "horizon" in r})
    fig, axes = plt.subplots(
        len(grads), len(horizons), figsize=(3.6 * len(horizons), 3.0 * len(grads)), squeeze=False, sharey=True
    )
    labels = sorted({_gradient_label(r) for r in rows})
    for i, m in enumerate(grads):
        for j, t in enumerate(horizons):
            ax = axes[i][j]
            for label in labels:
                pts = sorted(
                    (r["worlds"], r[m]["s"] / r["forward"]["s"])
                    for r in rows
                    if r.get("horizon") == t and _gradient_label(r) == label and r.get(m) and r.get("forward")
                )
                if pts:
                    ax.semilogx(*zip(*pts, strict=True), "o-", label=label)
            ax.set(title=f"{m}, T={t}", xlabel="worlds W", ylabel="gradient ÷ forward" if j == 0 else None)
            ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(fontsize=7)
    return _save(fig, out, "gradients.png")


def render_backends(data: dict, out: str) -> str:
    rows = data["results"]
    physics = [r for r in rows if r.get("measure") == "physics"]
    pid = [r for r in rows if r.get("measure") == "pid_loop"]
    camera = [r for r in rows if r.get("measure") == "camera"]
    sections = []
    if physics:
        sections.append(
            "Physics, one world, best of the timed runs:\n\n"
            + table(
                ["drones", "ctrl Hz", "backend", "loop", "physics steps/s", "drone-steps/s", "× real time"],
                [
                    [
                        r["drones"],
                        r["ctrl_freq"],
                        r["backend"],
                        r["loop"],
                        num(r["best"]["physics_steps_per_s"]),
                        num(r["best"]["drone_steps_per_s"]),
                        num(r["best"]["real_time_factor"], 1),
                    ]
                    for r in physics
                ],
                "rrllrrr",
            )
        )
    if pid:
        sections.append(
            "DSL PID at 48 Hz in the loop, PyBullet backend:\n\n"
            + table(
                ["drones", "obstacles", "physics steps/s", "× real time", "final height error m"],
                [
                    [
                        r["drones"],
                        r["obstacles"],
                        num(r["best"]["physics_steps_per_s"]),
                        num(r["best"]["real_time_factor"], 1),
                        sig(r.get("final_height_error_m")),
                    ]
                    for r in pid
                ],
            )
        )
    if camera:
        sections.append(
            "Camera captures (TinyRenderer, RGBA + depth + segmentation), per process:\n\n"
            + table(
                ["drones", "size", "frames/s (best)", "frames/s (median)", "kB/s RGBA (median)"],
                [
                    [
                        r["drones"],
                        f"{r['width']}×{r['height']}",
                        num(r["frames_per_s_best"]),
                        num(r["frames_per_s_median"]),
                        num(r["rgba_kB_per_s_median"]),
                    ]
                    for r in camera
                ],
            )
        )
    if physics:
        plt = _plt()
        fig, ax = plt.subplots(figsize=(7, 4.2))
        groups = sorted({(r["drones"], r["ctrl_freq"]) for r in physics})
        kinds = sorted({(r["backend"], r["loop"]) for r in physics})
        width = 0.8 / len(kinds)
        for k, kind in enumerate(kinds):
            best = {
                (r["drones"], r["ctrl_freq"]): r["best"]["drone_steps_per_s"]
                for r in physics
                if (r["backend"], r["loop"]) == kind
            }
            values = [best.get(g, 0) for g in groups]
            ax.bar([i + k * width for i in range(len(groups))], values, width, label=f"{kind[0]}, {kind[1]} loop")
        ax.set_xticks(
            [i + width * (len(kinds) - 1) / 2 for i in range(len(groups))], [f"{d} drones\n{f} Hz" for d, f in groups]
        )
        ax.set(yscale="log", ylabel="drone-steps/s (best)", title="PyBullet backend vs JAX core, one world")
        ax.legend(fontsize=8)
        sections.append(_save(fig, out, "backends.png"))
    return "\n\n".join(sections)


def render_table2(data: dict, out: str) -> str:
    rows = data["results"]
    backends = [b for b in ("jax", "pybullet", "original") if any(f"{b}_speedup" in r for r in rows)]
    return (
        "The paper's Table II: speed-up over the wall clock (240 Hz physics, 48 Hz PID, obstacles; vision: "
        "64×48 RGB, depth and segmentation at 24 Hz), with the paper's published speed-ups:\n\n"
        + table(
            ["configuration"] + backends + ["paper (i7-8850H)", "paper (i7-1068NG7)"],
            [
                [r["row"]]
                + [f"{num(r[f'{b}_speedup'], 1)}×" for b in backends]
                + [f"{r['paper_speedup'][0]}×", f"{r['paper_speedup'][1]}×"]
                for r in rows
            ],
        )
    )


def render_cameras(data: dict, out: str) -> str:
    rows = data["results"]
    cams = [r for r in rows if r["sim"] != "jaxdrones-env"]
    env = [r for r in rows if r["sim"] == "jaxdrones-env"]
    sections = [
        "Onboard cameras, 64 × 48, frames/s (median), by scene size P (primitives besides the ground):\n\n"
        + table(
            ["renderer", "images", "P", "worlds", "frames/s", "ms per call"],
            [
                [
                    r["sim"],
                    "+".join(r["kinds"]),
                    r["primitives"],
                    r["worlds"],
                    num(r["frames_per_s"]),
                    num(1e3 * r["s"], 1),
                ]
                for r in cams
            ],
            "llrrrr",
        )
    ]
    if env:
        sections.append(
            "Envs with depth and segmentation cameras at every 30 Hz control step, JAX backend:\n\n"
            + table(
                ["task", "P", "worlds", "env steps/s"],
                [[r.get("task", "fly_thru_gate"), r["primitives"], r["worlds"], num(r["frames_per_s"])] for r in env],
                "lrrr",
            )
        )
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for sim in sorted({r["sim"] for r in cams}):
        for p in sorted({r["primitives"] for r in cams if r["sim"] == sim}):
            pts = sorted((r["worlds"], r["frames_per_s"]) for r in cams if r["sim"] == sim and r["primitives"] == p)
            ax.plot(*zip(*pts, strict=True), marker="o", label=f"{sim}, P={p}")
    ax.set(xscale="log", yscale="log", xlabel="worlds", ylabel="frames/s", title="Onboard cameras, 64 × 48")
    ax.legend(fontsize=8)
    sections.append(_save(fig, out, "cameras.png"))
    return "\n\n".join(sections)


def render_encoders(data: dict, out: str) -> str:
    return (
        f"The vision encoder's gradient, {data['minibatches']} minibatches of {data['batch']} 24 × 32 images, "
        f"µs per sample (median), on {data['device']}:\n\n"
        + table(
            ["convolution", "program", "µs per sample"],
            [[r["encoder"], r["program"], num(r["us_per_sample"], 1)] for r in data["rows"]],
            "llr",
        )
    )


def render_train_algos(data: dict, out: str) -> str:
    rows = data["results"]
    algos = list(dict.fromkeys(r["algo"] for r in rows))
    unit = next((r.get("success_unit") for r in rows if r.get("success_unit")), "")
    metric = next((r.get("success_metric") for r in rows if r.get("success_metric")), "success metric")
    threshold = next((r.get("success_threshold") for r in rows if r.get("success_threshold") is not None), None)

    def budget(r):
        return "default" if r.get("budget") is None else num(r["budget"])

    def value(r):
        v = r.get("success_value")
        return None if v is None else f"{100 * v:.2f} cm" if unit == "m" else f"{v:.4g} {unit}"

    def phases(r):
        p = r.get("phases_s") or {}
        return " / ".join(f"{p[k]:.1f}" for k in ("setup", "train", "save", "plots") if k in p) or None

    runs = table(
        [
            "algo",
            "budget",
            "cache",
            "env steps",
            "wall s (outside)",
            "wall s (summary)",
            "setup / train / save / plots s",
            "solved at s (env steps)",
            metric,
            "terminated",
            "solved",
        ],
        [
            [
                r["algo"],
                budget(r),
                r["cache"],
                num(r.get("env_steps")),
                num(r.get("wall_time_s"), 1),
                num(r.get("summary_wall_time_s"), 1),
                phases(r),
                None if r.get("solved_at_s") is None else f"{r['solved_at_s']:.1f} ({num(r['solved_at_env_steps'])})",
                value(r),
                None if r.get("terminated_rate") is None else f"{r['terminated_rate']:.1%}",
                "**failed**: " + r["error"][:120] if r.get("error") else ("yes" if r.get("solved") else "no"),
            ]
            for r in rows
        ],
        "llllrrrrrrl",
    )
    first = data.get("first_solved") or {}
    solved = []
    for algo in algos:
        cold, warm = (first.get(algo) or {}).get("cold"), (first.get(algo) or {}).get("warm")
        if cold is None:
            solved.append([algo, "not solved", None, None, None, None, None, None])
            continue
        solved.append(
            [
                algo,
                budget(cold),
                num(cold.get("env_steps")),
                num(cold.get("wall_time_s"), 1),
                num((warm or {}).get("wall_time_s"), 1),
                num(cold.get("solved_at_s"), 1),
                num((warm or {}).get("solved_at_s"), 1),
                value(cold),
            ]
        )
    solved_table = table(
        [
            "algo",
            "smallest budget that solved",
            "env steps",
            "cold wall s",
            "warm wall s",
            "cold: solved at s",
            "warm: solved at s",
            metric,
        ],
        solved,
    )
    env_alone = {r["worlds"]: r["median_env_steps_per_s"] for r in data.get("env_rates") or []}
    speed, speed_plot = [], []
    for algo in algos:
        mine = [r for r in rows if r["algo"] == algo and r.get("env_steps")]
        if not mine:
            continue
        r = max(mine, key=lambda r: (r["env_steps"], r["cache"] == "warm"))
        env = env_alone.get(r.get("num_envs"))
        after = r.get("trainer_env_steps_per_s_after_first_eval")
        speed.append(
            [
                algo,
                num(r.get("num_envs")),
                f"{budget(r)}, {r['cache']}",
                num(r.get("trainer_env_steps_per_s")),
                num(after),
                num(env),
                None if not (env and after) else f"{after / env:.2f}",
            ]
        )
        speed_plot.append((algo, after, env, r.get("num_envs")))
    speed_table = table(
        [
            "algo",
            "worlds",
            "run",
            "trainer env-steps/s (train phase)",
            "after the first evaluation",
            "env alone (JAX-native, same worlds)",
            "trainer ÷ env",
        ],
        speed,
    )
    plot = _train_plot(rows, algos, first, speed_plot, out)
    return (
        f"Each run a fresh `jaxdrones train` process; *cold*: an empty `JAXDRONES_CACHE_DIR`, *warm*: the same "
        f"command again with the cache the cold run filled. Wall time outside: around the process; summary: "
        f"the command's own count from its process start. *Solved at*: from the process start to the first "
        f"evaluation meeting the threshold ({metric} < {threshold} {unit}, none terminated).\n\n{runs}\n\n"
        f"Time to a solved {data.get('task', 'task')}:\n\n{solved_table}\n\nTraining speed next to the env's "
        f"own (the run with the most env steps per algorithm; *after the first evaluation* excludes the "
        f"compilation):\n\n{speed_table}\n\n{plot}"
    )


def _train_plot(rows: list[dict], algos: list[str], first: dict, speed: list[tuple], out: str) -> str:
    """Left: wall time of the smallest solving run per algorithm, cold and warm cache (hatched: nothing solved, the
    largest run), with the time its first evaluation met the threshold as a dot. Right: env-steps/s of the trainer
    after its first evaluation and of the env alone at the same worlds."""
    from matplotlib.patches import Patch

    plt = _plt()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    colors = {"cold": "tab:blue", "warm": "tab:orange"}
    for k, cache in enumerate(colors):
        for i, algo in enumerate(algos):
            row = (first.get(algo) or {}).get(cache)
            solved = row is not None
            if not solved:
                runs = [r for r in rows if r["algo"] == algo and r["cache"] == cache and r.get("wall_time_s")]
                row = max(runs, key=lambda r: r.get("env_steps") or 0, default={})
            x = i + 0.4 * k
            ax.bar(
                x,
                row.get("wall_time_s", 0),
                0.4,
                color=colors[cache],
                hatch="" if solved else "//",
                edgecolor="black" if not solved else None,
            )
            if row.get("solved_at_s") is not None:
                ax.plot(x, row["solved_at_s"], "k.", markersize=9)
    ax.set_xticks([i + 0.2 for i in range(len(algos))], algos)
    ax.set_ylim(0, 1.5 * max([bar.get_height() for bar in ax.patches] + [1]))  # room for the legend
    ax.set(ylabel="s from the process start", title="time to a solved hover")
    ax.legend(
        handles=[
            Patch(color=colors["cold"], label="wall time, empty cache"),
            Patch(color=colors["warm"], label="wall time, warm cache"),
            Patch(facecolor="white", edgecolor="black", hatch="//", label="not solved (largest run)"),
            plt.Line2D(
                [],
                [],
                color="k",
                marker=".",
                linestyle="",
                markersize=9,
                label="first evaluation that met the threshold",
            ),
        ],
        fontsize=8,
    )
    names = [s[0] for s in speed]
    for k, (label, values) in enumerate(
        (
            ("trainer, after its first evaluation", [s[1] or 0 for s in speed]),
            ("env alone, same worlds", [s[2] or 0 for s in speed]),
        )
    ):
        ax2.bar([i + 0.4 * k for i in range(len(names))], values, 0.4, label=label)
    ax2.set_xticks(
        [i + 0.2 for i in range(len(names))],
        [f"{n}\n{w} worlds" for n, w in zip(names, [s[3] for s in speed], strict=True)],
    )
    ax2.set(yscale="log", ylabel="env-steps/s", title="training speed and the env's own")
    ax2.legend(fontsize=8)
    return _save(fig, out, "train_algos.png")


def render_printed(record: dict, out: str) -> str:
    """The section of a benchmark whose printed output is its result (its table)."""
    what = " (relative errors in %)" if record["name"] == "sysid_noise" else ""
    return f"Its printed output{what}:\n\n```\n{record.get('stdout', '').strip()}\n```"


def render_multi_agent(data: dict, out: str) -> str:
    rows = data["rows"]
    main = table(
        [
            "D",
            "worlds",
            "coupling",
            "downwash",
            "physics agent-steps/s",
            "ns per drone-substep",
            "env agent-steps/s",
            "MAPPO agent-steps/s",
            "force error ÷ weight",
        ],
        [
            [
                r["n_drones"],
                num(r["worlds"]),
                "lists" if r["lists"] else "all",
                "on" if r["downwash"] else "off",
                num(r["physics"]),
                num(r.get("physics_ns_per_drone_substep"), 1),
                num(r["env"]),
                num(r.get("mappo")),
                sig(r.get("downwash_error_over_weight"), 2),
            ]
            for r in rows
        ],
        "rrllrrrrr",
    )
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for lists in (False, True):
        for downwash in (False, True):
            pts = sorted(
                (r["n_drones"], r["env"]) for r in rows if bool(r["lists"]) == lists and r["downwash"] == downwash
            )
            if pts:
                ax.loglog(
                    *zip(*pts, strict=True),
                    "o-" if downwash else "s--",
                    label=f"env, {'lists' if lists else 'all pairs'}, downwash {'on' if downwash else 'off'}",
                )
    ax.set(xlabel="drones per world D", ylabel="agent-steps/s", title="multi_hover env throughput")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return f"{main}\n\n{_save(fig, out, 'multi_agent.png')}"


def render_downwash_policies(data: dict, out: str) -> str:
    return f"{data.get('episodes')} episodes per evaluation:\n\n" + table(
        ["policy", "seed", "flown with downwash", "largest altitude error cm", "tracking error cm", "terminated"],
        [
            [
                r["policy"],
                r.get("seed"),
                "on" if r["flown_with_downwash"] else "off",
                num(100 * r["max_altitude_error_m"], 2),
                num(100 * r["tracking_error_m"], 2),
                f"{r['terminated_rate']:.1%}",
            ]
            for r in data["rows"]
        ],
        "lrlrrr",
    )


def render_sb3_hover(data: dict, out: str) -> str:
    return (
        f"{data.get('algorithm')}, {data.get('n_envs')} envs, {data.get('env_kwargs')}, "
        f"{data.get('eval_episodes')} evaluation episodes:\n\n"
        + table(
            [
                "env steps",
                "train s",
                "train CPU s",
                "env-steps/s",
                "final distance cm (mean / median / max)",
                "return",
                "terminated early",
            ],
            [
                [
                    num(c["env_steps"]),
                    num(c["train_wall_s"], 1),
                    num(c["train_cpu_s"], 1),
                    num(c["env_steps"] / c["train_wall_s"]),
                    " / ".join(
                        f"{100 * c[k]:.2f}"
                        for k in ("final_distance_mean_m", "final_distance_median_m", "final_distance_max_m")
                    ),
                    num(c["episode_return_mean"], 1),
                    c["terminated_early"],
                ]
                for c in data["checkpoints"]
            ],
        )
    )


def render_jaxmarl_ippo(data: dict, out: str) -> str:
    keys = [k for k in data if not isinstance(data[k], (dict, list))] + ["final_z_m"]
    return table(
        keys, [[json.dumps(data[k]) if isinstance(data.get(k), list) else data.get(k) for k in keys]], "l" * len(keys)
    )


def render_firmware_loop(data: dict, out: str) -> str:
    return table(
        [
            "worlds",
            "ticks",
            "physics alone, 1 tick a call, drone-steps/s",
            "10 ticks a call",
            "tick by tick (`pid_tick`)",
            "/ the faster physics",
            "scheduled (`pid_ticks`)",
            "/ the faster physics",
        ],
        [
            [
                r["worlds"],
                r["ticks"],
                num(r["physics_drone_steps_per_s"]),
                num(r["physics_10_drone_steps_per_s"]),
                num(r["tick_by_tick_drone_steps_per_s"]),
                num(r["tick_by_tick_over_physics"], 2),
                num(r["scheduled_drone_steps_per_s"]),
                num(r["scheduled_over_physics"], 2),
            ]
            for r in data["results"]
        ],
    )


RENDERERS = {
    "throughput": render_throughput,
    "firmware_loop": render_firmware_loop,
    "envs": render_envs,
    "gradients": render_gradients,
    "backends": render_backends,
    "cameras": render_cameras,
    "encoders": render_encoders,
    "table2": render_table2,
    "train_algos": render_train_algos,
    "multi_agent": render_multi_agent,
    "downwash_policies": render_downwash_policies,
    "sb3_hover": render_sb3_hover,
    "jaxmarl_ippo": render_jaxmarl_ippo,
}


def render_section(record: dict, out: str) -> str:
    """A benchmark's section of REPORT.md from its run record and its JSON."""
    name = record["name"]
    lines = [f"## {name}", ""]
    if record["status"] == "skipped":
        return "\n".join(lines + [f"Skipped: {record['reason']}.", ""])
    lines.append(
        f"- Command: `{record['command']}`"
        + (f" with {' '.join(f'{k}={v}' for k, v in record['env'].items())}" if record.get("env") else "")
    )
    lines.append(
        f"- Run {record['date']}, {record.get('wall_s', 0):.0f} s; load average (1, 5, 15 min) before "
        f"{load_text(record['loadavg_before'])}, after {load_text(record['loadavg_after'])}."
    )
    if record["status"] != "ok":
        tail = "\n".join(record.get("stderr_tail") or [])
        out_tail = "\n".join(record.get("stdout_tail") or [])
        return "\n".join(
            lines
            + [
                "",
                (
                    f"**{record['status'].upper()}** (exit status {record.get('returncode')}); the "
                    f"last lines of its stderr ({record.get('stderr_log')}):"
                ),
                "",
                "```",
                tail,
                "```",
                "",
                f"and of its stdout ({record.get('stdout_log')}):",
                "",
                "```",
                out_tail,
                "```",
                "",
            ]
        )
    try:
        if record["output"] is None:
            return "\n".join(lines + ["", render_printed(record, out), ""])
        with open(record["output"]) as f:
            data = json.load(f)
        machine = data.get("machine")
        if isinstance(machine, dict):
            lines.append(f"- Machine: {machine_text(machine) or json.dumps(machine)}.")
        elif machine:
            lines.append(f"- Machine: {machine}, {data.get('cpus')} CPUs.")
        if data.get("loadavg_start") or data.get("loadavg_end"):
            lines.append(
                f"- Load average recorded by the benchmark: start {load_text(data.get('loadavg_start'))}, end "
                f"{load_text(data.get('loadavg_end'))}."
            )
        if isinstance(data.get("versions"), dict):
            lines.append(f"- Versions: {', '.join(f'{k} {v}' for k, v in data['versions'].items())}.")
        if data.get("settings"):
            lines.append(f"- Settings: {settings_text(data['settings'])}.")
        lines += ["", RENDERERS[name](data, out), ""]
    except Exception as err:  # noqa: BLE001  (one broken section must not lose the others)
        lines += ["", f"**Could not render** {record['output']}: {type(err).__name__}: {err}", ""]
    return "\n".join(lines)


def write_report(records: dict, probe_info: dict, out: str, invocation: str) -> str:
    """Write ``REPORT.md`` (and the plots) in ``out`` from the run records; returns its path."""
    p = probe_info
    device = (
        f"backend **{p.get('backend')}**, {len(p.get('devices', []))} device(s) ({p.get('device_kind', '?')}"
        + (f", {p['device_memory_gb']:.0f} GiB" if p.get("device_memory_gb") else "")
        + ")"
    )
    lines = [
        "# jaxdrones benchmarks",
        "",
        f"Generated by `{invocation}` on {_now()}.",
        "",
        f"- Device: {device}; jax {p.get('jax')} (jaxlib {p.get('jaxlib')}).",
        (
            f"- CPU: {p.get('cpu_model')}, {p.get('cpus_available')} of {p.get('cpu_count')} cores available; "
            f"{p.get('platform')}; Python {p.get('python')}."
        ),
        f"- Source: commit {p.get('git_commit')}.",
        (
            f"- Load average (1, 5, 15 min) at the start: {load_text(p.get('loadavg_start'))}; at the end: "
            f"{load_text(p.get('loadavg_end'))}. The timings are wall-clock: a busy machine slows them."
        ),
        "",
    ]
    if p.get("probe_error"):
        lines += [f"The device probe failed: {p['probe_error']}", ""]
    ordered = [records[name] for name in BENCHMARKS if name in records]
    lines += [
        table(
            ["benchmark", "status", "run", "wall time", "load before → after (1 min)"],
            [
                [
                    f"[{r['name']}](#{r['name']})",
                    r["status"],
                    r["date"],
                    None if "wall_s" not in r else f"{r['wall_s']:.0f} s",
                    f"{r['loadavg_before'][0]:.2f} → {r['loadavg_after'][0]:.2f}",
                ]
                for r in ordered
            ],
            "lllrr",
        ),
        "",
    ]
    lines += [render_section(r, out) for r in ordered]
    path = os.path.join(out, "REPORT.md")
    with open(path, "w") as f:
        f.write("\n".join(lines))
    return path


# -- main ----------------------------------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    names = list(BENCHMARKS)
    parser.add_argument("--quick", action="store_true", help="small grids: a smoke run (output in results/quick)")
    parser.add_argument("--only", nargs="+", choices=names, metavar="NAME", help=f"run only these: {names}")
    parser.add_argument("--skip", nargs="+", choices=names, default=[], metavar="NAME", help="do not run these")
    parser.add_argument("--all", action="store_true", help="also the benchmarks left out of the default run")
    parser.add_argument(
        "--out",
        default=None,
        help="output folder (default benchmarks/results, or benchmarks/results/quick with --quick)",
    )
    parser.add_argument(
        "--cpu", action="store_true", help="run on the CPU even where a GPU is present (JAX_PLATFORMS=cpu)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=4 * 3600,
        help="seconds per benchmark before it is stopped and reported as timed out (default 4 h)",
    )
    parser.add_argument("--jaxmarl-baselines", default=None, help="JaxMARL's baselines/IPPO folder, for jaxmarl_ippo")
    parser.add_argument(
        "--render-only",
        action="store_true",
        help="run nothing: rebuild REPORT.md and the plots from the results already in --out",
    )
    args = parser.parse_args(argv)
    args.out = os.path.abspath(args.out or (os.path.join(RESULTS, "quick") if args.quick else RESULTS))
    chosen = args.only or [n for n, b in BENCHMARKS.items() if b.default or args.all]
    args.selected = [n for n in chosen if n not in args.skip]
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    invocation = "python benchmarks/report.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    os.makedirs(args.out, exist_ok=True)
    runs_path = os.path.join(args.out, "report_runs.json")
    saved = {}
    if os.path.exists(runs_path):
        with open(runs_path) as f:
            saved = json.load(f)
    records = saved.get("records", {})
    env = dict(os.environ)
    if args.cpu:
        env["JAX_PLATFORMS"] = "cpu"
    if args.render_only:
        info = saved.get("probe") or probe(env)
        path = write_report(records, info, args.out, saved.get("invocation", invocation))
        print(f"wrote {path}")
        return 0
    info = probe(env) | {"loadavg_start": list(os.getloadavg())}
    gpu = info.get("backend") == "gpu"
    print(
        f"device: {info.get('backend')} {info.get('devices')}, jax {info.get('jax')}, {info['cpu_model']} "
        f"({info['cpus_available']} cores), load {load_text(info['loadavg_start'])}; running "
        f"{', '.join(args.selected)}{' (quick)' if args.quick else ''} into {args.out}",
        flush=True,
    )
    if info.get("probe_error"):
        print(f"device probe failed: {info['probe_error']}", flush=True)
    ctx = Context(
        quick=args.quick,
        gpu=gpu,
        out=args.out,
        crazyflow_ready=os.path.exists(os.path.join(CRAZYFLOW_VENV, "bin", "python")),
        jaxmarl_baselines=args.jaxmarl_baselines,
    )
    path = write_report(records, info, args.out, invocation)
    for name in args.selected:
        records[name] = run_benchmark(BENCHMARKS[name], ctx, env, args.timeout)
        info["loadavg_end"] = list(os.getloadavg())
        with open(runs_path, "w") as f:  # after each benchmark, so that a stopped run keeps what it measured
            json.dump({"invocation": invocation, "probe": info, "records": records}, f, indent=1)
        path = write_report(records, info, args.out, invocation)
    print(f"wrote {path}")
    failed = [n for n in args.selected if records[n]["status"] not in ("ok", "skipped")]
    if failed:
        print(f"failed: {', '.join(failed)} (see {path})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
