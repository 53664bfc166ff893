"""Take-off and hover, the paper's single-agent task (IROS 2021 §V, gym-pybullet-drones HoverAviary)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.envs.base import Env, EnvState, kinematic_obs
from jaxdrones.params import load_params
from jaxdrones.rotations import quat_from_euler
from jaxdrones.sim import SimConfig, make_step
from jaxdrones.state import DroneState

#: Normalised actions a in [-1, 1] map to rpm = hover_rpm · (1 + RPM_ACTION_SCALE · a) (facts §10.1).
RPM_ACTION_SCALE = 0.05
ACTION_TYPES = {"rpm": 4, "one_d_rpm": 1}
REWARDS = ("shaped", "paper")


@dataclasses.dataclass(frozen=True)
class HoverConfig:
    """Settings of the hover task (static; a field changes the compiled program).

    Attributes:
        model: drone model name or URDF path for `load_params`.
        sim_freq: physics rate, Hz.
        ctrl_freq: control (env step) rate, Hz; the paper's code uses 30 Hz for HoverAviary.
        episode_len_s: episode length, s (the paper's single-agent tasks: 5 s).
        target: (x, y, z) hover target, m, world frame (the paper: (0, 0, 1)).
        action_type: ``"one_d_rpm"`` (one value for all four motors, the paper's hover default) or ``"rpm"``
            (one per motor). Both map a in [-1, 1] to hover_rpm·(1 + 0.05 a) (facts §10.1); actions are clipped to
            [-1, 1] (the original does not clip).
        reward: ``"shaped"`` (default): r = max(0, exp(-d / 0.3) + 2 exp(-(d / 0.03)²) - 0.1 ‖v‖²) with
            d = ‖target - pos‖ in m and v in m/s: non-negative, so that ending an episode early never pays, and
            sharp near the target, so that PPO settles on it rather than near it; ``"paper"``: the paper's eq.
            (single), r = -d².
        drag, ground_effect, downwash: aerodynamic effects of the simulator.
        init_z: (low, high) start height range, m.
        init_vz: start vertical speed drawn from [-init_vz, init_vz], m/s.
        init_xy: start x, y drawn from [-init_xy, init_xy], m (keep 0 for ``one_d_rpm``, which cannot move sideways).
        init_rpy: start roll, pitch and yaw drawn from [-init_rpy, init_rpy], rad (keep 0 for ``one_d_rpm``).
        arena_xy: the episode terminates when |x| or |y| exceeds this, m.
        arena_z: the episode terminates when z exceeds this, m.
        max_tilt: the episode terminates when |roll| or |pitch| exceeds this, rad (the paper's code: 0.4).
        terminate_on_ground: a touch of the ground terminates the episode as a crash. Off by default: the ground
            holds the drone (see `dynamics.ground_contact`) and it may take off again, as in the paper's task.
    """

    model: str = "cf2x"
    sim_freq: int = 240
    ctrl_freq: int = 30
    episode_len_s: float = 5.0
    target: tuple[float, float, float] = (0.0, 0.0, 1.0)
    action_type: str = "one_d_rpm"
    reward: str = "shaped"
    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False
    init_z: tuple[float, float] = (0.1125, 1.8)
    init_vz: float = 0.2
    init_xy: float = 0.0
    init_rpy: float = 0.0
    arena_xy: float = 1.5
    arena_z: float = 2.5
    max_tilt: float = 0.4
    terminate_on_ground: bool = False

    def __post_init__(self):
        if self.action_type not in ACTION_TYPES:
            raise ValueError(f"hover: action_type must be one of {tuple(ACTION_TYPES)}, got {self.action_type!r}")
        if self.reward not in REWARDS:
            raise ValueError(f"hover: reward must be one of {REWARDS}, got {self.reward!r}")
        if len(self.target) != 3 or not all(math.isfinite(v) for v in self.target):
            raise ValueError(f"hover: target must be three finite numbers (x, y, z) in m, got {self.target}")
        if (len(self.init_z) != 2 or not all(math.isfinite(v) for v in self.init_z)
                or not 0 <= self.init_z[0] <= self.init_z[1]):
            raise ValueError(f"hover: init_z must be a finite (low, high) range with 0 <= low <= high, m, "
                             f"got {self.init_z}")
        for name in ("init_vz", "init_xy", "init_rpy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"hover: {name} must be a finite half-width >= 0, got {value}")
        for name in ("arena_xy", "arena_z", "max_tilt"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"hover: {name} must be > 0, got {value}")
        if not (math.isfinite(self.episode_len_s) and self.episode_len_s * self.ctrl_freq >= 1):
            raise ValueError(f"hover: episode_len_s·ctrl_freq must give at least one step, got {self.episode_len_s} s "
                             f"at {self.ctrl_freq} Hz")


class HoverEnv(Env):
    """One drone takes off and hovers at a target (brax protocol; jit and vmap over ``reset``/``step``).

    Observation: f[12] kinematic state (eq. obs): pos m, rpy rad, vel m/s (world), ang_vel rad/s (body).
    Action: f[1] (``one_d_rpm``) or f[4] (``rpm``) in [-1, 1], see `HoverConfig`.
    A non-finite action is replaced by 0 (hover RPM) for the physics, terminates the episode and sets
    ``metrics["invalid_action"]`` to 1.
    """

    def __init__(self, config: HoverConfig = HoverConfig()):
        self.config = config
        self.sim_config = SimConfig(n_drones=1, sim_freq=config.sim_freq, ctrl_freq=config.ctrl_freq,
                                    drag=config.drag, ground_effect=config.ground_effect,
                                    downwash=config.downwash)
        self.params = load_params(config.model)
        self._step = make_step(self.sim_config)
        self._target = np.asarray(config.target, dtype=np.float64)

    @property
    def observation_size(self) -> int:
        return 12

    @property
    def action_size(self) -> int:
        return ACTION_TYPES[self.config.action_type]

    @property
    def episode_length(self) -> int:
        return int(round(self.config.episode_len_s * self.config.ctrl_freq))

    @property
    def target(self) -> jax.Array:
        """f[3] hover target, m, world frame."""
        return jnp.asarray(self._target, dtype=self.params.mass.dtype)

    def reset(self, key: jax.Array) -> EnvState:
        cfg = self.config
        key, k_z, k_vz, k_xy, k_rpy = jax.random.split(key, 5)
        dtype = self.params.mass.dtype
        z = jax.random.uniform(k_z, (), dtype, cfg.init_z[0], cfg.init_z[1])
        xy = jax.random.uniform(k_xy, (2,), dtype, -cfg.init_xy, cfg.init_xy)
        vz = jax.random.uniform(k_vz, (), dtype, -cfg.init_vz, cfg.init_vz)
        rpy = jax.random.uniform(k_rpy, (3,), dtype, -cfg.init_rpy, cfg.init_rpy)
        zeros3 = jnp.zeros((1, 3), dtype)
        sim = DroneState(
            pos=jnp.concatenate([xy, z[None]])[None], quat=quat_from_euler(rpy)[None],
            vel=zeros3.at[0, 2].set(vz), ang_vel=zeros3, rpm=jnp.zeros((1, 4), dtype),
            contact=jnp.zeros((1,), jnp.int32),
        )
        zero = jnp.zeros((), dtype)
        return EnvState(
            sim=sim, params=self.params, key=key, obs=self._obs(sim), reward=zero,
            terminated=jnp.zeros((), bool), truncated=jnp.zeros((), bool), steps=jnp.zeros((), jnp.int32),
            metrics={"distance": self._distance(sim), "crash": zero, "invalid_action": zero},
        )

    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        cfg = self.config
        action = jnp.asarray(action)
        if action.shape != (self.action_size,):
            raise ValueError(f"hover: action must have shape ({self.action_size},) for action_type="
                             f"{cfg.action_type!r} (normalised RPM in [-1, 1]), got {action.shape}")
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise ValueError(f"hover: action must be a float array in [-1, 1], got dtype {action.dtype}")
        finite = jnp.all(jnp.isfinite(action))
        action = jnp.where(finite, jnp.clip(action, -1.0, 1.0), 0.0).astype(state.sim.pos.dtype)
        rpm = state.params.hover_rpm * (1.0 + RPM_ACTION_SCALE * jnp.broadcast_to(action, (4,)))
        sim = self._step(state.params, state.sim, rpm[None])
        steps = state.steps + 1
        obs = self._obs(sim)
        crashed = self._crashed(sim, rpy=obs[3:6])
        terminated = crashed | ~finite
        truncated = (steps >= self.episode_length) & ~terminated
        dtype = sim.pos.dtype
        metrics = {"distance": self._distance(sim), "crash": crashed.astype(dtype),
                   "invalid_action": (~finite).astype(dtype)}
        return state.replace(sim=sim, obs=obs, reward=self._reward(sim), terminated=terminated,
                             truncated=truncated, steps=steps, metrics=metrics)

    def _obs(self, sim: DroneState) -> jax.Array:
        return kinematic_obs(sim)[0]

    def _distance(self, sim: DroneState) -> jax.Array:
        return jnp.linalg.norm(sim.pos[0] - self.target)

    def _reward(self, sim: DroneState) -> jax.Array:
        d2 = jnp.sum((sim.pos[0] - self.target) ** 2)
        if self.config.reward == "paper":
            return -d2
        speed2 = jnp.sum(sim.vel[0] ** 2)
        shaped = jnp.exp(-jnp.sqrt(d2 + 1e-12) / 0.3) + 2.0 * jnp.exp(-d2 / 0.03**2) - 0.1 * speed2
        return jnp.maximum(0.0, shaped)

    def _crashed(self, sim: DroneState, rpy: jax.Array) -> jax.Array:
        """Left the arena or tilted too far (``rpy`` f[3] rad, from the observation), or touched the ground."""
        cfg = self.config
        pos = sim.pos[0]
        out = (jnp.any(jnp.abs(pos[:2]) > cfg.arena_xy) | (pos[2] > cfg.arena_z)
               | jnp.any(jnp.abs(rpy[:2]) > cfg.max_tilt))
        if cfg.terminate_on_ground:
            out = out | sim.ground_contact[0]
        return out
