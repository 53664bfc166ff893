"""Worked examples of the paper and beyond, each a module with a ``main`` (``python -m jaxdrones.examples.NAME``):
the PID flights, ground effect, downwash, the velocity task, the camera scene, the MPC, the paper's two-drone
workflow on RLlib (`rllib_leader_follower`, the rllib extra) and the Crazyflie firmware's C in the loop
(`firmware_in_the_loop`, with the firmware's sources). Only the command line imports them (the layers of
pyproject.toml's import contract)."""
