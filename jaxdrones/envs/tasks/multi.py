"""Multi-agent tasks (D ≥ 2): multi_hover, leader_follower, flock, meetup, crossing (docs/physics.md §11).

The default observation is ``neighbors`` (the kinematic state, the adjacency row and the relative positions of the
other drones), followed by the task's 3 entries: the offset from the drone to its reference point (defined per
task; ``crossing`` adds the reference velocity, 6 entries). Rewards are per drone, ``f[D]``. Episodes terminate
when any drone leaves the arena, tilts beyond ``max_tilt`` or its state is not finite, and truncate at
``episode_len_s``. Every task works for any D ≥ 2.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_real
from jaxdrones.envs import rewards
from jaxdrones.envs.actions import ACTION_SIZES, Reference
from jaxdrones.envs.config import TaskConfig
from jaxdrones.envs.observations import POS_BOUND, VEL_BOUND
from jaxdrones.envs.task import Task, TaskParams
from jaxdrones.envs.tasks.single import ANG_SPEED_WEIGHT, SPEED_WEIGHT
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.state import DroneState, default_start_pos


@dataclasses.dataclass(frozen=True)
class MultiConfig(TaskConfig):
    """Settings of the multi-agent tasks (see `TaskConfig`): by default 2 drones and the ``neighbors``
    observation."""

    n_drones: int = 2
    obs_type: str = "neighbors"


@dataclasses.dataclass(frozen=True)
class FlockConfig(MultiConfig):
    """Settings of `Flock`.

    Attributes:
        objective: ``"chain"`` (the paper's FlockAviary reward: each drone follows the altitude of the one before
            it) or ``"flocking"`` (velocity alignment, flock speed and spacing; see `Flock`).
    """

    objective: str = "chain"
    arena_xy: float = 5.0
    arena_z: float = 4.0

    def __post_init__(self):
        if self.objective not in ("chain", "flocking"):
            raise ValueError(f"flock: objective must be 'chain' or 'flocking', got {self.objective!r}")
        super().__post_init__()


class MultiTask(Task):
    """Shared pieces of the multi-agent tasks: D ≥ 2, the paper's default starts (drone i at (4iL, 4iL, 0.1125) m,
    here with any yaw and small random tilts and speeds so that episodes differ; level, at rest and facing +x
    with a 1-D action, which cannot level a drone), a 3-entry task observation (the
    offset to the drone's reference point `ref_points`) and shaped rewards towards those points."""

    config_cls = MultiConfig
    min_drones = 2
    max_drones = None
    nonnegative_reward = True
    obs_size = 3

    def obs_bound(self, config: MultiConfig) -> np.ndarray:
        return np.full(3, POS_BOUND, np.float32)

    def start_defaults(self, config: MultiConfig) -> dict:
        if ACTION_SIZES[config.action_type] == 1:  # 1-D actions (the paper's one_d_rpm) cannot level a tilted drone
            return dict(
                pos=default_start_pos(config.n_drones),
                pos_range=(0.02, 0.02, 0.0),
                tilt=0.0,
                yaw=0.0,
                vel=0.0,
                ang_vel=0.0,
            )
        return dict(
            pos=default_start_pos(config.n_drones),
            pos_range=(0.02, 0.02, 0.0),
            tilt=0.05,
            yaw=math.pi,
            vel=0.05,
            ang_vel=0.1,
        )

    def ref_points(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        """f[D, 3] m: where each drone should be, given the others (the shaped reward's target)."""
        return task.target

    def observe(self, config: MultiConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        return self.ref_points(config, task, sim) - sim.pos

    def weights(self, config: MultiConfig) -> dict[str, float]:
        if config.reward == "paper":
            return {"paper": 1.0}
        return {"closeness": 1.0, "speed_sq": -SPEED_WEIGHT, "ang_speed_sq": -ANG_SPEED_WEIGHT}

    def shaped_terms(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> dict:
        points = self.ref_points(config, task, sim)
        return {
            "closeness": rewards.closeness(sim.pos, points),
            "speed_sq": rewards.speed_sq(sim.vel),
            "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel),
        }

    def reward_terms(
        self, config: MultiConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        if config.reward == "paper":
            return {"paper": self.paper_reward(config, task, sim)}
        return self.shaped_terms(config, task, sim)

    def loss_terms(self, config: MultiConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """`Task.loss_terms` with the squared distance to each drone's reference point `ref_points` (m², which
        moves with the other drones: the gradient reaches both ends of a pair)."""
        terms = super().loss_terms(config, task, sim, steps)
        return {**terms, "distance_sq": rewards.distance_sq(sim.pos, self.ref_points(config, task, sim))}

    def metrics(self, config: MultiConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        return {"distance": jnp.mean(rewards.distance(sim.pos, self.ref_points(config, task, sim)))}


@dataclasses.dataclass(frozen=True)
class MultiHoverConfig(MultiConfig):
    """Settings of `MultiHover`: the ``kin_rotmat`` observation by default, as the single-agent tasks: the targets do
    not depend on the other drones, and the rotation matrix spares the policy the Euler angles' wrap at ±π (the
    drones start with any heading and their yaw wanders: in MAPPO runs with ``neighbors``, drones whose yaw spun up
    lost control and left the arena)."""

    obs_type: str = "kin_rotmat"


class MultiHover(MultiTask):
    """Every drone hovers at its own target: drone i at its start centre + (0, 0, 1/(i + 1)) m (gym-pybullet-drones
    MultiHoverAviary). Default observation ``kin_rotmat`` (`MultiHoverConfig`).

    Reward ``"shaped"``: per drone as `jaxdrones.envs.tasks.single.Hover`'s; ``"paper"``: per drone
    max(0, 2 − ‖target_i − p_i‖⁴) (MultiHoverAviary sums these into one scalar). Metric: ``distance`` (m, mean over
    drones) and ``max_distance``.
    """

    name = "multi_hover"
    config_cls = MultiHoverConfig
    success_metric = "max_distance"
    success_threshold = 0.1

    def target(self, config: MultiHoverConfig) -> np.ndarray:
        n = config.n_drones
        return default_start_pos(n) + np.stack([np.zeros(n), np.zeros(n), 1.0 / (np.arange(n) + 1)], -1)

    def paper_reward(self, config: MultiHoverConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        return jnp.maximum(0.0, 2.0 - rewards.distance_sq(sim.pos, task.target) ** 2)

    def metrics(
        self, config: MultiHoverConfig, task: TaskParams, sim: DroneState, steps: jax.Array
    ) -> dict[str, jax.Array]:
        d = rewards.distance(sim.pos, task.target)
        return {"distance": jnp.mean(d), "max_distance": jnp.max(d)}


class LeaderFollower(MultiTask):
    """The paper's leader-follower task (LeaderFollowerAviary): drone 0 climbs to (0, 0, 0.5) m; every other drone
    matches the leader's altitude over its own x, y.

    Reward ``"paper"``: r_0 = −‖(0, 0, 0.5) − p_0‖², r_i = −(1/D)(z_i − z_0)² for i ≥ 1; ``"shaped"``: towards
    those reference points as `jaxdrones.envs.tasks.single.Hover`'s. Metrics (m): ``leader_distance``,
    ``leader_altitude_error`` |z_0 − 0.5|, ``follower_altitude_error`` (mean |z_i − z_0| over followers) and
    ``max_altitude_error``, the largest of the leader's and every follower's altitude error (the success metric:
    every drone within 5 cm at the end of the episode).
    """

    name = "leader_follower"
    success_metric = "max_altitude_error"

    def target(self, config: MultiConfig) -> np.ndarray:
        return np.broadcast_to([0.0, 0.0, 0.5], (config.n_drones, 3))

    def ref_points(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        follow = sim.pos.at[..., 2].set(sim.pos[0, 2])
        return follow.at[0].set(task.target[0])

    def paper_reward(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        n = config.n_drones
        leader = -rewards.distance_sq(sim.pos[:1], task.target[:1])
        followers = -((sim.pos[1:, 2] - sim.pos[0, 2]) ** 2) / n
        return jnp.concatenate([leader, followers])

    def metrics(self, config: MultiConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        leader = jnp.abs(sim.pos[0, 2] - task.target[0, 2])
        followers = jnp.abs(sim.pos[1:, 2] - sim.pos[0, 2])
        return {
            "leader_distance": rewards.distance(sim.pos[0], task.target[0]),
            "leader_altitude_error": leader,
            "follower_altitude_error": jnp.mean(followers),
            "max_altitude_error": jnp.maximum(leader, jnp.max(followers)),
        }


class Flock(MultiTask):
    """The paper's FlockAviary, with its chain reward and a real flocking objective.

    ``objective="chain"`` (the code that runs in the original): drone 0 goes to (0, 0, 1) m, drone i ≥ 1 to the
    altitude of drone i − 1 over its own x, y; ``"paper"`` reward r_0 = −‖(0, 0, 1) − p_0‖²,
    r_i = −(z_{i−1} − z_i)². ``objective="flocking"`` (the objective the original wrote but never ran): per drone,
    the alignment of its velocity with the flock's mean velocity (cosine), the flock's speed ‖v̄‖ (capped at
    0.5 m/s), minus a penalty for each neighbour distance outside [1, 3] m (in m, mean over the others) and minus
    the variance of the neighbour distances (m²); the paper reward variant is the same sum.
    Metrics: chain — ``distance`` to the reference points (m); flocking — ``alignment``, ``flock_speed`` (m/s),
    ``spacing_violation`` (m).
    """

    name = "flock"
    config_cls = FlockConfig

    def target(self, config: FlockConfig) -> np.ndarray:
        return np.broadcast_to([0.0, 0.0, 1.0], (config.n_drones, 3))

    def ref_points(self, config: FlockConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        above = jnp.concatenate([task.target[:1, 2], sim.pos[:-1, 2]])
        return sim.pos.at[..., 2].set(above).at[0].set(task.target[0])

    def weights(self, config: FlockConfig) -> dict[str, float]:
        if config.objective == "flocking":
            return {"alignment": 1.0, "flock_speed": 1.0, "spacing": -1.0, "spacing_variance": -1.0}
        return super().weights(config)

    def reward_terms(
        self, config: FlockConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        if config.objective == "flocking":
            return flocking_terms(sim.pos, sim.vel)
        return super().reward_terms(config, task, sim, action, steps)

    def paper_reward(self, config: FlockConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        leader = -rewards.distance_sq(sim.pos[:1], task.target[:1])
        return jnp.concatenate([leader, -((sim.pos[:-1, 2] - sim.pos[1:, 2]) ** 2)])

    def metrics(self, config: FlockConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        if config.objective == "flocking":
            terms = flocking_terms(sim.pos, sim.vel)
            return {
                "alignment": jnp.mean(terms["alignment"]),
                "flock_speed": jnp.mean(terms["flock_speed"]),
                "spacing_violation": jnp.mean(terms["spacing"]),
            }
        return super().metrics(config, task, sim, steps)


#: Spacing band of the flocking objective, m, and the cap on the rewarded flock speed, m/s.
FLOCK_SPACING = (1.0, 3.0)
FLOCK_MAX_SPEED = 0.5


def flocking_terms(pos: jax.Array, vel: jax.Array) -> dict[str, jax.Array]:
    """The flocking objective's terms per drone (see `Flock`), each f[D]."""
    n = pos.shape[-2]
    mean_vel = jnp.mean(vel, axis=-2, keepdims=True)
    norms = jnp.sqrt(jnp.sum(vel**2, -1) * jnp.sum(mean_vel**2, -1) + 1e-12)
    alignment = jnp.sum(vel * mean_vel, -1) / norms
    speed = jnp.minimum(jnp.sqrt(jnp.sum(mean_vel**2, -1) + 1e-12), FLOCK_MAX_SPEED)
    delta = pos[..., None, :, :] - pos[..., :, None, :]
    dist = jnp.sqrt(jnp.sum(delta**2, -1) + 1e-12)
    others = ~jnp.eye(n, dtype=bool)
    low, high = FLOCK_SPACING
    violation = jnp.where(others, jnp.maximum(low - dist, 0.0) + jnp.maximum(dist - high, 0.0), 0.0)
    spacing = jnp.sum(violation, -1) / (n - 1)
    mean_d = jnp.sum(jnp.where(others, dist, 0.0), -1, keepdims=True) / (n - 1)
    variance = jnp.sum(jnp.where(others, (dist - mean_d) ** 2, 0.0), -1) / (n - 1)
    return {
        "alignment": alignment,
        "flock_speed": jnp.broadcast_to(speed, alignment.shape),
        "spacing": spacing,
        "spacing_variance": variance,
    }


class Meetup(MultiTask):
    """The paper's MeetupAviary: drones pair up, i with D − 1 − i, and meet.

    Each drone's reference point is its partner's position (for an odd team, the middle drone, which has no
    partner, flies to the team's centroid). Reward ``"paper"``: −‖p_i − p_partner‖² (the original's; its middle drone
    of an odd team gets 0); ``"shaped"``: towards the reference point as `jaxdrones.envs.tasks.single.Hover`'s.
    Metric: ``pair_distance`` (m, mean over drones).
    """

    name = "meetup"
    success_metric = "pair_distance"
    success_threshold = 0.1

    def ref_points(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        n = config.n_drones
        partner = sim.pos[::-1]
        if n % 2:
            partner = partner.at[n // 2].set(jnp.mean(sim.pos, axis=0))
        return partner

    def reference(self, config: MultiConfig, task: TaskParams, steps: jax.Array) -> Reference:
        return Reference(task.target, jnp.zeros_like(task.target))

    def paper_reward(self, config: MultiConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        return -rewards.distance_sq(sim.pos, sim.pos[::-1])

    def metrics(self, config: MultiConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        return {"pair_distance": jnp.mean(rewards.distance(sim.pos, sim.pos[::-1]))}


# ---------------------------------------------------------------------------------------------------------------
# crossing: the paper's downwash example as a task
# ---------------------------------------------------------------------------------------------------------------

#: Reference altitude of the lowest drone of `Crossing`, m (the lower drone of the original downwash example).
CROSSING_BASE_Z = 0.5


@dataclasses.dataclass(frozen=True)
class CrossingConfig(MultiConfig):
    """Settings of `Crossing`.

    Attributes:
        sim: the downwash on by default, unlike the other tasks: the drones fly over each other, and the upper
            drone's downwash on the lower one is what the task is about.
        period_s: period of each drone's back-and-forth along x, s (the original: 5 s).
        amplitude: half the length of each drone's path along x, m (the original: 0.5 m).
        spacing: vertical spacing of the drones' paths, m: drone i flies at 0.5 m + spacing·(D − 1 − i) (the
            original: 0.5 m, its drones at 1 m and 0.5 m).
        arena_z: raised to 4 m so that teams of up to 7 drones fit at the default spacing.

    Raises:
        ValueError: ``period_s``, ``amplitude`` or ``spacing`` not a finite number > 0, or a path outside the
            arena (``amplitude`` ≥ ``arena_xy``, or the top drone's altitude ≥ ``arena_z``).
    """

    sim: Any = SimConfig(ctrl_freq=30, downwash=True)
    period_s: float = 5.0
    amplitude: float = 0.5
    spacing: float = 0.5
    episode_len_s: float = 5.0
    arena_z: float = 4.0

    def __post_init__(self):
        for name in ("period_s", "amplitude", "spacing"):
            check_real(f"crossing: {name}", getattr(self, name), 0, low_open=True, what="a finite number")
        super().__post_init__()
        if self.amplitude >= self.arena_xy:
            raise ValueError(
                f"crossing: amplitude must be below arena_xy ({self.arena_xy} m), the path would leave "
                f"the arena, got {self.amplitude!r}"
            )
        top = CROSSING_BASE_Z + self.spacing * (self.n_drones - 1)
        if top >= self.arena_z:
            raise ValueError(
                f"crossing: the top drone's altitude 0.5 + spacing·(n_drones − 1) = {top:g} m must be "
                f"below arena_z ({self.arena_z} m): lower spacing ({self.spacing!r}) or n_drones, "
                f"or raise arena_z"
            )


class Crossing(MultiTask):
    """The paper's downwash example as a task (gym-pybullet-drones examples/downwash.py): the drones fly back and
    forth along x at different altitudes, half a period apart, so that they pass over each other twice per period
    and the upper drone's downwash pushes the lower one down (downwash is on by default, `CrossingConfig`).

    Drone i's reference point at time t = steps / ctrl_freq (s) is (A cos(2π t / T + π i), 0, z_i) with
    A = ``amplitude`` (m), T = ``period_s`` (s) and z_i = 0.5 + ``spacing``·(D − 1 − i) m; its reference velocity
    is the time derivative (−A (2π/T) sin(2π t / T + π i), 0, 0) m/s. For D = 2 these are the original's paths:
    drone 0 at 1 m from x = 0.5 m, drone 1 at 0.5 m from x = −0.5 m; the reference points cross (equal x) at
    t = T/4, 3T/4, ... (the original's drones, which lag their way-points, pass over each other about 0.5 s
    later). With D ≥ 3 the drones of even index share one path in x and those of odd index the other.
    ``task.target`` f[D, 3] holds the centres (0, 0, z_i) of the paths and ``task.data`` the amplitude (m), period
    (s) and phase π i (rad) of the reference; the starts use the config's values.

    Starts: at the reference's t = 0 points (at rest there), with the `MultiTask` randomisation (±0.02 m in x and
    y, tilts up to 0.05 rad, any yaw, up to ±0.05 m/s and ±0.1 rad/s; level, at rest and facing +x with a 1-D
    action). The observation appends the offset from the drone to its reference point (m) and the reference
    velocity (m/s), 6 entries.
    Reward ``"shaped"``: per drone max(0, closeness to the reference point (`rewards.closeness`) − 0.1 ‖v − v*‖²
    − 0.01 ‖ω‖²); ``"paper"``: per drone max(0, 2 − ‖p*_i − p_i‖⁴) (as `MultiHover`'s).
    Metrics (m): ``tracking_error`` (mean over drones of the distance to the reference point), ``altitude_error``
    (mean over drones of |z_i − z*_i|) and ``max_altitude_error`` (the largest over drones), the success metric,
    judged at its largest over the episode (``success_at = "max"``: the lower drone's dip as the other passes over
    it must stay within 5 cm).
    """

    name = "crossing"
    config_cls = CrossingConfig
    success_metric = "max_altitude_error"
    success_at = "max"
    obs_size = 6

    def obs_bound(self, config: CrossingConfig) -> np.ndarray:
        return np.array([POS_BOUND] * 3 + [VEL_BOUND] * 3, np.float32)

    def target(self, config: CrossingConfig) -> np.ndarray:
        n = config.n_drones
        z = CROSSING_BASE_Z + config.spacing * (n - 1 - np.arange(n))
        return np.stack([np.zeros(n), np.zeros(n), z], -1)

    def data(self, config: CrossingConfig) -> dict[str, np.ndarray]:
        return {
            "amplitude": np.asarray(config.amplitude),
            "period": np.asarray(config.period_s),
            "phase": np.pi * np.arange(config.n_drones),
        }

    def start_defaults(self, config: CrossingConfig) -> dict:
        start = super().start_defaults(config)
        phase = np.pi * np.arange(config.n_drones)
        start["pos"] = self.target(config) + np.stack([config.amplitude * np.cos(phase), 0 * phase, 0 * phase], -1)
        return start

    def reference(self, config: CrossingConfig, task: TaskParams, steps: jax.Array) -> Reference:
        """Reference(pos f[D, 3] m, vel f[D, 3] m/s) at control step ``steps`` (see the class docstring)."""
        amplitude, period, phase = task.data["amplitude"], task.data["period"], task.data["phase"]
        omega = 2 * jnp.pi / period
        theta = omega * (steps / config.sim.ctrl_freq) + phase
        zero = jnp.zeros_like(theta)
        offset = jnp.stack([amplitude * jnp.cos(theta), zero, zero], -1)
        vel = jnp.stack([-amplitude * omega * jnp.sin(theta), zero, zero], -1)
        return Reference(task.target + offset.astype(task.target.dtype), vel.astype(task.target.dtype))

    def observe(self, config: CrossingConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        ref = self.reference(config, task, steps)
        return jnp.concatenate([ref.pos - sim.pos, ref.vel], axis=-1)

    def loss_terms(self, config: CrossingConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """`Task.loss_terms`: towards the moving reference (`reference`), not the paths' centres."""
        return Task.loss_terms(self, config, task, sim, steps)

    def weights(self, config: CrossingConfig) -> dict[str, float]:
        if config.reward == "paper":
            return {"paper": 1.0}
        return {"closeness": 1.0, "velocity_error_sq": -SPEED_WEIGHT, "ang_speed_sq": -ANG_SPEED_WEIGHT}

    def reward_terms(
        self, config: CrossingConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        ref = self.reference(config, task, steps)
        if config.reward == "paper":
            return {"paper": jnp.maximum(0.0, 2.0 - rewards.distance_sq(sim.pos, ref.pos) ** 2)}
        return {
            "closeness": rewards.closeness(sim.pos, ref.pos),
            "velocity_error_sq": rewards.velocity_error_sq(sim.vel, ref.vel),
            "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel),
        }

    def metrics(
        self, config: CrossingConfig, task: TaskParams, sim: DroneState, steps: jax.Array
    ) -> dict[str, jax.Array]:
        ref = self.reference(config, task, steps)
        altitude = jnp.abs(sim.pos[..., 2] - ref.pos[..., 2])
        return {
            "tracking_error": jnp.mean(rewards.distance(sim.pos, ref.pos)),
            "altitude_error": jnp.mean(altitude),
            "max_altitude_error": jnp.max(altitude),
        }


MULTI_AGENT_TASKS = (MultiHover(), LeaderFollower(), Flock(), Meetup(), Crossing())
