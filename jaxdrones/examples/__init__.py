"""Worked examples of the paper and beyond, each a module with a ``main`` (``python -m jaxdrones.examples.NAME``):
the PID flights, ground effect, downwash, the velocity task, the camera scene, the MPC and the paper's two-drone
workflow on RLlib (`rllib_leader_follower`, the rllib extra). Only the command line imports them (the layers of
pyproject.toml's import contract)."""
