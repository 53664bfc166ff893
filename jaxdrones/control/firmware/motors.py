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

from jaxdrones.physics.params import DroneParams, align_params

#: The Crazyflie 2.x's motor lag, s: a first-order lag of the logged thrust fitted on Neural-Swarm's flights
#: (docs/validation.md §3, "Drag and motor lag"). The firmware's gains need motors that lag (docs/firmware.md).
CRAZYFLIE_MOTOR_TAU = 0.061
#: The motors' commands' full scale (a 16-bit ratio).
UINT16_MAX = 65535
#: platform_defaults_cf2.h, ``CONFIG_CRAZYFLIE_21_PLUS`` (the default): the most thrust per motor, N, and the least a
#: running motor gives.
THRUST_MAX = 0.12
THRUST_MIN = 0.012817578393224994
#: The firmware's motor-voltage → thrust cubics, N per motor: (c0, c1, c2, c3) with f = c0 + c1 v + c2 v² + c3 v³,
#: and the yaw torque per newton of thrust (``THRUST2TORQUE``, m), by propeller (bitcraze/crazyflie-firmware
#: ``platform_defaults_cf2.h``, CONFIG_CRAZYFLIE_LEGACY_PROPELLERS, CONFIG_CRAZYFLIE_21_PLUS,
#: CONFIG_CRAZYFLIE_THRUST_UPGRADE_KIT). The Crazyflie 2.1 of 2021 flew the legacy propellers.
FIRMWARE_THRUST = {
    "legacy": (
        (-0.014830744918356092, 0.04724465241828281, -0.01847364358025878, 0.005960923942142),
        0.007350862856566459,
    ),
    "cf21_plus": (
        (-0.02476537915958403, 0.06523793527519485, -0.026792504967750107, 0.006776789303971145),
        0.0069928948992470565,
    ),
    "thrust_upgrade": (
        (0.006728127583707208, 0.01011557616217668, 0.010263198062061085, 0.0028358638322392503),
        0.0051648627905205285,
    ),
}


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
