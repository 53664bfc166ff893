"""Does learning with the downwash matter? Policies trained on ``crossing`` with downwash on and off, each flown
with downwash on (and off), in one run.

``crossing`` is the paper's downwash example as a task: two Crazyflies fly back and forth along x, 0.5 m apart in
height and half a period apart, so that the upper one passes over the lower one twice per 5 s episode, and the
paper's downwash model pushes the lower one down. For each seed, ``jaxdrones train crossing`` (MAPPO, default
budget) trains one policy with downwash on (the task's default) and one with ``--no-downwash``, each a fresh
process; the run folders are kept under ``--out``. Each policy is then evaluated on the same 256 random starts
with downwash on and with it off: the largest altitude error of the team over the episode (the task's success
metric, mean over episodes: the lower drone's dip when the other passes over it), the mean distance to the
reference and the share of terminated episodes. For scale, the DSL PID (``action_type="pid"``, its target the
reference point) flies the same starts.

    python benchmarks/training/downwash_policies.py     # seed 0; writes benchmarks/results/downwash_policies.json
    python benchmarks/training/downwash_policies.py --seeds 0 1 2 --steps 3000000
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

EPISODES = 256


def train(downwash: bool, seed: int, steps: int | None, out: str) -> dict:
    """One ``jaxdrones train crossing`` process; its summary."""
    command = [
        sys.executable,
        "-m",
        "jaxdrones.cli",
        "train",
        "crossing",
        "--seed",
        str(seed),
        "--out",
        out,
        "--overwrite",
        "--no-progress",
        "--downwash" if downwash else "--no-downwash",
    ]
    if steps is not None:
        command += ["--steps", str(steps)]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    with open(os.path.join(out, "summary.json")) as f:
        return json.load(f)


def flown(env, policy) -> dict:
    """The evaluation of ``policy`` in ``env`` on `EPISODES` fixed starts."""
    import jax

    from jaxdrones.training import evaluate

    stats = evaluate(env, policy, jax.random.key(1234), EPISODES)
    return {
        "max_altitude_error_m": stats["success_value"],
        "tracking_error_m": stats["mean_tracking_error"],
        "terminated_rate": stats["terminated_rate"],
    }


def pid_policy(env):
    """The DSL PID with the reference point as its target (``action_type="pid"``: absolute targets)."""
    import jax.numpy as jnp

    def policy(obs, key):
        obs = jnp.reshape(obs, (env.n_drones, env.observation_size))
        return jnp.reshape(obs[:, :3] + obs[:, -6:-3], (-1,)), {}

    return policy


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--steps", type=int, default=None, help="env steps per training (default: the trainer's)")
    parser.add_argument(
        "--out",
        default=os.path.join(RESULTS, "downwash_policies"),
        help="folder for the run folders and the JSON",
    )
    args = parser.parse_args(argv)

    import jaxdrones as jd
    from jaxdrones.training import load_policy

    os.makedirs(args.out, exist_ok=True)
    rows = []
    print("policy                      flown with downwash   largest altitude error   tracking error  terminated")

    def report(name, trained_on, flown_with, result, **extra):
        rows.append(
            {"policy": name, "trained_with_downwash": trained_on, "flown_with_downwash": flown_with, **result, **extra}
        )
        print(
            f"{name:27s} {'on ' if flown_with else 'off'}                   "
            f"{100 * result['max_altitude_error_m']:8.2f} cm           {100 * result['tracking_error_m']:6.2f} cm"
            f"    {result['terminated_rate']:.1%}",
            flush=True,
        )

    for downwash in (True, False):
        env = jd.make("crossing", action_type="pid", downwash=downwash)
        report("DSL PID", None, downwash, flown(env, pid_policy(env)))
    for seed in args.seeds:
        for trained_on in (True, False):
            run = os.path.join(args.out, f"{'on' if trained_on else 'off'}_seed{seed}")
            summary = train(trained_on, seed, args.steps, run)
            for flown_with in (True, False):
                env, policy = load_policy(run, env=jd.make("crossing", downwash=flown_with))
                report(
                    f"MAPPO, trained {'with' if trained_on else 'without'}",
                    trained_on,
                    flown_with,
                    flown(env, policy),
                    seed=seed,
                    env_steps=summary["env_steps"],
                    wall_time_s=summary["wall_time_s"],
                )
    path = os.path.join(args.out, "downwash_policies.json")
    with open(path, "w") as f:
        json.dump(
            {
                "rows": rows,
                "episodes": EPISODES,
                "machine": platform.platform(),
                "cpus": os.cpu_count(),
                "load_avg": os.getloadavg(),
            },
            f,
            indent=2,
        )
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
