"""Simulation backends: the pure-JAX core (`jaxdrones.sim.JaxStep`) and PyBullet
(`jaxdrones.backends.pybullet.PyBulletStep`, for collisions and rendering).

Both are called as ``step(params, state, rpm) -> state`` and declare what else they can do: ``config`` (the
`SimConfig`), ``has_cameras`` (whether ``camera_images`` and ``render`` exist) and ``close()``.
"""

#: Physics backends accepted by `jaxdrones.sim.make_step`.
BACKENDS = ("jax", "pybullet")
#: Renderers of the PyBullet backend: TinyRenderer (CPU) or OpenGL through EGL (headless GPU).
RENDERERS = ("tiny", "egl")
