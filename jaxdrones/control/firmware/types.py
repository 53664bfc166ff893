"""The firmware's state, setpoint and control types as pytrees, and the firmware's state from a `DroneState`.

The Crazyflie firmware (bitcraze/crazyflie-firmware at 2a18fc29, ``src/modules/interface/stabilizer_types.h``)
passes its controllers a ``state_t`` (the estimator's attitude in degrees, in the legacy body frame whose pitch is
inverted; position and velocity in the world frame), a ``sensorData_t`` (the gyro in deg/s, body frame), a
``setpoint_t`` (what ``cflib`` sends: a mode per axis and the targets) and receives a ``control_t``. These pytrees
carry the fields the controllers read, with leading batch axes ``[..., ]`` (e.g. ``[W, D]``), float32 like the
firmware.

The frames are the firmware's and jaxdrones' alike: world x, y, z up; body x forward, y left, z up.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.physics.state import DroneState

#: ``stab_mode_t`` (stabilizer_types.h): an axis not controlled, controlled to an absolute value, or to a rate.
MODE_DISABLE, MODE_ABS, MODE_VELOCITY = 0, 1, 2
#: The fields of ``setpoint_mode_t``, in its order: the last axis of `Setpoint.mode`.
MODE_AXES = ("x", "y", "z", "roll", "pitch", "yaw", "quat")
RAD_TO_DEG = 57.29577951308232
_Tree = TypeVar("_Tree")


@struct.dataclass
class Setpoint:
    """``setpoint_t``: what the commander hands the controller.

    Attributes:
        mode: i32[..., 7], the mode (`MODE_DISABLE`, `MODE_ABS`, `MODE_VELOCITY`) of x, y, z, roll, pitch, yaw and
            quat (`MODE_AXES`).
        attitude: f32[..., 3] deg, roll, pitch, yaw (for modeAbs roll/pitch/yaw).
        attitude_rate: f32[..., 3] deg/s, roll, pitch, yaw rates (for modeVelocity roll/pitch/yaw).
        quat: f32[..., 4] (x, y, z, w), the attitude for mode quat (its yaw is used).
        thrust: f32[...] PWM units (0-65535), the thrust when z is modeDisable.
        position: f32[..., 3] m, world frame.
        velocity: f32[..., 3] m/s, world frame (body frame when ``velocity_body``).
        velocity_body: bool[...], the velocity is in the body (yaw) frame.
        acceleration: f32[..., 3] m/s², world frame, a feed-forward the Mellinger controller adds (the PID ignores
            it).
    """

    mode: jax.Array
    attitude: jax.Array
    attitude_rate: jax.Array
    quat: jax.Array
    thrust: jax.Array
    position: jax.Array
    velocity: jax.Array
    velocity_body: jax.Array
    acceleration: jax.Array

    @classmethod
    def zeros(cls, shape: tuple[int, ...] = ()) -> Setpoint:
        """A setpoint of zeros (every axis modeDisable) of batch shape ``shape``."""
        f = jnp.zeros((*shape, 3), jnp.float32)
        return cls(
            mode=jnp.zeros((*shape, 7), jnp.int32),
            attitude=f,
            attitude_rate=f,
            quat=jnp.zeros((*shape, 4), jnp.float32).at[..., 3].set(1.0),
            thrust=jnp.zeros(shape, jnp.float32),
            position=f,
            velocity=f,
            velocity_body=jnp.zeros(shape, bool),
            acceleration=f,
        )


@struct.dataclass
class FirmwareState:
    """``state_t`` and the gyro of ``sensorData_t``: what the controllers read of the estimate and the sensors.

    Attributes:
        attitude: f32[..., 3] deg, roll, pitch, yaw, with the pitch inverted (the legacy CF2 frame:
            ``state->attitude.pitch = -pitch``, kalman_core.c ``kalmanCoreExternalizeState``).
        quat: f32[..., 4] (x, y, z, w), body→world, not inverted (``attitudeQuaternion``).
        position: f32[..., 3] m, world frame.
        velocity: f32[..., 3] m/s, world frame.
        gyro: f32[..., 3] deg/s, body frame (``sensors->gyro``).
    """

    attitude: jax.Array
    quat: jax.Array
    position: jax.Array
    velocity: jax.Array
    gyro: jax.Array


@struct.dataclass
class Control:
    """``control_t`` in its legacy mode, the output of the PID and Mellinger controllers.

    Attributes:
        roll, pitch, yaw: i32[...] holding the firmware's int16 values (±32767), PWM units of the power
            distribution.
        thrust: f32[...] PWM units (0-65535).
    """

    roll: jax.Array
    pitch: jax.Array
    yaw: jax.Array
    thrust: jax.Array

    @classmethod
    def zeros(cls, shape: tuple[int, ...] = ()) -> Control:
        i = jnp.zeros(shape, jnp.int32)
        return cls(roll=i, pitch=i, yaw=i, thrust=jnp.zeros(shape, jnp.float32))


def select(cond: jax.Array, new: _Tree, old: _Tree) -> _Tree:
    """The pytree ``new`` where ``cond`` (bool[...], the batch's axes, broadcast over each leaf's trailing axes),
    else ``old``."""

    def pick(a, b):
        c = jnp.reshape(cond, jnp.shape(cond) + (1,) * (a.ndim - jnp.ndim(cond)))
        return jnp.where(c, a, b)

    return jax.tree.map(pick, new, old)


def every(period: int, tick: jax.Array | int, update: Callable[[], _Tree], held: _Tree) -> _Tree:
    """``update()`` on the ticks that are multiples of ``period`` (a loop of the firmware's that runs at its rate,
    ``RATE_DO_EXECUTE``), else ``held``. Only what runs is computed where it can be: a Python int ``tick`` decides
    when the program is traced, one traced tick for the whole batch through `jax.lax.cond`; per-drone ticks
    (i32[...]) compute ``update()`` and `select`."""
    if isinstance(tick, int | np.integer):
        return update() if tick % period == 0 else held
    tick = jnp.asarray(tick)
    if tick.ndim == 0:
        return jax.lax.cond(tick % period == 0, update, lambda: held)
    return select(tick % period == 0, update(), held)


def firmware_state(state: DroneState) -> FirmwareState:
    """The firmware's view of a `DroneState` as a perfect estimator would give it: float32, the attitude's Euler
    angles as ``kalmanCoreExternalizeState`` computes them from the quaternion (kalman_core.c, its ``atan2f`` and
    ``asinf`` forms), the gyro the body rates in deg/s.

    Args:
        state: `DroneState`, leading axes ``[..., D]``.

    Returns:
        `FirmwareState` with the same leading axes.
    """
    quat = state.quat.astype(jnp.float32)
    x, y, z, w = (quat[..., k] for k in range(4))
    yaw = jnp.arctan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z)
    pitch = jnp.arcsin(jnp.clip(-2 * (x * z - w * y), -1.0, 1.0))
    roll = jnp.arctan2(2 * (y * z + w * x), w * w - x * x - y * y + z * z)
    deg = jnp.float32(RAD_TO_DEG)
    return FirmwareState(
        attitude=jnp.stack([roll * deg, -pitch * deg, yaw * deg], axis=-1),
        quat=quat,
        position=state.pos.astype(jnp.float32),
        velocity=state.vel.astype(jnp.float32),
        gyro=state.ang_vel.astype(jnp.float32) * deg,
    )
