"""The Crazyflie 2.1's motor map as the firmware drives it: PWM → thrust → motor speed.

With ``CONFIG_ENABLE_THRUST_BAT_COMPENSATED`` (on in ``cf2_defconfig``), ``motorsCompensateBatteryVoltage``
(bitcraze/crazyflie-firmware at 2a18fc29, ``src/drivers/src/motors.c``) reads a motor's command as a thrust,
``pwm / 65535 · THRUST_MAX``, and inverts its cubic fit of thrust against motor voltage to reach that thrust at the
battery's voltage; a command under ``THRUST_MIN`` stops the motor. So the thrust is linear in the command whatever the
battery (while its voltage lasts), and the motor speed follows from the airframe's thrust coefficient, f = kf·rpm².
The constants are platform_defaults_cf2.h's for the 2.1+ propellers (the default); docs/validation.md §1 holds them
against a thrust stand.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxdrones.control.firmware.power import THRUST_MAX, UINT16_MAX
from jaxdrones.physics.params import DroneParams, align_params

#: platform_defaults_cf2.h (2.1+ propellers): the least thrust a running motor gives, N.
THRUST_MIN = 0.012817578393224994


def motor_thrust(pwm: jax.Array) -> jax.Array:
    """f32[..., 4] N: each motor's thrust for its command (PWM units, 0-65535), 0 under `THRUST_MIN`."""
    thrust = jnp.asarray(pwm, jnp.float32) / jnp.float32(UINT16_MAX) * jnp.float32(THRUST_MAX)
    return jnp.where(thrust < THRUST_MIN, 0.0, thrust)


def motor_rpm(params: DroneParams, pwm: jax.Array) -> jax.Array:
    """f[..., D, 4] RPM: the motor speeds that give `motor_thrust` with ``params.kf`` (√(f / kf)).

    Args:
        params: `DroneParams` of the drones (its ``kf``, batch axes broadcasting against ``[..., D]``).
        pwm: i32 or f32[..., D, 4], the power distribution's motor commands.
    """
    params = align_params(params, pwm.ndim - 1)
    return jnp.sqrt(motor_thrust(pwm) / params.kf[..., None])
