"""Time to solve a task with each of ``jaxdrones train``'s algorithms: PPO (brax), APG and SHAC, in one run.

Each algorithm trains the task once per budget of env steps, each run a fresh ``jaxdrones train TASK --algo ALGO
--steps N`` process (so that every wall time includes the imports and the JIT compilation, as a user's run does),
and the run's ``summary.json`` gives the env steps, the wall time and the task's success metric over 256 random
starts. The table marks the runs that solved the task (the metric below the task's threshold, no episode
terminated early) and, per algorithm, the smallest budget that did.

    python benchmarks/train_algos.py                                   # hover, budgets 0.5, 1, 2 and 3 M steps
    python benchmarks/train_algos.py --task velocity --budgets 1e6 3e6 --algos apg shac

Results go to ``benchmarks/results/train_algos_<task>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))


def run_once(task: str, algo: str, steps: int, seed: int) -> dict:
    """One ``jaxdrones train`` process; its summary (``env_steps``, ``wall_time_s``, ``success_value``, ...)."""
    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "jaxdrones.cli", "train", task, "--algo", algo, "--steps", str(steps),
                   "--seed", str(seed), "--out", os.path.join(out, "run"), "--no-progress"]
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        with open(os.path.join(out, "run", "summary.json")) as f:
            return json.load(f)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="hover")
    parser.add_argument("--algos", nargs="+", default=["ppo", "apg", "shac"])
    parser.add_argument("--budgets", nargs="+", type=float, default=[5e5, 1e6, 2e6, 3e6], help="env steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rows = []
    print(f"{args.task}: algo, budget, env steps, wall time (s, with compilation), success metric, solved")
    for algo in args.algos:
        for budget in args.budgets:
            summary = run_once(args.task, algo, int(budget), args.seed)
            row = {"algo": algo, "budget": int(budget), "env_steps": summary["env_steps"],
                   "wall_time_s": summary["wall_time_s"], "train_time_s": summary["train_time_s"],
                   "success_metric": summary["success_metric"], "success_value": summary["success_value"],
                   "terminated_rate": summary["eval"]["terminated_rate"], "solved": summary["success"]}
            rows.append(row)
            print(f"{algo:5s} {int(budget):>10,d} {row['env_steps']:>10,d} {row['wall_time_s']:7.1f} "
                  f"{row['success_value']:.4g} {'solved' if row['solved'] else '-'}", flush=True)
    first = {algo: next((r for r in rows if r["algo"] == algo and r["solved"]), None) for algo in args.algos}
    for algo, row in first.items():
        print(f"{algo}: " + (f"solved with {row['env_steps']:,} env steps in {row['wall_time_s']:.1f} s"
                             if row else "not solved within the budgets"))
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    path = os.path.join(HERE, "results", f"train_algos_{args.task}.json")
    with open(path, "w") as f:
        json.dump({"task": args.task, "rows": rows, "first_solved": first, "machine": platform.platform(),
                   "cpus": os.cpu_count(), "load_avg": os.getloadavg()}, f, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
