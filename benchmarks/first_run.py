"""The first and a warm ``jaxdrones train TASK`` under several settings of the environment, their runs interleaved.

Machines of one kind differ (four NVIDIA H200 machines took 8.5-16.5 s for the same first run), so settings are
compared only between runs interleaved on one machine. Each setting is a set of environment variables given to
``python -m jaxdrones.cli train TASK`` (e.g. ``JAX_THREEFRY_GPU_KERNEL_LOWERING=0``, which turns off the command
line's JAX option, or ``XLA_PYTHON_CLIENT_PREALLOCATE=true``, which brings back JAX's preallocation of the GPU's
memory; `jaxdrones._xla`); each has its own compilation cache (``JAXDRONES_CACHE_DIR``), emptied before each round.
A round runs every setting from the empty cache (``cold``), then every setting again (``warm``). Per run: the wall
time from outside (the process, its exit included), the run's phases and result (``summary.json``) and, with
``--xla-timers``, XLA's own timers per compiled program (``TF_CPP_VMODULE=gpu_compiler=1``: its HLO passes and its
backend, LLVM and PTX, as XLA:GPU logs them; nothing on the CPU).

    python benchmarks/first_run.py                                          # the command line's settings against
                                                                            # each GPU setting turned off
    python benchmarks/first_run.py --rounds 3 --xla-timers
    python benchmarks/first_run.py --setting nokernel JAX_THREEFRY_GPU_KERNEL_LOWERING=0 --train-args --defaults gpu

Results: a table of medians on stdout and every run in ``benchmarks/results/first_run_<TASK>.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
#: The settings compared by default: the command line's own, and each of its GPU settings turned off by the
#: user's environment variable (`jaxdrones._xla.GPU_JAX_OPTIONS`, `jaxdrones._xla.GPU_ENV`).
DEFAULT_SETTINGS = {
    "command line": {},
    "no threefry kernel": {"JAX_THREEFRY_GPU_KERNEL_LOWERING": "0"},
    "preallocated": {"XLA_PYTHON_CLIENT_PREALLOCATE": "true"},
}
_TIMER = re.compile(r"GpuCompiler::(RunHloPasses|RunBackend) for (\S+) time: ([0-9.]+) (s|ms|us)")
_UNIT = {"s": 1.0, "ms": 1e-3, "us": 1e-6}


def xla_timers(log: str) -> dict[str, list[float]]:
    """XLA:GPU's timers in a run's log: seconds of ``RunHloPasses`` and ``RunBackend``, one entry per program."""
    timers: dict[str, list[float]] = {"RunHloPasses": [], "RunBackend": []}
    for phase, _, value, unit in _TIMER.findall(log):
        timers[phase].append(round(float(value) * _UNIT[unit], 3))
    return timers


def run_once(task: str, env: dict, cache: str, out: str, train_args: list[str], timers: bool) -> dict:
    """One ``jaxdrones train`` process with ``env`` over the current environment; its times and result."""
    environ = {**os.environ, **env, "JAXDRONES_CACHE_DIR": cache}
    if timers:
        environ.update(TF_CPP_MIN_LOG_LEVEL="0", TF_CPP_VMODULE="gpu_compiler=1")
    command = [sys.executable, "-m", "jaxdrones.cli", "train", task, "--out", out, "--overwrite", "--no-progress"]
    start = time.perf_counter()
    done = subprocess.run([*command, *train_args], env=environ, capture_output=True, text=True)
    record = {"wall_time_s": time.perf_counter() - start, "returncode": done.returncode}
    if done.returncode != 0:
        record["error"] = done.stderr[-2000:]
        return record
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    record.update(
        summary_wall_time_s=summary["wall_time_s"],
        phases_s=summary["phases_s"],
        success_value=summary["success_value"],
        success=summary["success"],
        algo=summary["algo"],
        defaults=summary["defaults"],
    )
    if timers:
        record["xla_timers_s"] = xla_timers(done.stderr)
    return record


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="hover")
    parser.add_argument("--rounds", type=int, default=2, help="cold and warm runs per setting (default 2)")
    parser.add_argument(
        "--setting",
        nargs="+",
        action="append",
        metavar=("NAME", "VAR=VALUE"),
        help="a setting to compare: its name and environment variables (repeatable; default: the command line's "
        f"and each GPU setting turned off: {list(DEFAULT_SETTINGS)})",
    )
    parser.add_argument("--xla-timers", action="store_true", help="log XLA:GPU's timers per compiled program")
    parser.add_argument("--out", default=None, help="JSON output (default benchmarks/results/first_run_TASK.json)")
    parser.add_argument("--train-args", nargs=argparse.REMAINDER, default=[], help="passed to jaxdrones train")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    settings = DEFAULT_SETTINGS
    if args.setting:
        settings = {}
        for name, *variables in args.setting:
            pairs = [v.partition("=") for v in variables]
            if any(not sep or not key for key, sep, _ in pairs):
                parser.error(f"--setting {name}: variables are VAR=VALUE, got {variables}")
            settings[name] = {key: value for key, _, value in pairs}
    records = []
    with tempfile.TemporaryDirectory(prefix="jaxdrones-first-run-") as tmp:
        folders = {name: os.path.join(tmp, f"setting{k}") for k, name in enumerate(settings)}
        for round_ in range(args.rounds):
            for mode in ("cold", "warm"):
                for name, env in settings.items():
                    cache, out = folders[name] + "-cache", folders[name] + "-run"
                    if mode == "cold":
                        shutil.rmtree(cache, ignore_errors=True)
                    record = run_once(args.task, env, cache, out, args.train_args, args.xla_timers)
                    record.update(setting=name, env=env, mode=mode, round=round_)
                    records.append(record)
                    print(json.dumps(record), flush=True)
    print(f"\n{args.task}: medians of {args.rounds} round(s), seconds from the command to its exit")
    print(f"{'setting':<24} {'cold':>7} {'warm':>7}  final metric (cold runs)")
    for name in settings:
        row = []
        for mode in ("cold", "warm"):
            times = [r["wall_time_s"] for r in records if r["setting"] == name and r["mode"] == mode]
            row.append(statistics.median(times))
        values = [r.get("success_value") for r in records if r["setting"] == name and r["mode"] == "cold"]
        print(f"{name:<24} {row[0]:7.2f} {row[1]:7.2f}  {values}")
    path = args.out or os.path.join(HERE, "results", f"first_run_{args.task}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"task": args.task, "train_args": args.train_args, "records": records}, f, indent=1)
    print(f"wrote {path}")
    return 0 if all(r["returncode"] == 0 for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
