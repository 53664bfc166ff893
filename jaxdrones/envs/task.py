"""What a task is: the `Task` hooks (start ranges, task params and their sampling, observation, reward terms,
termination, success metrics, a moving reference), and the traced `TaskParams` with their `StartRanges` and `Bounds`.

Every hook takes the task's config first, then the task params, then the rest. A task's settings are a
`jaxdrones.envs.config.TaskConfig` subclass; `jaxdrones.envs.env.TaskEnv` runs the task with the shared action
(`jaxdrones.envs.actions`), observation (`jaxdrones.envs.observations`), reward (`jaxdrones.envs.rewards`) and
termination (`jaxdrones.envs.terminations`) modules.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdrones.envs import rewards, terminations
from jaxdrones.envs.actions import Reference
from jaxdrones.envs.config import TaskConfig
from jaxdrones.physics.state import DroneState
from jaxdrones.scene import resolve_obstacles

if TYPE_CHECKING:
    from jaxdrones.scene.primitives import Scene


@struct.dataclass
class StartRanges:
    """Where episodes start: uniform around a centre (m, rad, m/s, rad/s; world frame except ``ang_vel``).

    Attributes:
        pos: f[D, 3] centre of the start positions, m.
        pos_range: f[3] half-widths in x, y, z, m (z is kept above the ground).
        rpy: f[D, 3] centre attitude, rad.
        tilt: f[] largest random tilt, rad: roll = t cos φ, pitch = t sin φ, t ~ U[0, tilt], φ ~ U[0, 2π).
        yaw: f[] half-width of the random yaw, rad (π: any heading).
        vel: f[3] half-widths of the start velocity, m/s.
        ang_vel: f[3] half-widths of the start body rates, rad/s.
    """

    pos: jax.Array
    pos_range: jax.Array
    rpy: jax.Array
    tilt: jax.Array
    yaw: jax.Array
    vel: jax.Array
    ang_vel: jax.Array


@struct.dataclass
class Bounds:
    """Termination bounds: the arena box and the largest tilt.

    Attributes:
        pos_low: f[3] m, world frame.
        pos_high: f[3] m.
        max_tilt: f[] rad, angle between body z and world z.
    """

    pos_low: jax.Array
    pos_high: jax.Array
    max_tilt: jax.Array


@struct.dataclass
class TaskParams:
    """The traced params of a task's episode (see the module docstring).

    Attributes:
        target: f[D, 3] m, each drone's position target (world frame).
        start: `StartRanges`.
        bounds: `Bounds`.
        weights: reward weight by term name, f[].
        data: task-specific arrays (e.g. ``"target_vel"`` f[D, 3], ``"waypoints"`` f[K, D, 3]).
        scene: what the JAX backend's cameras see besides the drones, a `jaxdrones.cameras.Scene` (`Task.scene`;
            a task may draw it per episode in `Task.sample`, e.g. the ``avoid`` task's obstacles), or None without
            cameras.
    """

    target: jax.Array
    start: StartRanges
    bounds: Bounds
    weights: dict[str, jax.Array]
    data: dict[str, jax.Array] = struct.field(default_factory=dict)
    scene: Any = None


class Task(abc.ABC):
    """A task: its start sampling, reward terms and termination rule; `TaskEnv` does the rest.

    Subclasses set the class attributes and override what differs from the defaults.

    Attributes:
        name: the registered name.
        config_cls: its `TaskConfig` subclass.
        min_drones, max_drones: the drone counts it allows (``None``: no upper limit).
        nonnegative_reward: clip the shaped reward at 0 (the ``"paper"`` reward is never clipped).
        success_metric, success_at, success_threshold: how an evaluation is judged (see the class attributes;
            ``success_at`` is ``"final"``, ``"mean"`` or ``"max"``).
    """

    name: str = ""
    config_cls: type[TaskConfig] = TaskConfig
    #: The metric (a key of ``metrics``) that says how well the task is solved, lower is better; whether it is read
    #: at the episode's last step (``"final"``), averaged over the episode (``"mean"``) or taken at its largest over
    #: the episode's steps (``"max"``, e.g. the worst altitude error of a flight); and the threshold below which an
    #: evaluation counts as solved.
    success_metric: str = "distance"
    success_at: str = "final"
    success_threshold: float = 0.05
    #: The unit of `success_metric` (and its threshold), for progress displays and plots.
    success_unit: str = "m"
    #: The values `success_at` may take.
    SUCCESS_AT = ("final", "mean", "max")
    min_drones: int = 1
    max_drones: int | None = 1
    nonnegative_reward: bool = False
    #: The task reads `TaskParams.scene` itself (e.g. for collisions), so it is built even without cameras.
    uses_scene: bool = False
    #: The success metric already counts the episodes that terminate (``avoid``'s collisions are failures): a run
    #: can succeed with some terminated; otherwise success also needs no terminated episode.
    success_counts_terminations: bool = False

    def __init_subclass__(cls, **kwargs):
        """Check the class attributes when a task class is defined.

        Raises:
            ValueError: a `success_at` other than ``"final"``, ``"mean"`` or ``"max"``.
        """
        super().__init_subclass__(**kwargs)
        if cls.success_at not in Task.SUCCESS_AT:
            raise ValueError(f"{cls.__name__}: success_at must be one of {Task.SUCCESS_AT}, got {cls.success_at!r}")

    def variant(self, config: TaskConfig) -> Task:
        """The task that runs ``config`` (default: this one; a setting that changes what a task observes, rewards
        and is judged by gives another, e.g. ``fly_thru_gate`` with ``gate_pose="random"``)."""
        return self

    def check(self, config: TaskConfig) -> None:
        """Validate the config against what the task allows.

        Raises:
            ValueError: a drone count the task does not allow.
        """
        n, lo, hi = config.n_drones, self.min_drones, self.max_drones
        if n < lo or (hi is not None and n > hi):
            allowed = f"exactly {lo}" if lo == hi else (f"{lo} or more" if hi is None else f"{lo} to {hi}")
            raise ValueError(f"{self.name}: n_drones must be {allowed}, got {n}")

    def start_defaults(self, config: TaskConfig) -> dict:
        """Default random start: centre ``pos`` f[D, 3] m and the half-widths (see `TaskConfig`)."""
        from jaxdrones.physics.state import default_start_pos

        return dict(
            pos=default_start_pos(config.n_drones), pos_range=(0.0, 0.0, 0.0), tilt=0.0, yaw=0.0, vel=0.0, ang_vel=0.0
        )

    def target(self, config: TaskConfig) -> np.ndarray:
        """f[D, 3] m, the position targets (default: 1 m above each start centre)."""
        return self.start_defaults(config)["pos"] + np.array([0.0, 0.0, 1.0])

    @abc.abstractmethod
    def weights(self, config: TaskConfig) -> dict[str, float]:
        """Reward weights by term name, for ``config.reward``."""

    def data(self, config: TaskConfig) -> dict[str, np.ndarray]:
        """Task-specific arrays of the task params (default: none)."""
        return {}

    def sample(self, config: TaskConfig, task: TaskParams, key: jax.Array) -> TaskParams:
        """Per-episode randomness of the task params (default: none)."""
        return task

    def scene(self, config: TaskConfig) -> Scene:
        """What the JAX backend's cameras see (`TaskParams.scene`), built once per env: by default the config's
        ``obstacles`` (`jaxdrones.cameras.make_scene`)."""
        from jaxdrones.scene.primitives import make_scene

        return make_scene(resolve_obstacles(config.obstacles))

    #: Entries per drone of the task's own observation, appended after the observation type's (e.g. a commanded
    #: velocity, the offset to a waypoint); 0 for none.
    obs_size: int = 0

    def obs_bound(self, config: TaskConfig) -> np.ndarray:
        """f[obs_size], the symmetric bound of the task observation (it is clipped to it)."""
        return np.zeros(0, np.float32)

    def observe(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        """The task observation f[D, obs_size] (what the policy must know of the task: targets, commands)."""
        return jnp.zeros(sim.pos.shape[:-1] + (0,), sim.pos.dtype)

    def privileged(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array | None:
        """f[D, k]: what a critic may read and the policy does not (an asymmetric actor-critic: Pinto et al.,
        "Asymmetric Actor Critic for Image-Based Robot Learning", RSS 2018), e.g. the obstacles a camera sees;
        ``None`` (the default) when the task has none."""
        return None

    def reference(self, config: TaskConfig, task: TaskParams, steps: jax.Array) -> Reference:
        """Where the drones should be at control step ``steps`` (default: at the target, at rest)."""
        return Reference(task.target, jnp.zeros_like(task.target))

    def tracking_error(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> jax.Array:
        """f[D, 3]: what the observation's error integral sums (`TaskConfig.error_integral`); by default the
        reference position minus the position, m, world frame (`reference`)."""
        return self.reference(config, task, steps).pos - sim.pos

    @abc.abstractmethod
    def reward_terms(
        self, config: TaskConfig, task: TaskParams, sim: DroneState, action: jax.Array, steps: jax.Array
    ) -> dict[str, jax.Array]:
        """Reward terms by name, each f[D], from the post-step state."""

    def terminated(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        """bool[]: the world's episode ends (default: any drone crashed, see `terminations.crashed`)."""
        return jnp.any(terminations.crashed(sim, task.bounds, config.terminate_on_ground))

    def reached(self, config: TaskConfig, task: TaskParams, sim: DroneState) -> jax.Array:
        """bool[]: the world's episode ends at its goal (terminated, but not a crash; default: never, the episode
        runs to its time limit)."""
        return jnp.zeros((), bool)

    def loss_weights(self, config: TaskConfig) -> dict[str, float]:
        """Weights of `loss_terms` in the differentiable training loss (default: distance² 1, velocity error² 0.1,
        body rate² 0.01), kept apart from the RL reward's weights."""
        return {"distance_sq": 1.0, "velocity_error_sq": 0.1, "ang_speed_sq": 0.01}

    def loss_terms(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """Terms of the differentiable training loss, each f[D], from the post-step state: the squared distance
        to the reference position (m²), the squared velocity error to the reference velocity ((m/s)²) and the
        squared body rate ((rad/s)²). Smooth everywhere, unlike shaped RL rewards such as max(0, ...), which have
        no gradient far from the target."""
        ref = self.reference(config, task, steps)
        return {
            "distance_sq": rewards.distance_sq(sim.pos, ref.pos),
            "velocity_error_sq": rewards.velocity_error_sq(sim.vel, ref.vel),
            "ang_speed_sq": rewards.ang_speed_sq(sim.ang_vel),
        }

    def metrics(self, config: TaskConfig, task: TaskParams, sim: DroneState, steps: jax.Array) -> dict:
        """Success metrics, f[] per world (default: ``distance``, the mean distance to the reference, m)."""
        ref = self.reference(config, task, steps)
        return {"distance": jnp.mean(rewards.distance(sim.pos, ref.pos))}
