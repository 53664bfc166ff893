"""Where the time of a gradient through the default env's physics goes: an XLA:CPU trace, summed by operation.

The work: a ``lax.scan`` of T control steps over ``jaxdrones.make_step(jd.make("hover").config.sim)`` (the hover
env's physics at its defaults: 240 Hz physics, 30 Hz control, 8 substeps per step) for W worlds of one cf2x,
starting 5-30 cm up, RPM commands within 2 % of hover, the loss of `benchmarks/gradients/gradients.py` (its start
positions and ``trajectory_loss``). The forward pass and the value and gradient w.r.t. the commands are timed in
rounds (medians, and their ratio); then ``jax.profiler`` traces ``--traced`` gradient calls and the trace's
operations (XLA's thunks: fusions, loops, copies) are summed per call, by name with the numeric suffix dropped,
and listed by the share of the time they take. On jax >= 0.11 each inner ``while`` loop (the substeps) runs as one
``call``; on jax 0.10 the loops' own fusions appear (and the profiler's per-operation overhead inflates them).
``--caller default_env`` traces the whole env step instead (`benchmarks/gradients/gradients.py`'s ``default_env``
caller: ``jd.make("hover")``'s vmapped step, a linear tanh policy, the env's loss), differentiated w.r.t. the offsets,
or w.r.t. the policy's parameters with ``--wrt policy`` (the ``grad(policy)`` column of
`benchmarks/gradients/gradients.py`).

Usage::

    python benchmarks/gradients/gradient_profile.py                    # W = 1024, T = 100
    python benchmarks/gradients/gradient_profile.py --worlds 4096 --top 30
    python benchmarks/gradients/gradient_profile.py --caller default_env
    python benchmarks/gradients/gradient_profile.py --caller default_env --wrt policy
"""

from __future__ import annotations

import argparse
import collections
import functools
import glob
import gzip
import json
import re
import statistics
import tempfile
import time

#: Trace events that are the profiler's or the runtime's own bookkeeping, not operations of the program.
_PROFILER_EVENTS = ("$", "ThunkExecutor", "PjitFunction", "end:", "ThreadpoolListener")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (median)")
    parser.add_argument("--traced", type=int, default=3, help="gradient calls traced by the profiler")
    parser.add_argument("--top", type=int, default=20, help="operations listed")
    parser.add_argument(
        "--caller",
        choices=("physics", "default_env", "default_env_crazyflie"),
        default="physics",
        help="physics: a scan over the default env's step function (default); default_env(_crazyflie): the whole "
        "env step with a policy, as benchmarks/gradients/gradients.py's callers of that name",
    )
    parser.add_argument(
        "--wrt",
        choices=("commands", "policy"),
        default="commands",
        help="default_env callers: differentiate w.r.t. the per-step offsets (default) or the policy's parameters",
    )
    args = parser.parse_args(argv)
    if args.wrt == "policy" and args.caller == "physics":
        parser.error("--wrt policy needs a default_env caller (the physics caller has no policy)")

    import jax
    import jax.numpy as jnp
    import numpy as np
    from gradients import default_env_setup, start_positions, trajectory_loss  # gradients.py's work

    import jaxdrones as jd

    w, t = args.worlds, args.horizon
    if args.caller == "physics":
        config = jd.make("hover").config.sim
        params = jd.load_params("cf2x")
        init = jd.init_state(config, pos=jnp.asarray(start_positions(np, w)))
        step = jd.make_step(config)
        noise = np.random.default_rng(1).standard_normal((t, w, 1, 4))
        commands = jnp.asarray(float(params.hover_rpm) * (1 + 0.02 * noise), jnp.float32)

        def loss(commands, init):
            def body(s, rpm):
                s = step(params, s, rpm)
                return s, (s.pos, s.vel)

            _, (p, v) = jax.lax.scan(body, init, commands)
            return trajectory_loss(jnp, p, v)

        what = f"{config.n_substeps} substeps per control step"
        inputs = (commands, init)
    else:
        realism = None if args.caller == "default_env" else args.caller.removeprefix("default_env_")
        loss_of, policy, commands, init = default_env_setup(jax, jd, np, t, w, realism)
        if args.wrt == "policy":
            loss, inputs, wrt = loss_of, (policy, commands, init), "policy's parameters"
        else:
            loss, inputs, wrt = functools.partial(loss_of, policy), (commands, init), "per-step offsets"
        what = f"caller {args.caller}, the gradient w.r.t. the {wrt}"

    compiled = {
        name: jax.jit(fn).lower(*inputs).compile()
        for name, fn in (("forward", loss), ("gradient", jax.value_and_grad(loss)))
    }
    for fn in compiled.values():
        jax.block_until_ready(fn(*inputs))
    times = {name: [] for name in compiled}
    for _ in range(args.repeats):
        for name, fn in compiled.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*inputs))
            times[name].append(time.perf_counter() - t0)
    ratio = statistics.median(g / f for g, f in zip(times["gradient"], times["forward"], strict=True))
    print(
        f"jax {jax.__version__}; {what}, W={w}, T={t}: forward "
        f"{1e3 * statistics.median(times['forward']):.1f} ms, value and gradient "
        f"{1e3 * statistics.median(times['gradient']):.1f} ms ({ratio:.2f}x)"
    )

    profiles = {name: operations(jax, fn, inputs, args.traced) for name, fn in compiled.items()}
    runs = {name: sum(count.values()) for name, (_, count) in profiles.items()}
    print(
        f"operations run per call (XLA's thunks, the profiler's own events left out): forward {runs['forward']:,.0f}, "
        f"value and gradient {runs['gradient']:,.0f} ({runs['gradient'] / runs['forward']:.2f}x)"
    )
    total, count = profiles["gradient"]
    overall = sum(total.values())
    print(f"traced operations, per gradient call: {overall:.1f} ms in all")
    print("| operation | ms per call | share | runs per call |\n|---|---|---|---|")
    for key, ms in total.most_common(args.top):
        print(f"| {key} | {ms:.2f} | {100 * ms / overall:.1f} % | {count[key]:.0f} |")
    return 0


def operations(jax, fn, inputs, traced: int) -> tuple[collections.Counter, collections.Counter]:
    """Milliseconds and runs per call of each operation of ``traced`` calls of the compiled ``fn``, by name with
    the numeric suffix dropped, from a ``jax.profiler`` trace."""
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir, create_perfetto_trace=True)
        for _ in range(traced):
            jax.block_until_ready(fn(*inputs))
        jax.profiler.stop_trace()
        path = sorted(glob.glob(f"{trace_dir}/**/*.trace.json.gz", recursive=True))[-1]
        events = json.load(gzip.open(path))["traceEvents"]
    total, count = collections.Counter(), collections.Counter()
    for event in events:
        name = event.get("name", "")
        if event.get("ph") != "X" or name.startswith(_PROFILER_EVENTS):
            continue
        key = re.sub(r"\.\d+$", "", name)
        total[key] += event.get("dur", 0) / traced / 1e3
        count[key] += 1 / traced
    return total, count


if __name__ == "__main__":
    raise SystemExit(main())
