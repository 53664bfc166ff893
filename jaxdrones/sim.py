"""The functional step's one door: `make_step` builds the control step of the pure-JAX core
(`jaxdrones.physics.step.JaxStep`) or of the PyBullet backend (`jaxdrones.backends.pybullet.PyBulletStep`) behind
the same signature. Also re-exports the core's `rollout`, `SimConfig` and `StepFn`, and `shard_worlds`
(`jaxdrones.devices`), where they have always been imported from.
"""

from __future__ import annotations

from typing import Any

from jaxdrones.backends import BACKENDS
from jaxdrones.devices import shard_worlds
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.state import Disturbance
from jaxdrones.physics.step import JaxStep, StepFn, physics_substep_c, rollout

__all__ = ["Disturbance", "JaxStep", "SimConfig", "StepFn", "make_step", "physics_substep_c", "rollout", "shard_worlds"]


def make_step(config: SimConfig, backend: str = "jax", **options: Any) -> StepFn:
    """Build the control step ``step(params, state, rpm) -> state`` for a config.

    One call holds ``rpm`` over ``config.n_substeps`` physics substeps (run under ``lax.scan``). RPMs are clipped
    to [0, max_rpm] as the paper's code does (smoothly or straight-through with ``config.kinks``, see
    `jaxdrones.physics.kinks`). The step is pure (no hidden state, no key), jitted, and works under
    ``jit``, ``vmap`` and ``grad``; arrays may carry leading world axes ``[W, D, ...]``. Worlds spread over several
    devices with `shard_worlds` are stepped on each device in parallel, in the same jitted call.

    Args:
        config: SimConfig.
        backend: ``"jax"`` (this pure-JAX core) or ``"pybullet"`` (`jaxdrones.backends.pybullet.PyBulletStep`:
            collisions with the ground, obstacles and other drones, cameras; not differentiable).
        **options: PyBullet backend options: ``obstacles`` (None, True/"paper", or a sequence of
            `jaxdrones.scene.Obstacle` / URDF paths), ``damping`` (keep Bullet's velocity damping,
            default False), ``gui`` (show world 0 in PyBullet's GUI), ``renderer`` ("tiny" or "egl").

    Returns:
        The backend's step (a `JaxStep` or a `jaxdrones.backends.pybullet.PyBulletStep`, both with ``config``,
        ``has_cameras`` and ``close``), called as ``step(params, state, rpm, disturbance=None)`` where ``rpm`` is
        f[..., D, 4] in RPM (ints are cast to the state's float dtype) with the leading shape of ``state``, and
        ``disturbance`` an optional `jaxdrones.physics.state.Disturbance` (external force, torque, wind) held over the
        step. ``state.contact`` reports ground contact during this step. With ``config.motor_dynamics`` the
        returned ``state.rpm`` is the motors' actual speeds at the end of the step.

    Raises:
        ValueError: unknown backend or option; and, when ``step`` is called, an ``rpm``, ``state`` or ``disturbance``
            of the wrong shape or a non-numeric dtype, a wind without ``config.drag``, or (with
            ``config.motor_dynamics``, on concrete params) a negative or non-finite motor time constant. Called on
            concrete arrays (outside ``jit``), a non-finite ``rpm`` raises too; inside ``jit`` NaN propagates into
            the state (the envs detect and report it).
        ModuleNotFoundError: ``backend="pybullet"`` without pybullet installed (`jaxdrones.backends.require_pybullet`).
    """
    if not isinstance(config, SimConfig):
        raise ValueError(f"make_step expects a SimConfig, got {type(config).__name__}")
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}: expected one of {BACKENDS}")
    if backend == "pybullet":  # pybullet is imported only when this backend is asked for
        from jaxdrones.backends.pybullet import OPTIONS, PyBulletStep

        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise ValueError(f"unknown PyBullet backend option(s) {unknown}: expected some of {OPTIONS}")
        return PyBulletStep(config, **options)
    if options:
        raise ValueError(f"the jax backend takes no options, got {sorted(options)} (they are PyBullet's)")
    return JaxStep(config)
