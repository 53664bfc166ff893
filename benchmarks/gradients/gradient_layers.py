"""The default env's gradient by layer: what the physics, the env layer, the observation and the policy each add.

The work of `benchmarks/gradients/gradients.py`'s ``default_env`` caller (``jd.make("hover")`` at its defaults: 30 Hz
control, 8 physics substeps per step; T control steps of W worlds; per-step offsets 0.4 N(0, 1); the env's loss
averaged over the steps), built up one layer at a time. Each variant is a ``lax.scan`` of T steps:

- ``physics``: the env's physics step alone (``jd.make_step(env.config.sim)``, ``env.params``), commanded
  ``hover_rpm (1 + 0.05 tanh(offset))`` (the hover env's RPM action of ``tanh(offset)``: 0.05 is
  ``jaxdrones.envs.actions.RPM_ACTION_SCALE``), the env's loss of the state;
- ``open_loop``: the env's ``step`` with the action ``tanh(offset)``. Nothing reads the observation, so XLA leaves
  it out of both passes: this is the env layer (action clip and mapping, reward, termination) around the physics;
- ``policy``: the env's ``step`` with the action ``tanh(obs @ w + b + offset)``, the ``default_env`` caller itself;
- ``policy_obs_stopped``: the same with ``jax.lax.stop_gradient`` on the observation the policy reads. Not a
  gradient anyone wants (it drops the feedback through the observation): it bounds from below what any derivative
  of the observation could cost.

Timed as in `benchmarks/gradients/gradients.py` (`gradients.time_calls`: rounds of one call of each, medians): the
forward pass, the loss and its gradient w.r.t. the offsets, and for the policy variants w.r.t. the policy's parameters;
each ratio is the median over rounds of the gradient's time over the same variant's forward time.

Usage::

    python benchmarks/gradients/gradient_layers.py      # T = 100, W = 1024; writes results/gradient_layers.json
    python benchmarks/gradients/gradient_layers.py --repeats 9
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

DEFAULT_OUT = os.path.join(RESULTS, "gradient_layers.json")
VARIANTS = ("physics", "open_loop", "policy", "policy_obs_stopped")


def losses(jax, jd, np, horizon: int, worlds: int) -> tuple[dict, tuple]:
    """``({variant: loss_of(policy, offsets, state)}, (policy, offsets, state))`` of `VARIANTS` (see above)."""
    from gradients import default_env_parts, env_scan_loss, linear_tanh_policy

    from jaxdrones.envs.actions import RPM_ACTION_SCALE

    jnp = jax.numpy
    parts = default_env_parts(jax, jd, np, horizon, worlds)
    env, start, env_loss = parts["env"], parts["start"], parts["env_loss"]
    physics_step = jd.make_step(env.config.sim)
    hover_rpm = env.params.hover_rpm[:, None]

    def physics(policy, offsets, state):
        def body(sim, offset):
            sim = physics_step(env.params, sim, hover_rpm * (1.0 + RPM_ACTION_SCALE * jnp.tanh(offset)))
            return sim, jnp.mean(env_loss(start.replace(sim=sim)))

        return jnp.mean(jax.lax.scan(body, start.sim.replace(**state), offsets)[1])

    variants = {
        "physics": physics,
        "open_loop": env_scan_loss(jax, parts, lambda policy, obs, offset: jnp.tanh(offset)),
        "policy": env_scan_loss(jax, parts, functools.partial(linear_tanh_policy, jax)),
        "policy_obs_stopped": env_scan_loss(
            jax,
            parts,
            lambda policy, obs, offset: linear_tanh_policy(jax, policy, jax.lax.stop_gradient(obs), offset),
        ),
    }
    return variants, (parts["policy"], parts["offsets"], parts["state"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--horizon", type=int, default=100, help="control steps T (default 100)")
    parser.add_argument("--worlds", type=int, default=1024, help="worlds W (default 1024)")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (median; default 7)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output path (default: %(default)s)")
    args = parser.parse_args(argv)
    if min(args.horizon, args.worlds, args.repeats) < 1:
        parser.error("--horizon, --worlds and --repeats must be positive")

    import jax
    import numpy as np
    from common import write_report
    from gradients import machine_header, time_calls

    import jaxdrones as jd

    info, load_start = machine_header(jax, f"; T={args.horizon}, W={args.worlds}")
    variants, inputs = losses(jax, jd, np, args.horizon, args.worlds)
    calls = {}
    for name, loss_of in variants.items():
        calls[f"{name}/forward"] = (loss_of, inputs)
        calls[f"{name}/grad_commands"] = (jax.value_and_grad(loss_of, argnums=1), inputs)
        if name.startswith("policy"):
            calls[f"{name}/grad_policy"] = (jax.value_and_grad(loss_of), inputs)
    timed = time_calls(jax, calls, args.repeats)
    results = []
    print("| variant | forward ms | grad(commands) ms | ratio | grad(policy) ms | ratio |\n|---|---|---|---|---|---|")
    for name in variants:
        forward = timed[f"{name}/forward"]
        row = {"variant": name, "forward_s": forward["s"], "forward_times_s": forward["times_s"]}
        cells = [f"{1e3 * forward['s']:.1f}"]
        for wrt in ("commands", "policy"):
            grad = timed.get(f"{name}/grad_{wrt}")
            if grad is None:
                cells += ["", ""]
                continue
            ratio = statistics.median(g / f for g, f in zip(grad["times_s"], forward["times_s"], strict=True))
            row |= {f"grad_{wrt}_s": grad["s"], f"grad_{wrt}_times_s": grad["times_s"], f"ratio_{wrt}": ratio}
            cells += [f"{1e3 * grad['s']:.1f}", f"{ratio:.2f}x"]
        results.append(row)
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    settings = vars(args) | {"env": 'jd.make("hover")', "variants": list(variants)}
    settings.pop("out")
    write_report(args.out, "the default env's gradient by layer", info, settings, results, loadavg_start=load_start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
