"""Time to solve a task with each of ``jaxdrones train``'s algorithms, with an empty and with a warm compilation cache.

Each algorithm (default: ``ppo``, our PPO; ``brax_ppo``, brax's PPO; ``apg``; ``shac``) trains the task once per
budget of env steps, each run a fresh ``python -m jaxdrones.cli train TASK --algo ALGO --steps N`` process, so that
every wall time includes the start of Python, the imports and the JIT compilation, as a user's run does. Every
budget runs twice with the same seed and settings:

- ``cold``: ``JAXDRONES_CACHE_DIR`` set to a new, empty folder (one per algorithm and budget), so the run compiles
  everything;
- ``warm``: the same command again with that folder, now holding the first run's compiled programs (JAX's
  persistent compilation cache, on by default in the command line).

Per run, from outside (``time.perf_counter`` around ``subprocess.run``: ``wall_time_s``) and from the run's
``summary.json`` (``summary_wall_time_s``, counted by the command from the start of its process; ``phases_s``: setup,
train, save and plots; ``train_time_s``; ``env_steps``; ``success_value``, the task's success metric over 256
random starts, and ``success``: below the task's threshold with no episode terminated early) and ``progress.json``
(one row ``{env_steps, time_s, success_value, terminated_rate, ...}`` per evaluation):

- ``solved_at_s``: seconds from the start of the process to the first evaluation that met the task's success
  criterion (``solved_at_env_steps`` env steps), whether or not the final one does;
- ``trainer_env_steps_per_s``: env steps over the train phase (compilation included);
- ``trainer_env_steps_per_s_after_first_eval``: the env steps between the first and the last evaluation over the
  time between them, i.e. the training speed once compiled (collection, updates and the evaluations in between).

Beside the trainers' speed, the JAX-native env alone: ``VmapAutoReset(jd.make(TASK, ctrl_freq=30))`` stepped under
``lax.scan`` with random actions at each trainer's number of worlds (``num_envs`` of its config), timed by
`envs.bench_native` in this process after all the runs (``env_rates`` in the JSON). A run is solved when the task's
metric is below its threshold (hover: final distance < 5 cm) with no episode terminated early; the summary gives,
per algorithm, the smallest budget that solved it, with its cold and warm wall times.

    python benchmarks/training/train_algos.py                                   # hover, budgets 0.5, 1, 2 and 3 M steps
    python benchmarks/training/train_algos.py --budgets default                 # each trainer's own budget for the task
    python benchmarks/training/train_algos.py --task velocity --budgets 1e6 3e6 --algos apg shac --stop-at-solved

Results go to ``benchmarks/results/train_algos_<task>.json`` (``--out``). ``--train-args`` adds arguments to every
``jaxdrones train`` command (e.g. ``--train-args "--realism crazyflie --action-type ctbr"``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

ALGOS = ("ppo", "brax_ppo", "apg", "shac")
BUDGETS = (5e5, 1e6, 2e6, 3e6)
CACHES = ("cold", "warm")


def budget(text: str) -> int | None:
    """An env-step budget: a number (``1e6``), or ``default`` for the trainer's own budget for the task (None)."""
    if text == "default":
        return None
    value = float(text)
    if value < 1 or value != int(value):
        raise argparse.ArgumentTypeError(f"a budget must be a positive whole number of env steps, got {text!r}")
    return int(value)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="hover")
    parser.add_argument(
        "--algos", nargs="+", default=list(ALGOS), help="algorithms of jaxdrones train --algo (default: %(default)s)"
    )
    parser.add_argument(
        "--budgets",
        nargs="+",
        type=budget,
        default=[int(b) for b in BUDGETS],
        help="env steps per run, or 'default' for the trainer's own (default 5e5 1e6 2e6 3e6)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--stop-at-solved",
        action="store_true",
        help="per algorithm, skip the budgets after the first one that solved the task",
    )
    parser.add_argument(
        "--env-repeats", type=int, default=5, help="timed runs of the env-alone measurement (0 skips it; default 5)"
    )
    parser.add_argument(
        "--train-args",
        default="",
        metavar="ARGS",
        help="more arguments for every jaxdrones train command, e.g. '--realism crazyflie --action-type ctbr'",
    )
    parser.add_argument("--out", default=None, help="JSON output (default benchmarks/results/train_algos_TASK.json)")
    args = parser.parse_args(argv)
    args.out = args.out or os.path.join(RESULTS, f"train_algos_{args.task}.json")
    # Smallest first, so that the first budget that solves is the smallest; the trainer's own budget last.
    args.budgets = sorted({b for b in args.budgets if b is not None}) + [None] * (None in args.budgets)
    if args.env_repeats < 0:
        parser.error("--env-repeats must be >= 0")
    return args


def run_once(task: str, algo: str, steps: int | None, seed: int, cache_dir: str, extra: str = "") -> dict:
    """One ``jaxdrones train`` process with ``JAXDRONES_CACHE_DIR=cache_dir`` (and the arguments ``extra``); a row
    of the results."""
    row = {
        "algo": algo,
        "budget": steps,
        "cache_dir_entries_before": _entries(cache_dir),
        "loadavg_before": list(os.getloadavg()),
    }
    with tempfile.TemporaryDirectory() as out:
        command = [
            sys.executable,
            "-m",
            "jaxdrones.cli",
            "train",
            task,
            "--algo",
            algo,
            "--seed",
            str(seed),
            "--out",
            os.path.join(out, "run"),
            "--no-progress",
        ]
        if steps is not None:
            command += ["--steps", str(steps)]
        command += shlex.split(extra)
        start = time.perf_counter()
        proc = subprocess.run(
            command, env=os.environ | {"JAXDRONES_CACHE_DIR": cache_dir}, capture_output=True, text=True, check=False
        )
        row["wall_time_s"] = time.perf_counter() - start
        row["loadavg_after"] = list(os.getloadavg())
        shown = command[3 : command.index("--out")] + command[command.index("--out") + 3 :]  # no temporary folder
        row["command"] = "jaxdrones " + " ".join(shown)
        row["stdout_tail"] = proc.stdout.strip().splitlines()[-2:]
        try:
            with open(os.path.join(out, "run", "summary.json")) as f:
                summary = json.load(f)
            with open(os.path.join(out, "run", "progress.json")) as f:
                progress = json.load(f)
        except OSError as err:
            summary = progress = None
            row["error"] = f"exit {proc.returncode}, no summary ({err.strerror}): " + " | ".join(
                proc.stderr.strip().splitlines()[-5:]
            )
    row["cache_dir_entries_after"] = _entries(cache_dir)
    row["cache_dir_mb_after"] = _size_mb(cache_dir)
    if summary is not None:
        row.update(from_summary(summary, progress))
        if proc.returncode != 0:
            row["error"] = f"exit {proc.returncode}: " + " | ".join(proc.stderr.strip().splitlines()[-5:])
    return row


def from_summary(summary: dict, progress: list[dict]) -> dict:
    """The row's figures from a run's ``summary.json`` and ``progress.json`` (missing fields give None)."""
    phases = summary.get("phases_s") or {}
    config = summary.get("config") or {}
    evaluation = summary.get("eval") or {}
    env_steps = summary.get("env_steps")
    train_s = phases.get("train", summary.get("train_time_s"))
    threshold = summary.get("success_threshold")
    row = {
        "env_steps": env_steps,
        "summary_wall_time_s": summary.get("wall_time_s"),
        "train_time_s": summary.get("train_time_s"),
        "phases_s": phases,
        "num_envs": config.get("num_envs"),
        "success_metric": summary.get("success_metric"),
        "success_value": summary.get("success_value"),
        "success_unit": summary.get("success_unit"),
        "success_threshold": threshold,
        "terminated_rate": evaluation.get("terminated_rate"),
        "solved": summary.get("success"),
        "interrupted": summary.get("interrupted"),
        "trainer_env_steps_per_s": env_steps / train_s if env_steps and train_s else None,
        "trainer_env_steps_per_s_after_first_eval": None,
        "first_eval_s": None,
        "evaluations": len(progress),
        "solved_at_env_steps": None,
        "solved_at_s": None,
        "config": config,
        "provenance": {
            k: (summary.get("provenance") or {}).get(k)
            for k in ("versions", "backend", "devices", "device_kind", "git_commit", "loadavg")
        },
    }
    # progress.json's time_s counts from the end of the setup phase; the summary's wall time from the process start.
    offset = None
    if summary.get("wall_time_s") is not None and phases:
        offset = summary["wall_time_s"] - sum(phases.values()) + phases.get("setup", 0.0)
    if progress:
        first, last = progress[0], progress[-1]
        row["first_eval_s"] = None if offset is None else offset + first["time_s"]
        if last["time_s"] > first["time_s"] and last["env_steps"] > first["env_steps"]:
            row["trainer_env_steps_per_s_after_first_eval"] = (last["env_steps"] - first["env_steps"]) / (
                last["time_s"] - first["time_s"]
            )
        met = next(
            (
                r
                for r in progress
                if threshold is not None
                and r.get("success_value", math.nan) < threshold
                and r.get("terminated_rate", 1.0) == 0.0
            ),
            None,
        )
        if met is not None:
            row["solved_at_env_steps"] = met["env_steps"]
            row["solved_at_s"] = None if offset is None else offset + met["time_s"]
    return row


def _entries(path: str) -> int:
    return len(os.listdir(path)) if os.path.isdir(path) else 0


def _size_mb(path: str) -> float:
    total = 0
    for folder, _, files in os.walk(path):
        total += sum(os.path.getsize(os.path.join(folder, f)) for f in files)
    return total / 2**20


def env_rates(task: str, worlds: list[int], repeats: int) -> list[dict]:
    """Env-steps/s of the JAX-native env alone (`envs.bench_native`) at each number of worlds."""
    import jaxdrones as jd  # noqa: I001  (first: it sets XLA's flags before JAX starts)
    import jax
    from speed.envs import MAX_STEPS, TARGET_ENV_STEPS, bench_native

    if task != "hover":
        print(f"env alone: measured on hover (envs.bench_native), not {task}")
    settings = argparse.Namespace(steps=None, target=TARGET_ENV_STEPS, repeats=repeats, devices=1)
    rows = []
    for n in worlds:
        result = bench_native(jax, jd, n, settings)
        rows.append(
            {
                k: result[k]
                for k in (
                    "env",
                    "worlds",
                    "steps",
                    "compile_s",
                    "median_env_steps_per_s",
                    "best_env_steps_per_s",
                    "cpu_util",
                    "loadavg_1min",
                )
            }
            | {"task": "hover", "max_steps": MAX_STEPS}
        )
        print(
            f"env alone (JAX-native hover, lax.scan, random actions) at {n} worlds: "
            f"{result['median_env_steps_per_s']:,.0f} env-steps/s median",
            flush=True,
        )
    return rows


def print_row(row: dict) -> None:
    head = f"{row['algo']:<9} {row['budget'] or 'default':>9} {row['cache']:<5}"
    if row.get("env_steps") is None:
        print(f"{head} FAILED: {row.get('error')}", flush=True)
        return

    def cell(key, spec, width):
        value = row.get(key)
        return f"{'-' if value is None else format(value, spec):>{width}}"

    row = row | {"train_s": (row.get("phases_s") or {}).get("train")}
    print(
        f"{head} {row['env_steps']:>10,d} {cell('wall_time_s', '.1f', 8)} {cell('summary_wall_time_s', '.1f', 8)} "
        f"{cell('train_s', '.1f', 7)} {cell('solved_at_s', '.1f', 9)} {cell('success_value', '.4g', 9)} "
        f"{cell('terminated_rate', '.1%', 6)} {cell('trainer_env_steps_per_s_after_first_eval', ',.0f', 10)} "
        f"{'solved' if row.get('solved') else '-'}{'  (' + row['error'] + ')' if row.get('error') else ''}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    load_start = os.getloadavg()
    rows = []
    print(
        f"{args.task}, seed {args.seed}: wall s (outside / summary), train s, solved at s (first evaluation "
        f"meeting the threshold, from the process start), env-steps/s after the first evaluation"
    )
    print(
        f"{'algo':<9} {'budget':>9} {'cache':<5} {'env steps':>10} {'wall s':>8} {'summary':>8} {'train':>7} "
        f"{'solved at':>9} {'metric':>9} {'term.':>6} {'steps/s':>10}"
    )
    with tempfile.TemporaryDirectory(prefix="jaxdrones-cache-") as caches:
        for algo in args.algos:
            for steps in args.budgets:
                cache_dir = os.path.join(caches, f"{algo}-{steps or 'default'}")  # empty for the first run
                pair = []
                for cache in CACHES:
                    row = {"cache": cache, **run_once(args.task, algo, steps, args.seed, cache_dir, args.train_args)}
                    rows.append(row)
                    pair.append(row)
                    print_row(row)
                if args.stop_at_solved and pair[0].get("solved"):
                    break
    first = first_solved(rows, args.algos)
    for algo, by_cache in first.items():
        cold, warm = by_cache.get("cold"), by_cache.get("warm")
        print(
            f"{algo}: "
            + (
                f"solved with {cold['env_steps']:,} env steps in {cold['wall_time_s']:.1f} s with an "
                f"empty cache, "
                + (f"{warm['wall_time_s']:.1f} s with a warm one" if warm else "the warm run did not solve it")
                if cold
                else "not solved within the budgets"
            )
        )
    worlds = sorted({r["num_envs"] for r in rows if r.get("num_envs")})
    env_alone = env_rates(args.task, worlds, args.env_repeats) if args.env_repeats > 0 and worlds else []

    import jax
    from common import machine_info, write_report

    settings = {k: v for k, v in vars(args).items() if k != "out"} | {
        "eval_episodes": 256,
        "cache_dirs": "a new empty folder per algorithm and budget, reused by its warm run",
    }
    write_report(
        args.out,
        f"time to solve {args.task} with each jaxdrones train algorithm, empty and warm compilation cache",
        machine_info(jax),
        settings,
        rows,
        loadavg_start=load_start,
        task=args.task,
        first_solved=first,
        env_rates=env_alone,
    )
    return 0


def first_solved(rows: list[dict], algos: list[str]) -> dict:
    """Per algorithm and cache, the row of the smallest budget that solved the task (None if none did)."""
    out = {}
    for algo in algos:
        out[algo] = {
            cache: next((r for r in rows if r["algo"] == algo and r["cache"] == cache and r.get("solved")), None)
            for cache in CACHES
        }
    return out


if __name__ == "__main__":
    sys.exit(main())
