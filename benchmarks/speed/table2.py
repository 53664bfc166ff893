"""The paper's Table II, re-measured: speed-up over the wall clock of 240 Hz physics with 48 Hz PID control per drone,
with obstacles, on the JAX core, the PyBullet backend and (with ``--original``) the original, in one run.

The rows are the paper's (gym-pybullet-drones README, reference facts §15): 1 drone without and with vision,
10 drones without vision, 5 drones with vision, 80 drones in 4 envs without vision. Every row flies the drones of
the paper's formation to 0.5 m above their starts with the DSL PID, for ``--seconds`` simulated seconds, among the
paper's obstacles. Vision: every drone's 64×48 onboard camera (RGB, depth and segmentation) at 24 Hz, every other
control step, as the original's ``VISION_ATTR`` path captures them (``IMG_CAPTURE_FREQ``).

- ``jax``: one jitted ``lax.scan`` of PID, physics and (vision) `jaxdrones.cameras.render`; the 4 envs are a
  leading world axis (``vmap``). The JAX cameras draw the obstacles' primitives (the paper scene's duck mesh is
  Bullet's only: left out there, and its collisions too, since the JAX physics models the ground only).
- ``pybullet``: `jd.make_step(backend="pybullet", obstacles="paper")` called from a Python loop on NumPy state, the
  jitted PID between calls, `PyBulletStep.camera_images` (TinyRenderer) for vision; 4 envs are 4 Bullet worlds of one
  process.
- ``original``: ``CtrlAviary(pyb_freq=240, ctrl_freq=48, obstacles=True)`` stepped with its ``DSLPIDControl`` per
  drone, and for vision its ``_getDroneImages`` per drone every other step (what ``step`` does with
  ``vision_attributes``, without writing the PNG files); 4 envs are 4 processes, as its ``parallelism.sh``, and
  their time is the longest of their loops (each env is built before its loop's timer starts).

Speed-up: simulated seconds per env ÷ wall seconds (the median of ``--repeats`` timed runs after a warm-up, which
compiles). The paper's published speed-ups (i7-8850H/P2000 and MacBook i7-1068NG7) are printed beside.

Usage::

    python benchmarks/speed/table2.py                                   # writes benchmarks/results/table2.json
    python benchmarks/speed/table2.py --original /path/to/gym-pybullet-drones --seconds 2
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
import original
from common import RESULTS, machine_info, timed, write_report

import jaxdrones as jd
from jaxdrones import cameras
from jaxdrones.control import PIDGains, pid_control, pid_init
from jaxdrones.scene import PAPER_OBSTACLES

DEFAULT_OUT = os.path.join(RESULTS, "table2.json")
SIM_FREQ, CTRL_FREQ, CAMERA_FREQ = 240, 48, 24
#: (label, drones per env, envs, vision) and the paper's speed-ups (i7-8850H/P2000, MacBook i7-1068NG7).
ROWS = (
    ("1 drone, no vision", 1, 1, False, (15.5, 16.8)),
    ("1 drone, vision", 1, 1, True, (10.8, 1.3)),
    ("10 drones, no vision", 10, 1, False, (2.1, 2.3)),
    ("5 drones, vision", 5, 1, True, (2.5, 0.2)),
    ("80 drones in 4 envs, no vision", 20, 4, False, (0.8, 0.95)),
)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="simulated seconds per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--backends", nargs="+", default=["jax", "pybullet", "original"], choices=["jax", "pybullet", "original"]
    )
    parser.add_argument("--out", default=DEFAULT_OUT)
    original.add_argument(parser)
    return parser.parse_args(argv)


def median_time(run, repeats: int) -> float:
    """Median wall seconds of ``run()`` over ``repeats`` calls after a warm-up (`common.timed`)."""
    return timed(run, repeats)[1]


def setup(n_drones: int, n_envs: int):
    config = jd.SimConfig(n_drones=n_drones, sim_freq=SIM_FREQ, ctrl_freq=CTRL_FREQ)
    state = jd.init_state(config)
    if n_envs > 1:
        state = jax.tree.map(lambda x: jnp.broadcast_to(x, (n_envs,) + x.shape), state)
    return config, jd.load_params("cf2x"), state


def run_jax(n_drones: int, n_envs: int, vision: bool, n_steps: int):
    config, params, state = setup(n_drones, n_envs)
    step = jd.make_step(config)
    gains = PIDGains.dsl()
    target = state.pos + jnp.asarray([0.0, 0.0, 0.5])
    scene = cameras.make_scene([o for o in PAPER_OBSTACLES if o.shape != "urdf"])
    spec = cameras.CameraSpec()
    every = CTRL_FREQ // CAMERA_FREQ

    def body(carry, t):
        s, pid, seen = carry
        rpm, pid = pid_control(params, gains, pid, s, target, ctrl_dt=config.ctrl_dt)
        s = step(params, s, rpm)
        if vision:
            images = jax.lax.cond(
                t % every == 0, lambda: cameras.render(spec, scene, params, s.pos, s.quat), lambda: seen
            )
            seen = images
        return (s, pid, seen), None

    seen = jax.eval_shape(lambda: cameras.render(spec, scene, params, state.pos, state.quat)) if vision else None
    seen = None if seen is None else jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), seen)
    run = jax.jit(lambda s: jax.lax.scan(body, (s, pid_init(s), seen), jnp.arange(n_steps))[0][0])
    return lambda: jax.block_until_ready(run(state))


def run_pybullet(n_drones: int, n_envs: int, vision: bool, n_steps: int):
    config, params, state = setup(n_drones, n_envs)
    np_state = jax.tree.map(np.asarray, state)
    gains = PIDGains.dsl()
    target = np.asarray(np_state.pos) + np.array([0.0, 0.0, 0.5])
    controller = jax.jit(lambda pid, s: pid_control(params, gains, pid, s, target, ctrl_dt=config.ctrl_dt))
    step = jd.make_step(config, backend="pybullet", obstacles="paper")
    every = CTRL_FREQ // CAMERA_FREQ

    def loop():
        s, pid = np_state, pid_init(np_state)
        for t in range(n_steps):
            rpm, pid = controller(pid, s)
            s = step(params, s, rpm)
            if vision and t % every == 0:
                step.camera_images(params, s)
        return s

    return loop


def original_loop(n_drones: int, vision: bool, n_steps: int, path: str) -> float:
    """Wall seconds of the original's loop (in this process); the env is built before the timer starts."""
    original.load(path)
    from gym_pybullet_drones.control.DSLPIDControl import DSLPIDControl
    from gym_pybullet_drones.utils.enums import DroneModel

    env = original.ctrl_aviary(n_drones, CTRL_FREQ, obstacles=True)
    if vision:
        env.IMG_RES = np.array([64, 48])
    ctrls = [DSLPIDControl(drone_model=DroneModel.CF2X) for _ in range(n_drones)]
    action = original.hover_action(env)
    obs, *_ = env.step(action)
    targets = [obs[i][0:3] + np.array([0.0, 0.0, 0.5]) for i in range(n_drones)]
    every = CTRL_FREQ // CAMERA_FREQ
    start = time.perf_counter()
    for t in range(n_steps):
        obs, *_ = env.step(action)
        for i in range(n_drones):
            action[i], _, _ = ctrls[i].computeControlFromState(
                control_timestep=env.CTRL_TIMESTEP, state=obs[i], target_pos=targets[i]
            )
        if vision and t % every == 0:
            for i in range(n_drones):
                env._getDroneImages(i, segmentation=True)
    elapsed = time.perf_counter() - start
    env.close()
    return elapsed


def _original_worker(args):
    return original_loop(*args)


def run_original(n_drones: int, n_envs: int, vision: bool, n_steps: int, path: str, repeats: int) -> float:
    """Median over ``repeats`` runs (after a warm-up) of the wall seconds of ``n_envs`` envs flown in parallel
    processes: the longest of their loops, each timed from its first step (its env built before)."""
    times = []
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(n_envs) as pool:
        for _ in range(repeats + 1):
            times.append(max(pool.map(_original_worker, [(n_drones, vision, n_steps, path)] * n_envs)))
    return statistics.median(times[1:])


def main(argv=None) -> int:
    args = parse_args(argv)
    if "original" in args.backends and args.original is None:
        args.backends = [b for b in args.backends if b != "original"]
    if args.original is not None:
        original.load(args.original)
    info = machine_info(jax)
    n_steps = int(args.seconds * CTRL_FREQ)
    print(f"jax {info['jax']} on {info['backend']}, {info['cpu_model']}, load {os.getloadavg()}")
    print(f"{'configuration':<32} " + " ".join(f"{b:>10}" for b in args.backends) + f" {'paper':>14}")
    results = []
    for label, n_drones, n_envs, vision, paper in ROWS:
        row = {
            "row": label,
            "drones": n_drones,
            "envs": n_envs,
            "vision": vision,
            "sim_s": args.seconds,
            "paper_speedup": paper,
        }
        for backend in args.backends:
            if backend == "jax":
                seconds = median_time(run_jax(n_drones, n_envs, vision, n_steps), args.repeats)
            elif backend == "pybullet":
                seconds = median_time(run_pybullet(n_drones, n_envs, vision, n_steps), args.repeats)
            else:
                seconds = run_original(n_drones, n_envs, vision, n_steps, args.original, args.repeats)
            row[f"{backend}_wall_s"] = seconds
            row[f"{backend}_speedup"] = args.seconds / seconds
        results.append(row)
        print(
            f"{label:<32} "
            + " ".join(f"{row[f'{b}_speedup']:>9,.1f}x" for b in args.backends)
            + f" {paper[0]:>6.1f}x {paper[1]:>5.2f}x",
            flush=True,
        )
    write_report(
        args.out,
        "the paper's Table II: speed-up over the wall clock",
        info,
        {k: v for k, v in vars(args).items() if k != "out"},
        results,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
