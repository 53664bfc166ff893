"""Dynamic state of the drones of one or many worlds."""

from __future__ import annotations

from typing import Protocol

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from numpy.typing import ArrayLike

from jaxdrones.physics.rotations import quat_from_euler

#: Arm length of the Crazyflie used by the paper's default start pose (docs/physics.md §1.1, §14.4).
_CF2_ARM = 0.0397
#: Default start height of the paper's environments: collision half-height + 0.1 m (docs/physics.md §1.1).
DEFAULT_START_Z = 0.1125

#: Bits of `DroneState.contact`: what a drone touched during the last control step.
CONTACT_GROUND = 1
CONTACT_OBSTACLE = 2
CONTACT_DRONE = 4


@struct.dataclass
class DroneState:
    """State of ``D`` drones, with optional leading world axes ``[W, ...]``.

    Attributes:
        pos: f[..., D, 3] m, world frame, z up.
        quat: f[..., D, 4] (x, y, z, w), body→world, unit norm.
        vel: f[..., D, 3] m/s, world frame.
        ang_vel: f[..., D, 3] rad/s, body frame.
        rpm: f[..., D, 4] RPM, the clipped motor speeds applied in the last physics substep (zero at start).
            The drag model uses it, as the paper's code uses ``last_clipped_action`` (docs/physics.md §6.2).
        contact: i32[..., D] what the drone touched during the last control step, a bit mask of
            `CONTACT_GROUND` (1), `CONTACT_OBSTACLE` (2) and `CONTACT_DRONE` (4); 0 = nothing. The JAX backend
            models the ground only; the PyBullet backend reports all three.
    """

    pos: jax.Array
    quat: jax.Array
    vel: jax.Array
    ang_vel: jax.Array
    rpm: jax.Array
    contact: jax.Array

    @property
    def ground_contact(self) -> jax.Array:
        """bool[..., D], whether the drone touched the ground during the last control step."""
        return (self.contact & CONTACT_GROUND) != 0

    @property
    def collided(self) -> jax.Array:
        """bool[..., D], whether the drone touched an obstacle or another drone during the last control step."""
        return (self.contact & (CONTACT_OBSTACLE | CONTACT_DRONE)) != 0


@struct.dataclass
class Disturbance:
    """What acts on the drones from outside during a control step, held over its physics substeps: an input of
    the step (``step(params, state, rpm, disturbance)``), not part of the state. Each field is None (nothing) or
    an array with the state's leading shape ``[..., D, 3]``; `jaxdrones.envs.realism` draws them for the envs.

    Attributes:
        force: f[..., D, 3] N, world frame, at the centre of mass (e.g. a random disturbance force).
        torque: f[..., D, 3] N·m, body frame.
        wind: f[..., D, 3] m/s, world frame, the air's velocity: it acts through the drag model (paper eq. (drag)
            on the velocity relative to the air, docs/physics.md §6.2), so it needs ``SimConfig(drag=True)``.
    """

    force: jax.Array | None = None
    torque: jax.Array | None = None
    wind: jax.Array | None = None


def default_start_pos(n_drones: int) -> np.ndarray:
    """The paper's default start: drone i at (4iL, 4iL, 0.1125) m with the Crazyflie's L (docs/physics.md §1.1)."""
    i = np.arange(n_drones, dtype=np.float64)
    return np.stack([4 * i * _CF2_ARM, 4 * i * _CF2_ARM, np.full(n_drones, DEFAULT_START_Z)], axis=-1)


class HasNDrones(Protocol):
    """What `init_state` reads of its config: ``n_drones``, as a `jaxdrones.SimConfig` has it (the config module
    imports this one, so the hint names the attribute rather than the class)."""

    @property
    def n_drones(self) -> int:
        """The number of drones D."""


def init_state(
    config: HasNDrones,
    *,
    pos: ArrayLike | None = None,
    rpy: ArrayLike | None = None,
    quat: ArrayLike | None = None,
    vel: ArrayLike | None = None,
    ang_vel: ArrayLike | None = None,
    rpm: ArrayLike | None = None,
) -> DroneState:
    """Build a `DroneState` for ``config.n_drones`` drones, broadcasting the given fields to a common shape.

    Any field may carry leading world axes, e.g. ``pos`` f[W, D, 3]; all fields are broadcast to the same
    leading shape. Arrays use JAX's default float dtype.

    Args:
        config: a `SimConfig` (only ``n_drones`` is read).
        pos: f[..., D, 3] m, world frame. Default: the paper's start, drone i at (4iL, 4iL, 0.1125).
        rpy: f[..., D, 3] rad, roll/pitch/yaw (PyBullet convention). Mutually exclusive with ``quat``. Default 0.
        quat: f[..., D, 4] (x, y, z, w); normalised here.
        vel: f[..., D, 3] m/s, world frame. Default 0.
        ang_vel: f[..., D, 3] rad/s, body frame. Default 0.
        rpm: f[..., D, 4] RPM, the motor speeds of the previous step (used by drag). Default 0.

    Raises:
        ValueError: if a field's trailing shape is not (D, 3) / (D, 4), if leading shapes do not broadcast,
            if both ``rpy`` and ``quat`` are given, if a value is not finite, or if ``quat`` has zero norm.
    """
    n = config.n_drones
    dtype = jnp.result_type(float)
    if rpy is not None and quat is not None:
        raise ValueError("init_state: give either rpy or quat, not both")
    fields = {
        "pos": (default_start_pos(n) if pos is None else pos, 3),
        "vel": (np.zeros((n, 3)) if vel is None else vel, 3),
        "ang_vel": (np.zeros((n, 3)) if ang_vel is None else ang_vel, 3),
        "rpm": (np.zeros((n, 4)) if rpm is None else rpm, 4),
    }
    if quat is not None:
        fields["quat"] = (quat, 4)
    else:
        fields["rpy"] = (np.zeros((n, 3)) if rpy is None else rpy, 3)
    arrays = {}
    for name, (value, width) in fields.items():
        value = np.asarray(value, dtype=np.float64)
        if value.ndim < 2 or value.shape[-2:] != (n, width):
            raise ValueError(
                f"init_state: {name} must have shape [..., {n}, {width}] for n_drones={n}, got {value.shape}"
            )
        if not np.all(np.isfinite(value)):
            raise ValueError(f"init_state: {name} contains non-finite values")
        arrays[name] = value
    try:
        lead = np.broadcast_shapes(*(a.shape[:-2] for a in arrays.values()))
    except ValueError:
        raise ValueError(
            f"init_state: leading (world) shapes do not broadcast: { {k: v.shape for k, v in arrays.items()} }"
        ) from None
    if "quat" in arrays:
        norm = np.linalg.norm(arrays["quat"], axis=-1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError("init_state: quat must have non-zero norm")
        quat_arr = jnp.asarray(arrays.pop("quat") / norm, dtype=dtype)
    else:
        quat_arr = quat_from_euler(jnp.asarray(arrays.pop("rpy"), dtype=dtype))

    def full(x, width):
        return jnp.broadcast_to(jnp.asarray(x, dtype=dtype), lead + (n, width))

    return DroneState(
        pos=full(arrays["pos"], 3),
        quat=full(quat_arr, 4),
        vel=full(arrays["vel"], 3),
        ang_vel=full(arrays["ang_vel"], 3),
        rpm=full(arrays["rpm"], 4),
        contact=jnp.zeros(lead + (n,), dtype=jnp.int32),
    )
