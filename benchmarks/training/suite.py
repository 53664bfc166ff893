"""The suite at its defaults: ``jaxdrones train TASK --seed S`` for every task (or those named) and seed, as a user
runs it, and one table of the results.

Each run is ``python -m jaxdrones.cli train TASK --seed S --no-progress`` in a subprocess (with ``--defaults`` where
given), into ``OUT/TASK-S``. The first seed of each task runs from an empty compilation cache (a folder of its own,
``JAXDRONES_CACHE_DIR``): its wall time is the ``first run``; the task's other seeds load those programs (the seed is
an input of the compiled programs, not part of them) and their median is the ``warm`` time. With one seed, that
seed runs a second time, warm. With ``--mapped`` a task's seeds run as one ``jaxdrones train TASK --seeds N``
(one program mapped over the seeds; brax's PPO, one seed after another), from the empty cache, its wall time in the
``first run`` column. Wall times are taken from outside the process: Python's start, imports, compilation, training,
evaluation and the saved plots.

Per task the table gives the trainer and env steps of the task's recipe (`jaxdrones.training.recipes`), the wall
times, each seed's result against the task's threshold (``summary.json``: the success metric over 256 evaluation
starts), the largest share of evaluation episodes that ended early (crashed or left the arena), and the seeds
solved (`jaxdrones.training.evaluation.failed_criteria`: below the threshold, and none ended early where the task's
metric does not count them itself).

    python benchmarks/training/suite.py --seeds 0 1 2                      # every task, cpu or gpu by the device
    python benchmarks/training/suite.py --tasks takeoff crossing --seeds 0 --no-rerun
    python benchmarks/training/suite.py --defaults gpu --seeds 0 1 2       # the gpu profile (GPU: warm goal 60 s)
    python benchmarks/training/suite.py --mapped --seeds 0 1 2 3           # each task's seeds in one run (--seeds 4)

Results: the table (Markdown) on stdout and in ``OUT/suite.md``, every run's record in ``OUT/suite.json`` (default
``OUT``: ``benchmarks/results/suite``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

HERE = os.path.dirname(os.path.abspath(__file__))


def train(task: str, seed: int, out: str, cache: str, extra: list[str], n_seeds: int = 0) -> list[dict]:
    """One ``jaxdrones train`` run in a subprocess with the compilation cache ``cache`` (with ``n_seeds``, of seeds
    ``seed`` to ``seed + n_seeds - 1``: ``--seeds``): a record per seed (the summary's fields the table reads and
    the wall time of the whole process from outside), or the error's last lines when it failed."""
    command = [sys.executable, "-m", "jaxdrones.cli", "train", task, "--seed", str(seed), "--no-progress"]
    command += ["--out", out, "--overwrite", *extra] + (["--seeds", str(n_seeds)] if n_seeds else [])
    env = {**os.environ, "JAXDRONES_CACHE_DIR": cache}
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    record = {"task": task, "seed": seed, "wall_s": wall, "returncode": done.returncode, "command": command}
    summary_path = os.path.join(out, "summary.json")
    if done.returncode != 0 or not os.path.exists(summary_path):
        return [{**record, "error": (done.stderr or done.stdout).strip().splitlines()[-5:]}]
    if not n_seeds:
        return [_record(record, summary_path)]
    return [
        _record({**record, "seed": s}, os.path.join(out, f"seed_{s}", "summary.json"))
        for s in range(seed, seed + n_seeds)
    ]


def _record(record: dict, summary_path: str) -> dict:
    """``record`` with the fields of a run's ``summary.json`` that the table reads."""
    with open(summary_path) as f:
        summary = json.load(f)
    stats = summary["eval"]
    return {
        **record,
        "algo": summary["algo"],
        "defaults": summary["defaults"],
        "env_steps": summary["env_steps"],
        "success": summary["success"],
        "success_metric": summary["success_metric"],
        "success_value": summary["success_value"],
        "success_threshold": summary["success_threshold"],
        "success_unit": summary["success_unit"],
        "ended_early": stats["terminated_rate"],
        "failed_criteria": summary["failed_criteria"],
        "run_wall_s": summary["wall_time_s"],
    }


def run_task(
    task: str, seeds: list[int], out: str, extra: list[str], log, rerun: bool = True, mapped: bool = False
) -> list[dict]:
    """Every seed of ``task``: the first from an empty compilation cache, the others (or the first again, with one
    seed and ``rerun``) from the cache it filled; with ``mapped``, all in one run from the empty cache (``--seeds``).
    """
    cache = tempfile.mkdtemp(prefix=f"suite-cache-{task}-")
    try:
        records = []
        if mapped:
            plan = [(seeds[0], "mapped", len(seeds))]
        else:
            plan = [(seed, "first", 0) for seed in seeds[:1]]
            plan += [(seed, "warm", 0) for seed in seeds[1:] or seeds[:rerun]]
        for seed, kind, n_seeds in plan:
            for record in train(task, seed, os.path.join(out, f"{task}-{seed}"), cache, extra, n_seeds):
                records.append({**record, "cache": kind})
                log(records[-1])
        return records
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def describe(record: dict) -> str:
    """One run as a line of the log."""
    if "error" in record:
        return f"{record['task']} seed {record['seed']}: failed ({record['returncode']}): {' / '.join(record['error'])}"
    verdict = "solved" if record["success"] else "NOT solved: " + "; ".join(record["failed_criteria"])
    return (
        f"{record['task']} seed {record['seed']} ({record['cache']} cache): {record['algo']}, "
        f"{record['env_steps']:,} env steps, {record['success_value']:.4g} {record['success_unit']} "
        f"(< {record['success_threshold']:g}), {record['ended_early']:.1%} ended early, {record['wall_s']:.0f} s: "
        f"{verdict}"
    )


def table(records: list[dict]) -> str:
    """The suite's table (Markdown): one row per task."""
    lines = [
        "| task | trainer | env steps | first run (s) | warm (s) | result per seed (not solved: bold) | ended "
        "early (most) | seeds solved |",
        "|---|---|---:|---:|---:|---|---:|---:|",
    ]
    for task in dict.fromkeys(r["task"] for r in records):
        runs = [r for r in records if r["task"] == task]
        ok = [r for r in runs if "error" not in r]
        by_seed = {}
        for r in runs:  # a seed run twice (one seed: first and warm) reports its first run
            by_seed.setdefault(r["seed"], r)
        if not ok:
            lines.append(f"| {task} | failed: {' / '.join(runs[0]['error'])} | | | | | | 0/{len(by_seed)} |")
            continue
        first = [r["wall_s"] for r in runs if r["cache"] in ("first", "mapped")]  # mapped: every seed's
        warm = [r["wall_s"] for r in runs if r["cache"] == "warm" and "error" not in r]
        results = " / ".join(  # a run not solved in bold
            "error"
            if "error" in r
            else f"{r['success_value']:.3g}"
            if r["success"]
            else f"**{r['success_value']:.3g}**"
            for r in by_seed.values()
        )
        head = ok[0]
        solved = sum(1 for r in by_seed.values() if r.get("success"))
        warm_s = f"{statistics.median(warm):.0f}" if warm else ""
        cells = [
            task,
            head["algo"],
            f"{head['env_steps'] / 1e6:.2f} M",
            f"{first[0]:.0f}" if first else "",
            warm_s,
            f"{results} {head['success_unit']} (< {head['success_threshold']:g})",
            f"{max(r['ended_early'] for r in ok):.1%}",
            f"{solved}/{len(by_seed)}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    from jaxdrones.training.trainers import TRAINABLE

    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TRAINABLE), choices=TRAINABLE, metavar="TASK")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--defaults", choices=("cpu", "gpu"), default=None, help="the profile (default: the device's)")
    parser.add_argument("--out", default=os.path.join(RESULTS, "suite"))
    parser.add_argument(
        "--no-rerun", action="store_true", help="with one seed, no second (warm) run: the first run's time only"
    )
    parser.add_argument(
        "--mapped",
        action="store_true",
        help="each task's seeds (consecutive) in one run, `jaxdrones train TASK --seeds N`; its wall time in 'first "
        "run'",
    )
    parser.add_argument("--train-args", nargs=argparse.REMAINDER, default=[], help="more jaxdrones train options")
    args = parser.parse_args()
    if args.mapped and args.seeds != list(range(args.seeds[0], args.seeds[0] + len(args.seeds))):
        parser.error(f"--mapped trains consecutive seeds (--seeds N from --seed), got {args.seeds}")
    extra = ([] if args.defaults is None else ["--defaults", args.defaults]) + args.train_args
    os.makedirs(args.out, exist_ok=True)
    started = time.strftime("%Y-%m-%d %H:%M")
    commit = subprocess.run(
        ["git", "-C", HERE, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    records: list[dict] = []

    def log(record):
        print(describe(record), flush=True)
        with open(os.path.join(args.out, "suite.json"), "w") as f:
            json.dump({"started": started, "commit": commit, "machine": machine(), "runs": records}, f, indent=1)

    def keep(record):
        records.append(record)
        log(record)

    for task in args.tasks:
        run_task(task, args.seeds, args.out, extra, keep, rerun=not args.no_rerun, mapped=args.mapped)
    text = (
        f"Suite at its defaults ({started}, commit {commit}, {machine()}; "
        f"`python benchmarks/training/suite.py {' '.join(sys.argv[1:])}`)\n\n{table(records)}\n"
    )
    print("\n" + text)
    with open(os.path.join(args.out, "suite.md"), "w") as f:
        f.write(text)
    return 0 if all(r.get("success") for r in records) else 1


def machine() -> str:
    """The machine in a few words: CPU model and cores, or the GPU where JAX has one."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    gpu = ""
    if shutil.which("nvidia-smi"):
        query = ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"]
        gpu = subprocess.run(query, capture_output=True, text=True, check=False).stdout.strip() + ", "
    return f"{gpu}{os.cpu_count()} × {cpu}, Python {platform.python_version()}"


if __name__ == "__main__":
    sys.exit(main())
