"""Host-side checks of RPM commands, states and params, shared by the simulation backends (`jaxdrones.sim` and
`jaxdrones.backends.pybullet`); they raise `ValueError` at the API boundary."""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from jaxdrones.physics.params import DroneParams, params_batch_shape
from jaxdrones.physics.state import Disturbance, DroneState

if TYPE_CHECKING:
    from jaxdrones.physics.config import SimConfig


def check_rpm(config: SimConfig, state: DroneState, rpm: ArrayLike) -> jax.Array | np.ndarray:
    """Validate an RPM command against the config and state; returns it as a float array of the state's dtype.

    Raises:
        ValueError: see `make_step`.
    """
    dtype = rpm.dtype if hasattr(rpm, "dtype") else np.asarray(rpm).dtype
    check_rpm_shape(config, state, np.shape(rpm), dtype)
    if isinstance(rpm, jax.core.Tracer):
        return rpm.astype(state.pos.dtype)
    # On the host, in NumPy (a JAX array on the CPU is read without a copy): an eager jnp conversion would cost a
    # dispatch per call, several times the jitted step itself in a Python control loop.
    host = np.asarray(rpm)
    if not np.all(np.isfinite(host)):
        raise ValueError("rpm contains NaN or inf")
    if isinstance(rpm, jax.Array):
        return rpm if rpm.dtype == state.pos.dtype else rpm.astype(state.pos.dtype)
    return host.astype(state.pos.dtype, copy=False)


def check_state_shape(config: SimConfig, state: DroneState) -> tuple[int, ...]:
    """Check that ``state`` has pos f[..., D, 3] and quat f[..., D, 4] with D = ``config.n_drones`` and the same
    leading shape; returns that shape ``[..., D]``.

    Raises:
        ValueError: on other shapes.
    """
    n = config.n_drones
    pos, quat = np.shape(state.pos), np.shape(state.quat)
    if pos[-2:] != (n, 3) or quat[-2:] != (n, 4) or pos[:-1] != quat[:-1]:
        raise ValueError(
            f"state has pos {pos} and quat {quat}; expected [..., {n}, 3] and [..., {n}, 4] with the "
            f"same leading shape, for n_drones={n} (build it with jd.init_state(config, ...))"
        )
    return tuple(pos[:-1])


def check_rpm_shape(config: SimConfig, state: DroneState, shape: tuple[int, ...], dtype: DTypeLike) -> None:
    """Check an RPM command's shape and dtype (and the state's drone axis) against the config and state.

    Raises:
        ValueError: see `make_step`.
    """
    n = config.n_drones
    check_state_shape(config, state)
    if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)) or np.dtype(dtype) == np.bool_:
        raise ValueError(f"rpm must be a real (float or int) array in RPM, got dtype {dtype}")
    expected = state.rpm.shape
    if tuple(shape) != tuple(expected):
        raise ValueError(
            f"rpm must have shape {expected} ([..., n_drones={n}, 4] motor speeds in RPM, with the "
            f"state's leading shape {expected[:-2]}), got {tuple(shape)}"
        )


def check_params_batch(params: DroneParams, state: DroneState) -> None:
    """Check that the params' batch axes line up with the state's ``[..., D]`` (right-aligned broadcasting).

    Per-drone params are ``[D]`` or ``[W, D]``; per-world params are ``[W, 1]`` (or used under ``vmap``).

    Raises:
        ValueError: if the params' batch shape does not broadcast to the state's leading shape ``[..., D]``.
    """
    lead = state.pos.shape[:-1]
    batch = params_batch_shape(params)
    try:
        ok = np.broadcast_shapes(batch, lead) == lead
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(
            f"params have batch shape {batch}, which does not line up with the state's [..., D] = "
            f"{lead}: batched params are right-aligned with the drone axis, so per-drone params are "
            f"[D] or [W, D] and per-world params [W, 1] (or vmap the step over worlds)"
        )


def check_disturbance(config: SimConfig, state: DroneState, disturbance: Disturbance | None) -> Disturbance | None:
    """Validate a step's `Disturbance` (or None); returns it with each given field broadcast to the state's
    ``[..., D, 3]`` in the state's dtype.

    Raises:
        ValueError: not a `Disturbance`; a field that is not a real array broadcasting to ``[..., D, 3]``; a
            non-finite value (checked on concrete arrays); a ``wind`` without ``config.drag`` (the wind acts
            through the drag model, so it would do nothing).
    """
    if disturbance is None:
        return None
    if not isinstance(disturbance, Disturbance):
        raise ValueError(
            f"disturbance must be a jaxdrones.Disturbance(force=, torque=, wind=) or None, got "
            f"{type(disturbance).__name__}"
        )
    if disturbance.wind is not None and not config.drag:
        raise ValueError(
            "disturbance.wind acts through the drag model (paper eq. (drag) on the velocity relative "
            "to the air): it needs SimConfig(drag=True)"
        )
    shape = tuple(np.shape(state.pos))
    fields = {}
    for name, unit in (("force", "N, world frame"), ("torque", "N·m, body frame"), ("wind", "m/s, world frame")):
        value = getattr(disturbance, name)
        if value is None:
            fields[name] = None
            continue
        dtype = value.dtype if hasattr(value, "dtype") else np.asarray(value).dtype
        if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)) or dtype == np.bool_:
            raise ValueError(f"disturbance.{name} must be a real array ({unit}), got dtype {dtype}")
        try:
            ok = np.broadcast_shapes(np.shape(value), shape) == shape
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"disturbance.{name} must broadcast to the state's {shape} ([..., n_drones, 3], "
                f"{unit}), got {np.shape(value)}"
            )
        if not isinstance(value, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(value))):
            raise ValueError(f"disturbance.{name} contains NaN or inf")
        fields[name] = jnp.broadcast_to(jnp.asarray(value, state.pos.dtype), shape)
    return Disturbance(**fields)


def check_motor_time_constants(params: DroneParams) -> None:
    """With `SimConfig.motor_dynamics`: the params' ``motor_tau_up`` and ``motor_tau_down`` must be finite and
    >= 0 s (checked on concrete arrays; traced ones pass).

    Raises:
        ValueError: a negative or non-finite time constant.
    """
    for name in ("motor_tau_up", "motor_tau_down"):
        value = getattr(params, name)
        if isinstance(value, jax.core.Tracer):
            continue
        host = np.asarray(value)
        if not np.all(np.isfinite(host)) or np.any(host < 0):
            raise ValueError(
                f"DroneParams.{name} must be finite time constants >= 0 s (0: instant motors), got {host.tolist()}"
            )
