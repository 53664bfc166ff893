"""What each robustness measure buys: policies trained under the paper's physics, under the ``crazyflie`` realism
preset, and under the preset with domain randomisation, each evaluated under the paper's physics, the preset and a
harsher setting.

Every policy is trained as ``jaxdrones train TASK --realism crazyflie`` trains it (`jaxdrones.training.run.train_task`
with the task's recipe under the preset, `jaxdrones.training.recipes.RECIPES`: its algorithm and budget, its
action and memory, `jaxdrones.training.recipes.REALISM_ENV`: collective thrust and body rates, ``ctbr``, the Crazyflie
firmware's own interface, and the integral of the tracking error in the observation), only the physics of its
training env differing (`TRAIN`), with a seed (``--steps`` overrides the budget):

- ``paper``: the paper's physics (no realism);
- ``crazyflie``: ``realism="crazyflie"`` (Learning to Fly in Seconds' Crazyflie: 0.15 s motor lag, observation
  noise, a random force and torque per episode; docs/physics.md §16);
- ``crazyflie_dr``: the preset with its values drawn per episode from ranges (motor time constants 0.075-0.3 s,
  noise σ 0-2 times the preset's, force and torque σ 0-2 times the preset's, an observation delay of 0-1 steps) and
  the drones' mass, inertia, kf and km within ±10 % (`jaxdrones.envs.DomainRandomization`).

Evaluation settings (`EVAL`), each policy flown from 256 random starts (`jaxdrones.training.evaluation.evaluate`,
the same keys for every policy) in its own env with the physics replaced: ``paper``; ``crazyflie``; ``harsh``:
``realism="crazyflie_harsh"`` (twice the lag and the noise, Dryden turbulence of σ 1 m/s at 2 m, drag on).

Per policy and evaluation: the task's success metric (hover: the final distance to the target, m; velocity: the
mean velocity error, m/s) and the share of episodes terminated early (crashes). A policy succeeds in a setting when
the metric is below the task's threshold with no episode terminated. The table gives, per training setting and
task, the metric's median over seeds (each seed's value beside it) and the terminated share.

Usage::

    python benchmarks/experiments/robustness.py       # hover and velocity, seeds 0 1 2
    python benchmarks/experiments/robustness.py --tasks hover --seeds 0 --steps 500000 --episodes 64   # a quick look
    python benchmarks/experiments/robustness.py --tasks hover --settings crazyflie_dr --dr-turbulence 1.0   # wind

Results go to ``benchmarks/results/robustness.json`` (``--out``) and the table to stdout (markdown).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
DEFAULT_OUT = os.path.join(RESULTS, "robustness.json")
TASKS = ("hover", "velocity")
SEEDS = (0, 1, 2)

_PRESET = {"preset": "crazyflie"}
#: The training settings: env overrides for ``jd.make`` / ``train_task``.
TRAIN = {
    "paper": {},
    "crazyflie": {"realism": "crazyflie"},
    "crazyflie_dr": {
        "realism": {
            **_PRESET,
            "motor_tau_up": (0.075, 0.3),
            "motor_tau_down": (0.075, 0.3),
            "obs_noise_pos": (0.0, 0.002),
            "obs_noise_att": (0.0, 0.002),
            "obs_noise_vel": (0.0, 0.004),
            "obs_noise_ang_vel": (0.0, 0.004),
            "disturbance_force": (0.0, 0.0265),
            "disturbance_torque": (0.0, 5.3e-5),
            "obs_delay": (0, 1),
        },
        "randomize": {"mass": 0.1, "inertia": 0.1, "kf": 0.1, "km": 0.1},
    },
}
#: The evaluation settings.
EVAL = {"paper": {}, "crazyflie": {"realism": "crazyflie"}, "harsh": {"realism": "crazyflie_harsh"}}


def train_and_evaluate(
    task: str, setting: str, seed: int, steps: int | None, episodes: int, folder: str, defaults: str = "cpu"
) -> dict:
    """Train one policy as ``jaxdrones train TASK --realism crazyflie --defaults DEFAULTS`` does, with the `TRAIN`
    setting's physics, and evaluate it in every `EVAL` setting; returns its record."""
    import jax

    import jaxdrones as jd
    from jaxdrones.training import checkpoint
    from jaxdrones.training.evaluation import evaluate
    from jaxdrones.training.recipes import recipe
    from jaxdrones.training.run import train_task

    # The recipe under the preset (its trainer, budget, action and memory), in the setting's physics.
    plan = recipe(task, defaults, {"realism": "crazyflie"}).with_options(seed=seed, steps=steps)
    plan = dataclasses.replace(plan, env={**{k: v for k, v in plan.env.items() if k != "realism"}, **TRAIN[setting]})
    algo, overrides = plan.algo, dict(plan.env)
    run = os.path.join(folder, f"{task}-{setting}-{seed}")
    summary = train_task(plan, run, overwrite=True, progress=False)
    record = {
        "task": task,
        "train": setting,
        "seed": seed,
        "algo": algo,
        "defaults": defaults,
        "env": overrides,
        "env_steps": summary["env_steps"],
        "train_wall_s": summary["wall_time_s"],
        "eval": {},
    }
    threshold = jd.envs.get_task(task).success_threshold
    base = {k: v for k, v in overrides.items() if k not in ("realism", "randomize")}
    for name, physics in EVAL.items():
        env, policy = checkpoint.load_policy(run, env=jd.make(task, **base, **physics))
        stats = evaluate(env, policy, jax.random.key(10_000), episodes)
        record["eval"][name] = {
            "success_value": stats["success_value"],
            "terminated_rate": stats["terminated_rate"],
            "success": bool(stats["success_value"] < threshold and stats["terminated_rate"] == 0.0),
        }
    return record


def table(records: list[dict]) -> str:
    """The markdown table: one row per task and training setting, one column per evaluation setting."""
    import jaxdrones as jd

    lines = [
        "| task | trained with | " + " | ".join(f"evaluated: {e}" for e in EVAL) + " |",
        "|---|---|" + "---|" * len(EVAL),
    ]
    for task in dict.fromkeys(r["task"] for r in records):
        unit = "m" if task == "hover" else "m/s"
        threshold = jd.envs.get_task(task).success_threshold
        for setting in TRAIN:
            rows = [r for r in records if r["task"] == task and r["train"] == setting]
            if not rows:
                continue
            cells = []
            for name in EVAL:
                values = [r["eval"][name]["success_value"] for r in rows]
                crashed = [r["eval"][name]["terminated_rate"] for r in rows]
                solved = sum(r["eval"][name]["success"] for r in rows)
                cells.append(
                    f"{statistics.median(values):.3g} {unit} ({' / '.join(f'{v:.3g}' for v in values)}); "
                    f"terminated {statistics.median(crashed):.1%}; solved {solved}/{len(rows)}"
                )
            lines.append(f"| {task} (< {threshold:g} {unit}) | {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--settings", nargs="+", default=list(TRAIN), choices=list(TRAIN))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--steps", type=int, default=None, help="env steps per training (default: the preset's budget)")
    parser.add_argument("--episodes", type=int, default=256, help="evaluation episodes per setting")
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--runs", default=None, help="folder of the trained runs (default: a temporary folder)")
    parser.add_argument(
        "--defaults", default="cpu", choices=("cpu", "gpu"), help="the profile of training settings (default cpu)"
    )
    parser.add_argument(
        "--dr-turbulence",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="crazyflie_dr also draws Dryden turbulence of σ uniform in [0, SIGMA] m/s per episode (default 0: none)",
    )
    args = parser.parse_args(argv)
    if args.dr_turbulence > 0:
        TRAIN["crazyflie_dr"]["realism"]["turbulence"] = (0.0, args.dr_turbulence)
    records = []
    with tempfile.TemporaryDirectory() as scratch:
        for task in args.tasks:
            for setting in args.settings:
                for seed in args.seeds:
                    record = train_and_evaluate(
                        task, setting, seed, args.steps, args.episodes, args.runs or scratch, args.defaults
                    )
                    records.append(record)
                    print(json.dumps(record), flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"train": TRAIN, "eval": EVAL, "records": records, "args": vars(args)}, f, indent=1)
    print(table(records))


if __name__ == "__main__":
    main()
