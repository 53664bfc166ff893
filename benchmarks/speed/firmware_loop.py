"""The firmware's PID cascade in the loop with the physics against the physics alone, in drone-steps per second.

One drone-step is one firmware tick (1 ms) of one drone. Every program runs ``--ticks`` ticks of ``--worlds`` worlds
of one cf2x in one jitted `lax.scan`, on jaxdrones' physics at 1 kHz with first-order motors (τ = 61 ms,
docs/validation.md §3):

* physics alone, one tick a call: `jaxdrones.make_step` of ``SimConfig(sim_freq=1000, ctrl_freq=1000)`` at hover RPM;
* physics alone, ten ticks a call: ``SimConfig(sim_freq=1000, ctrl_freq=100)``, whose substeps are unrolled on a GPU
  (`SimConfig.unroll_substeps`): on a GPU the faster, as a scan's iterations cost launches there;
* tick by tick: `jaxdrones.control.firmware.pid_tick` (the firmware's state of each drone, `controller_pid` with
  only the loops of the tick, the power distribution and its cap, the motor map, then the same physics step),
  holding a position setpoint;
* scheduled: `jaxdrones.control.firmware.pid_ticks`, the same ticks in one call, the loops' schedule written into
  the program (what the envs' firmware actions run), the same setpoint.

Each program is compiled and warmed up, then they are timed in turn within each of ``--repeats`` rounds
(`common.timed_together`), so that a change of the machine's load reaches all; the table gives the medians, and each
firmware loop's rate over the faster physics program's.

    python benchmarks/speed/firmware_loop.py     # 4096 worlds; writes benchmarks/results/firmware_loop.json
    python benchmarks/speed/firmware_loop.py --worlds 1024 16384 --repeats 9
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS, machine_info, timed_together, write_report

DEFAULT_OUT = os.path.join(RESULTS, "firmware_loop.json")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--worlds", type=int, nargs="+", default=[4096], help="worlds of one drone (default 4096)")
    parser.add_argument("--ticks", type=int, default=1000, help="firmware ticks (1 ms each) per timed call")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (medians; default 7)")
    parser.add_argument("--out", default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if min(args.worlds) < 1 or args.ticks < 1 or args.repeats < 1:
        parser.error("--worlds, --ticks and --repeats must be positive")
    if args.ticks % 10:
        parser.error("--ticks must be a multiple of 10 (the position loop's period; the ten-tick physics)")
    return args


def programs(worlds: int, ticks: int):
    """({name: a function of nothing that runs ``ticks`` ticks and blocks}, {name: its compile time, s}, the two
    firmware loops' largest position difference at the end, m) of the four programs; ``ticks`` a multiple of 10."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxdrones as jd
    from jaxdrones.control import firmware as fw
    from jaxdrones.examples.firmware_in_the_loop import physics

    step, params, config = physics()  # 1 ms steps, motors of τ = 61 ms
    hover = np.full((worlds, 1, 4), float(params.hover_rpm), np.float32)
    start = jd.init_state(config, pos=np.random.default_rng(0).uniform(0.5, 1.5, (worlds, 1, 3)), rpm=hover)
    setpoint = fw.Setpoint.zeros((worlds, 1)).replace(
        mode=jnp.broadcast_to(jnp.array([1, 1, 1, 0, 0, 1, 0], jnp.int32), (worlds, 1, 7)),
        position=jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), (worlds, 1, 3)),
    )
    gains = fw.PidControllerGains.crazyflie()
    rpm = jnp.asarray(hover)

    step10 = jd.make_step(dataclasses.replace(config, ctrl_freq=100))

    @jax.jit
    def physics(drone):
        return jax.lax.scan(lambda d, _: (step(params, d, rpm), None), drone, None, length=ticks)[0]

    @jax.jit
    def physics10(drone):
        return jax.lax.scan(lambda d, _: (step10(params, d, rpm), None), drone, None, length=ticks // 10)[0]

    @jax.jit
    def loop(state):
        return jax.lax.scan(
            lambda s, _: (fw.pid_tick(step, params, gains, s, setpoint)[0], None),
            state,
            None,
            length=ticks,
        )[0]

    @jax.jit
    def scheduled(state):
        return fw.pid_ticks(step, params, gains, state, setpoint, ticks)[0]

    loop_start = fw.pid_loop_init(start, tick=0)
    compile_s = {}
    programs = {
        "physics": (physics, start),
        "physics_10": (physics10, start),
        "tick_by_tick": (loop, loop_start),
        "scheduled": (scheduled, loop_start),
    }
    for name, (fn, arg) in programs.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        compile_s[name] = time.perf_counter() - t0
    runs = {name: (lambda fn=fn, arg=arg: jax.block_until_ready(fn(arg))) for name, (fn, arg) in programs.items()}
    # The two loops fly the same ticks: their drones' largest distance apart at the end, m (a check on the timing).
    apart = float(jnp.max(jnp.abs(loop(loop_start).drone.pos - scheduled(loop_start).drone.pos)))
    return runs, compile_s, apart


def main(argv=None) -> int:
    args = parse_args(argv)
    import jaxdrones  # noqa: F401, I001  (first: it sets XLA's flags before JAX starts)
    import jax

    info = machine_info(jax)
    print(f"jax {info['jax']} on {info['backend']}, {info['cpu_model']}, load {os.getloadavg()}")
    load_start = os.getloadavg()
    results = []
    print("| worlds | physics, 1 tick a call | 10 ticks a call | tick by tick | / physics | scheduled | / physics |")
    print("|---|---|---|---|---|---|---|")
    for worlds in args.worlds:
        runs, compile_s, apart = programs(worlds, args.ticks)
        times = timed_together(runs, args.repeats)
        rate = {name: worlds * args.ticks / median for name, (_, median) in times.items()}
        fastest = max(rate["physics"], rate["physics_10"])
        row = {
            "worlds": worlds,
            "ticks": args.ticks,
            "physics_drone_steps_per_s": rate["physics"],
            "physics_10_drone_steps_per_s": rate["physics_10"],
            "tick_by_tick_drone_steps_per_s": rate["tick_by_tick"],
            "tick_by_tick_over_physics": rate["tick_by_tick"] / fastest,
            "scheduled_drone_steps_per_s": rate["scheduled"],
            "scheduled_over_physics": rate["scheduled"] / fastest,
            "median_s": {name: t[1] for name, t in times.items()},
            "best_s": {name: t[0] for name, t in times.items()},
            "compile_s": compile_s,
            "loops_apart_m": apart,
        }
        results.append(row)
        print(
            f"| {worlds} | {rate['physics']:.3g} | {rate['physics_10']:.3g} | {rate['tick_by_tick']:.3g} "
            f"| {row['tick_by_tick_over_physics']:.2f} "
            f"| {rate['scheduled']:.3g} | {row['scheduled_over_physics']:.2f} |",
            flush=True,
        )
    write_report(
        args.out,
        "the firmware's PID in the loop against the physics",
        info,
        vars(args),
        results,
        loadavg_start=load_start,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
