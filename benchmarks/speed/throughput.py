"""Throughput of the JAX physics core: drone-steps per second over a grid of worlds × drones × effects.

A drone-step is one physics substep (1/sim_freq s) of one drone. Each measurement jits a function that runs
``T`` control steps of `jaxdrones.make_step` (``sim_freq/ctrl_freq`` physics substeps each, under ``lax.scan``)
inside one call, holding a per-drone RPM command, and counts worlds × drones × T × substeps drone-steps. The
call is compiled and timed for compile time, run once to warm up, then timed ``--repeats`` times with
``block_until_ready``; the table gives the best and the median.

The worlds are spread over all of the host's devices with `jaxdrones.sim.shard_worlds` whenever their number
divides evenly (one device otherwise). On a CPU host this script gives JAX one device per core by setting
``XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`` before importing jax, unless ``XLA_FLAGS`` already
chooses a count; ``--devices`` overrides it. Machine load is recorded because the timings are wall-clock.

Memory: ``state_mb`` is the size of the simulated state, ``xla_temp_mb`` the scratch memory XLA allocates for
the call (from the compiled executable's memory analysis), ``rss_peak_mb`` the process's peak resident set so far
and ``rss_growth_mb`` how much that peak grew during the measurement (the grid runs from small to large, so
this is the measurement's own footprint when it sets a new peak); on GPUs the device's ``peak_bytes_in_use``
is recorded too.

Usage::

    python benchmarks/speed/throughput.py                      # full grid, writes benchmarks/results/throughput.json
    python benchmarks/speed/throughput.py --quick              # smaller grid, fewer repeats
    python benchmarks/speed/throughput.py --worlds 16384 --drones 1 --effects on
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS, configure_devices, machine_info, write_report

WORLDS = (1, 64, 1024, 16384, 131072)
DRONES = (1, 4)
QUICK_WORLDS = (1, 1024, 16384)
DEFAULT_OUT = os.path.join(RESULTS, "throughput.json")
#: Aim for calls of about this many drone-steps, so each timed call lasts long enough to measure.
TARGET_DRONE_STEPS = 2_000_000


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help=f"smaller grid (worlds {QUICK_WORLDS}) and 5 repeats")
    parser.add_argument("--worlds", type=int, nargs="+", help=f"numbers of worlds (default {WORLDS})")
    parser.add_argument("--drones", type=int, nargs="+", help=f"drones per world (default {DRONES})")
    parser.add_argument(
        "--effects",
        choices=("on", "off"),
        nargs="+",
        default=["on", "off"],
        help="aerodynamic effects: on = drag, ground effect and downwash (a no-op with one drone)",
    )
    parser.add_argument("--integrator", choices=("euler", "rk4"), default="euler")
    parser.add_argument(
        "--unroll-substeps",
        action="store_true",
        help="write the substeps out in the compiled step (SimConfig.unroll_substeps=True; default: a loop)",
    )
    parser.add_argument(
        "--pallas",
        action="store_true",
        help="the control step as Pallas kernels (jaxdrones.experimental.pallas; for a GPU, interpreted on the CPU); "
        "downwash off, as the kernel takes no coupling between drones",
    )
    parser.add_argument("--sim-freq", type=int, default=240, help="physics rate, Hz")
    parser.add_argument("--ctrl-freq", type=int, default=48, help="control rate, Hz (sim_freq/ctrl_freq substeps)")
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="control steps per timed call (default: chosen per size, about "
        f"{TARGET_DRONE_STEPS:.0e} drone-steps per call)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per measurement (default 10; 5 quick)")
    parser.add_argument(
        "--devices",
        type=int,
        default=None,
        help="CPU devices to create (default: one per core, or what XLA_FLAGS says)",
    )
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output path (default: %(default)s)")
    args = parser.parse_args(argv)
    args.worlds = args.worlds or (QUICK_WORLDS if args.quick else WORLDS)
    args.drones = args.drones or DRONES
    args.repeats = args.repeats or (5 if args.quick else 10)
    for name in ("worlds", "drones"):
        if min(getattr(args, name)) < 1:
            parser.error(f"--{name} must be positive")
    return args


def measure(jax, jd, args, n_worlds: int, n_drones: int, effects_on: bool) -> dict:
    import jax.numpy as jnp
    import numpy as np

    config = jd.SimConfig(
        n_drones=n_drones,
        sim_freq=args.sim_freq,
        ctrl_freq=args.ctrl_freq,
        drag=effects_on,
        ground_effect=effects_on,
        downwash=effects_on and not args.pallas,
        integrator=args.integrator,
        unroll_substeps=args.unroll_substeps,
    )
    substeps = config.n_substeps
    steps = args.steps or int(np.clip(TARGET_DRONE_STEPS // (n_worlds * n_drones * substeps), 2, 2000))
    params = jd.load_params("cf2x")

    # Drones in the paper's start formation, each world shifted and given its own hover-ish command.
    rng = np.random.default_rng(0)
    pos = jd.state.default_start_pos(n_drones) + np.zeros((n_worlds, 1, 1))
    pos[..., :2] += rng.uniform(-1.0, 1.0, (n_worlds, 1, 2))
    state = jd.init_state(config, pos=pos)
    hover = float(params.hover_rpm)
    rpm = jnp.asarray(hover * rng.uniform(0.98, 1.06, (n_worlds, n_drones, 4)), dtype=state.pos.dtype)

    devices = jax.devices()
    n_dev = max(k for k in range(1, len(devices) + 1) if n_worlds % k == 0 and len(devices) % k == 0)
    state, rpm = jd.sim.shard_worlds((state, rpm), devices=devices[:n_dev])
    if args.pallas:
        from jaxdrones.experimental import pallas

        step = pallas.make_step(config)
    else:
        step = jd.make_step(config)

    def run(params, state, rpm):
        return jax.lax.fori_loop(0, steps, lambda _, s: step(params, s, rpm), state)

    rss_before = _maxrss_mb()
    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(params, state, rpm).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(params, state, rpm))  # warm-up
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, state, rpm))
        times.append(time.perf_counter() - t0)
    drone_steps = n_worlds * n_drones * steps * substeps

    result = {
        "worlds": n_worlds,
        "drones": n_drones,
        "effects": "on" if effects_on else "off",
        "drag": config.drag,
        "ground_effect": config.ground_effect,
        "downwash": config.downwash,
        "integrator": config.integrator,
        "devices": n_dev,
        "control_steps": steps,
        "substeps": substeps,
        "drone_steps_per_call": drone_steps,
        "compile_s": compile_s,
        "times_s": times,
        "best_drone_steps_per_s": drone_steps / min(times),
        "median_drone_steps_per_s": drone_steps / float(np.median(times)),
        "state_mb": sum(x.nbytes for x in jax.tree.leaves(state)) / 2**20,
        "rss_peak_mb": _maxrss_mb(),
        "rss_growth_mb": _maxrss_mb() - rss_before,
        "loadavg_1min": os.getloadavg()[0],
    }
    analysis = compiled.memory_analysis()
    if analysis is not None:
        result["xla_temp_mb"] = analysis.temp_size_in_bytes / 2**20
    stats = devices[0].memory_stats()
    if stats and "peak_bytes_in_use" in stats:
        result["device_peak_mb"] = stats["peak_bytes_in_use"] / 2**20
    return result


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def print_row(r: dict | None) -> None:
    if r is None:
        print(
            f"{'worlds':>7} {'drones':>6} {'effects':>7} {'dev':>3} {'steps':>9} {'compile s':>9} "
            f"{'best steps/s':>13} {'median':>10} {'state MB':>8} {'temp MB':>8} {'RSS MB':>7} {'load':>5}"
        )
        return
    print(
        f"{r['worlds']:>7} {r['drones']:>6} {r['effects']:>7} {r['devices']:>3} "
        f"{r['control_steps']:>5}×{r['substeps']:<3} {r['compile_s']:>9.2f} "
        f"{r['best_drone_steps_per_s']:>13.3e} {r['median_drone_steps_per_s']:>10.2e} "
        f"{r['state_mb']:>8.2f} {r.get('xla_temp_mb', float('nan')):>8.2f} {r['rss_peak_mb']:>7.0f} "
        f"{r['loadavg_1min']:>5.2f}",
        flush=True,
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    xla_flags = configure_devices(args.devices)
    import jax

    import jaxdrones as jd

    info = machine_info(jax)
    print(
        f"jax {info['jax']} on {info['backend']}: {len(jax.devices())} devices, {info['cpu_model']}, "
        f"XLA_FLAGS={xla_flags!r}, load {os.getloadavg()}"
    )
    load_start = os.getloadavg()
    results = []
    print_row(None)
    grid = sorted((w * d, w, d, e) for w in args.worlds for d in args.drones for e in args.effects)
    for _, n_worlds, n_drones, effects in grid:
        result = measure(jax, jd, args, n_worlds, n_drones, effects == "on")
        results.append(result)
        print_row(result)

    settings = {k: v for k, v in vars(args).items() if k != "out"} | {
        "worlds": list(args.worlds),
        "drones": list(args.drones),
    }
    write_report(args.out, "jaxdrones physics core throughput", info, settings, results, loadavg_start=load_start)
    return 0


if __name__ == "__main__":
    sys.exit(main())
