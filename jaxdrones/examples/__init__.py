"""Worked examples of the paper and beyond, each a module with a ``main`` (``python -m jaxdrones.examples.NAME``):
the PID flights, ground effect, downwash, the velocity task, the camera scene and the MPC."""
