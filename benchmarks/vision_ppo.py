"""Seconds per iteration of brax's vision PPO on a task with cameras, as ``jaxdrones train TASK`` runs it.

The work: ``brax.training.agents.ppo.train`` on the training env of ``jaxdrones train TASK --vision depth``
(`jaxdrones.training.run.default_env`: for ``avoid`` 32 × 24 depth, for ``fly_thru_gate`` the gate drawn per
episode on 64 × 48 depth) with the trainer's default config (`jaxdrones.training.brax_ppo.default_config`: 256
worlds × 16-step unrolls × 4 minibatches, 16,384 env steps an iteration) for ``--epochs`` epochs of ``--iterations``
iterations. The time of each epoch is that between brax's progress calls; brax compiles its epoch at the first call
(at times again at the second), so the steady iteration time is taken from the third epoch on. Iterations of
``jaxdrones train`` are the same program, so the run's wall time is about (2 M / 16,384) × the steady time plus
the compilations and evaluations.

Usage::

    python benchmarks/vision_ppo.py                        # avoid; writes benchmarks/results/vision_ppo.json
    python benchmarks/vision_ppo.py --task fly_thru_gate --epochs 4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "results", "vision_ppo.json")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="avoid", choices=("avoid", "fly_thru_gate"))
    parser.add_argument("--epochs", type=int, default=4, help="epochs timed (the first two compile)")
    parser.add_argument("--iterations", type=int, default=2, help="PPO iterations per epoch")
    parser.add_argument("--out", default=DEFAULT_OUT)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import jaxdrones as jd  # before JAX starts: its XLA flags
    import jax
    import numpy as np
    from brax.training.agents.ppo import train as ppo

    from jaxdrones.adapters import brax as adapter
    from jaxdrones.training import brax_ppo
    from jaxdrones.training.run import default_env

    env = jd.make(args.task, **default_env(args.task, {"vision": ("depth",)}))
    config = brax_ppo.default_config(args.task, vision=True)
    per_iteration = config.batch_size * config.unroll_length * config.num_minibatches
    config = dataclasses.replace(config, num_timesteps=per_iteration * args.iterations * args.epochs,
                                 num_evals=args.epochs + 1)
    kwargs = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
              if f.name not in brax_ppo.NETWORK_FIELDS}
    stamps = []
    load = os.getloadavg()
    start = time.perf_counter()
    ppo.train(adapter.BraxEnv(env), episode_length=env.episode_length, wrap_env_fn=adapter.wrap_for_brax_training,
              network_factory=brax_ppo._network_factory(config, True), vision=True, run_evals=False,
              progress_fn=lambda steps, metrics: stamps.append((int(steps), time.perf_counter())), **kwargs)
    times = np.diff([start] + [t for _, t in stamps])
    epochs = times[1:]  # the first call comes before any training (brax's initial progress)
    steady = epochs[2:] / args.iterations
    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}, load {load}; {args.task}, image "
          f"{env.config.image_size}, {per_iteration:,} env steps an iteration")
    for k, t in enumerate(epochs):
        print(f"epoch {k + 1}: {t:.1f} s ({t / args.iterations:.1f} s an iteration){' (compiles)' if k < 2 else ''}")
    if steady.size:
        print(f"steady: median {np.median(steady):.2f} s an iteration, {per_iteration / np.median(steady):,.0f} env "
              f"steps/s")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"task": args.task, "image_size": list(env.config.image_size), "per_iteration": per_iteration,
                   "iterations_per_epoch": args.iterations, "epoch_s": epochs.tolist(),
                   "steady_iteration_s": float(np.median(steady)) if steady.size else None,
                   "jax": jax.__version__, "load_start": load, "load_end": os.getloadavg()}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
