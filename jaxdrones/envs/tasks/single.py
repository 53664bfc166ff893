"""Single-agent tasks (D = 1): hover, firmware_hover, takeoff, velocity, waypoints, tune (docs/physics.md §11);
fly_thru_gate is in `jaxdrones.envs.tasks.gate`.

Each documents its reward (``reward="shaped"``, the default, tuned for fast RL; ``reward="paper"``, the
original's), its termination and its source. All terminate when the drone leaves the arena
(``arena_xy``, ``arena_z``), tilts beyond ``max_tilt`` (default π/2: on its side) or its state is not finite, and
truncate at ``episode_len_s``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control.firmware.motors import CRAZYFLIE_MOTOR_TAU
from jaxdrones.envs import rewards
from jaxdrones.envs.actions import ACTION_SIZES, Reference
from jaxdrones.envs.config import DomainRandomization, TaskConfig
from jaxdrones.envs.observations import POS_BOUND, VEL_BOUND
from jaxdrones.envs.task import Task, TaskParams
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.state import DEFAULT_START_Z, DroneState

#: Shaped hover-type rewards: r = max(0, closeness − SPEED_WEIGHT ‖v‖² − ANG_SPEED_WEIGHT ‖ω‖²) (see
#: `rewards.closeness`), non-negative so that ending an episode early never pays.
SPEED_WEIGHT = 0.1
ANG_SPEED_WEIGHT = 0.01


def _target_check(name: str, target) -> tuple[float, float, float]:
    arr = np.asarray(target, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: target must be three finite numbers (x, y, z) in m, got {target!r}")
    if arr[2] < 0:
        raise ValueError(f"{name}: target must be above the ground (z >= 0 m), got z = {arr[2]}")
    return tuple(float(v) for v in arr)


def hover_weights(config: TaskConfig, paper: dict[str, float]) -> dict[str, float]:
    """The reward weights of the hover-type tasks: the paper's (``paper``) with ``reward="paper"``, else the shaped
    reward's closeness and speed penalties (`SPEED_WEIGHT`, `ANG_SPEED_WEIGHT`)."""
    if config.reward == "paper":
        return paper
    return {"closeness": 1.0, "speed_sq": -SPEED_WEIGHT, "ang_speed_sq": -ANG_SPEED_WEIGHT}


def _tracking_terms(config: TaskConfig, target: jax.Array, sim: DroneState) -> dict[str, jax.Array]:
    """The shaped terms towards ``target`` f[D, 3] and the paper's squared distance."""
    if config.reward == "paper":
        return {"distance_sq": rewards.distance_sq(sim.pos, target)}
    return {
        "closeness": rewards.closeness(sim.pos, target),
        "speed_sq": rewards.speed_sq(sim.vel),
        "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel),
    }


def _one_d(config: TaskConfig) -> bool:
    return ACTION_SIZES[config.action_type] == 1


# ---------------------------------------------------------------------------------------------------------------
# hover
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class HoverConfig(TaskConfig):
    """Settings of `Hover` (see `TaskConfig` for the shared fields).

    Attributes:
        target: (x, y, z) hover target, m, world frame (the paper: (0, 0, 1)).
    """

    target: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self):
        object.__setattr__(self, "target", _target_check(type(self).__name__, self.target))
        super().__post_init__()


class Hover(Task):
    """Take off and hover at a target: the paper's single-agent task (IROS 2021 §V, eq. single; gym-pybullet-drones
    HoverAviary).

    Default: the full 3-D problem — four-motor ``rpm`` actions, random starts within ±0.5 m of the target in each
    axis, tilted up to 0.5 rad with any yaw, moving at up to ±0.5 m/s and ±1 rad/s per axis. With a 1-D action
    (``action_type="one_d_rpm"``, ``"one_d_pid"`` or ``"one_d_thrust"``, the paper's hover setting) the starts are
    level, on the target's vertical, at z in [0.1125, 1.8] m with vz in ±0.2 m/s.

    Reward ``"shaped"``: max(0, exp(−d/0.3) + 2 exp(−(d/0.03)²) − 0.1 ‖v‖² − 0.01 ‖ω‖²) with d the distance to the
    target in m; ``"paper"``: −d² (the paper's eq. single; the paper branch's HoverAviary).
    Success metric: ``distance`` (m).
    """

    name = "hover"
    config_cls = HoverConfig
    nonnegative_reward = True

    def start_defaults(self, config: HoverConfig) -> dict:
        target = np.asarray(config.target)
        if _one_d(config):
            low, high = DEFAULT_START_Z, 1.8
            return dict(
                pos=[[target[0], target[1], (low + high) / 2]],
                pos_range=(0.0, 0.0, (high - low) / 2),
                tilt=0.0,
                yaw=0.0,
                vel=(0.0, 0.0, 0.2),
                ang_vel=0.0,
            )
        return dict(pos=[target], pos_range=(0.5, 0.5, 0.5), tilt=0.5, yaw=math.pi, vel=0.5, ang_vel=1.0)

    def target(self, config: HoverConfig) -> np.ndarray:
        return np.asarray([config.target])

    def weights(self, config: HoverConfig) -> dict[str, float]:
        return hover_weights(config, {"distance_sq": -1.0})

    def reward_terms(
        self, config: HoverConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        return _tracking_terms(config, task.target, sim)


@dataclasses.dataclass(frozen=True)
class FirmwareHoverConfig(HoverConfig):
    """Settings of `FirmwareHover`: those of `HoverConfig` with the firmware's velocity setpoints as the action, the
    physics at the firmware's 1 kHz, a setpoint every 20 ms (50 Hz, as ``cflib`` scripts send them) and the
    Crazyflie's motor lag (61 ms, `jaxdrones.control.firmware.CRAZYFLIE_MOTOR_TAU`)."""

    action_type: str = "firmware_vel"
    sim: Any = SimConfig(sim_freq=1000, ctrl_freq=50)
    randomize: Any = DomainRandomization(
        motor_tau_up=(CRAZYFLIE_MOTOR_TAU, CRAZYFLIE_MOTOR_TAU),
        motor_tau_down=(CRAZYFLIE_MOTOR_TAU, CRAZYFLIE_MOTOR_TAU),
    )


class FirmwareHover(Hover):
    """`Hover` through the Crazyflie firmware: the policy sends what ``cflib``'s ``send_velocity_world_setpoint``
    sends a real Crazyflie (a world velocity up to 1 m/s and a yaw rate, ``action_type="firmware_vel"``), and the
    firmware's own PID cascade, power distribution and motor map fly it at 1 kHz (`jaxdrones.control.firmware`,
    checked against the firmware's C: docs/firmware.md). ``action_type="firmware_pos"`` sends position setpoints
    instead. Starts, reward, termination and success metric: `Hover`'s.
    """

    name = "firmware_hover"
    config_cls = FirmwareHoverConfig


# ---------------------------------------------------------------------------------------------------------------
# takeoff
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TakeoffConfig(HoverConfig):
    """Settings of `Takeoff`: those of `HoverConfig` (``target`` is where to climb to)."""


class Takeoff(Task):
    """Take off from the ground and climb to the target (the paper's TakeoffAviary).

    Starts: on the ground at the paper's default start (0, 0, 0.1125) m, level, x and y within ±0.1 m (3-D actions)
    and any yaw.
    Reward ``"shaped"``: as `Hover`'s, towards the target; ``"paper"``: −5 if z < 0.02 m, else −1/(10 z)
    (TakeoffAviary: no target, higher is better). Success metric: ``distance`` to the target (m).
    """

    name = "takeoff"
    config_cls = TakeoffConfig
    nonnegative_reward = True

    def start_defaults(self, config: TakeoffConfig) -> dict:
        target = np.asarray(config.target)
        spread = 0.0 if _one_d(config) else 0.1
        return dict(
            pos=[[target[0], target[1], DEFAULT_START_Z]],
            pos_range=(spread, spread, 0.0),
            tilt=0.0,
            yaw=0.0 if _one_d(config) else math.pi,
            vel=0.0,
            ang_vel=0.0,
        )

    def target(self, config: TakeoffConfig) -> np.ndarray:
        return np.asarray([config.target])

    def weights(self, config: TakeoffConfig) -> dict[str, float]:
        return hover_weights(config, {"takeoff": 1.0})

    def reward_terms(
        self, config: TakeoffConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        if config.reward == "paper":
            return {"takeoff": rewards.takeoff_paper(sim.pos[..., 2])}
        return _tracking_terms(config, task.target, sim)


# ---------------------------------------------------------------------------------------------------------------
# velocity
# ---------------------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class VelocityConfig(TaskConfig):
    """Settings of `Velocity`.

    Attributes:
        max_command: (vx, vy, vz) half-widths of the commanded velocity drawn per episode, m/s.
    """

    max_command: tuple[float, float, float] = (0.5, 0.5, 0.25)
    arena_xy: float = 4.0
    arena_z: float = 4.5

    def __post_init__(self):
        cmd = np.asarray(self.max_command, dtype=np.float64)
        if cmd.shape != (3,) or not np.all(np.isfinite(cmd)) or np.any(cmd < 0):
            raise ValueError(
                f"velocity: max_command must be three finite half-widths >= 0 in m/s, got {self.max_command!r}"
            )
        object.__setattr__(self, "max_command", tuple(float(v) for v in cmd))
        super().__post_init__()


class Velocity(Task):
    """Track a commanded velocity, drawn per episode uniformly within ``max_command`` (m/s, world frame).

    The command is part of the observation (3 entries after the kinematic state). Starts: around (0, 0, 2) m
    within ±0.2 m, tilted up to 0.2 rad, any yaw, at up to ±0.2 m/s.
    Reward ``"shaped"``: max(0, exp(−‖v − v*‖/0.25) + 0.2 exp(−d_z/0.3) − 0.01 ‖ω‖²) where d_z is the distance of z
    from the start's command-integrated altitude (keeps it off the ground); ``"paper"``: −‖v − v*‖² (the original
    has no velocity-tracking RL task: its VelocityAviary returns −1). Success metric: ``velocity_error`` (m/s).
    """

    name = "velocity"
    config_cls = VelocityConfig
    success_metric = "velocity_error"
    success_at = "mean"
    success_threshold = 0.1
    success_unit = "m/s"
    nonnegative_reward = True
    obs_size = 3

    def obs_bound(self, config: VelocityConfig) -> np.ndarray:
        return np.full(3, VEL_BOUND, np.float32)

    def start_defaults(self, config: VelocityConfig) -> dict:
        return dict(pos=[[0.0, 0.0, 2.0]], pos_range=(0.2, 0.2, 0.2), tilt=0.2, yaw=math.pi, vel=0.2, ang_vel=0.5)

    def target(self, config: VelocityConfig) -> np.ndarray:
        return np.array([[0.0, 0.0, 2.0]])

    def data(self, config: VelocityConfig) -> dict[str, np.ndarray]:
        return {"max_command": np.asarray(config.max_command), "target_vel": np.zeros((config.n_drones, 3))}

    def weights(self, config: VelocityConfig) -> dict[str, float]:
        if config.reward == "paper":
            return {"velocity_error_sq": -1.0}
        return {"velocity_tracking": 1.0, "altitude": 0.2, "ang_speed_sq": -ANG_SPEED_WEIGHT}

    def sample(self, config: VelocityConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        u = jax.random.uniform(key, task.target.shape, task.target.dtype, -1.0, 1.0)
        cmd = jnp.broadcast_to(task.data["max_command"], u.shape) * u
        return task.replace(data={**task.data, "target_vel": cmd})

    def observe(self, config: VelocityConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        return task.data["target_vel"]

    def reference(self, config: VelocityConfig, task: TaskParams, steps: jax.Array) -> Reference:
        vel = task.data["target_vel"]
        return Reference(task.start.pos + vel * (steps / config.sim.ctrl_freq), vel)

    def tracking_error(self, config: VelocityConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        """The commanded minus the measured velocity, m/s, world frame (its integral: how far the drone has fallen
        behind the commanded flight since its start, m)."""
        return task.data["target_vel"] - sim.vel

    def loss_weights(self, config: VelocityConfig) -> dict[str, float]:
        # The reference position integrates the command from the start range's centre, not from the drone's own
        # start: only its velocity is tracked.
        return {"distance_sq": 0.0, "velocity_error_sq": 1.0, "ang_speed_sq": 0.01}

    def reward_terms(
        self, config: VelocityConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        vel = task.data["target_vel"]
        if config.reward == "paper":
            return {"velocity_error_sq": rewards.velocity_error_sq(sim.vel, vel)}
        z_ref = self.reference(config, task, steps).pos[..., 2]
        return {
            "velocity_tracking": rewards.velocity_tracking(sim.vel, vel),
            "altitude": jnp.exp(-jnp.abs(sim.pos[..., 2] - z_ref) / rewards.BROAD_SCALE_M),
            "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel),
        }

    def metrics(
        self, config: VelocityConfig, task: TaskParams, sim: DroneState, steps: jax.Array
    ) -> dict[str, jax.Array]:
        return {"velocity_error": jnp.mean(rewards.distance(sim.vel, task.data["target_vel"]))}


# ---------------------------------------------------------------------------------------------------------------
# waypoints (and tune, which flies the same reference with the TUN action)
# ---------------------------------------------------------------------------------------------------------------

#: Reference paths of the waypoints task.
PATHS = ("circle", "figure8", "random")


@dataclasses.dataclass(frozen=True)
class WaypointsConfig(TaskConfig):
    """Settings of `Waypoints`.

    Attributes:
        path: ``"circle"``, ``"figure8"`` or ``"random"`` (drawn per episode from the two).
        radius: (low, high) range of the path's radius drawn per episode, m.
        centre: (x, y, z) of the path's centre, m.
        laps: laps of the path per episode.
    """

    path: str = "random"
    radius: tuple[float, float] = (0.3, 0.6)
    centre: tuple[float, float, float] = (0.0, 0.0, 1.0)
    laps: float = 0.5
    episode_len_s: float = 8.0

    def __post_init__(self):
        if self.path not in PATHS:
            raise ValueError(f"{type(self).__name__}: path must be one of {PATHS}, got {self.path!r}")
        r = np.asarray(self.radius, dtype=np.float64)
        if r.shape != (2,) or not np.all(np.isfinite(r)) or not 0 < r[0] <= r[1]:
            raise ValueError(f"radius must be a (low, high) range with 0 < low <= high, m, got {self.radius!r}")
        object.__setattr__(self, "radius", (float(r[0]), float(r[1])))
        object.__setattr__(self, "centre", _target_check("waypoints centre", self.centre))
        if not (isinstance(self.laps, (int, float)) and math.isfinite(self.laps) and self.laps > 0):
            raise ValueError(f"laps must be a finite number > 0, got {self.laps!r}")
        super().__post_init__()


def path_points(
    kind: jax.Array, radius: jax.Array, phase: jax.Array, direction: jax.Array, centre: jax.Array, angle: jax.Array
) -> jax.Array:
    """Points of a circle (``kind`` 0) or a figure-8 (``kind`` 1, a lemniscate of Gerono) in the horizontal plane.

    Args:
        kind: [] path kind: 0 a circle, 1 a figure-8.
        radius: f[] m.
        phase: f[] rad, where on the path the episode starts.
        direction: f[] ±1, the sense of travel.
        centre: f[3] m.
        angle: f[K] rad, progress along the path (2π per lap).

    Returns:
        f[K, 3] m, world frame; the path starts at angle 0.
    """
    theta = phase + direction * angle
    circle = jnp.stack([jnp.cos(theta) - jnp.cos(phase), jnp.sin(theta) - jnp.sin(phase)], axis=-1)
    eight = jnp.stack(
        [jnp.sin(theta) - jnp.sin(phase), jnp.sin(theta) * jnp.cos(theta) - jnp.sin(phase) * jnp.cos(phase)], axis=-1
    )
    xy = radius * jnp.where(kind == 0, circle, eight)
    offset = jnp.concatenate([xy, jnp.zeros_like(xy[:, :1])], axis=-1)
    return jnp.broadcast_to(centre, offset.shape) + offset


class ReferenceTask(Task):
    """A task that tracks a moving reference point (`Task.reference`): the observation appends the offset to the
    reference and its velocity (6 entries), and the shaped reward pulls towards the reference as `Hover`'s."""

    nonnegative_reward = True
    obs_size = 6

    def obs_bound(self, config: TaskConfig) -> np.ndarray:
        return np.array([POS_BOUND] * 3 + [VEL_BOUND] * 3, np.float32)

    def observe(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        ref = self.reference(config, task, steps)
        return jnp.concatenate([ref.pos - sim.pos, ref.vel], axis=-1)

    def reward_terms(
        self, config: TaskConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        return _tracking_terms(config, self.reference(config, task, steps).pos, sim)


class Waypoints(ReferenceTask):
    """Follow a sequence of waypoints drawn per episode: a circle or a figure-8 of random radius, start phase and
    sense, one waypoint per control step (a moving reference at ``laps`` laps per episode).

    The observation appends the offset to the current waypoint and the reference velocity (6 entries). Starts:
    within ±0.1 m of the first waypoint, level up to 0.1 rad, any yaw, at rest up to ±0.1 m/s.
    Reward ``"shaped"``: as `Hover`'s, towards the current waypoint; ``"paper"``: −‖p* − p‖² (the paper's tracking
    reward of TuneAviary). Success metric: ``waypoint_distance`` (m).
    """

    name = "waypoints"
    config_cls = WaypointsConfig
    success_metric = "waypoint_distance"
    success_at = "mean"
    success_threshold = 0.1

    def start_defaults(self, config: WaypointsConfig) -> dict:
        return dict(pos=[config.centre], pos_range=(0.1, 0.1, 0.1), tilt=0.1, yaw=math.pi, vel=0.1, ang_vel=0.2)

    def target(self, config: WaypointsConfig) -> np.ndarray:
        return np.asarray([config.centre])

    def data(self, config: WaypointsConfig) -> dict[str, np.ndarray]:
        kind = {"circle": 0, "figure8": 1, "random": -1}[config.path]
        # The episode's path: its kind, radius, start phase and sense (`sample`), whose points `reference` computes
        # at each step (no table of waypoints in the state).
        return {"path": np.asarray(kind), "radius": np.asarray(config.radius), "curve": np.array([0.0, 0.0, 0.0, 1.0])}

    def weights(self, config: WaypointsConfig) -> dict[str, float]:
        return hover_weights(config, {"distance_sq": -1.0})

    def sample(self, config: WaypointsConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        k_kind, k_r, k_phase, k_dir = jax.random.split(key, 4)
        dtype = task.target.dtype
        kind = jnp.where(
            task.data["path"] < 0, jax.random.bernoulli(k_kind).astype(jnp.int32), task.data["path"].astype(jnp.int32)
        )
        radius = jax.random.uniform(k_r, (), dtype, task.data["radius"][0], task.data["radius"][1])
        phase = jax.random.uniform(k_phase, (), dtype, 0.0, 2 * jnp.pi)
        direction = jnp.where(jax.random.bernoulli(k_dir), 1.0, -1.0).astype(dtype)
        curve = jnp.stack([kind.astype(dtype), radius, phase, direction])
        task = task.replace(data={**task.data, "curve": curve})
        start = task.start.replace(pos=self.reference(config, task, jnp.zeros((), jnp.int32)).pos)
        return task.replace(start=start)

    def reference(self, config: WaypointsConfig, task: TaskParams, steps: jax.Array) -> Reference:
        """The waypoint of control step ``steps`` and the next one's, ``laps`` laps of the path per episode (the
        last waypoint held after the episode's length)."""
        kind, radius, phase, direction = task.data["curve"]
        n = int(round(config.episode_len_s * config.sim.ctrl_freq))  # waypoints 0 .. n, one per control step
        k = jnp.minimum(steps, n).astype(radius.dtype)
        angle = 2 * jnp.pi * config.laps * jnp.stack([k, k + 1]) / n
        points = jax.vmap(lambda c: path_points(kind, radius, phase, direction, c, angle))(task.target)  # [D, 2, 3]
        return Reference(points[:, 0], (points[:, 1] - points[:, 0]) * config.sim.ctrl_freq)

    def metrics(
        self, config: WaypointsConfig, task: TaskParams, sim: DroneState, steps: jax.Array
    ) -> dict[str, jax.Array]:
        return {"waypoint_distance": jnp.mean(rewards.distance(sim.pos, self.reference(config, task, steps).pos))}


@dataclasses.dataclass(frozen=True)
class TuneConfig(WaypointsConfig):
    """Settings of `Tune`: those of `WaypointsConfig`, with the ``tun`` action."""

    action_type: str = "tun"

    def __post_init__(self):
        if self.action_type != "tun":
            raise ValueError(
                f"tune: action_type must be 'tun' (the policy scales the PID gains), got {self.action_type!r}"
            )
        super().__post_init__()


class Tune(Waypoints):
    """Tune the DSL PID's gains online (the paper's TuneAviary): the ``tun`` action scales the six gain vectors by
    (a + 1) while the PID tracks the waypoints task's reference.

    The original's reference is (0, 4 cos(0.006 k), 1) m at control step k, which starts 4 m from the drone; this
    task tracks the waypoints task's circles and figure-8s instead. Reward and metric: as `Waypoints` (``"paper"``:
    −‖p* − p‖², TuneAviary's).
    """

    name = "tune"
    config_cls = TuneConfig
