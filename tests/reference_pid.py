"""Independent NumPy re-implementation of gym-pybullet-drones' DSLPIDControl (main branch).

It spells out the controller as docs/physics.md §0 and §12 describe it (section numbers below refer to that
document); nothing here imports jaxdrones. The class mirrors the original's structure: one controller per drone,
with ``reset()``, mutable integrals and ``last_rpy``, and ``computeControl`` split into the position and attitude
loops. The intrinsic 'XYZ' Euler conversions use scipy, as the original does; PyBullet's quaternion→matrix and
quaternion→Euler functions are spelled out from §0.3-0.4.

All arrays are float64. Quaternions are (x, y, z, w), body→world.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

#: Gravity of the original code, m/s² (§0.5).
G = 9.8

#: Mixers of the original (§12.1; main-branch cf2x motor order).
MIXERS = {
    "cf2x": np.array([[-0.5, -0.5, -1.0], [-0.5, 0.5, 1.0], [0.5, 0.5, -1.0], [0.5, -0.5, 1.0]]),
    "cf2p": np.array([[0.0, -1.0, -1.0], [1.0, 0.0, 1.0], [0.0, 1.0, -1.0], [-1.0, 0.0, 1.0]]),
}
#: (mass kg, kf N/rpm²) from the airframe table (§1).
AIRFRAMES = {"cf2x": (0.027, 3.16e-10), "cf2p": (0.027, 3.16e-10)}


def matrix_from_quaternion(q) -> np.ndarray:
    """``getMatrixFromQuaternion``: the rotation matrix of (x, y, z, w), normalised first (§0.3)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def euler_from_quaternion(q) -> np.ndarray:
    """``getEulerFromQuaternion`` including its gimbal-lock branch (§0.4)."""
    x, y, z, w = (float(v) for v in q)
    s = -2.0 * (x * z - w * y)
    if s <= -0.99999:
        return np.array([0.0, -math.pi / 2, 2 * math.atan2(x, -y)])
    if s >= 0.99999:
        return np.array([0.0, math.pi / 2, 2 * math.atan2(-x, y)])
    return np.array(
        [
            math.atan2(2 * (y * z + w * x), w * w - x * x - y * y + z * z),
            math.asin(s),
            math.atan2(2 * (x * y + w * z), w * w + x * x - y * y - z * z),
        ]
    )


class DSLPIDControl:
    """The paper's PID controller for one Crazyflie (§12)."""

    P_COEFF_FOR = np.array([0.4, 0.4, 1.25])
    I_COEFF_FOR = np.array([0.05, 0.05, 0.05])
    D_COEFF_FOR = np.array([0.2, 0.2, 0.5])
    P_COEFF_TOR = np.array([70000.0, 70000.0, 60000.0])
    I_COEFF_TOR = np.array([0.0, 0.0, 500.0])
    D_COEFF_TOR = np.array([20000.0, 20000.0, 12000.0])
    PWM2RPM_SCALE = 0.2685
    PWM2RPM_CONST = 4070.3
    MIN_PWM = 20000
    MAX_PWM = 65535

    def __init__(self, model: str = "cf2x"):
        if model not in MIXERS:
            raise ValueError(f"DSLPIDControl supports only cf2x and cf2p, got {model!r}")
        mass, self.KF = AIRFRAMES[model]
        self.GRAVITY = G * mass
        self.MIXER_MATRIX = MIXERS[model]
        self.reset()

    def reset(self):
        self.last_rpy = np.zeros(3)
        self.integral_pos_e = np.zeros(3)
        self.integral_rpy_e = np.zeros(3)

    def computeControl(
        self,
        control_timestep,
        cur_pos,
        cur_quat,
        cur_vel,
        cur_ang_vel,
        target_pos,
        target_rpy=np.zeros(3),
        target_vel=np.zeros(3),
        target_rpy_rates=np.zeros(3),
    ):
        """Returns (rpm (4), pos_e (3), yaw error)."""
        thrust, target_euler, pos_e = self._position(
            control_timestep,
            np.asarray(cur_pos),
            cur_quat,
            np.asarray(cur_vel),
            np.asarray(target_pos),
            np.asarray(target_rpy),
            np.asarray(target_vel),
        )
        rpm = self._attitude(control_timestep, thrust, cur_quat, target_euler, np.asarray(target_rpy_rates))
        cur_rpy = euler_from_quaternion(cur_quat)
        return rpm, pos_e, target_euler[2] - cur_rpy[2]

    def _position(self, dt, cur_pos, cur_quat, cur_vel, target_pos, target_rpy, target_vel):
        cur_rotation = matrix_from_quaternion(cur_quat)
        pos_e = target_pos - cur_pos
        vel_e = target_vel - cur_vel
        self.integral_pos_e = self.integral_pos_e + pos_e * dt
        self.integral_pos_e = np.clip(self.integral_pos_e, -2.0, 2.0)
        self.integral_pos_e[2] = np.clip(self.integral_pos_e[2], -0.15, 0.15)
        target_thrust = (
            self.P_COEFF_FOR * pos_e
            + self.I_COEFF_FOR * self.integral_pos_e
            + self.D_COEFF_FOR * vel_e
            + np.array([0.0, 0.0, self.GRAVITY])
        )
        scalar_thrust = max(0.0, float(np.dot(target_thrust, cur_rotation[:, 2])))
        thrust = (math.sqrt(scalar_thrust / (4 * self.KF)) - self.PWM2RPM_CONST) / self.PWM2RPM_SCALE
        target_z_ax = target_thrust / np.linalg.norm(target_thrust)
        target_x_c = np.array([math.cos(target_rpy[2]), math.sin(target_rpy[2]), 0.0])
        target_y_ax = np.cross(target_z_ax, target_x_c) / np.linalg.norm(np.cross(target_z_ax, target_x_c))
        target_x_ax = np.cross(target_y_ax, target_z_ax)
        target_rotation = np.vstack([target_x_ax, target_y_ax, target_z_ax]).transpose()
        target_euler = Rotation.from_matrix(target_rotation).as_euler("XYZ", degrees=False)
        return thrust, target_euler, pos_e

    def _attitude(self, dt, thrust, cur_quat, target_euler, target_rpy_rates):
        cur_rotation = matrix_from_quaternion(cur_quat)
        cur_rpy = euler_from_quaternion(cur_quat)
        target_quat = Rotation.from_euler("XYZ", target_euler, degrees=False).as_quat()
        w, x, y, z = target_quat  # the original's mislabelled unpacking; packed back in the same order
        target_rotation = Rotation.from_quat([w, x, y, z]).as_matrix()
        rot_matrix_e = target_rotation.T @ cur_rotation - cur_rotation.T @ target_rotation
        rot_e = np.array([rot_matrix_e[2, 1], rot_matrix_e[0, 2], rot_matrix_e[1, 0]])
        rpy_rates_e = target_rpy_rates - (cur_rpy - self.last_rpy) / dt
        self.last_rpy = cur_rpy
        self.integral_rpy_e = self.integral_rpy_e - rot_e * dt
        self.integral_rpy_e = np.clip(self.integral_rpy_e, -1500.0, 1500.0)
        self.integral_rpy_e[0:2] = np.clip(self.integral_rpy_e[0:2], -1.0, 1.0)
        target_torques = (
            -self.P_COEFF_TOR * rot_e + self.D_COEFF_TOR * rpy_rates_e + self.I_COEFF_TOR * self.integral_rpy_e
        )
        target_torques = np.clip(target_torques, -3200, 3200)
        pwm = thrust + self.MIXER_MATRIX @ target_torques
        pwm = np.clip(pwm, self.MIN_PWM, self.MAX_PWM)
        return self.PWM2RPM_SCALE * pwm + self.PWM2RPM_CONST


def velocity_targets(state_pos, state_quat, action, speed_limit):
    """The VEL action (§10.1): (target_pos, target_vel, target_rpy) for one drone."""
    v = np.asarray(action, dtype=np.float64)
    norm = np.linalg.norm(v[0:3])
    unit = v[0:3] / norm if norm != 0 else np.zeros(3)
    yaw = euler_from_quaternion(state_quat)[2]
    return np.asarray(state_pos), speed_limit * abs(v[3]) * unit, np.array([0.0, 0.0, yaw])
