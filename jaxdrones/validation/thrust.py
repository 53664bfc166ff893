"""The motors' thrust map against a thrust stand: the models' f = kf·rpm², the firmware's map from PWM and battery
voltage, and the maps fitted to the stand (docs/validation.md §2).

A Crazyflie flies its motors by PWM duty cycle; the motor voltage is the duty cycle times the battery voltage, and
the thrust follows the motor voltage. The firmware (bitcraze/crazyflie-firmware,
``src/platform/interface/platform_defaults_cf2.h``) models it per motor as a cubic in the motor voltage
v = vbat·pwm/65535, with Bitcraze's fitted coefficients for each propeller (`FIRMWARE_THRUST`). The simulator's
models take the motor speed: f = kf·rpm² with the URDF's kf (``cf2x`` and ``cf2p`` share the paper's 3.16e-10
N/rpm²). On a stand that logs thrust, PWM, battery voltage and each motor's RPM both maps can be scored, and fitted:
`fit_kf` (the square law), `fit_rpm` (the motor speed against the motor voltage, linear) and `fit_cubic` (the
firmware's form).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxdrones.control.firmware.motors import FIRMWARE_THRUST, UINT16_MAX
from jaxdrones.validation.readers import ThrustStand

#: PWM full scale (the firmware's 16-bit ratio).
PWM_MAX = float(UINT16_MAX)


def motor_voltage(pwm: np.ndarray, vbat: np.ndarray) -> np.ndarray:
    """The motor voltage, V: the duty cycle pwm / 65535 times the battery voltage ``vbat`` (V)."""
    return np.asarray(vbat) * np.asarray(pwm) / PWM_MAX


def firmware_thrust(pwm: np.ndarray, vbat: np.ndarray, propeller: str = "legacy") -> np.ndarray:
    """Thrust per motor, N, from PWM (0-65535) and battery voltage (V), as the firmware models it
    (`FIRMWARE_THRUST`); 0 where the cubic would be negative.

    Raises:
        ValueError: an unknown ``propeller``.
    """
    if propeller not in FIRMWARE_THRUST:
        raise ValueError(f"propeller must be one of {sorted(FIRMWARE_THRUST)}, got {propeller!r}")
    return np.maximum(np.polyval(FIRMWARE_THRUST[propeller][0][::-1], motor_voltage(pwm, vbat)), 0.0)


def tare(stand: ThrustStand) -> ThrustStand:
    """``stand`` with the load cell's zero offset removed: the median thrust of the samples where every motor stands
    still subtracted from every sample (the stand reads -1.06 g at rest in one of IMRCLab's sweeps).

    Raises:
        ValueError: no sample has every motor still.
    """
    still = np.all(stand.rpm == 0, axis=-1)
    if not still.any():
        raise ValueError(f"{stand.source!r}: no sample with the motors still, to take the stand's zero from")
    return dataclasses.replace(stand, thrust=stand.thrust - np.median(stand.thrust[still]))


def steady(stand: ThrustStand, settle: float = 0.5, min_samples: int = 4) -> np.ndarray:
    """bool[N]: the samples of ``stand`` at a steady command: of each run of consecutive rows at one nonzero PWM with
    the motors turning, the last ``1 − settle`` of the run (the load cell and the motors lag a step of the command by
    up to a few samples), runs of fewer than ``min_samples`` rows left out.

    Raises:
        ValueError: ``settle`` outside [0, 1) or ``min_samples`` < 1.
    """
    if not 0.0 <= settle < 1.0 or min_samples < 1:
        raise ValueError(f"settle must be in [0, 1) and min_samples >= 1, got {settle!r}, {min_samples!r}")
    pwm = stand.pwm
    starts = np.flatnonzero(np.r_[True, pwm[1:] != pwm[:-1]])
    ends = np.r_[starts[1:], len(pwm)]
    keep = np.zeros(len(pwm), bool)
    for a, b in zip(starts, ends, strict=True):
        if b - a >= min_samples and pwm[a] > 0:
            keep[a + int(np.ceil(settle * (b - a))) : b] = True
    return keep & np.all(stand.rpm > 0, axis=-1)


@dataclasses.dataclass(frozen=True)
class ThrustMap:
    """A fitted PWM → RPM → thrust map, per motor: rpm = a + b·v (v the motor voltage, V) and f = kf·rpm².

    Attributes:
        kf: N/rpm², the square law's constant.
        rpm_offset: rev/min, a.
        rpm_per_volt: rev/min per V, b.
    """

    kf: float
    rpm_offset: float
    rpm_per_volt: float

    def rpm(self, pwm: np.ndarray, vbat: np.ndarray) -> np.ndarray:
        """rev/min per motor from PWM and battery voltage (V)."""
        return np.maximum(self.rpm_offset + self.rpm_per_volt * motor_voltage(pwm, vbat), 0.0)

    def thrust(self, pwm: np.ndarray, vbat: np.ndarray) -> np.ndarray:
        """N per motor from PWM and battery voltage (V)."""
        return self.kf * self.rpm(pwm, vbat) ** 2


def fit_kf(rpm: np.ndarray, thrust: np.ndarray) -> float:
    """The least-squares kf (N/rpm²) of thrust = kf·Σ rpm_i² over the motors: ``rpm`` f[N, 4], ``thrust`` f[N] N."""
    s = np.sum(np.asarray(rpm, np.float64) ** 2, axis=-1)
    return float(s @ thrust / (s @ s))


def fit_thrust_map(stand: ThrustStand, mask: np.ndarray) -> ThrustMap:
    """`ThrustMap` fitted to the samples ``mask`` of ``stand``: kf by `fit_kf`, the speed's line against the motor
    voltage by least squares over every motor's samples."""
    v = np.repeat(motor_voltage(stand.pwm[mask], stand.vbat[mask]), 4)
    (b, a) = np.polyfit(v, stand.rpm[mask].reshape(-1), 1)
    return ThrustMap(fit_kf(stand.rpm[mask], stand.thrust[mask]), float(a), float(b))


def fit_cubic(stand: ThrustStand, mask: np.ndarray) -> tuple[float, float, float, float]:
    """The firmware's form refitted: (c0, c1, c2, c3) of thrust / 4 = c0 + c1 v + c2 v² + c3 v³ (N per motor, v the
    motor voltage) by least squares over the samples ``mask``."""
    v = motor_voltage(stand.pwm[mask], stand.vbat[mask])
    return tuple(float(c) for c in np.polyfit(v, stand.thrust[mask] / 4, 3)[::-1])


def rmse_percent(predicted: np.ndarray, measured: np.ndarray) -> float:
    """The root-mean-square error of ``predicted`` as a percentage of the mean of ``measured``."""
    measured = np.asarray(measured)
    return float(100.0 * np.sqrt(np.mean((np.asarray(predicted) - measured) ** 2)) / np.mean(measured))
