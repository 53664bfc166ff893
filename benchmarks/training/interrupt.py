"""A Ctrl-C at any moment keeps what was done: ``jaxdrones train TASK --out R --overwrite`` over a finished run ``R``,
stopped by SIGINT at each of the given seconds after its start, as a user's Ctrl-C would. After each stop the table
says what ``R`` holds (the old run or a complete new one, by its seed; anything else is a failure), the exit status
(130, or 0 where the run had finished), and where an interrupted run with something trained went (``R-1``, ...).

Each trial starts from an empty compilation cache, as a first run does (``--warm``: from the cache the first run
filled). The new run's seed differs from the old one's, so that ``R``'s summary tells them apart.

    python benchmarks/training/interrupt.py                        # hover at its defaults; SIGINT at 1, 3, 6 and 10 s
    python benchmarks/training/interrupt.py --at 2 5 --warm
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time


def train(args: list[str], out: str, cache: str, stop_after: float | None) -> tuple[int, float]:
    """Run ``jaxdrones train`` into ``out``; SIGINT after ``stop_after`` s unless it ended; ``(status, seconds)``."""
    env = {**os.environ, "JAXDRONES_CACHE_DIR": cache}
    command = [sys.executable, "-m", "jaxdrones.cli", "train", *args, "--out", out, "--overwrite", "--no-progress"]
    start = time.perf_counter()
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        process.wait(timeout=stop_after)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
    status = process.wait()
    return status, time.perf_counter() - start


def holds(folder: str) -> str:
    """What a run folder holds: ``seed S, complete`` or ``seed S, interrupted``, or what is wrong with it."""
    try:
        with open(os.path.join(folder, "summary.json")) as f:
            summary = json.load(f)
    except (OSError, ValueError) as err:
        return f"NO RUN ({type(err).__name__})"
    state = "interrupted" if summary["interrupted"] else "complete"
    missing = [name for name in ("policy.pkl", "progress.json") if not os.path.exists(os.path.join(folder, name))]
    return f"seed {summary['config']['seed']}, {state}" + (f", MISSING {missing}" if missing else "")


def main() -> None:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="hover")
    parser.add_argument("--at", type=float, nargs="+", default=[1, 3, 6, 10], help="seconds to the SIGINT")
    parser.add_argument("--warm", action="store_true", help="each trial from the filled compilation cache")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        run, cache = os.path.join(tmp, "R"), os.path.join(tmp, "cache")
        status, seconds = train([args.task, "--seed", "0"], run, cache, None)
        print(f"the old run: exit {status} after {seconds:.1f} s, R holds {holds(run)}")
        for k, at in enumerate(args.at, start=1):
            if not args.warm:
                shutil.rmtree(cache, ignore_errors=True)
            status, seconds = train([args.task, "--seed", str(k)], run, cache, at)
            siblings = sorted(name for name in os.listdir(tmp) if name.startswith("R-"))
            partial = sorted(name for name in os.listdir(tmp) if ".partial" in name)
            rows.append((at, status, seconds, holds(run), [f"{s}: {holds(os.path.join(tmp, s))}" for s in siblings]))
            print(f"| {at:g} s | {status} | {seconds:.1f} s | {rows[-1][3]} | {'; '.join(rows[-1][4]) or '-'} |")
            assert not partial, partial
            for sibling in siblings:
                shutil.rmtree(os.path.join(tmp, sibling))
    print("\n| SIGINT at | exit | ended after | R holds | interrupted run saved in |\n|---|---:|---:|---|---|")
    for at, status, seconds, held, siblings in rows:
        print(f"| {at:g} s | {status} | {seconds:.1f} s | {held} | {'; '.join(siblings) or '-'} |")


if __name__ == "__main__":
    main()
