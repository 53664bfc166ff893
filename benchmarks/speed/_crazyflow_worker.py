"""Worker of `envs.py`: env-steps/s of crazyflow's gymnasium vector env, run in crazyflow's own venv.

``gymnasium.make_vec("DroneReachPos-v0", num_envs=N, freq=<ctrl Hz>, device=<the JAX backend: "gpu" or "cpu">)``
(crazyflow's attitude control and default ``so_rpy`` model; its env class fixes the physics at 500 Hz, so a 30 Hz
step is 500 // 30 = 16 substeps, with a warning that 500 is not a multiple of 30), wrapped in crazyflow's
``NormalizeActions`` (actions in [-1, 1]) and gymnasium's ``JaxToNumpy`` (NumPy in and out), timed by
`envs.time_vector_env`, the loop that times the jaxdrones vector env. Prints one ``INFO {json}`` line, then one
``RESULT {json}`` line per size.

Usage (what `envs.py` runs)::

    benchmarks/.venv-crazyflow/bin/python benchmarks/speed/_crazyflow_worker.py --sizes 1 64 --repeats 3
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import sys
import warnings

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from envs import MAX_STEPS, MIN_STEPS, TARGET_ENV_STEPS, steps_for, time_vector_env

ENV_ID = "DroneReachPos-v0"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", required=True)
    parser.add_argument("--steps", type=int, default=None, help=f"default: {MIN_STEPS} to {MAX_STEPS}, by --target")
    parser.add_argument("--target", type=int, default=TARGET_ENV_STEPS, help="env-steps per timed run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--ctrl-freq", type=int, default=30)
    args = parser.parse_args(argv)

    import crazyflow  # noqa: F401  (registers the gymnasium ids)
    import gymnasium
    import jax
    from crazyflow.envs import NormalizeActions

    DEVICE = "gpu" if jax.default_backend() == "gpu" else "cpu"  # crazyflow's default is "cpu" on any machine
    from gymnasium.wrappers.vector import JaxToNumpy

    def make(n):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Simulation frequency should be a multiple")
            return JaxToNumpy(
                NormalizeActions(gymnasium.make_vec(ENV_ID, num_envs=n, freq=args.ctrl_freq, device=DEVICE))
            )

    env = make(1)
    sim = env.unwrapped.sim
    info = {
        "env_id": ENV_ID,
        "crazyflow": importlib.metadata.version("crazyflow"),
        "jax": jax.__version__,
        "gymnasium": gymnasium.__version__,
        "backend": jax.default_backend(),
        "ctrl_freq": args.ctrl_freq,
        "sim_freq": sim.freq,
        "substeps": env.unwrapped.n_substeps,
        "dynamics": str(sim.dynamics),
        "drone": str(sim.drone),
        "control": str(sim.control),
        "wrappers": ["NormalizeActions", "JaxToNumpy"],
    }
    env.close()
    print("INFO " + json.dumps(info), flush=True)
    for n in args.sizes:
        env = make(n)
        try:
            result = time_vector_env(env, n, steps_for(n, args.steps, args.target), args.repeats)
        finally:
            env.close()
        print(
            "RESULT "
            + json.dumps(
                {
                    "env": "crazyflow",
                    **result,
                    "sim_freq": info["sim_freq"],
                    "ctrl_freq": args.ctrl_freq,
                    "substeps": info["substeps"],
                }
            ),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
