"""The firmware's power distribution for a quadrotor (``src/modules/src/power_distribution_quadrotor.c``,
bitcraze/crazyflie-firmware at 2a18fc29): a control output to the four motors' PWM, batched over leading axes.

Motor order and signs are the firmware's (M1 front right, then clockwise seen from above: M2 back right, M3 back
left, M4 front left), which is the order of the ``cf2x`` model's motors in jaxdrones (docs/physics.md §2).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control.firmware.motors import FIRMWARE_THRUST, THRUST_MAX, UINT16_MAX
from jaxdrones.control.firmware.types import Control

_F = np.float32
#: platform_defaults_cf2.h, ``CONFIG_CRAZYFLIE_21_PLUS`` (the default): arm length m and the yaw torque per newton
#: of thrust m.
ARM_LENGTH = 0.046
THRUST2TORQUE = FIRMWARE_THRUST["cf21_plus"][1]


def _trunc_i32(x: jax.Array) -> jax.Array:
    """C's float → int32 conversion (truncation toward zero)."""
    return jnp.trunc(x).astype(jnp.int32)


def power_distribution_legacy(control: Control) -> jax.Array:
    """``powerDistributionLegacy``: i32[..., 4] uncapped motor PWM from the legacy control (int16 roll, pitch, yaw
    and float thrust): r = roll / 2 and p = pitch / 2 truncated to int16, M1 = T − r + p + yaw, M2 = T − r − p − yaw,
    M3 = T + r − p + yaw, M4 = T + r + p − yaw, each truncated to int32."""
    r = jnp.trunc(control.roll.astype(jnp.float32) / 2.0)
    p = jnp.trunc(control.pitch.astype(jnp.float32) / 2.0)
    yaw = control.yaw.astype(jnp.float32)
    t = control.thrust
    motors = [t - r + p + yaw, t - r - p - yaw, t + r - p + yaw, t + r + p - yaw]
    return _trunc_i32(jnp.stack(motors, axis=-1))


def power_distribution_force_torque(
    thrust: jax.Array,
    torque: jax.Array,
    arm_length: float = ARM_LENGTH,
    thrust_max: float = THRUST_MAX,
    thrust_to_torque: float = THRUST2TORQUE,
) -> jax.Array:
    """``powerDistributionForceTorque``: i32[..., 4] uncapped motor PWM from a collective thrust f32[...] N and body
    torques f32[..., 3] N·m (the Brescianini controller's output): each motor's force, at least 0, as a share of
    ``thrust_max`` times 65535."""
    arm = _F(0.707106781) * _F(arm_length)
    roll = _F(0.25) / arm * torque[..., 0]
    pitch = _F(0.25) / arm * torque[..., 1]
    collective = _F(0.25) * thrust
    yaw = _F(0.25) * torque[..., 2] / _F(thrust_to_torque)
    forces = jnp.stack(
        [
            collective - roll - pitch - yaw,
            collective - roll + pitch + yaw,
            collective + roll + pitch - yaw,
            collective + roll - pitch + yaw,
        ],
        axis=-1,
    )
    forces = jnp.where(forces < 0.0, 0.0, forces)
    return _trunc_i32(forces / _F(thrust_max) * _F(UINT16_MAX))


def power_distribution_cap(uncapped: jax.Array, idle_thrust: int = 0) -> jax.Array:
    """``powerDistributionCap``: i32[..., 4] motor PWM (0-65535) from uncapped values: all lowered by the highest's
    excess over 65535, then each raised to at least ``idle_thrust`` (0 without arming, as ``cf2_defconfig``)."""
    highest = jnp.maximum(jnp.max(uncapped, axis=-1, keepdims=True), 0)
    reduction = jnp.where(highest > UINT16_MAX, highest - UINT16_MAX, 0)
    capped = uncapped - reduction
    return jnp.where(capped < idle_thrust, idle_thrust, capped).astype(jnp.int32)
