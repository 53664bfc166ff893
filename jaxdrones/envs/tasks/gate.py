"""``fly_thru_gate``: fly through the paper's gate, at its fixed place following a reference (`FlyThruGate`), or,
with ``gate_pose="random"``, drawn per episode ahead of the drone and seen only through its camera (`GatePass`).

The paper's FlyThruGateAviary puts its gate at a fixed place and rewards following a reference through it, so a
policy needs no camera. Here the gate's pose (distance, offset across and yaw) is drawn per episode and is in no
part of the observation, which is the drone's kinematic state alone: the policy finds the gate in its images.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs import terminations
from jaxdrones.envs.actions import Reference
from jaxdrones.envs.config import TaskConfig
from jaxdrones.envs.task import Task, TaskParams
from jaxdrones.envs.tasks.avoid import GoalTask, collided, progress
from jaxdrones.envs.tasks.single import ReferenceTask, hover_weights
from jaxdrones.physics.state import DEFAULT_START_Z, DroneState
from jaxdrones.scene import Obstacle

if TYPE_CHECKING:
    from jaxdrones.scene.primitives import Scene

#: The paper's gate (FlyThruGateAviary): at y = −1 m, two 0.05 m columns 0.5 m tall at x = ±0.3 m and a
#: 0.8 × 0.05 × 0.05 m architrave at z = 0.55 m, on the ground: its boxes as (centre, size) in the gate's frame
#: (origin on the ground below the architrave's centre, x along it, y across the gate).
GATE_Y = -1.0
GATE_COLUMN_X = 0.3
GATE_PARTS = (
    ((-GATE_COLUMN_X, 0.0, 0.245), (0.05, 0.05, 0.5)),
    ((GATE_COLUMN_X, 0.0, 0.245), (0.05, 0.05, 0.5)),
    ((0.0, 0.0, 0.55), (0.8, 0.05, 0.05)),
)
#: The gate's opening in its frame: |x| < 0.275 m between the columns, below z = 0.525 m (the architrave).
GATE_OPENING_HALF_X = GATE_COLUMN_X - 0.025
GATE_OPENING_TOP = 0.525
#: The gate's reference: a point moving from (0, 0, 0.75) to (0, −2, 0.75) m over the episode.
GATE_REF_Z = 0.75
GATE_REF_DY = -2.0


def gate_obstacles() -> tuple:
    """The paper's gate as obstacles (`jaxdrones.scene.Obstacle` boxes)."""
    colour = (0.6, 0.6, 0.6, 1.0)
    return tuple(Obstacle("box", size=size, pos=(x, GATE_Y + y, z), rgba=colour) for (x, y, z), size in GATE_PARTS)


@dataclasses.dataclass(frozen=True)
class GateConfig(TaskConfig):
    """Settings of `FlyThruGate`.

    Attributes:
        gate_pose: ``"fixed"``, the paper's gate at y = −1 m, a reference to follow through it (`FlyThruGate`);
            ``"random"``, the gate drawn per episode ahead of the drone and seen only through its camera, with no
            reference (`jaxdrones.envs.tasks.gate.GatePass`; JAX backend).
        gate_distance: ``"random"``: (low, high) of the gate's distance ahead of the start (along +x), m.
        gate_offset: ``"random"``: the gate's centre within ±gate_offset m across (y).
        gate_yaw: ``"random"``: the gate's yaw within ±gate_yaw rad.

    With ``"fixed"``, on the PyBullet backend and with ``vision`` on the JAX backend (the cameras see it),
    ``obstacles`` defaults to the gate (`gate_obstacles`).

    Raises:
        ValueError: an unknown ``gate_pose``, a range out of order or negative, or ``"random"`` with
            ``backend="pybullet"`` or with ``obstacles``.
    """

    arena_xy: float = 3.0
    gate_pose: str = "fixed"
    gate_distance: tuple[float, float] = (1.5, 2.5)
    gate_offset: float = 0.4
    gate_yaw: float = 0.5

    def __post_init__(self):
        if self.gate_pose not in GATE_POSES:
            raise ValueError(f"fly_thru_gate: gate_pose must be one of {GATE_POSES}, got {self.gate_pose!r}")
        lo, hi = (float(v) for v in self.gate_distance)
        if not (math.isfinite(hi) and 1.0 <= lo <= hi):
            raise ValueError(
                f"fly_thru_gate: gate_distance must be (low, high) m with 1 <= low <= high, got {self.gate_distance!r}"
            )
        object.__setattr__(self, "gate_distance", (lo, hi))
        for name in ("gate_offset", "gate_yaw"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"fly_thru_gate: {name} must be a finite number >= 0, got {value!r}")
        if self.gate_pose == "random":
            if self.backend != "jax" or self.obstacles is not None:
                raise ValueError(
                    "fly_thru_gate: gate_pose='random' draws the gate per episode in the task params: "
                    "backend='jax' and no obstacles"
                )
        elif (self.backend == "pybullet" or self.vision) and self.obstacles is None:
            object.__setattr__(self, "obstacles", gate_obstacles())
        super().__post_init__()


#: The values of `GateConfig.gate_pose`.
GATE_POSES = ("fixed", "random")


class FlyThruGate(ReferenceTask):
    """Fly through the paper's gate (FlyThruGateAviary): follow a reference point moving from (0, 0, 0.75) m to
    (0, −2, 0.75) m over the episode, through the gate at y = −1 m.

    On the JAX backend the gate is only the reference; on the PyBullet backend its columns and architrave are
    obstacles (contacts reported in ``state.sim.contact``). With ``gate_pose="random"`` the env runs
    `GatePass` instead (the gate drawn per episode, seen only through the camera). The observation appends the
    offset to the reference point and its velocity (6 entries). Starts: the paper's default start (0, 0, 0.1125) m,
    within ±0.05 m in x and y, any yaw.
    Reward ``"shaped"``: as `Hover`'s, towards the moving reference; ``"paper"``: −10 ‖p* − p‖².
    Success metric: ``distance`` to the reference (m).
    """

    name = "fly_thru_gate"
    config_cls = GateConfig
    success_at = "mean"
    success_threshold = 0.1

    def variant(self, config: GateConfig) -> Task:
        if config.gate_pose == "random":
            return GATE_PASS
        return self

    def start_defaults(self, config: GateConfig) -> dict:
        return dict(
            pos=[[0.0, 0.0, DEFAULT_START_Z]], pos_range=(0.05, 0.05, 0.0), tilt=0.0, yaw=math.pi, vel=0.0, ang_vel=0.0
        )

    def target(self, config: GateConfig) -> np.ndarray:
        return np.array([[0.0, GATE_REF_DY, GATE_REF_Z]])

    def weights(self, config: GateConfig) -> dict[str, float]:
        return hover_weights(config, {"distance_sq": -10.0})

    def reference(self, config: GateConfig, task: TaskParams, steps: jax.Array) -> Reference:
        duration = config.episode_len_s
        tau = jnp.minimum(steps / config.sim.ctrl_freq, duration) / duration
        start = task.target.at[..., 1].set(0.0)
        vel = (task.target - start) / duration
        return Reference(start + (task.target - start) * tau, jnp.where(tau < 1, vel, 0.0))


# ---------------------------------------------------------------------------------------------------------------
# the gate drawn per episode
# ---------------------------------------------------------------------------------------------------------------

#: The start's height, m: the opening's mid height (the drone starts at the origin facing +x, towards the gate).
START_Z = 0.25
#: Where the progress reward pulls, in the gate's frame: 0.5 m beyond the opening's centre, at its mid height.
AIM = (0.0, -0.5, 0.25)


class GatePass(GoalTask):
    """Fly through the paper's gate (its two columns and architrave, `GATE_PARTS`), drawn per episode: its centre
    ``gate_distance`` m ahead along +x, within ±``gate_offset`` m across (y), facing the start (its frame's −y
    along +x) yawed within ±``gate_yaw`` rad.

    Starts at (0, 0, 0.25) m within ±0.1 m across, level, facing +x. The observation is the kinematic state only
    (``obs_size`` 0): the gate is in `TaskParams.scene` (the cameras draw it) and nowhere else. The episode ends at
    its goal (`reached`) when the drone crosses the gate's plane inside the opening (|x| < 0.275 m, z < 0.525 m in
    the gate's frame) without touching it; it terminates on a collision with the gate (the drone's centre within its
    collision radius of a box, `jaxdrones.cameras.distance`), on crossing the plane outside the opening (missed),
    touching the ground or leaving the arena.

    Reward (both ``reward`` settings): ``progress``, the velocity towards a point 0.5 m beyond the opening's centre
    (m/s), weight 1; ``reached``, 1 on passing, weight 10; ``crash``, 1 on any termination but passing, weight −50.
    Success metric: ``failure``, 0 when the episode ends through the opening, else 1; solved when at most 10 % of the
    evaluation episodes fail (``success_rate`` ≥ 0.9).
    """

    name = "fly_thru_gate"
    config_cls = GateConfig
    obs_size = 0

    def check(self, config: GateConfig) -> None:
        super().check(config)
        if not config.vision:
            raise ValueError(
                "fly_thru_gate with gate_pose='random' sees the gate only through its camera: set "
                "vision, e.g. vision=('depth',)"
            )

    def obs_bound(self, config: GateConfig) -> np.ndarray:
        return np.zeros(0, np.float32)

    def start_defaults(self, config: GateConfig) -> dict:
        return dict(pos=[[0.0, 0.0, START_Z]], pos_range=(0.0, 0.1, 0.0), tilt=0.0, yaw=0.0, vel=0.0, ang_vel=0.0)

    def target(self, config: GateConfig) -> np.ndarray:
        return np.array([[config.gate_distance[0] - AIM[1], AIM[0], AIM[2]]])

    def data(self, config: GateConfig) -> dict[str, np.ndarray]:
        return {**super().data(config), "gate_pos": np.zeros(3), "gate_rot": np.eye(3)}

    def scene(self, config: GateConfig) -> Scene:
        from jaxdrones.scene.primitives import make_scene

        return make_scene((), capacity={"box": len(GATE_PARTS)})

    def sample(self, config: GateConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        u = jax.random.uniform(key, (3,), task.target.dtype)
        lo, hi = config.gate_distance
        centre = jnp.stack([lo + (hi - lo) * u[1], config.gate_offset * (2 * u[0] - 1), jnp.zeros_like(u[0])])
        yaw = math.pi / 2 + config.gate_yaw * (2 * u[2] - 1)  # the gate's −y along +x: it faces the start
        c, s, zero, one = jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw), jnp.ones_like(yaw)
        rot = jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])
        local = jnp.asarray([p for p, _ in GATE_PARTS], centre.dtype)
        half = jnp.asarray([size for _, size in GATE_PARTS], centre.dtype) / 2
        box = task.scene.box.replace(
            pos=centre[None] + local @ rot.T,
            rot=jnp.broadcast_to(rot, (len(GATE_PARTS), 3, 3)),
            size=half,
            seg=1 + jnp.arange(len(GATE_PARTS), dtype=jnp.int32),
            valid=jnp.ones(len(GATE_PARTS), bool),
            rgb=jnp.full((len(GATE_PARTS), 3), 0.6, centre.dtype),
        )
        aim = centre + rot @ jnp.asarray(AIM, centre.dtype)
        return task.replace(
            target=jnp.broadcast_to(aim, task.target.shape),
            scene=task.scene.replace(box=box),
            data={**task.data, "gate_pos": centre, "gate_rot": rot},
        )

    def observe(self, config: GateConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        return jnp.zeros(sim.pos.shape[:-1] + (0,), sim.pos.dtype)

    def reward_terms(
        self, config: GateConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        dtype = sim.pos.dtype
        return {
            "progress": progress(sim, task.target),
            "reached": _through(task, sim).astype(dtype),
            "crash": self._failed(config, task, sim).astype(dtype),
        }

    def terminated(self, config: GateConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        return jnp.any(self._failed(config, task, sim))

    def reached(self, config: GateConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        return jnp.all(_through(task, sim)) & ~self.terminated(config, task, sim)

    def metrics(self, config: GateConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict[str, jax.Array]:
        hit = jnp.any(collided(task, sim))
        passed = self.reached(config, task, sim)
        dtype = sim.pos.dtype
        return {
            "collision": hit.astype(dtype),
            "missed": jnp.any(_missed(task, sim)).astype(dtype),
            "failure": (~passed).astype(dtype),
        }

    @staticmethod
    def _failed(config, task, sim: DroneState) -> jax.Array:
        """bool[D]: a collision with the gate, a miss, the ground (whatever ``terminate_on_ground``: the opening is
        0.5 m tall) or out of the arena."""
        lost = terminations.crashed(sim, task.bounds, True)
        return collided(task, sim) | _missed(task, sim) | lost


def _in_gate_frame(task, sim: DroneState) -> jax.Array:
    """f[D, 3]: the drones' positions in the gate's frame (x along the architrave, y across, z up)."""
    return (sim.pos - jnp.broadcast_to(task.data["gate_pos"], sim.pos.shape)) @ task.data["gate_rot"]


def _crossed(task, sim: DroneState) -> tuple[jax.Array, jax.Array]:
    """bool[D] twice: beyond the gate's plane (the start is on its +y side), and within the opening."""
    local = _in_gate_frame(task, sim)
    inside = (jnp.abs(local[..., 0]) < GATE_OPENING_HALF_X) & (local[..., 2] < GATE_OPENING_TOP)
    return local[..., 1] < 0, inside


def _through(task, sim: DroneState) -> jax.Array:
    beyond, inside = _crossed(task, sim)
    return beyond & inside


def _missed(task, sim: DroneState) -> jax.Array:
    beyond, inside = _crossed(task, sim)
    return beyond & ~inside


GATE_PASS = GatePass()

FLY_THRU_GATE = FlyThruGate()
