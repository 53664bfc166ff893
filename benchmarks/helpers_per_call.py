"""The cost of one call of the public helpers a Python control loop calls (pid.py's loop: a step, a PID per drone,
Euler angles for a log), jitted as they ship against the same functions run op by op (``jax.disable_jit``), in one
run. Three Crazyflies at 240/48 Hz; medians of ``--repeats`` timings of ``--calls`` calls each, after two warm-up
calls (the compilation is not counted).

    python benchmarks/helpers_per_call.py [--calls 200] [--repeats 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

import jaxdrones as jd
from jaxdrones.control.pid import PIDGains, pid_control, pid_init
from jaxdrones.rotations import quat_from_euler, quat_to_euler


def per_call_us(fn, calls: int, repeats: int) -> float:
    fn(), fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            out = fn()
        jax.block_until_ready(out)
        times.append((time.perf_counter() - start) / calls * 1e6)
    return statistics.median(times)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    config = jd.SimConfig(n_drones=3, sim_freq=240, ctrl_freq=48)
    step, params = jd.make_step(config), jd.load_params("cf2x")
    state = jd.init_state(config, pos=np.array([[0, 0, 0.1], [0.3, 0, 0.15], [0, 0.3, 0.2]]))
    gains, memory, rpm = PIDGains.dsl(), pid_init(state), np.full((3, 4), 14468.0)
    target = np.array([[0.0, 0.0, 0.5]] * 3)
    helpers = {
        "make_step's step (3 drones, 5 substeps)": lambda: step(params, state, rpm),
        "pid_control (3 drones)": lambda: pid_control(params, gains, memory, state, target, ctrl_dt=1 / 48),
        "quat_to_euler": lambda: quat_to_euler(state.quat),
        "quat_from_euler": lambda: quat_from_euler(np.zeros((3, 3))),
    }
    results = {}
    for name, fn in helpers.items():
        jitted = per_call_us(fn, args.calls, args.repeats)
        with jax.disable_jit():
            eager = per_call_us(fn, max(1, args.calls // 10), args.repeats)
        results[name] = {"jitted_us": jitted, "op_by_op_us": eager}
        print(f"{name:<40} {jitted:8.0f} us jitted   {eager:8.0f} us op by op   ({eager / jitted:.0f}x)")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
    return results


if __name__ == "__main__":
    main()
