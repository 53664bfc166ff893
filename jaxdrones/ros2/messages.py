"""ROS 2 messages of the drones' states and commands, as plain field trees (no ROS needed to build or check them).

Each ``*_fields`` function returns a message's fields as nested dicts (the message's field names; NumPy arrays for
arrays), complete, so that the same tree fills an rclpy message (`fill_rclpy`) or builds a rosbags message
(`build_rosbags`, which serialises to CDR exactly as rclpy does): the conversion is tested without ROS.

Messages (per drone, world frame ``world`` unless stated):

- the paper's ``obs``: ``std_msgs/Float32MultiArray`` of 20 floats (`OBS_NAMES`): pos (m), quat (x, y, z, w), rpy
  (rad, PyBullet's ``getEulerFromQuaternion``), vel (m/s, world), ang_vel (rad/s, body), and the RPM applied
  during the last step (gym-pybullet-drones' ROS 2 wrapper publishes the same 20 entries per drone);
- ``geometry_msgs/PoseStamped``: position and orientation;
- ``nav_msgs/Odometry``: pose in ``world``, twist in the body frame (``child_frame_id``, REP 105: linear velocity
  Rᵀv, angular velocity ω), covariances zero (the simulator knows the state exactly);
- commands: ``action`` (``Float32MultiArray`` of 4 RPM, as the paper's node), ``cmd_vel`` (``geometry_msgs/Twist``:
  linear velocity in m/s, world frame) and ``cmd_position`` (``geometry_msgs/PoseStamped``: a position and yaw to
  hold), parsed by `rpm_command`, `velocity_command` and `position_command`, which raise ValueError on a message
  of the wrong length or with non-finite values.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

#: The entries of the paper's ``obs`` array, per drone.
OBS_NAMES = (
    "x",
    "y",
    "z",
    "qx",
    "qy",
    "qz",
    "qw",
    "roll",
    "pitch",
    "yaw",
    "vx",
    "vy",
    "vz",
    "wx",
    "wy",
    "wz",
    "rpm0",
    "rpm1",
    "rpm2",
    "rpm3",
)


def time_fields(t: float) -> dict:
    """``builtin_interfaces/Time`` of ``t`` s (t >= 0)."""
    nanoseconds = round(t * 1e9)
    return {"sec": nanoseconds // 1_000_000_000, "nanosec": nanoseconds % 1_000_000_000}


def obs_vector(
    pos: ArrayLike, quat: ArrayLike, rpy: ArrayLike, vel: ArrayLike, ang_vel: ArrayLike, rpm: ArrayLike
) -> np.ndarray:
    """The paper's observation of one drone, f32[20] (`OBS_NAMES`); ``rpy`` from
    `jaxdrones.physics.rotations.quat_to_euler` (PyBullet's ``getEulerFromQuaternion``)."""
    return np.concatenate(
        [np.ravel(pos), np.ravel(quat), np.ravel(rpy), np.ravel(vel), np.ravel(ang_vel), np.ravel(rpm)]
    ).astype(np.float32)


def float_array_fields(data: ArrayLike) -> dict:
    """``std_msgs/Float32MultiArray`` of a flat array (no layout dimensions, as gym-pybullet-drones' node)."""
    return {"layout": {"dim": [], "data_offset": 0}, "data": np.asarray(data, np.float32).ravel()}


def _header(t: float, frame_id: str) -> dict:
    return {"stamp": time_fields(t), "frame_id": frame_id}


def _pose(pos, quat) -> dict:
    p, q = np.asarray(pos, np.float64).ravel(), np.asarray(quat, np.float64).ravel()
    return {"position": {"x": p[0], "y": p[1], "z": p[2]}, "orientation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]}}


def _vector(v) -> dict:
    v = np.asarray(v, np.float64).ravel()
    return {"x": v[0], "y": v[1], "z": v[2]}


def pose_fields(pos: ArrayLike, quat: ArrayLike, t: float, frame_id: str = "world") -> dict:
    """``geometry_msgs/PoseStamped`` of one drone: pos f[3] m and quat f[4] (x, y, z, w) in ``frame_id`` at t s."""
    return {"header": _header(t, frame_id), "pose": _pose(pos, quat)}


def odometry_fields(
    pos: ArrayLike,
    quat: ArrayLike,
    vel: ArrayLike,
    ang_vel: ArrayLike,
    t: float,
    frame_id: str = "world",
    child_frame_id: str = "cf0",
) -> dict:
    """``nav_msgs/Odometry`` of one drone: the pose in ``frame_id``, the twist in the body frame ``child_frame_id``
    (linear Rᵀ v from the world-frame velocity ``vel``, angular ``ang_vel`` already body-frame), zero covariances."""
    x, y, z, w = np.asarray(quat, np.float64).ravel()
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    body_vel = rot.T @ np.asarray(vel, np.float64).ravel()
    return {
        "header": _header(t, frame_id),
        "child_frame_id": child_frame_id,
        "pose": {"pose": _pose(pos, quat), "covariance": np.zeros(36)},
        "twist": {"twist": {"linear": _vector(body_vel), "angular": _vector(ang_vel)}, "covariance": np.zeros(36)},
    }


def clock_fields(t: float) -> dict:
    """``rosgraph_msgs/Clock`` at t s."""
    return {"clock": time_fields(t)}


def _finite(values, what: str, size: int) -> np.ndarray:
    array = np.asarray(values, np.float64).ravel()
    if array.size != size:
        raise ValueError(f"{what} must have {size} entries, got {array.size}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} has non-finite entries: {array}")
    return array


def rpm_command(data: ArrayLike) -> np.ndarray:
    """An ``action`` message's data (the paper's: 4 motor RPM) as f64[4]; the step clips to [0, max_rpm]."""
    return _finite(data, "an action message (4 motor RPM)", 4)


def velocity_command(linear: Any) -> np.ndarray:
    """A ``cmd_vel`` Twist's ``linear`` (an object with x, y, z, or a sequence of 3) as f64[3] m/s, world frame."""
    values = [linear.x, linear.y, linear.z] if hasattr(linear, "x") else linear
    return _finite(values, "a velocity setpoint (linear x, y, z in m/s)", 3)


def position_command(pose: Any) -> tuple[np.ndarray, float]:
    """A ``cmd_position`` pose (a ``geometry_msgs/Pose``, or any object with ``position`` and ``orientation``)
    as (f64[3] m, yaw rad)."""
    p, q = pose.position, pose.orientation
    pos = _finite([p.x, p.y, p.z], "a position setpoint", 3)
    quat = _finite([q.x, q.y, q.z, q.w], "a position setpoint's orientation", 4)
    norm = np.linalg.norm(quat)
    if norm == 0:  # an all-zero orientation (a message that leaves it unset): yaw 0
        return pos, 0.0
    from jaxdrones.physics.rotations import quat_to_euler

    return pos, float(quat_to_euler(quat / norm)[2])


def fill_rclpy(message: Any, fields: dict) -> Any:
    """Fill an rclpy message (default-constructed, e.g. ``PoseStamped()``) from a field tree; returns it."""
    for name, value in fields.items():
        if isinstance(value, dict):
            fill_rclpy(getattr(message, name), value)
        elif isinstance(value, np.ndarray):
            setattr(message, name, value.tolist() if value.ndim else value.item())
        elif isinstance(value, np.generic):
            setattr(message, name, value.item())
        else:
            setattr(message, name, value)
    return message


def build_rosbags(typestore: Any, msgtype: str, fields: dict) -> Any:
    """A rosbags message of ``msgtype`` (e.g. ``"geometry_msgs/msg/PoseStamped"``) from a field tree, with
    ``typestore`` from ``rosbags.typesys.get_typestore``; serialise it with ``typestore.serialize_cdr``."""
    cls = typestore.types[msgtype]
    values = {}
    for name, field in cls.__dataclass_fields__.items():
        if name.startswith("__"):
            continue
        value, kind = fields[name], str(field.type)
        if isinstance(value, dict):
            value = build_rosbags(typestore, kind.replace("__msg__", "/msg/"), value)
        elif "np.ndarray" in kind:
            value = np.asarray(value, np.float32 if "float32" in kind else np.float64)
        elif kind == "float":
            value = float(value)
        values[name] = value
    return cls(**values)
