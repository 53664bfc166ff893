"""Multi-agent tasks (D ≥ 2): multi_hover, leader_follower, flock, meetup (docs/physics.md §11).

The default observation is ``neighbors`` (the kinematic state, the adjacency row and the relative positions of the
other drones), followed by the task's 3 entries: the offset from the drone to its reference point (defined per
task). Rewards are per drone, ``f[D]``. Episodes terminate when any drone leaves the arena, tilts beyond
``max_tilt`` or its state is not finite, and truncate at ``episode_len_s``. Every task works for any D ≥ 2.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs import rewards
from jaxdrones.envs.actions import ACTION_SIZES, Reference
from jaxdrones.envs.core import Task, TaskConfig
from jaxdrones.envs.observations import POS_BOUND
from jaxdrones.envs.tasks.single import ANG_SPEED_WEIGHT, SPEED_WEIGHT
from jaxdrones.state import default_start_pos


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

    def obs_bound(self, config):
        return np.full(3, POS_BOUND, np.float32)

    def start_defaults(self, config):
        if ACTION_SIZES[config.action_type] == 1:  # 1-D actions (the paper's one_d_rpm) cannot level a tilted drone
            return dict(pos=default_start_pos(config.n_drones), pos_range=(0.02, 0.02, 0.0), tilt=0.0, yaw=0.0,
                        vel=0.0, ang_vel=0.0)
        return dict(pos=default_start_pos(config.n_drones), pos_range=(0.02, 0.02, 0.0), tilt=0.05, yaw=math.pi,
                    vel=0.05, ang_vel=0.1)

    def ref_points(self, config, task, sim) -> jax.Array:
        """f[D, 3] m: where each drone should be, given the others (the shaped reward's target)."""
        return task.target

    def observe(self, config, task, sim, steps):
        return self.ref_points(config, task, sim) - sim.pos

    def weights(self, config):
        if config.reward == "paper":
            return {"paper": 1.0}
        return {"closeness": 1.0, "speed_sq": -SPEED_WEIGHT, "ang_speed_sq": -ANG_SPEED_WEIGHT}

    def shaped_terms(self, config, task, sim) -> dict:
        points = self.ref_points(config, task, sim)
        return {"closeness": rewards.closeness(sim.pos, points), "speed_sq": rewards.speed_sq(sim.vel),
                "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel)}

    def reward_terms(self, config, task, sim, action, steps):
        if config.reward == "paper":
            return {"paper": self.paper_reward(config, task, sim)}
        return self.shaped_terms(config, task, sim)

    def metrics(self, config, task, sim, steps):
        return {"distance": jnp.mean(rewards.distance(sim.pos, self.ref_points(config, task, sim)))}


class MultiHover(MultiTask):
    """Every drone hovers at its own target: drone i at its start centre + (0, 0, 1/(i + 1)) m (gym-pybullet-drones
    MultiHoverAviary).

    Reward ``"shaped"``: per drone as `jaxdrones.envs.tasks.single.Hover`'s; ``"paper"``: per drone
    max(0, 2 − ‖target_i − p_i‖⁴) (MultiHoverAviary sums these into one scalar). Metric: ``distance`` (m, mean over
    drones) and ``max_distance``.
    """

    name = "multi_hover"
    success_metric = "max_distance"
    success_threshold = 0.1

    def target(self, config):
        n = config.n_drones
        return default_start_pos(n) + np.stack([np.zeros(n), np.zeros(n), 1.0 / (np.arange(n) + 1)], -1)

    def paper_reward(self, config, task, sim):
        return jnp.maximum(0.0, 2.0 - rewards.distance_sq(sim.pos, task.target) ** 2)

    def metrics(self, config, task, sim, steps):
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

    def target(self, config):
        return np.broadcast_to([0.0, 0.0, 0.5], (config.n_drones, 3))

    def ref_points(self, config, task, sim):
        follow = sim.pos.at[..., 2].set(sim.pos[0, 2])
        return follow.at[0].set(task.target[0])

    def paper_reward(self, config, task, sim):
        n = config.n_drones
        leader = -rewards.distance_sq(sim.pos[:1], task.target[:1])
        followers = -(sim.pos[1:, 2] - sim.pos[0, 2]) ** 2 / n
        return jnp.concatenate([leader, followers])

    def metrics(self, config, task, sim, steps):
        leader = jnp.abs(sim.pos[0, 2] - task.target[0, 2])
        followers = jnp.abs(sim.pos[1:, 2] - sim.pos[0, 2])
        return {"leader_distance": rewards.distance(sim.pos[0], task.target[0]), "leader_altitude_error": leader,
                "follower_altitude_error": jnp.mean(followers),
                "max_altitude_error": jnp.maximum(leader, jnp.max(followers))}


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

    def target(self, config):
        return np.broadcast_to([0.0, 0.0, 1.0], (config.n_drones, 3))

    def ref_points(self, config, task, sim):
        above = jnp.concatenate([task.target[:1, 2], sim.pos[:-1, 2]])
        return sim.pos.at[..., 2].set(above).at[0].set(task.target[0])

    def weights(self, config):
        if config.objective == "flocking":
            return {"alignment": 1.0, "flock_speed": 1.0, "spacing": -1.0, "spacing_variance": -1.0}
        return super().weights(config)

    def reward_terms(self, config, task, sim, action, steps):
        if config.objective == "flocking":
            return flocking_terms(sim.pos, sim.vel)
        return super().reward_terms(config, task, sim, action, steps)

    def paper_reward(self, config, task, sim):
        leader = -rewards.distance_sq(sim.pos[:1], task.target[:1])
        return jnp.concatenate([leader, -(sim.pos[:-1, 2] - sim.pos[1:, 2]) ** 2])

    def metrics(self, config, task, sim, steps):
        if config.objective == "flocking":
            terms = flocking_terms(sim.pos, sim.vel)
            return {"alignment": jnp.mean(terms["alignment"]), "flock_speed": jnp.mean(terms["flock_speed"]),
                    "spacing_violation": jnp.mean(terms["spacing"])}
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
    return {"alignment": alignment, "flock_speed": jnp.broadcast_to(speed, alignment.shape), "spacing": spacing,
            "spacing_variance": variance}


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

    def ref_points(self, config, task, sim):
        n = config.n_drones
        partner = sim.pos[::-1]
        if n % 2:
            partner = partner.at[n // 2].set(jnp.mean(sim.pos, axis=0))
        return partner

    def reference(self, task, steps, config):
        return Reference(task.target, jnp.zeros_like(task.target))

    def paper_reward(self, config, task, sim):
        return -rewards.distance_sq(sim.pos, sim.pos[::-1])

    def metrics(self, config, task, sim, steps):
        return {"pair_distance": jnp.mean(rewards.distance(sim.pos, sim.pos[::-1]))}


MULTI_AGENT_TASKS = (MultiHover(), LeaderFollower(), Flock(), Meetup())
