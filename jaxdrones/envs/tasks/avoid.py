"""``avoid``: fly to a goal through a field of obstacles drawn per episode, seen only through the depth camera.

Not a task of the paper: the vision task that needs its camera. The paper's vision workflow (§III-D: per-drone
64×48 images along the body x axis) has no task whose solution depends on the image; here the obstacles are in
no part of the kinematic observation, so a policy that avoids them reads them from the depth image.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_int, check_real
from jaxdrones.envs import rewards, terminations
from jaxdrones.envs.config import TaskConfig
from jaxdrones.envs.observations import POS_BOUND
from jaxdrones.envs.task import Task, TaskParams
from jaxdrones.physics.state import DroneState

if TYPE_CHECKING:
    from jaxdrones.scene.primitives import Scene

#: Obstacle colours, cycled (RGB in [0, 1]): greys and muted tones, distinct in the RGB image.
COLOURS = ((0.55, 0.35, 0.25), (0.35, 0.45, 0.55), (0.5, 0.5, 0.45), (0.3, 0.5, 0.35))


@dataclasses.dataclass(frozen=True)
class AvoidConfig(TaskConfig):
    """Settings of `Avoid`.

    Attributes:
        n_cylinders: vertical cylinders per episode (radius in ``cylinder_radius``).
        n_boxes: upright boxes per episode, at a random yaw (half extents in x and y in ``box_half``).
        cylinder_radius: (low, high) of the cylinders' radii, m.
        box_half: (low, high) of the boxes' horizontal half extents, m.
        obstacle_height: the obstacles' height, m, from the ground (above ``arena_z``: they cannot be flown over).
        field_x: (low, high) of the obstacles' centres along x, m.
        field_y: the obstacles' centres within |y| ≤ field_y, m; a drone beyond |y| > field_y + 0.5 m has left the
            field (terminated).
        goal_x: the goal's x, m; its y is drawn per episode within ±``goal_y``, its z is ``flight_z``.
        goal_y: half-width of the goal's y, m.
        goal_radius: the goal is reached within this distance, m (0.5 m: at up to 1 m/s, a policy that flies through
            the field then past its goal, 0.1 m low and 0.3 m aside, has done what the task asks of its camera).
        flight_z: start and goal altitude, m.
        start_y: half-width of the start's y, m (the start is at x = 0, facing +x).

    The defaults: 12 cylinders and 4 boxes (16 primitives) over 2.2 × 3 m, the goal 3.8 m ahead, ``pid`` actions
    with relative targets up to 0.3 m away per axis (``pid_scale``; the DSL PID flies them at up to 1 m/s, the goal
    4.7 s away in a straight line; at the paper's 0.1 m, 0.5 m/s and 10.6 s of the 12), the depth camera at 15 Hz
    of a 30 Hz control, episodes of 12 s. The camera is a wide strip, 64 × 16 pixels (``image_size``) at a 75°
    vertical field of view (``camera_fov``): 144° across, 5.5° a pixel at its centre, 1,024 rays.
    The obstacles are upright and the flight level, so the image's width is what a policy needs: with the paper's
    60° at 4:3 (75° across) most collisions of trained policies were with obstacles more than 37.5° aside, and with
    110° at 4:3 (125° across) with obstacles just beyond the image's edge, 56–85° aside in 21 of 23, as the drone
    passed them (`jaxdrones train avoid`: 87 % success at 125° across; at 144°, with its other defaults, 95 % and
    92 % with seeds 0 and 1).

    Raises:
        ValueError: a count that is not a non-negative integer, a range out of order, the field overlapping the
            start or the goal, or ``backend="pybullet"`` (the obstacles are drawn per episode, in the task params).
    """

    n_cylinders: int = 12
    n_boxes: int = 4
    cylinder_radius: tuple[float, float] = (0.05, 0.12)
    box_half: tuple[float, float] = (0.05, 0.15)
    obstacle_height: float = 4.0
    field_x: tuple[float, float] = (0.8, 3.0)
    field_y: float = 1.5
    goal_x: float = 3.8
    goal_y: float = 0.5
    goal_radius: float = 0.5
    flight_z: float = 1.0
    start_y: float = 0.5
    action_type: str = "pid"
    pid_target: str = "relative"
    pid_scale: float = 0.3
    vision: tuple[str, ...] = ("depth",)
    camera_freq: float = 15.0
    image_size: tuple[int, int] = (64, 16)
    camera_fov: float = 75.0
    episode_len_s: float = 12.0
    arena_xy: float = 5.0
    terminate_on_ground: bool = True

    def __post_init__(self):
        for name in ("n_cylinders", "n_boxes"):
            check_int(f"avoid: {name}", getattr(self, name), low=0)
        for name in ("cylinder_radius", "box_half", "field_x"):
            lo, hi = _range(name, getattr(self, name))
            object.__setattr__(self, name, (lo, hi))
        for name in ("obstacle_height", "field_y", "goal_x", "goal_y", "goal_radius", "flight_z", "start_y"):
            check_real(f"avoid: {name}", getattr(self, name), 0, what="a finite distance in m")
        reach = max(self.cylinder_radius[1], math.sqrt(2) * self.box_half[1])
        if self.field_x[0] - reach <= 0.2 or self.field_x[1] + reach >= self.goal_x - self.goal_radius:
            raise ValueError(
                f"avoid: the obstacles (centres in x {self.field_x}, up to {reach:.2f} m wide) must "
                f"leave the start (x = 0) and the goal (x = {self.goal_x}) clear"
            )
        if self.backend != "jax":
            raise ValueError(
                "avoid runs on backend='jax': its obstacles are drawn per episode in the task params, "
                "which the PyBullet backend's fixed worlds cannot follow"
            )
        super().__post_init__()


def _range(name: str, value) -> tuple[float, float]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)) or arr[0] < 0 or arr[0] > arr[1]:
        raise ValueError(f"avoid: {name} must be (low, high) with 0 <= low <= high, got {value!r}")
    return float(arr[0]), float(arr[1])


class GoalTask(Task):
    """A task judged per episode through a scene of obstacles (``avoid``, the gate drawn per episode): success is
    ending at its goal (`Task.reached`) without a collision; the scene is the task params' (collisions from
    `collided`, each drone's radius in `collision_data`); reward terms ``progress`` (weight 1), ``reached`` (10) and
    ``crash`` (−50). Its privileged observation (`Task.privileged`, for a critic) is the scene around each drone,
    `scene_clearances` at `clearance_bearings` bearings × `clearance_ranges` distances."""

    uses_scene = True
    #: Where `privileged` samples the scene around a drone (`scene_clearances`): this many bearings, evenly spaced
    #: from world +x in the horizontal plane, at these distances (m) from the drone's centre.
    clearance_bearings: int = 16
    clearance_ranges: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0, 1.5)
    success_counts_terminations = True
    success_metric = "failure"
    success_at = "final"
    success_threshold = 0.1
    success_unit = "share"

    def data(self, config: TaskConfig) -> dict[str, np.ndarray]:
        return collision_data(config)

    def privileged(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array | None:
        return scene_clearances(task, sim, self.clearance_bearings, self.clearance_ranges)

    def weights(self, config: TaskConfig) -> dict[str, float]:
        # A crash costs 50: at 10 it cost less than the speed it bought (the progress term pays up to ~1.3 per step),
        # and trained policies flew fast and collided (``avoid``, asymmetric critic: 47 % success in a run where 50
        # gave 79 %); at 100 they learned to stay at the start (``avoid``: 0 %).
        return {"progress": 1.0, "reached": 10.0, "crash": -50.0}


class Avoid(GoalTask):
    """Reach a goal 3.8 m ahead through 16 obstacles placed per episode, seen only through the depth camera.

    Each episode draws the obstacles' positions, sizes and (boxes) yaws uniformly within the config's ranges and
    the goal's y; they are in `TaskParams.scene` (the cameras draw them) and nowhere in the kinematic observation,
    which appends only the offset to the goal (3 entries). A drone whose centre comes within its collision radius
    of an obstacle (`jaxdrones.cameras.distance`) has collided: the episode terminates, as it does when the drone
    touches the ground, leaves the field (|y| > field_y + 0.5 m) or the arena. The episode also ends, at its goal
    (`reached`, not a crash), when the drone comes within ``goal_radius`` of the goal.

    Reward (both ``reward`` settings): ``progress``, the velocity towards the goal (m/s), weight 1;
    ``reached``, 1 at the step the goal is reached, weight 10; ``crash``, 1 on a collision or any other
    termination, weight −50; ``proximity``, 1 − clearance / 0.25 m within 0.25 m of an obstacle (`proximity`),
    weight −1.
    Success metric: ``failure``, 0 when the episode ends within ``goal_radius`` of the goal without a collision
    (it ended there), else 1 (a collision, or the time ran out), read at the episode's end; solved when at most
    10 % of the evaluation episodes fail (``success_rate`` ≥ 0.9 in the evaluation's statistics).
    """

    #: A coarser map for the critic than `GoalTask`'s, 8 bearings × 0.25, 0.5, 1 m: a third of the distance
    #: computations (docs/experiments.md, "Vision: the avoid task": within 10 minutes).
    clearance_bearings = 8
    clearance_ranges = (0.25, 0.5, 1.0)

    name = "avoid"
    config_cls = AvoidConfig
    obs_size = 3

    def obs_bound(self, config: AvoidConfig) -> np.ndarray:
        return np.array([POS_BOUND] * 3, np.float32)

    def start_defaults(self, config: AvoidConfig) -> dict:
        return dict(
            pos=[[0.0, 0.0, config.flight_z]],
            pos_range=(0.0, config.start_y, 0.0),
            tilt=0.0,
            yaw=0.0,
            vel=0.0,
            ang_vel=0.0,
        )

    def target(self, config: AvoidConfig) -> np.ndarray:
        return np.array([[config.goal_x, 0.0, config.flight_z]])

    def scene(self, config: AvoidConfig) -> Scene:
        from jaxdrones.scene.primitives import make_scene

        return make_scene((), capacity={"cylinder": config.n_cylinders, "box": config.n_boxes})

    def sample(self, config: AvoidConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        k_goal, k_cyl, k_box = jax.random.split(key, 3)
        dtype = task.target.dtype
        goal_y = jax.random.uniform(k_goal, (), dtype, -config.goal_y, config.goal_y)
        scene = task.scene
        half_z = config.obstacle_height / 2
        n_cyl, n_box = config.n_cylinders, config.n_boxes
        u = jax.random.uniform(k_cyl, (n_cyl, 3), dtype)
        cyl = scene.cylinder.replace(
            pos=_field_points(config, u, half_z),
            size=jnp.stack(
                [
                    _between(config.cylinder_radius, u[:, 2]),
                    jnp.full((n_cyl,), half_z, dtype),
                    jnp.zeros((n_cyl,), dtype),
                ],
                -1,
            ),
            seg=1 + jnp.arange(n_cyl, dtype=jnp.int32),
            valid=jnp.ones((n_cyl,), bool),
            rgb=jnp.asarray(np.resize(np.asarray(COLOURS), (n_cyl, 3)), dtype),
        )
        u = jax.random.uniform(k_box, (n_box, 5), dtype)
        yaw = 2 * jnp.pi * u[:, 4]
        c, s, zero, one = jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw), jnp.ones_like(yaw)
        rot = jnp.stack(
            [jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1), jnp.stack([zero, zero, one], -1)], -2
        )
        box = scene.box.replace(
            pos=_field_points(config, u, half_z),
            rot=rot,
            size=jnp.stack(
                [
                    _between(config.box_half, u[:, 2]),
                    _between(config.box_half, u[:, 3]),
                    jnp.full((n_box,), half_z, dtype),
                ],
                -1,
            ),
            seg=1 + n_cyl + jnp.arange(n_box, dtype=jnp.int32),
            valid=jnp.ones((n_box,), bool),
            rgb=jnp.asarray(np.resize(np.asarray(COLOURS[::-1]), (n_box, 3)), dtype),
        )
        return task.replace(target=task.target.at[..., 1].set(goal_y), scene=scene.replace(cylinder=cyl, box=box))

    def observe(self, config: AvoidConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        return task.target - sim.pos

    def weights(self, config: AvoidConfig) -> dict[str, float]:
        return {**super().weights(config), "proximity": -1.0}

    def reward_terms(
        self, config: AvoidConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        dist = rewards.distance(sim.pos, task.target)
        clear = clearance(task, sim)
        crash = (clear < 0) | self._lost(config, task, sim)
        return {
            "progress": progress(sim, task.target),
            "reached": (dist < config.goal_radius).astype(dist.dtype),
            "crash": crash.astype(dist.dtype),
            "proximity": proximity(clear),
        }

    def terminated(self, config: AvoidConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        return jnp.any(collided(task, sim) | self._lost(config, task, sim))

    def reached(self, config: AvoidConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        near = rewards.distance(sim.pos, task.target) < config.goal_radius
        return jnp.all(near) & ~self.terminated(config, task, sim)

    def metrics(self, config: AvoidConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        dist = rewards.distance(sim.pos, task.target)
        hit = jnp.any(collided(task, sim))
        reached = jnp.all(dist < config.goal_radius)
        return {
            "distance": jnp.mean(dist),
            "collision": hit.astype(dist.dtype),
            "failure": (hit | ~reached).astype(dist.dtype),
        }

    @staticmethod
    def _lost(config, task, sim: DroneState) -> jax.Array:
        """bool[D]: the drone crashed (`terminations.crashed`) or left the field's sides."""
        side = jnp.abs(sim.pos[..., 1]) > config.field_y + 0.5
        return terminations.crashed(sim, task.bounds, config.terminate_on_ground) | side


def collision_data(config: TaskConfig) -> dict[str, np.ndarray]:
    """`Task.data` of a task that detects collisions with its scene: each drone's collision radius (the URDF's),
    ``collision_radius`` f[D] m."""
    from jaxdrones.physics.params import load_params

    models = config.model if isinstance(config.model, tuple) else (config.model,)
    return {"collision_radius": np.array([float(load_params(m).collision_radius) for m in models])}


def clearance(task: TaskParams, sim: DroneState) -> jax.Array:
    """f[D] m: the gap between each drone's collision radius and the nearest obstacle of ``task.scene``
    (`jaxdrones.cameras.distance` less ``task.data["collision_radius"]``, `collision_data`); negative when they
    touch."""
    from jaxdrones.scene.primitives import distance

    return distance(task.scene, sim.pos) - task.data["collision_radius"]


#: The largest clearance `scene_clearances` reports, m.
SAMPLE_CLIP_M = 1.0


def scene_clearances(
    task: TaskParams, sim: DroneState, bearings: int = 16, distances: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0, 1.5)
) -> jax.Array:
    """f[D, 1 + B·R] m: `clearance` at the drone's centre, then at ``bearings`` B bearings (evenly spaced from world
    +x, in the horizontal plane at its altitude) × the R ``distances`` (m) around it, bearing-major, clipped to
    [−`SAMPLE_CLIP_M`, `SAMPLE_CLIP_M`]: a map of the obstacles near the drone, in every direction, which its camera
    sees only in part. Privileged: for a critic (`Task.privileged`), not the policy."""
    from jaxdrones.scene.primitives import distance

    bearing = 2 * np.pi * np.arange(bearings)[:, None] / bearings
    ranges = np.asarray(distances, np.float64)[None, :]
    offsets = np.stack([np.cos(bearing) * ranges, np.sin(bearing) * ranges, 0 * bearing * ranges], -1)
    around = sim.pos[..., None, :] + offsets.reshape((1,) * (sim.pos.ndim - 1) + (-1, 3))
    points = jnp.concatenate([sim.pos[..., None, :], around], axis=-2)
    clear = distance(task.scene, points) - task.data["collision_radius"][..., None]
    return jnp.clip(clear, -SAMPLE_CLIP_M, SAMPLE_CLIP_M)


def collided(task: TaskParams, sim: DroneState) -> jax.Array:
    """bool[D]: the drone's centre is within its collision radius of an obstacle of ``task.scene`` (`clearance`
    below 0)."""
    return clearance(task, sim) < 0


#: The clearance below which `proximity` grows, m: two of the Crazyflie's collision diameters (2 × 0.126 m), 0.25 s
#: at the task's 1 m/s.
PROXIMITY_M = 0.25


def proximity(clear: jax.Array) -> jax.Array:
    """f[D] in [0, 1]: 1 − clearance / `PROXIMITY_M`, clipped: 0 with `PROXIMITY_M` or more between the drone and
    every obstacle, 1 at contact. A dense warning before a collision, which the crash term alone gives only once."""
    return jnp.clip(1.0 - clear / PROXIMITY_M, 0.0, 1.0)


def progress(sim: DroneState, target: jax.Array) -> jax.Array:
    """f[D]: the velocity towards ``target`` f[D, 3], m/s (the rate at which the distance shrinks), a reward for
    closing in. Not clipped: a policy that flies at full speed is still paid for its heading (clipped at 1 m/s, a
    flight 40° off the goal at 1.3 m/s was paid as much as one straight at it, and policies flew past their goal)."""
    heading = (target - sim.pos) / jnp.maximum(rewards.distance(sim.pos, target), 1e-6)[..., None]
    return jnp.sum(sim.vel * heading, axis=-1)


def _between(bounds: tuple[float, float], u: jax.Array) -> jax.Array:
    return bounds[0] + (bounds[1] - bounds[0]) * u


def _field_points(config: AvoidConfig, u: jax.Array, z: float) -> jax.Array:
    """Centres f[N, 3] uniform in the field (x in field_x, |y| ≤ field_y) at height z, from u f[N, ≥2] in [0, 1)."""
    return jnp.stack(
        [_between(config.field_x, u[:, 0]), config.field_y * (2 * u[:, 1] - 1), jnp.full(u.shape[:1], z, u.dtype)], -1
    )


AVOID = Avoid()
