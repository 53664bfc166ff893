"""Simulation backends: the pure-JAX core (`jaxdrones.sim.JaxStep`) and PyBullet
(`jaxdrones.backends.pybullet.PyBulletStep`, for collisions and rendering).

Both are called as ``step(params, state, rpm) -> state`` and declare what else they can do: ``config`` (the
`SimConfig`), ``has_cameras`` (whether ``camera_images`` and ``render`` exist) and ``close()``.
"""

from types import ModuleType

#: Physics backends accepted by `jaxdrones.sim.make_step`.
BACKENDS = ("jax", "pybullet")
#: Renderers of the PyBullet backend: TinyRenderer (CPU) or OpenGL through EGL (headless GPU).
RENDERERS = ("tiny", "egl")

#: How to install pybullet, in every error that asks for it.
PYBULLET_INSTALL = (
    'pip install pybullet, or the pybullet extra (pip install ".[pybullet]" from a clone): a wheel '
    "on Python 3.11; on Python >= 3.12 pip builds it from source (a C++ build of a few minutes)"
)


def require_pybullet() -> ModuleType:
    """Import and return the ``pybullet`` module, which only ``backend="pybullet"`` and the PyBullet examples use.

    Raises:
        ModuleNotFoundError: if pybullet is not installed, in one line naming the extra that installs it.
    """
    try:
        import pybullet
    except ModuleNotFoundError as e:
        if e.name != "pybullet":
            raise
        raise ModuleNotFoundError(
            f"the PyBullet backend needs pybullet, which is not installed: {PYBULLET_INSTALL}", name="pybullet"
        ) from None
    return pybullet
