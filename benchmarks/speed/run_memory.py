"""Memory of mapped runs: the peak resident memory of ``jaxdrones train TASK --seeds N`` for N = 1 and N = 1 + K, one
update of each task's recipe (``--steps 1 --num-evals 1``: the programs and their buffers are those of the full
run), against the estimate that ``jaxdrones train`` checks before compiling (`jaxdrones.training.runs.run_bytes`).

Each run is a subprocess that reports its own peak resident set size (``resource.getrusage``); the memory of one run
is the difference over K runs. The ratio is that memory over the estimate without its factor
(`jaxdrones.training.runs.MEMORY_FACTOR`, which is the largest ratio measured): under 1 the check is too strict,
over it too lax.

    python benchmarks/speed/run_memory.py                       # hover, velocity, crossing, leader_follower; K = 32
    python benchmarks/speed/run_memory.py --tasks hover --extra 64
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile

_CHILD = """
import resource, sys
from jaxdrones.cli import main
status = main(sys.argv[1:])
print("PEAK_KIB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, status)
"""


def peak_kib(task: str, n_seeds: int, out: str) -> int:
    """The peak resident memory (KiB) of one ``jaxdrones train`` process of ``n_seeds`` mapped seeds."""
    argv = ["train", task, "--steps", "1", "--num-evals", "1", "--seeds", str(n_seeds), "--no-progress"]
    result = subprocess.run(
        [sys.executable, "-c", _CHILD, *argv, "--out", out], capture_output=True, text=True, check=True
    )
    line = next(line for line in result.stdout.splitlines() if line.startswith("PEAK_KIB"))
    return int(line.split()[1])


def estimate(task: str) -> int:
    """`jaxdrones.training.runs.run_bytes` without its factor: the bytes of one run's known arrays."""
    from jaxdrones.envs import make
    from jaxdrones.training import runs
    from jaxdrones.training.recipes import recipe

    plan = recipe(task, "cpu")
    env = make(task, **plan.env)
    train_env = make(task, **plan.env, **plan.train_env) if plan.train_env else env
    return runs.run_bytes(plan.config, env, train_env, 256) / runs.MEMORY_FACTOR


def main() -> None:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["hover", "velocity", "crossing", "leader_follower"])
    parser.add_argument("--extra", type=int, default=32, help="K: the runs added to measure one run's memory")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for task in args.tasks:
            one = peak_kib(task, 1, f"{tmp}/{task}-1")
            more = peak_kib(task, 1 + args.extra, f"{tmp}/{task}-{1 + args.extra}")
            per_run = (more - one) * 1024 / args.extra
            known = estimate(task)
            rows.append(dict(task=task, peak_1_mib=one / 1024, per_run_mib=per_run / 2**20, known_mib=known / 2**20))
            rows[-1]["ratio"] = per_run / known
    print("| task | peak, 1 run (MiB) | per run (MiB) | known arrays (MiB) | ratio |\n|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['task']} | {r['peak_1_mib']:.0f} | {r['per_run_mib']:.2f} | {r['known_mib']:.2f} "
            f"| {r['ratio']:.2f} |"
        )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
