"""The first and a warm ``jaxdrones train TASK`` under several settings of the environment, their runs interleaved.

Machines of one kind differ (four NVIDIA H200 machines took 8.5-16.5 s for the same first run), so settings are
compared only between runs interleaved on one machine. Each setting is a set of environment variables given to
``python -m jaxdrones.cli train TASK`` (e.g. ``JAX_THREEFRY_GPU_KERNEL_LOWERING=0``, which turns off the command
line's JAX option, or ``XLA_PYTHON_CLIENT_PREALLOCATE=true``, which brings back JAX's preallocation of the GPU's
memory; `jaxdrones.cli.xla`); each has its own compilation cache (``JAXDRONES_CACHE_DIR``), emptied before each round.
A round runs every setting from the empty cache (``cold``), then every setting again (``warm``, ``--warm`` times).
Per run: the wall time from outside (the process, its exit included), the run's phases and result
(``summary.json``), the seconds after training started at which each evaluation ended (``progress.json``: the
first one waits for the programs' compilation or loading, the others each follow one chunk of updates) and, with
``--xla-timers``, XLA's own timers per compiled program (``TF_CPP_VMODULE=gpu_compiler=1``: its HLO passes and its
backend, LLVM and PTX, as XLA:GPU logs them; nothing on the CPU). ``--timeline`` adds, from JAX's own log
(``JAX_LOGGING_LEVEL=DEBUG``), each program's lowering to StableHLO, its compilation or its loading from the cache
(hit or miss), and when that ended, in seconds from the process's start: where a warm run's training phase goes
before its first update.

A setting can also be another checkout of jaxdrones, run from ``PYTHONPATH`` (from a folder outside either
checkout, so that the current folder does not come first), e.g. a commit against the working tree::

    git worktree add /tmp/base COMMIT && cd /tmp
    python /path/to/benchmarks/speed/first_run.py --rounds 2 --warm 3 --setting base PYTHONPATH=/tmp/base \
        --setting now PYTHONPATH=/path/to/checkout

    python benchmarks/speed/first_run.py                                          # the command line's settings against
                                                                            # each GPU setting turned off
    python benchmarks/speed/first_run.py --rounds 3 --xla-timers
    python benchmarks/speed/first_run.py --rounds 1 --warm 2 --timeline --setting default
    python benchmarks/speed/first_run.py --setting nokernel JAX_THREEFRY_GPU_KERNEL_LOWERING=0 \
        --train-args --defaults gpu
    python benchmarks/speed/first_run.py --setting one --setting seeds4 TRAIN_ARGS='--seeds 4'    # 4 seeds against 1
    python benchmarks/speed/first_run.py --setting one --setting sweep \
        TRAIN_ARGS='--sweep learning_rate=1.5e-3,3e-3,6e-3 --seeds 3'                         # 9 runs against 1

Results: a table of medians on stdout and every run in ``benchmarks/results/first_run_<TASK>.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

#: The settings compared by default: the command line's own, and each of its GPU settings turned off by the
#: user's environment variable (`jaxdrones.cli.xla.GPU_JAX_OPTIONS`, `jaxdrones.cli.xla.GPU_ENV`).
DEFAULT_SETTINGS = {
    "command line": {},
    "no threefry kernel": {"JAX_THREEFRY_GPU_KERNEL_LOWERING": "0"},
    "preallocated": {"XLA_PYTHON_CLIENT_PREALLOCATE": "true"},
}
_TIMER = re.compile(r"GpuCompiler::(RunHloPasses|RunBackend) for (\S+) time: ([0-9.]+) (s|ms|us)")
_UNIT = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
#: JAX's debug log lines (``JAX_LOGGING_LEVEL=DEBUG``; `jax._src.logging_config`'s format) that `timeline` reads.
_LOG_LINE = re.compile(r"^DEBUG:(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}):(\S+?):\d+: (.*)$")
_LOWERED = re.compile(r"Finished jaxpr to MLIR module conversion (\S+) in ([0-9.]+) sec")
_COMPILED = re.compile(r"Finished XLA compilation of (\S+) in ([0-9.]+) sec")
_CACHE = re.compile(r"(Persistent compilation cache hit|PERSISTENT COMPILATION CACHE MISS) for '([^']+)'")


def xla_timers(log: str) -> dict[str, list[float]]:
    """XLA:GPU's timers in a run's log: seconds of ``RunHloPasses`` and ``RunBackend``, one entry per program."""
    timers: dict[str, list[float]] = {"RunHloPasses": [], "RunBackend": []}
    for phase, _, value, unit in _TIMER.findall(log):
        timers[phase].append(round(float(value) * _UNIT[unit], 3))
    return timers


def timeline(log: str, start: float) -> list[dict]:
    """The compiled programs of a run in JAX's debug log, in the order their compilation (or loading from the
    cache) ended: ``{program, lowering_s, compile_s, cache, ended_at_s}``, ``ended_at_s`` in seconds after
    ``start`` (the process's start, ``time.time()``; the log's clock, to its milliseconds); ``lowering_s`` is a
    lowering to StableHLO of a program of the same name, ``cache`` ``hit``, ``miss`` or None (the cache off).
    Programs built side by side share names (``jit(call)``), so these are paired in the order they were logged: a
    close reading, not an exact one."""
    programs = []
    lowered: dict[str, list[float]] = collections.defaultdict(list)
    cache: dict[str, list[str]] = collections.defaultdict(list)
    for line in log.splitlines():
        match = _LOG_LINE.match(line)
        if not match:
            continue
        stamp, _, message = match.groups()
        when = time.mktime(time.strptime(stamp[:19], "%Y-%m-%d %H:%M:%S")) + int(stamp[20:]) / 1e3
        if found := _LOWERED.search(message):
            lowered[found[1]].append(float(found[2]))
        elif found := _CACHE.search(message):
            cache[found[2]].append("hit" if found[1].endswith("hit") else "miss")
        elif found := _COMPILED.search(message):
            name = found[1]
            hits = cache[name.replace("(", "_").rstrip(")")]
            programs.append(
                {
                    "program": name,
                    "lowering_s": lowered[name].pop(0) if lowered[name] else None,
                    "compile_s": float(found[2]),
                    "cache": hits.pop(0) if hits else None,
                    "ended_at_s": round(when - start, 3),
                }
            )
    return programs


def run_once(
    task: str, env: dict, cache: str, out: str, train_args: list[str], timers: bool, log: bool = False
) -> dict:
    """One ``jaxdrones train`` process with ``env`` over the current environment; its times and result (with
    ``log``, its programs' `timeline`)."""
    environ = {**os.environ, **env, "JAXDRONES_CACHE_DIR": cache}
    if timers:
        environ.update(TF_CPP_MIN_LOG_LEVEL="0", TF_CPP_VMODULE="gpu_compiler=1")
    if log:
        environ.update(JAX_LOGGING_LEVEL="DEBUG")
    command = [sys.executable, "-m", "jaxdrones.cli", "train", task, "--out", out, "--overwrite", "--no-progress"]
    started = time.time()
    start = time.perf_counter()
    done = subprocess.run([*command, *train_args], env=environ, capture_output=True, text=True)
    record = {"wall_time_s": time.perf_counter() - start, "returncode": done.returncode}
    if done.returncode != 0:
        record["error"] = done.stderr[-2000:]
        return record
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    # .get: an older checkout (a setting's PYTHONPATH) writes fewer fields
    fields = ("wall_time_s", "phases_s", "success_value", "success", "algo", "defaults")
    record.update({("summary_" if k == "wall_time_s" else "") + k: summary.get(k) for k in fields})
    if "aggregate" in summary:  # --seeds N: each seed's result, and the evaluations of the first seed's rows
        record.update(success_value=[r["success_value"] for r in summary["runs"]], success=summary["aggregate"])
    if "settings" in summary:  # --sweep: each setting's results and aggregate
        labels = [",".join(f"{k}={v}" for k, v in part["setting"].items()) for part in summary["settings"]]
        parts = dict(zip(labels, summary["settings"], strict=True))
        record["success_value"] = {label: [r["success_value"] for r in p["runs"]] for label, p in parts.items()}
        record["success"] = {label: p["aggregate"] for label, p in parts.items()}
    with open(os.path.join(out, "progress.json")) as f:
        rows = json.load(f)
    rows = next(iter(rows.values())) if isinstance(rows, dict) else rows
    record["evals_at_s"] = [round(row["time_s"], 3) for row in rows]
    if timers:
        record["xla_timers_s"] = xla_timers(done.stderr)
    if log:
        record["programs"] = timeline(done.stderr, started)
    return record


def main() -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="hover")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of a cold and warm runs (default 2)")
    parser.add_argument("--warm", type=int, default=1, help="warm runs per setting and round (default 1)")
    parser.add_argument(
        "--setting",
        nargs="+",
        action="append",
        metavar=("NAME", "VAR=VALUE"),
        help="a setting to compare: its name and environment variables, and its own jaxdrones train options as "
        "TRAIN_ARGS='--OPTION ...' (repeatable; default: the command line's "
        f"and each GPU setting turned off: {list(DEFAULT_SETTINGS)})",
    )
    parser.add_argument("--xla-timers", action="store_true", help="log XLA:GPU's timers per compiled program")
    parser.add_argument(
        "--timeline", action="store_true", help="each program's lowering and compilation or loading, from JAX's log"
    )
    parser.add_argument("--out", default=None, help="JSON output (default benchmarks/results/first_run_TASK.json)")
    parser.add_argument("--train-args", nargs=argparse.REMAINDER, default=[], help="passed to jaxdrones train")
    args = parser.parse_args()
    if args.rounds < 1 or args.warm < 1:
        parser.error("--rounds and --warm must be >= 1")
    settings = DEFAULT_SETTINGS
    setting_args: dict[str, list[str]] = collections.defaultdict(list)  # a setting's own jaxdrones train options
    if args.setting:
        settings = {}
        for name, *variables in args.setting:
            pairs = [v.partition("=") for v in variables]
            if any(not sep or not key for key, sep, _ in pairs):
                parser.error(f"--setting {name}: variables are VAR=VALUE, got {variables}")
            settings[name] = {key: value for key, _, value in pairs}
            setting_args[name] = settings[name].pop("TRAIN_ARGS", "").split()
    records = []
    with tempfile.TemporaryDirectory(prefix="jaxdrones-first-run-") as tmp:
        folders = {name: os.path.join(tmp, f"setting{k}") for k, name in enumerate(settings)}
        for round_ in range(args.rounds):
            for mode in ("cold", *["warm"] * args.warm):
                for name, env in settings.items():
                    cache, out = folders[name] + "-cache", folders[name] + "-run"
                    if mode == "cold":
                        shutil.rmtree(cache, ignore_errors=True)
                    train_args = [*args.train_args, *setting_args[name]]
                    record = run_once(args.task, env, cache, out, train_args, args.xla_timers, args.timeline)
                    record.update(setting=name, env=env, train_args=setting_args[name], mode=mode, round=round_)
                    records.append(record)
                    print(json.dumps(record), flush=True)
    print(
        f"\n{args.task}: medians of {args.rounds} round(s) of a cold and {args.warm} warm run(s), seconds from the "
        "command to its exit, and of the training phase's first evaluation (after loading or compiling the "
        "programs) and each later chunk with its evaluation"
    )
    print(f"{'setting':<24} {'cold':>7} {'warm':>7} {'1st eval':>9} {'chunk':>7}  final metric (cold runs)")
    for name in settings:
        row = []
        for mode in ("cold", "warm"):
            times = [r["wall_time_s"] for r in records if r["setting"] == name and r["mode"] == mode]
            row.append(statistics.median(times))
        warm = [r for r in records if r["setting"] == name and r["mode"] == "warm" and r.get("evals_at_s")]
        first = statistics.median([r["evals_at_s"][0] for r in warm]) if warm else float("nan")
        gaps = [b - a for r in warm for a, b in itertools.pairwise(r["evals_at_s"])]
        chunk = statistics.median(gaps) if gaps else float("nan")
        values = [r.get("success_value") for r in records if r["setting"] == name and r["mode"] == "cold"]
        print(f"{name:<24} {row[0]:7.2f} {row[1]:7.2f} {first:9.2f} {chunk:7.3f}  {values}")
        for record in warm[-1:] if args.timeline else []:
            for program in record["programs"]:
                print(f"{'':<4}last warm run: {json.dumps(program)}")
    path = args.out or os.path.join(RESULTS, f"first_run_{args.task}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump({"task": args.task, "train_args": args.train_args, "records": records}, f, indent=1)
    print(f"wrote {path}")
    return 0 if all(r["returncode"] == 0 for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
