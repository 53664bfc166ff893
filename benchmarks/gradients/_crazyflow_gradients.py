"""Worker of `gradients.py`: the same gradient timings on crazyflow 0.4.0, run in crazyflow's own venv.

crazyflow's ``Sim(n_worlds=W, n_drones=1, dynamics="first_principles", control="rotor_vel", freq=240)`` (its
Crazyflie 2.1 model with rotor drag and first-order rotor dynamics, no ground effect), stepped by its pure step
function ``sim._step(data, 1)`` under ``lax.scan`` with the RPM command set by ``crazyflow.sim.functional
.rotor_vel_control`` each step; commands within 2 % of its hover RPM, starts and loss as in `gradients.py`,
gradients w.r.t. the commands and the initial position and velocity. Prints one ``INFO {json}`` line, then one
``RESULT {json}`` line per (horizon, worlds).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from gradients import SIM_FREQ, measure, start_positions, trajectory_loss


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--horizons", type=int, nargs="+", required=True)
    parser.add_argument("--worlds", type=int, nargs="+", required=True)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np
    from crazyflow.sim import Sim
    from crazyflow.sim import functional as F
    from crazyflow.sim import sim as sim_module

    print(
        "INFO "
        + json.dumps(
            {
                "crazyflow": importlib.metadata.version("crazyflow"),
                "jax": jax.__version__,
                "dynamics": "first_principles",
                "control": "rotor_vel",
                "freq": SIM_FREQ,
            }
        ),
        flush=True,
    )
    for horizon in args.horizons:
        for worlds in args.worlds:
            sim = Sim(
                n_worlds=worlds,
                n_drones=1,
                dynamics="first_principles",
                control="rotor_vel",
                freq=SIM_FREQ,
                device="gpu" if jax.default_backend() == "gpu" else "cpu",
            )  # crazyflow's default: "cpu"
            constants = sim_module.load_dynamics_params(sim.dynamics, sim.drone)
            hover = float(
                sim_module.motor_force2rotor_vel(np.asarray(constants["mass"] * 9.81 / 4), constants["rpm2thrust"])
            )
            data = sim.data.replace(states=sim.data.states.replace(pos=jnp.asarray(start_positions(np, worlds))))
            state = {"pos": data.states.pos, "vel": data.states.vel}
            noise = np.random.default_rng(1).standard_normal((horizon, worlds, 1, 4))
            commands = jnp.asarray(hover * (1 + 0.02 * noise), jnp.float32)
            step = sim._step

            def loss(commands, state, data=data, step=step):
                def body(d, rpm):
                    d = step(F.rotor_vel_control(d, rpm), 1)
                    return d, (d.states.pos, d.states.vel)

                _, (pos, vel) = jax.lax.scan(body, data.replace(states=data.states.replace(**state)), commands)
                return trajectory_loss(jnp, pos, vel)

            result = measure(jax, loss, commands, state, horizon, worlds, args.repeats)
            print(
                "RESULT " + json.dumps({"sim": "crazyflow", "caller": "user_scan", "remat": False, **result}),
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
