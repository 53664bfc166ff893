"""Simulation backends other than the pure-JAX core (`jaxdrones.sim`): PyBullet, for collisions and rendering."""
