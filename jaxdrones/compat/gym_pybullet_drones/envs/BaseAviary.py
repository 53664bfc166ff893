"""gym-pybullet-drones' ``BaseAviary`` on the jaxdrones physics: the same constructor, constants, state vector and
``reset``/``step``/``render`` cycle, with each step one jitted physics call (``make_step``).

Subclasses implement the original's hooks (``_actionSpace``, ``_observationSpace``, ``_preprocessAction``,
``_computeObs``, ``_computeReward``, ``_computeTerminated``, ``_computeTruncated``, ``_computeInfo``) in NumPy on the
host, reading the drones' state with ``_getDroneStateVector(i)``, so that an aviary subclassed from the original's
runs here unchanged. docs/migrating.md lists what differs.
"""

from __future__ import annotations

import abc
import time
import warnings

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.compat.gym_pybullet_drones._common import KeywordHints
from jaxdrones.compat.gym_pybullet_drones.utils.enums import PHYSICS_EFFECTS, DroneModel, Physics
from jaxdrones.envs.config import fixed_triples
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import load_params
from jaxdrones.physics.rotations import quat_to_euler, quat_to_rotmat
from jaxdrones.physics.state import DEFAULT_START_Z, init_state
from jaxdrones.sim import make_step

#: The backends an aviary runs on: the JAX core, or PyBullet (collisions with the ground and the obstacles).
BACKENDS = ("jax", "pybullet")


class BaseAviary(KeywordHints, gym.Env, metaclass=abc.ABCMeta):
    """The base of the aviaries: D drones of one model, stepped at ``ctrl_freq`` with ``pyb_freq // ctrl_freq``
    physics substeps per step.

    Args:
        drone_model: a `DroneModel` (or its value, e.g. ``"cf2x"``).
        num_drones: D ≥ 1.
        neighbourhood_radius: m, kept as ``NEIGHBOURHOOD_RADIUS`` (the original's adjacency radius).
        initial_xyzs: f[D, 3] m, world frame; default drone i at (4iL, 4iL, 0.1125), the original's.
        initial_rpys: f[D, 3] rad (roll, pitch, yaw); default 0.
        physics: a `Physics` member: the aerodynamics (drag, ground effect, downwash) of its name on the paper's
            explicit update (`jaxdrones.compat.gym_pybullet_drones.utils.enums.Physics`).
        pyb_freq: physics rate, Hz, a multiple of ``ctrl_freq``.
        ctrl_freq: control rate, Hz.
        gui, record, user_debug_gui: PyBullet's window, video and sliders: not available here; ``gui`` and
            ``record`` warn once and run headless.
        obstacles: the original's four obstacles; they collide only with ``backend="pybullet"`` (a warning says so
            on the JAX backend, whose physics has the ground only).
        vision_attributes: must be False (see `jaxdrones.make`'s ``vision`` for cameras).
        output_folder: kept as ``OUTPUT_FOLDER``.
        backend: ``"jax"`` (default) or ``"pybullet"`` (PyBullet's integrator and collisions; needs pybullet).

    Attributes: the original's constants, from the model's URDF (`jaxdrones.physics.params`): ``M``, ``L``,
    ``THRUST2WEIGHT_RATIO``, ``J``, ``J_INV``, ``KF``, ``KM``, ``COLLISION_H``, ``COLLISION_R``, ``MAX_SPEED_KMH``,
    ``GND_EFF_COEFF``, ``PROP_RADIUS``, ``DRAG_COEFF``, ``DW_COEFF_1..3``, ``G``, ``GRAVITY``, ``HOVER_RPM``,
    ``MAX_RPM``, ``MAX_THRUST``, ``MAX_XY_TORQUE``, ``MAX_Z_TORQUE``, ``GND_EFF_H_CLIP``; the rates ``CTRL_FREQ``,
    ``PYB_FREQ``, ``PYB_STEPS_PER_CTRL``, ``CTRL_TIMESTEP``, ``PYB_TIMESTEP``; ``NUM_DRONES``, ``INIT_XYZS``,
    ``INIT_RPYS``, ``step_counter`` (physics substeps since the reset); the drones' state ``pos``, ``quat``, ``rpy``,
    ``vel``, ``ang_v`` (world frame, as PyBullet's ``getBaseVelocity``) and ``last_clipped_action`` (RPM).

    Raises:
        ValueError: an unknown model, physics or backend, ``pyb_freq`` not a multiple of ``ctrl_freq``, initial
            positions or attitudes not of shape (D, 3), or ``vision_attributes``.
        TypeError: an unknown keyword (with the closest valid one).
    """

    metadata = {"render_modes": ["human"]}

    def __init__(
        self,
        drone_model: DroneModel = DroneModel.CF2X,
        num_drones: int = 1,
        neighbourhood_radius: float = np.inf,
        initial_xyzs=None,
        initial_rpys=None,
        physics: Physics = Physics.PYB,
        pyb_freq: int = 240,
        ctrl_freq: int = 240,
        gui: bool = False,
        record: bool = False,
        obstacles: bool = False,
        user_debug_gui: bool = True,
        vision_attributes: bool = False,
        output_folder: str = "results",
        backend: str = "jax",
    ):
        self.DRONE_MODEL, self.PHYSICS = DroneModel(drone_model), Physics(physics)
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if vision_attributes:
            raise ValueError(
                "vision_attributes: the compat aviaries have no cameras; jaxdrones.make(task, "
                "vision=('rgb',)) gives camera observations"
            )
        if not (isinstance(num_drones, (int, np.integer)) and num_drones >= 1):
            raise ValueError(f"num_drones must be a positive integer, got {num_drones!r}")
        self.G, self.RAD2DEG, self.DEG2RAD = 9.8, 180 / np.pi, np.pi / 180
        self.CTRL_FREQ, self.PYB_FREQ = ctrl_freq, pyb_freq
        if pyb_freq % ctrl_freq != 0:
            raise ValueError(f"pyb_freq ({pyb_freq} Hz) must be a multiple of ctrl_freq ({ctrl_freq} Hz)")
        self.PYB_STEPS_PER_CTRL = int(pyb_freq // ctrl_freq)
        self.CTRL_TIMESTEP, self.PYB_TIMESTEP = 1.0 / ctrl_freq, 1.0 / pyb_freq
        self.NUM_DRONES, self.NEIGHBOURHOOD_RADIUS = int(num_drones), neighbourhood_radius
        self.GUI, self.RECORD, self.OBSTACLES, self.USER_DEBUG = gui, record, obstacles, user_debug_gui
        self.URDF, self.OUTPUT_FOLDER, self.VISION_ATTR = self.DRONE_MODEL.value + ".urdf", output_folder, False
        self.BACKEND = backend
        for flag, what in ((gui, "gui (PyBullet's window)"), (record, "record (PyBullet's video)")):
            if flag:
                warnings.warn(
                    f"{type(self).__name__}: {what} is not available here; running headless "
                    f"(jaxdrones fly and jaxdrones.video record flights)",
                    UserWarning,
                    stacklevel=3,
                )
        if obstacles and backend == "jax":
            warnings.warn(
                f"{type(self).__name__}: obstacles are not simulated on the JAX backend (its physics has "
                f"the ground only); pass backend='pybullet' for collisions",
                UserWarning,
                stacklevel=3,
            )
        self._set_constants(load_params(self.DRONE_MODEL.value))
        n = self.NUM_DRONES
        i = np.arange(n)
        default = np.stack([4 * i * self.L, 4 * i * self.L, np.full(n, DEFAULT_START_Z)], axis=-1)
        xyzs = default if initial_xyzs is None else initial_xyzs
        rpys = np.zeros((n, 3)) if initial_rpys is None else initial_rpys
        self.INIT_XYZS = np.asarray(fixed_triples("initial_xyzs", xyzs, n))
        self.INIT_RPYS = np.asarray(fixed_triples("initial_rpys", rpys, n))
        drag, ground_effect, downwash = PHYSICS_EFFECTS[self.PHYSICS]
        self._config = SimConfig(
            n_drones=n,
            sim_freq=pyb_freq,
            ctrl_freq=ctrl_freq,
            drag=drag,
            ground_effect=ground_effect,
            downwash=downwash,
        )
        options = {"obstacles": "paper" if obstacles else None} if backend == "pybullet" else {}
        self._sim_step = make_step(self._config, backend=backend, **options)
        self.action_space = self._actionSpace()
        self.observation_space = self._observationSpace()
        self._housekeeping()
        self._updateAndStoreKinematicInformation()

    def _set_constants(self, params) -> None:
        self._params = params
        p = jax.tree.map(np.asarray, params)
        self.M, self.L, self.THRUST2WEIGHT_RATIO = float(p.mass), float(p.arm), float(p.thrust2weight)
        self.J, self.J_INV = np.asarray(p.inertia, np.float64), np.asarray(p.inertia_inv, np.float64)
        self.KF, self.KM = float(p.kf), float(p.km)
        self.COLLISION_H, self.COLLISION_R = float(p.collision_height), float(p.collision_radius)
        self.MAX_SPEED_KMH, self.GND_EFF_COEFF = float(p.max_speed_kmh), float(p.gnd_eff_coeff)
        self.PROP_RADIUS, self.DRAG_COEFF = float(p.prop_radius), np.asarray(p.drag_coeff, np.float64)
        self.DW_COEFF_1, self.DW_COEFF_2, self.DW_COEFF_3 = (float(c) for c in np.asarray(p.dw_coeff))
        self.GRAVITY = self.G * self.M
        self.HOVER_RPM, self.MAX_RPM, self.MAX_THRUST = float(p.hover_rpm), float(p.max_rpm), float(p.max_thrust)
        self.MAX_XY_TORQUE, self.MAX_Z_TORQUE = float(p.max_xy_torque), float(p.max_z_torque)
        self.GND_EFF_H_CLIP = float(p.gnd_eff_h_clip)

    # -- the gymnasium cycle ----------------------------------------------------------------------------------------

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start again from ``INIT_XYZS`` and ``INIT_RPYS`` at rest; returns ``(obs, info)`` (`_computeObs`,
        `_computeInfo`). ``seed`` seeds ``np_random`` (the start is not random); ``options`` is unused."""
        super().reset(seed=seed, options=options)
        self._housekeeping()
        self._updateAndStoreKinematicInformation()
        return self._computeObs(), self._computeInfo()

    def step(self, action):
        """One control step: ``_preprocessAction(action)`` gives the RPMs f[D, 4], the physics advances
        ``PYB_STEPS_PER_CTRL`` substeps; returns ``(obs, reward, terminated, truncated, info)`` from the hooks."""
        rpm = np.reshape(self._preprocessAction(action), (self.NUM_DRONES, 4))
        self._state = self._sim_step(self._params, self._state, rpm)
        self.last_clipped_action = rpm
        self._updateAndStoreKinematicInformation()
        out = (
            self._computeObs(),
            self._computeReward(),
            self._computeTerminated(),
            self._computeTruncated(),
            self._computeInfo(),
        )
        self.step_counter += self.PYB_STEPS_PER_CTRL
        return out

    def render(self, mode: str = "human", close: bool = False) -> None:
        """Print the drones' state (the original's text output)."""
        if self.first_render_call and not self.GUI:
            print("[WARNING] render() prints the state as text; jaxdrones fly shows flights")
            self.first_render_call = False
        elapsed = time.time() - self.RESET_TIME
        sim_time = self.step_counter * self.PYB_TIMESTEP
        print(
            f"\n[INFO] render() ——— it {self.step_counter:04d} ——— wall-clock time {elapsed:.1f}s, simulation "
            f"time {sim_time:.1f}s@{self.PYB_FREQ:d}Hz ({sim_time / max(elapsed, 1e-9):.2f}x)"
        )
        for i in range(self.NUM_DRONES):
            (x, y, z), v, a, w = self.pos[i], self.vel[i], self.rpy[i] * self.RAD2DEG, self.ang_v[i]
            print(
                f"[INFO] render() ——— drone {i:d} ——— x {x:+06.2f}, y {y:+06.2f}, z {z:+06.2f} ——— velocity "
                f"{v[0]:+06.2f}, {v[1]:+06.2f}, {v[2]:+06.2f} ——— roll {a[0]:+06.2f}, pitch {a[1]:+06.2f}, yaw "
                f"{a[2]:+06.2f} ——— angular velocity {w[0]:+06.4f}, {w[1]:+06.4f}, {w[2]:+06.4f} ——— "
            )

    def close(self) -> None:
        """Release the backend (PyBullet's worlds)."""
        self._sim_step.close()

    def getPyBulletClient(self) -> int:
        """PyBullet's client id with ``backend="pybullet"`` (once the world exists: after the first step); -1 on the
        JAX backend (no PyBullet world)."""
        clients = getattr(self._sim_step, "clients", ())  # the PyBullet backend's worlds (one here, after a step)
        return int(clients[0]) if clients else -1

    def getDroneIds(self) -> np.ndarray:
        """i64[D]: the drones' body ids as in the original (1 to D; 0 is the ground plane)."""
        return np.arange(1, self.NUM_DRONES + 1)

    # -- state ------------------------------------------------------------------------------------------------------

    def _housekeeping(self) -> None:
        self.RESET_TIME = time.time()
        self.step_counter = 0
        self.first_render_call = True
        self.last_clipped_action = np.zeros((self.NUM_DRONES, 4))
        self._state = init_state(self._config, pos=self.INIT_XYZS, rpy=self.INIT_RPYS)

    def _updateAndStoreKinematicInformation(self) -> None:
        """Read the drones' state into ``pos``, ``quat``, ``rpy``, ``vel``, ``ang_v`` (NumPy, float64)."""
        packed = np.asarray(
            _kinematics(self._state.pos, self._state.quat, self._state.vel, self._state.ang_vel), np.float64
        )  # one transfer
        self.pos, self.quat, self.rpy, self.vel, self.ang_v = np.split(packed, [3, 7, 10, 13], axis=-1)

    def _getDroneStateVector(self, nth_drone: int) -> np.ndarray:
        """f64[20] of drone ``nth_drone``: pos (m), quat (x, y, z, w), roll/pitch/yaw (rad), vel (m/s), angular
        velocity (rad/s, world frame), the last RPM command."""
        i = nth_drone
        return np.concatenate(
            [self.pos[i], self.quat[i], self.rpy[i], self.vel[i], self.ang_v[i], self.last_clipped_action[i]]
        )

    # -- hooks: each aviary defines them (the original's) ----------------------------------------------------------

    @abc.abstractmethod
    def _actionSpace(self):
        """The action space (a gymnasium ``Box``)."""

    @abc.abstractmethod
    def _observationSpace(self):
        """The observation space."""

    @abc.abstractmethod
    def _preprocessAction(self, action):
        """``action`` as RPM commands f[D, 4]."""

    @abc.abstractmethod
    def _computeObs(self):
        """The observation of the current state."""

    @abc.abstractmethod
    def _computeReward(self):
        """The reward of the step."""

    @abc.abstractmethod
    def _computeTerminated(self):
        """Whether the episode ended (a goal or a failure)."""

    @abc.abstractmethod
    def _computeTruncated(self):
        """Whether the episode was cut short (time, bounds)."""

    @abc.abstractmethod
    def _computeInfo(self):
        """The ``info`` dict."""


def action_array(action, n: int, size: int, what: str, dtype=np.float64) -> np.ndarray:
    """``action`` as ``dtype[n, size]`` for the hooks' ``_preprocessAction``.

    Raises:
        ValueError: not ``n × size`` numbers (``what`` says what they are), or NaN or inf among them.
    """
    try:
        action = np.asarray(action, dtype)
    except (TypeError, ValueError):
        raise ValueError(f"action must be f[{n}, {size}] {what}, got {action!r}") from None
    if action.size != n * size:
        raise ValueError(f"action must be f[{n}, {size}] {what} (num_drones={n}), got shape {action.shape}")
    if not np.all(np.isfinite(action)):
        raise ValueError(f"action must be finite, got {action.tolist()}")
    return action.reshape(n, size)


@jax.jit
def _kinematics(pos, quat, vel, ang_vel):
    """f[D, 16]: pos, quat, PyBullet roll/pitch/yaw, vel and the world-frame angular velocity R ω (the original reads
    ``getBaseVelocity``'s, in the world frame; the core's is in the body frame)."""
    ang_v = (quat_to_rotmat(quat) @ ang_vel[..., None])[..., 0]
    return jnp.concatenate([pos, quat, quat_to_euler(quat), vel, ang_v], axis=-1)
