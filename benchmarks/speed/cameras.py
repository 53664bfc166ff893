"""Frames per second of the JAX cameras (`jaxdrones.cameras.render`) against worlds and scene size, with the PyBullet
backend's onboard cameras (TinyRenderer and EGL) on the same scene in the same run.

The work: W worlds of one cf2x hovering at (0, 0, 1) m with random tilts (±0.3 rad) and headings, each rendering
its onboard camera (64 × 48, 60° vertical field of view; depth and segmentation, or all of RGB, depth and
segmentation) of a scene of P primitives (boxes, spheres, cylinders and capsules in equal shares, placed
uniformly within 3 m) plus the ground. The JAX cameras run as one ``jit(vmap)`` call over the worlds, the poses
already on the device; the time is the median of ``--repeats`` calls after compilation. The PyBullet backend
renders the same scene for 16 worlds, one ``getCameraImage`` per drone. Last, the envs: ``fly_thru_gate`` (3 boxes)
and ``avoid`` (16 primitives drawn per episode) with depth and segmentation cameras at every 30 Hz control step,
env steps/s of ``jit(vmap(step))`` in a ``lax.scan``.

Usage::

    python benchmarks/speed/cameras.py                          # writes benchmarks/results/cameras.json
    python benchmarks/speed/cameras.py --worlds 1 64 1024 --primitives 16 --no-pybullet
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS, timed

DEFAULT_OUT = os.path.join(RESULTS, "cameras.json")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 64, 1024, 4096])
    parser.add_argument("--primitives", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--kinds", nargs="+", default=["depth", "seg"], choices=["rgb", "depth", "seg"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--pybullet",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also time the PyBullet backend's cameras (TinyRenderer and EGL) on 16 worlds",
    )
    parser.add_argument("--out", default=DEFAULT_OUT)
    return parser.parse_args(argv)


def scene_obstacles(n: int, seed: int = 0):
    """``n`` primitives, the four shapes in turn, within 3 m of the origin (none within 0.5 m of the drone)."""
    import numpy as np

    from jaxdrones.scene import Obstacle

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        xy = rng.uniform(-3, 3, 2)
        xy = xy if np.linalg.norm(xy) > 0.5 else xy + 0.5
        pos = (float(xy[0]), float(xy[1]), float(rng.uniform(0.2, 1.5)))
        rpy = tuple(float(a) for a in rng.uniform(-0.5, 0.5, 3))
        shape = ("box", "sphere", "cylinder", "capsule")[k % 4]
        size = {"box": tuple(rng.uniform(0.1, 0.5, 3)), "sphere": (rng.uniform(0.1, 0.3),)}.get(
            shape, (rng.uniform(0.05, 0.2), rng.uniform(0.2, 1.0))
        )
        out.append(Obstacle(shape, size=tuple(float(s) for s in size), pos=pos, rpy=rpy))
    return out


def poses(worlds: int, seed: int = 1):
    import numpy as np

    import jaxdrones as jd

    rng = np.random.default_rng(seed)
    config = jd.SimConfig(n_drones=1)
    rpy = np.concatenate([rng.uniform(-0.3, 0.3, (worlds, 1, 2)), rng.uniform(-np.pi, np.pi, (worlds, 1, 1))], -1)
    pos = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (worlds, 1, 3))
    return jd.init_state(config, pos=pos, rpy=rpy)


def time_jax(worlds: int, n_primitives: int, kinds, repeats: int) -> dict:
    """`jaxdrones.cameras.render` of ``kinds`` over ``worlds`` poses, one scene of ``n_primitives``."""
    import functools

    import jax

    import jaxdrones as jd
    from jaxdrones import cameras

    params = jd.load_params("cf2x")
    spec = cameras.CameraSpec()
    scene = cameras.make_scene(scene_obstacles(n_primitives))
    state = poses(worlds)
    kinds = tuple(kinds)
    render = functools.partial(cameras.render, spec, kinds=kinds)
    # The scene is an input (as a scene drawn per episode is), not a constant XLA would fold into the program.
    fn = jax.jit(jax.vmap(lambda s, p, q: render(s, params, p, q), in_axes=(None, 0, 0)))
    start = time.perf_counter()
    compiled = fn.lower(scene, state.pos, state.quat).compile()
    compile_s = time.perf_counter() - start
    best, s = timed(lambda: jax.block_until_ready(compiled(scene, state.pos, state.quat)), repeats)
    return {
        "sim": "jaxdrones",
        "worlds": worlds,
        "primitives": n_primitives,
        "kinds": list(kinds),
        "s": s,
        "best_s": best,
        "compile_s": compile_s,
        "frames_per_s": worlds / s,
    }


#: The envs timed with their cameras, and their primitives (besides the ground): the paper's gate (3 boxes) and the
#: ``avoid`` field (12 cylinders and 4 boxes, drawn per episode).
ENV_TASKS = {"fly_thru_gate": 3, "avoid": 16}


def time_env(task: str, worlds: int, repeats: int, steps: int = 30) -> dict:
    """Env steps/s of ``task`` with 64×48 depth and segmentation cameras rendered at every control step
    (``camera_freq = ctrl_freq = 30``) on the JAX backend: ``steps`` steps of ``jit(vmap(step))`` in one
    ``lax.scan``, zero actions (a drone holding its start)."""
    import jax
    import jax.numpy as jnp

    import jaxdrones as jd

    env = jd.make(task, vision=("depth", "seg"), ctrl_freq=30, camera_freq=30, image_size=(64, 48))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), worlds))
    actions = jnp.zeros((worlds, env.n_drones, env.action_size))

    @jax.jit
    def run(state):
        return jax.lax.scan(lambda s, _: (jax.vmap(env.step)(s, actions), None), state, None, length=steps)[0]

    best, s = timed(lambda: jax.block_until_ready(run(state)), repeats)
    return {
        "sim": "jaxdrones-env",
        "task": task,
        "worlds": worlds,
        "primitives": ENV_TASKS[task],
        "kinds": ["depth", "seg"],
        "s": s / steps,
        "best_s": best / steps,
        "frames_per_s": worlds * steps / s,
    }


def time_pybullet(worlds: int, n_primitives: int, renderer: str, repeats: int) -> dict:
    import jax
    import numpy as np

    import jaxdrones as jd

    params = jd.load_params("cf2x")
    state = jax.tree.map(np.asarray, poses(worlds))
    config = jd.SimConfig(n_drones=1)
    with jd.make_step(config, backend="pybullet", obstacles=scene_obstacles(n_primitives), renderer=renderer) as step:
        best, s = timed(lambda: step.camera_images(params, state), repeats)
    return {
        "sim": f"pybullet-{renderer}",
        "worlds": worlds,
        "primitives": n_primitives,
        "kinds": ["rgb", "depth", "seg"],
        "s": s,
        "best_s": best,
        "frames_per_s": worlds / s,
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax

    import jaxdrones  # noqa: F401  (before JAX starts: its XLA flags)

    load = os.getloadavg()
    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}, load {load}", flush=True)
    results = []
    for p in args.primitives:
        for w in args.worlds:
            r = time_jax(w, p, args.kinds, args.repeats)
            results.append(r)
            print(
                f"jax cameras P={p:3d} W={w:6d}: {r['frames_per_s']:12,.0f} "
                f"frames/s  ({r['s'] * 1e3:.1f} ms, compile {r['compile_s']:.1f} s)",
                flush=True,
            )
        if args.pybullet:
            for renderer in ("tiny", "egl"):
                try:
                    r = time_pybullet(16, p, renderer, args.repeats)
                except Exception as e:  # EGL may be missing on a machine
                    print(f"pybullet {renderer}: not run ({type(e).__name__}: {e})")
                    continue
                results.append(r)
                print(f"pybullet {renderer:4s} P={p:3d} W={16:6d}: {r['frames_per_s']:12,.0f} frames/s", flush=True)
    for task in ENV_TASKS:
        for w in args.worlds:
            r = time_env(task, w, args.repeats)
            results.append(r)
            print(f"env {task}, depth+seg every step, W={w:6d}: {r['frames_per_s']:12,.0f} env-steps/s", flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(
            {
                "jax": jax.__version__,
                "device": str(jax.devices()[0]),
                "load_start": load,
                "load_end": os.getloadavg(),
                "results": results,
            },
            f,
            indent=1,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
