"""Independent NumPy re-derivation of gym-pybullet-drones' explicit dynamics (DYN mode, main branch).

It spells out the original's equations as docs/physics.md §1, §1.1, §2, §3.1 and §4 state them (section numbers
below refer to that document); nothing here imports jaxdrones. Constants are typed in from the airframe table (§1),
derived constants follow §1.1, the per-model thrust/torque formulas are spelled out as in §3.1, and one physics step
is the semi-implicit Euler update of §4 with the Λ-matrix quaternion map of §4.6, followed by the normalisation
PyBullet applies on write-back (§4.7).

All arrays are float64. Quaternions are (x, y, z, w), body→world; ``ang_vel`` is the body-frame rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Gravity of the original code, m/s² (§0.5).
G = 9.8


@dataclass(frozen=True)
class Airframe:
    """The §1 table for one model (SI units; kf in N/rpm², km in N·m/rpm²)."""

    name: str
    mass: float
    arm: float
    inertia: tuple[float, float, float]
    kf: float
    km: float
    thrust2weight: float
    prop_radius: float
    gnd_eff_coeff: float = 11.36859
    collision_height: float = 0.025

    @property
    def weight(self) -> float:
        return G * self.mass

    @property
    def hover_rpm(self) -> float:
        return math.sqrt(self.weight / (4 * self.kf))

    @property
    def max_rpm(self) -> float:
        return math.sqrt(self.thrust2weight * self.weight / (4 * self.kf))

    @property
    def max_thrust(self) -> float:
        return 4 * self.kf * self.max_rpm**2

    @property
    def max_xy_torque(self) -> float:
        if self.name == "cf2p":
            return self.arm * self.kf * self.max_rpm**2
        return 2 * self.arm * self.kf * self.max_rpm**2 / math.sqrt(2)

    @property
    def max_z_torque(self) -> float:
        return 2 * self.km * self.max_rpm**2

    @property
    def gnd_eff_h_clip(self) -> float:
        return (self.prop_radius / 4) * math.sqrt(15 * self.max_rpm**2 * self.kf * self.gnd_eff_coeff / self.max_thrust)


AIRFRAMES = {
    "cf2x": Airframe("cf2x", 0.027, 0.0397, (1.4e-5, 1.4e-5, 2.17e-5), 3.16e-10, 7.94e-12, 2.25, 2.31348e-2),
    "cf2p": Airframe("cf2p", 0.027, 0.0397, (2.3951e-5, 2.3951e-5, 3.2347e-5), 3.16e-10, 7.94e-12, 2.25, 2.31348e-2),
    "racer": Airframe("racer", 0.830, 0.109, (0.003113, 0.003113, 0.003113), 8.47e-9, 2.13e-11, 4.17, 12.7e-2),
}

#: The §1.1 derived-constant table, as printed in docs/physics.md.
DERIVED_TABLE = {
    "cf2x": dict(
        hover_rpm=14468.4292,
        max_rpm=21702.6438,
        max_thrust=0.59535,
        max_xy_torque=8.35637e-3,
        max_z_torque=7.47956e-3,
        gnd_eff_h_clip=0.0377637,
    ),
    "cf2p": dict(
        hover_rpm=14468.4292,
        max_rpm=21702.6438,
        max_thrust=0.59535,
        max_xy_torque=5.90885e-3,
        max_z_torque=7.47956e-3,
        gnd_eff_h_clip=0.0377637,
    ),
    "racer": dict(
        hover_rpm=15494.6005,
        max_rpm=31640.8696,
        max_thrust=33.91878,
        max_xy_torque=1.307139,
        max_z_torque=4.264876e-2,
        gnd_eff_h_clip=0.2073064,
    ),
}

#: §2, the positive-torque RPM patterns of the mixers: raise the + motors, lower the - motors.
POSITIVE_TORQUE_PATTERNS = {
    "cf2x": {"roll": (-1, -1, 1, 1), "pitch": (-1, 1, 1, -1), "yaw": (-1, 1, -1, 1)},
    "cf2p": {"roll": (0, 1, 0, -1), "pitch": (-1, 0, 1, 0), "yaw": (-1, 1, -1, 1)},
    "racer": {"roll": (1, 1, -1, -1), "pitch": (-1, 1, 1, -1), "yaw": (1, -1, 1, -1)},
}


def forces_torques(frame: Airframe, rpm: np.ndarray) -> tuple[float, np.ndarray]:
    """Total body-z thrust (N) and body torque (N·m) of §3.1 for one drone; rpm f[4] already clipped."""
    f0, f1, f2, f3 = frame.kf * rpm**2
    t0, t1, t2, t3 = frame.km * rpm**2
    thrust = f0 + f1 + f2 + f3
    arm = frame.arm
    if frame.name == "cf2x":
        tau_x = arm / math.sqrt(2) * (-f0 - f1 + f2 + f3)
        tau_y = arm / math.sqrt(2) * (-f0 + f1 + f2 - f3)
        tau_z = -t0 + t1 - t2 + t3
    elif frame.name == "racer":
        tau_x = arm / math.sqrt(2) * (f0 + f1 - f2 - f3)
        tau_y = arm / math.sqrt(2) * (-f0 + f1 + f2 - f3)
        tau_z = -(-t0 + t1 - t2 + t3)
    elif frame.name == "cf2p":
        tau_x = arm * (f1 - f3)
        tau_y = arm * (f2 - f0)
        tau_z = -t0 + t1 - t2 + t3
    else:
        raise KeyError(frame.name)
    return thrust, np.array([tau_x, tau_y, tau_z])


def rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (world = R @ body) of an (x, y, z, w) quaternion, normalised first (§0.3)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def integrate_quat(q: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """§4.6: (I cos θ + (2/|ω|) Λ sin θ) q with θ = |ω| dt / 2; no-op when |ω| ≤ 1e-8 (``isclose(|ω|, 0)``)."""
    norm = np.linalg.norm(omega)
    if np.isclose(norm, 0):
        return q
    wx, wy, wz = omega
    lam = 0.5 * np.array(
        [
            [0, wz, -wy, wx],
            [-wz, 0, wx, wy],
            [wy, -wx, 0, wz],
            [-wx, -wy, -wz, 0],
        ]
    )
    theta = norm * dt / 2
    return (np.eye(4) * math.cos(theta) + 2 / norm * lam * math.sin(theta)) @ q


def step(frame: Airframe, pos, quat, vel, ang_vel, rpm, dt: float):
    """One DYN physics step (§4) of one drone; returns (pos, quat, vel, ang_vel) after write-back."""
    rpm = np.clip(np.asarray(rpm, dtype=np.float64), 0.0, frame.max_rpm)
    rot = rotmat(quat)
    thrust, torque = forces_torques(frame, rpm)
    force = rot @ np.array([0.0, 0.0, thrust]) - np.array([0.0, 0.0, frame.mass * G])
    inertia = np.diag(frame.inertia)
    torque = torque - np.cross(ang_vel, inertia @ ang_vel)
    ang_acc = np.linalg.solve(inertia, torque)
    acc = force / frame.mass
    vel = vel + dt * acc
    ang_vel = ang_vel + dt * ang_acc
    pos = pos + dt * vel
    quat = integrate_quat(quat, ang_vel, dt)
    quat = quat / np.linalg.norm(quat)  # PyBullet normalises on resetBasePositionAndOrientation
    return pos, quat, vel, ang_vel


def simulate(frame: Airframe, pos, quat, vel, ang_vel, rpms, sim_freq: int, ctrl_freq: int):
    """Run ``len(rpms)`` control steps, each holding its RPM for sim_freq // ctrl_freq physics steps.

    Returns:
        dict of arrays with a leading time axis [T, ...]: the state after each control step.
    """
    assert sim_freq % ctrl_freq == 0
    dt = 1.0 / sim_freq
    state = tuple(np.asarray(x, dtype=np.float64) for x in (pos, quat, vel, ang_vel))
    out = {k: [] for k in ("pos", "quat", "vel", "ang_vel")}
    for rpm in rpms:
        for _ in range(sim_freq // ctrl_freq):
            state = step(frame, *state, rpm, dt)
        for k, v in zip(out, state, strict=True):
            out[k].append(v)
    return {k: np.stack(v) for k, v in out.items()}
