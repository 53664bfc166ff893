"""Seconds per iteration of brax's vision PPO on a task with cameras, as ``jaxdrones train TASK`` runs it.

The work: `jaxdrones.training.brax_ppo.train` (brax's ``ppo.train``) on the env of ``jaxdrones train TASK --vision
depth`` (the task's recipe, `jaxdrones.training.recipes.recipe`: for ``avoid`` its own 64 × 16 depth, for
``fly_thru_gate`` the gate drawn per episode on 64 × 48 depth) with the recipe's config of brax's PPO (16-step
unrolls × 4 minibatches of 512 worlds for ``avoid``, 32,768 env steps an iteration, and of 256 worlds,
16,384 steps, for the gate) for ``--epochs`` epochs of ``--iterations`` iterations. The time of each epoch is
that between its progress calls (the first from the start, with brax's compilation; at times it compiles again in
the second), so the steady iteration time is taken from the third epoch on. Iterations of ``jaxdrones train`` are the
same program, so the run's wall time is about (steps / steps an iteration) × the steady time plus the compilations and
evaluations.

Both critics are timed in the same run, one after the other: the asymmetric one of the defaults
(``privileged_critic``: an MLP on the state and the task's privileged observation) and one with the policy's
architecture (a CNN on the images too); ``--critic`` times one.

Usage::

    python benchmarks/experiments/vision_ppo.py    # avoid; writes benchmarks/results/vision_ppo.json
    python benchmarks/experiments/vision_ppo.py --task fly_thru_gate --epochs 4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
DEFAULT_OUT = os.path.join(RESULTS, "vision_ppo.json")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="avoid", choices=("avoid", "fly_thru_gate"))
    parser.add_argument("--epochs", type=int, default=4, help="epochs timed (the first two compile)")
    parser.add_argument("--iterations", type=int, default=2, help="PPO iterations per epoch")
    parser.add_argument(
        "--critic",
        choices=("both", "privileged", "images"),
        default="both",
        help="the critic(s) to time (default both)",
    )
    parser.add_argument("--out", default=DEFAULT_OUT)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax
    import numpy as np

    import jaxdrones as jd
    from jaxdrones.training import brax_ppo
    from jaxdrones.training.recipes import recipe

    plan = recipe(args.task, "cpu", {"vision": ("depth",)})
    env = jd.make(args.task, **plan.env)
    base = plan.config
    per_iteration = base.batch_size * base.unroll_length * base.num_minibatches
    base = dataclasses.replace(
        base, num_timesteps=per_iteration * args.iterations * args.epochs, num_evals=args.epochs + 1
    )

    def time_training(privileged: bool):
        stamps = []
        start = time.perf_counter()
        brax_ppo.train(
            env,
            dataclasses.replace(base, privileged_critic=privileged),
            progress=lambda steps, metrics: stamps.append(time.perf_counter()),
        )
        epochs = np.diff([start] + stamps)  # the first from the start: it compiles
        return epochs, epochs[2:] / args.iterations

    critics = ("privileged", "images") if args.critic == "both" else (args.critic,)
    load = os.getloadavg()
    results = {critic: time_training(critic == "privileged") for critic in critics}
    print(
        f"jax {jax.__version__} on {jax.devices()[0].device_kind}, load {load}; {args.task}, image "
        f"{env.config.image_size}, {per_iteration:,} env steps an iteration"
    )
    out = {
        "task": args.task,
        "image_size": list(env.config.image_size),
        "per_iteration": per_iteration,
        "iterations_per_epoch": args.iterations,
        "jax": jax.__version__,
        "load_start": load,
        "critics": {},
    }
    for critic, (epochs, steady) in results.items():
        print(f"critic: {critic}")
        for k, t in enumerate(epochs):
            print(
                f"  epoch {k + 1}: {t:.1f} s ({t / args.iterations:.1f} s an iteration){' (compiles)' if k < 2 else ''}"
            )
        median = float(np.median(steady)) if steady.size else None
        if median:
            print(f"  steady: median {median:.2f} s an iteration, {per_iteration / median:,.0f} env steps/s")
        out["critics"][critic] = {"epoch_s": epochs.tolist(), "steady_iteration_s": median}
    if len(results) == 2 and all(v["steady_iteration_s"] for v in out["critics"].values()):
        ratio = out["critics"]["images"]["steady_iteration_s"] / out["critics"]["privileged"]["steady_iteration_s"]
        out["images_over_privileged"] = ratio
        print(f"an iteration with the images' critic takes {ratio:.2f}x the asymmetric critic's")
    out["load_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
