"""PyBullet backend vs the JAX core: physics steps per second, PID-in-the-loop speed, camera frames.

What is measured (all on one host process, wall clock, best and median of ``--repeats`` timed runs):

- ``physics``: one world of 1, 10 and 80 drones at 240 Hz physics, hovering at their start positions (the paper's
  formation), effects off, no rendering. The PyBullet backend is called from a Python loop on NumPy state, one
  call per control step; ``ctrl_freq`` 240 (one Bullet step per call) and 48 (five). The JAX core does the same
  work (same config, same number of steps) two ways: called from the same Python loop, and as one jitted
  ``jd.rollout`` (``lax.scan``). The PyBullet backend is also called on JAX arrays (``loop`` ``python-jax``: from the
  state `jd.init_state` returns, with a JAX RPM array at every call, as a jitted controller gives), and, with
  ``--original``, the original's ``CtrlAviary.step`` at hover RPM (``benchmarks/speed/original.py``). Reported: physics
  steps/s (Bullet steps, i.e. 1/240 s of one world), drone-steps/s and the real-time factor (physics steps/s ÷ 240).
- ``pid_loop``: the original's speed test setup (docs/physics.md §13, §15): 240 Hz physics, 48 Hz DSL PID control
  of each drone toward a target 0.5 m above its start, the PID (`jaxdrones.control.pid_control`, jitted with params,
  gains and target closed over) called once per control step from the same Python loop as the backend, with and
  without the paper's obstacle scene. The original's PYB mode ran its PID loop at about
  18,500 physics steps/s (77× real time) on this class of machine, and 15.5-16.8× real time in the paper's Table.
- ``camera``: per-drone 64×48 captures (`PyBulletStep.camera_images`, RGBA + depth + segmentation) with
  TinyRenderer, in the paper's obstacle scene: frames/s per drone and kB/s of RGBA (the paper reports about
  750 kB/s of TinyRenderer frames).

Usage::

    python benchmarks/speed/backends.py            # writes benchmarks/results/backends.json
    python benchmarks/speed/backends.py --quick    # fewer steps and repeats
    python benchmarks/speed/backends.py --original /path/to/gym-pybullet-drones   # the original in the same run
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
import original
from common import RESULTS, machine_info, timed, timed_together, write_report

import jaxdrones as jd
from jaxdrones.control import PIDGains, pid_control, pid_init

DEFAULT_OUT = os.path.join(RESULTS, "backends.json")
DRONES = (1, 10, 80)
SIM_FREQ = 240


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="fewer simulated seconds and 3 repeats")
    parser.add_argument("--drones", type=int, nargs="+", default=list(DRONES), help="drones per world")
    parser.add_argument("--seconds", type=float, default=None, help="simulated seconds per timed run (default 5)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per measurement (default 5)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output path (default: %(default)s)")
    original.add_argument(parser)
    args = parser.parse_args(argv)
    args.seconds = args.seconds or (1.0 if args.quick else 5.0)
    args.repeats = args.repeats or (3 if args.quick else 5)
    return args


def hover_setup(n_drones: int, ctrl_freq: int):
    config = jd.SimConfig(n_drones=n_drones, sim_freq=SIM_FREQ, ctrl_freq=ctrl_freq)
    params = jd.load_params("cf2x")
    state = jd.init_state(config)
    rpm = np.full((n_drones, 4), float(params.hover_rpm), dtype=np.asarray(state.pos).dtype)
    return config, params, state, rpm


def rates(n_ctrl_steps: int, config, seconds: float) -> dict:
    physics = n_ctrl_steps * config.n_substeps / seconds
    return {
        "physics_steps_per_s": physics,
        "drone_steps_per_s": physics * config.n_drones,
        "real_time_factor": physics / config.sim_freq,
    }


def bench_physics(args, n_drones: int, ctrl_freq: int) -> list[dict]:
    config, params, state, rpm = hover_setup(n_drones, ctrl_freq)
    n_steps = int(args.seconds * ctrl_freq)
    np_state = jax.tree.map(np.asarray, state)
    rpm_jax = jax.numpy.asarray(rpm)
    jax_step = jd.make_step(config)
    rpms = jax.numpy.broadcast_to(rpm_jax, (n_steps,) + rpm.shape)

    def loop(call, s):
        for _ in range(n_steps):
            s = call(s)
        return jax.block_until_ready(s)

    with contextlib.ExitStack() as stack:
        step = stack.enter_context(jd.make_step(config, backend="pybullet"))
        loops = {  # python-jax: from jd.init_state's JAX arrays, with a JAX RPM array (a jitted policy's) at every call
            ("pybullet", "python"): lambda: loop(lambda s: step(params, s, rpm), np_state),
            ("pybullet", "python-jax"): lambda: loop(lambda s: step(params, s, rpm_jax), state),
            ("jax", "python"): lambda: loop(lambda s: jax_step(params, s, rpm_jax), state),
            ("jax", "lax.scan"): lambda: jax.block_until_ready(jd.rollout(jax_step, params, state, rpms)),
        }
        if args.original_module is not None:
            env = original.ctrl_aviary(n_drones, ctrl_freq)
            stack.callback(env.close)
            action = original.hover_action(env)
            loops["original", "env.step"] = lambda: loop(lambda _: env.step(action), None)
        times = timed_together(loops, args.repeats)
    rows = []
    for (backend, kind), (best, median) in times.items():
        rows.append(
            {
                "measure": "physics",
                "backend": backend,
                "loop": kind,
                "drones": n_drones,
                "ctrl_freq": ctrl_freq,
                "ctrl_steps": n_steps,
                "best_s": best,
                "median_s": median,
                "best": rates(n_steps, config, best),
                "median": rates(n_steps, config, median),
            }
        )
    return rows


def bench_pid_loop(args, n_drones: int, obstacles: bool) -> dict:
    ctrl_freq = 48
    config, params, state, _ = hover_setup(n_drones, ctrl_freq)
    n_steps = int(args.seconds * ctrl_freq)
    gains = PIDGains.dsl()
    target = np.asarray(state.pos) + np.array([0.0, 0.0, 0.5])
    np_state = jax.tree.map(np.asarray, state)
    controller = jax.jit(lambda pid, s: pid_control(params, gains, pid, s, target, ctrl_dt=config.ctrl_dt))
    with jd.make_step(config, backend="pybullet", obstacles="paper" if obstacles else None) as step:

        def loop():
            s, pid = np_state, pid_init(np_state)
            for _ in range(n_steps):
                rpm, pid = controller(pid, s)
                s = step(params, s, np.asarray(rpm))
            return s

        best, median = timed(loop, args.repeats)
        final = loop()
    return {
        "measure": "pid_loop",
        "backend": "pybullet",
        "drones": n_drones,
        "obstacles": obstacles,
        "ctrl_freq": ctrl_freq,
        "ctrl_steps": n_steps,
        "best_s": best,
        "median_s": median,
        "best": rates(n_steps, config, best),
        "median": rates(n_steps, config, median),
        "final_height_error_m": float(np.max(np.abs(final.pos[:, 2] - target[:, 2]))),
    }


def bench_camera(args, n_drones: int) -> dict:
    config, params, state, _ = hover_setup(n_drones, 48)
    np_state = jax.tree.map(np.asarray, state)
    n_frames = max(5, int(args.seconds * 24))  # the original's 24 Hz capture rate
    with jd.make_step(config, backend="pybullet", obstacles="paper") as step:

        def capture():
            for _ in range(n_frames):
                images = step.camera_images(params, np_state)
            return images

        best, median = timed(capture, args.repeats)
        images = capture()
    rgba_bytes = images["rgb"][..., 0, :, :, :].nbytes  # one drone's frame
    frames = n_frames * n_drones
    return {
        "measure": "camera",
        "backend": "pybullet",
        "renderer": "tiny",
        "drones": n_drones,
        "width": images["rgb"].shape[-2],
        "height": images["rgb"].shape[-3],
        "frames": frames,
        "best_s": best,
        "median_s": median,
        "frames_per_s_best": frames / best,
        "frames_per_s_median": frames / median,
        "rgba_kB_per_s_best": frames * rgba_bytes / best / 1e3,
        "rgba_kB_per_s_median": frames * rgba_bytes / median / 1e3,
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    args.original_module = original.load(args.original)
    info = machine_info(jax)
    print(f"jax {info['jax']} on {info['backend']}, {info['cpu_model']}, load {os.getloadavg()}")
    results = []
    print(
        f"{'measure':<9} {'backend':<9} {'loop':<10} {'drones':>6} {'ctrl Hz':>7} {'physics steps/s':>16} "
        f"{'median':>9} {'drone-steps/s':>14} {'x real time':>11}"
    )
    for n_drones in args.drones:
        for ctrl_freq in (240, 48):
            for row in bench_physics(args, n_drones, ctrl_freq):
                results.append(row)
                best = row["best"]
                print(
                    f"{'physics':<9} {row['backend']:<9} {row['loop']:<10} {n_drones:>6} {ctrl_freq:>7} "
                    f"{best['physics_steps_per_s']:>16,.0f} {row['median']['physics_steps_per_s']:>9,.0f} "
                    f"{best['drone_steps_per_s']:>14,.0f} {best['real_time_factor']:>11,.1f}"
                )
    for n_drones in (1, 10):
        for obstacles in (False, True):
            row = bench_pid_loop(args, n_drones, obstacles)
            results.append(row)
            best = row["best"]
            loop = "pid+obst" if obstacles else "pid"
            print(
                f"{'pid_loop':<9} {'pybullet':<9} {loop:<10} {n_drones:>6} {48:>7} "
                f"{best['physics_steps_per_s']:>16,.0f} {row['median']['physics_steps_per_s']:>9,.0f} "
                f"{best['drone_steps_per_s']:>14,.0f} {best['real_time_factor']:>11,.1f}"
            )
    for n_drones in (1, 10):
        row = bench_camera(args, n_drones)
        results.append(row)
        print(
            f"camera    tiny      64x48     {n_drones:>6}: {row['frames_per_s_best']:,.0f} frames/s per process, "
            f"{row['rgba_kB_per_s_best']:,.0f} kB/s RGBA (median {row['rgba_kB_per_s_median']:,.0f})"
        )
    write_report(
        args.out,
        "jaxdrones PyBullet backend vs JAX core",
        info,
        {k: v for k, v in vars(args).items() if k not in ("out", "original_module")},
        results,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
