"""Static simulation config, the functional step, rollouts, and spreading worlds over devices.

The step runs on the component form of the state (each vector a tuple of f[..., D] arrays, see
`jaxdrones.rotations`): the state is split once per control step, the physics substeps are scanned on the
components, and the result is joined back, so that XLA fuses each substep into a few vectorised loops.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones import dynamics
from jaxdrones.params import DroneParams, params_batch_shape
from jaxdrones.rotations import join, normalize_c, split
from jaxdrones.state import CONTACT_GROUND, DroneState

StepFn = Callable[[DroneParams, DroneState, jax.Array], DroneState]


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static simulation settings (hashable; changing one recompiles).

    Attributes:
        n_drones: drones per world, D ≥ 1.
        sim_freq: physics rate, Hz (the paper's ``pyb_freq``, default 240).
        ctrl_freq: control rate, Hz; one `step` call runs ``sim_freq // ctrl_freq`` physics substeps with the
            same RPM command. ``sim_freq`` must be a multiple of ``ctrl_freq`` (as in the paper's code).
        drag: rotor drag, paper eq. (drag).
        ground_effect: per-propeller ground effect, paper eq. (ground).
        downwash: downwash between the drones of a world, paper eq. (down).
        integrator: ``"euler"`` (the paper code's semi-implicit Euler with exact quaternion exponential map) or
            ``"rk4"``.

    Raises:
        ValueError: on a non-positive count or rate, ``sim_freq`` not a multiple of ``ctrl_freq``, or an unknown
            integrator.
    """

    n_drones: int = 1
    sim_freq: int = 240
    ctrl_freq: int = 240
    drag: bool = False
    ground_effect: bool = False
    downwash: bool = False
    integrator: str = "euler"

    def __post_init__(self):
        for name in ("n_drones", "sim_freq", "ctrl_freq"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise ValueError(f"SimConfig.{name} must be a positive integer, got {value!r}")
        if self.sim_freq % self.ctrl_freq:
            raise ValueError(f"SimConfig: sim_freq ({self.sim_freq} Hz) must be a multiple of ctrl_freq "
                             f"({self.ctrl_freq} Hz), e.g. sim_freq=240 with ctrl_freq in 240, 120, 80, 48, 30, ...")
        if self.integrator not in dynamics.INTEGRATORS:
            raise ValueError(f"SimConfig.integrator must be one of {tuple(dynamics.INTEGRATORS)}, "
                             f"got {self.integrator!r}")

    @property
    def n_substeps(self) -> int:
        """Physics substeps per control step."""
        return self.sim_freq // self.ctrl_freq

    @property
    def dt(self) -> float:
        """Physics timestep, s."""
        return 1.0 / self.sim_freq

    @property
    def ctrl_dt(self) -> float:
        """Control period, s."""
        return 1.0 / self.ctrl_freq

    @property
    def effects(self) -> dynamics.Effects:
        return dynamics.Effects(self.drag, self.ground_effect, self.downwash)


def physics_substep_c(config: SimConfig, params: DroneParams, state: DroneState, rpm: tuple,
                      motors: dynamics.Motors | None = None, unit_quat: bool = False) -> DroneState:
    """One physics step of ``config.dt`` with already-clipped RPM, pure and differentiable, in component form:
    ``state``'s vector fields and ``rpm`` are tuples of f[..., D] arrays (``contact`` stays i32[..., D]); ``motors`` is ``dynamics.motors_c(params, rpm)`` when already known;
    ``unit_quat=True`` if ``state.quat`` is known to be of unit norm (see `dynamics.accelerations_c`)."""
    if motors is None:
        motors = dynamics.motors_c(params, rpm)
    integrate = dynamics.INTEGRATORS[config.integrator]
    kin = dynamics.Kinematics(state.pos, state.quat, state.vel, state.ang_vel)
    kin = integrate(params, config.effects, kin, motors, state.rpm, config.dt, unit_quat)
    kin, touching = dynamics.ground_contact_c(params, kin)
    return DroneState(*kin, rpm=rpm, contact=state.contact | jnp.where(touching, CONTACT_GROUND, 0).astype(jnp.int32))


def _split_state(state: DroneState) -> DroneState:
    vectors = {name: split(getattr(state, name)) for name in ("pos", "quat", "vel", "ang_vel", "rpm")}
    return DroneState(**vectors, contact=state.contact)


def _join_state(state: DroneState) -> DroneState:
    vectors = {name: join(getattr(state, name)) for name in ("pos", "quat", "vel", "ang_vel", "rpm")}
    return DroneState(**vectors, contact=state.contact)


def make_step(config: SimConfig, backend: str = "jax", **options) -> StepFn:
    """Build the control step ``step(params, state, rpm) -> state`` for a config.

    One call holds ``rpm`` over ``config.n_substeps`` physics substeps (run under ``lax.scan``). RPMs are clipped
    to [0, max_rpm] as the paper's code does. The step is pure (no hidden state, no key), jitted, and works under
    ``jit``, ``vmap`` and ``grad``; arrays may carry leading world axes ``[W, D, ...]``. Worlds spread over several
    devices with `shard_worlds` are stepped on each device in parallel, in the same jitted call.

    Args:
        config: SimConfig.
        backend: ``"jax"`` (this pure-JAX core) or ``"pybullet"`` (`jaxdrones.backends.pybullet.PyBulletStep`:
            collisions with the ground, obstacles and other drones, cameras; not differentiable).
        **options: PyBullet backend options: ``obstacles`` (None, True/"paper", or a sequence of
            `jaxdrones.backends.scene.Obstacle` / URDF paths), ``damping`` (keep Bullet's velocity damping,
            default False), ``gui`` (show world 0 in PyBullet's GUI), ``renderer`` ("tiny" or "egl").

    Returns:
        ``step(params, state, rpm)`` where ``rpm`` is f[..., D, 4] in RPM (ints are cast to the state's float
        dtype) with the leading shape of ``state``. ``state.contact`` reports ground contact during this step.

    Raises:
        ValueError: unknown backend or option; and, when ``step`` is called, an ``rpm`` or ``state`` of the wrong shape or a
            non-numeric dtype. Called on concrete arrays (outside ``jit``), a non-finite ``rpm`` raises too; inside
            ``jit`` NaN propagates into the state (the envs detect and report it).
    """
    if not isinstance(config, SimConfig):
        raise ValueError(f"make_step expects a SimConfig, got {type(config).__name__}")
    if backend == "pybullet":
        from jaxdrones.backends.pybullet import OPTIONS, PyBulletStep

        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise ValueError(f"unknown PyBullet backend option(s) {unknown}: expected some of {OPTIONS}")
        return PyBulletStep(config, **options)
    if backend != "jax":
        raise ValueError(f"unknown backend {backend!r}: expected 'jax' or 'pybullet'")
    if options:
        raise ValueError(f"the jax backend takes no options, got {sorted(options)} (they are PyBullet's)")

    @jax.jit
    def core(params: DroneParams, state: DroneState, rpm: jax.Array) -> DroneState:
        rpm = split(jnp.clip(rpm, 0.0, params.max_rpm[..., None]))
        state = _split_state(state.replace(contact=jnp.zeros_like(state.contact)))
        # The quaternion is normalised here once; every substep then leaves it of unit norm, so the substeps need
        # not normalise it again for their rotation matrices. The motors' output is held over the substeps too.
        state = state.replace(quat=normalize_c(state.quat))
        motors = dynamics.motors_c(params, rpm)
        # The RPM of the previous substep, which drag uses, is the state's in the first substep and the held
        # command in the others: it is chosen per substep rather than carried (and copied) through the loop.
        rpm_before = state.rpm

        def substep(s, first):
            rpm_prev = tuple(jnp.where(first, before, now) for before, now in zip(rpm_before, rpm))
            s = physics_substep_c(config, params, s.replace(rpm=rpm_prev), rpm, motors, unit_quat=True)
            return s.replace(rpm=()), None

        first = jnp.arange(config.n_substeps) == 0
        state, _ = jax.lax.scan(substep, state.replace(rpm=()), first)
        return _join_state(state.replace(rpm=rpm))

    def step(params: DroneParams, state: DroneState, rpm) -> DroneState:
        rpm = check_rpm(config, state, rpm)
        check_params_batch(params, state)
        return core(params, state, rpm)

    step.config = config
    return step


def check_rpm(config: SimConfig, state: DroneState, rpm) -> jax.Array:
    """Validate an RPM command against the config and state; returns it as a float array of the state's dtype.

    Raises:
        ValueError: see `make_step`.
    """
    dtype = rpm.dtype if hasattr(rpm, "dtype") else np.asarray(rpm).dtype
    check_rpm_shape(config, state, np.shape(rpm), dtype)
    rpm = jnp.asarray(rpm, dtype=state.pos.dtype)
    if not isinstance(rpm, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(rpm))):
        raise ValueError("rpm contains NaN or inf")
    return rpm


def check_state_shape(config: SimConfig, state: DroneState) -> tuple[int, ...]:
    """Check that ``state`` has pos f[..., D, 3] and quat f[..., D, 4] with D = ``config.n_drones`` and the same
    leading shape; returns that shape ``[..., D]``.

    Raises:
        ValueError: on other shapes.
    """
    n = config.n_drones
    pos, quat = np.shape(state.pos), np.shape(state.quat)
    if pos[-2:] != (n, 3) or quat[-2:] != (n, 4) or pos[:-1] != quat[:-1]:
        raise ValueError(f"state has pos {pos} and quat {quat}; expected [..., {n}, 3] and [..., {n}, 4] with the "
                         f"same leading shape, for n_drones={n} (build it with jd.init_state(config, ...))")
    return tuple(pos[:-1])


def check_rpm_shape(config: SimConfig, state: DroneState, shape: tuple[int, ...], dtype) -> None:
    """Check an RPM command's shape and dtype (and the state's drone axis) against the config and state.

    Raises:
        ValueError: see `make_step`.
    """
    n = config.n_drones
    check_state_shape(config, state)
    if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)) or dtype == bool:
        raise ValueError(f"rpm must be a real (float or int) array in RPM, got dtype {dtype}")
    expected = state.rpm.shape
    if tuple(shape) != tuple(expected):
        raise ValueError(f"rpm must have shape {expected} ([..., n_drones={n}, 4] motor speeds in RPM, with the "
                         f"state's leading shape {expected[:-2]}), got {tuple(shape)}")


def check_params_batch(params: DroneParams, state: DroneState) -> None:
    """Check that the params' batch axes line up with the state's ``[..., D]`` (right-aligned broadcasting).

    Per-drone params are ``[D]`` or ``[W, D]``; per-world params are ``[W, 1]`` (or used under ``vmap``).

    Raises:
        ValueError: if the params' batch shape does not broadcast to the state's leading shape ``[..., D]``.
    """
    lead = state.pos.shape[:-1]
    batch = params_batch_shape(params)
    try:
        ok = np.broadcast_shapes(batch, lead) == lead
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"params have batch shape {batch}, which does not line up with the state's [..., D] = "
                         f"{lead}: batched params are right-aligned with the drone axis, so per-drone params are "
                         f"[D] or [W, D] and per-world params [W, 1] (or vmap the step over worlds)")


def rollout(step: StepFn, params: DroneParams, state: DroneState, rpms: jax.Array) -> DroneState:
    """Apply ``step`` to a sequence of RPM commands under ``lax.scan``.

    Args:
        step: a step function from `make_step`.
        params: DroneParams.
        state: initial DroneState with leading shape ``L`` (e.g. ``[W]`` or none).
        rpms: f[T, *L, D, 4] RPM, one command per control step.

    Returns:
        DroneState whose leaves have a leading time axis ``[T, *L, ...]``: the state after each step.

    Raises:
        ValueError: if ``rpms`` is not f[T, *L, D, 4]. The commands are not checked for NaN (the scan runs under
            ``jit``): a NaN command propagates into the states from that step on.
    """
    rpms = jnp.asarray(rpms)
    if rpms.ndim != state.rpm.ndim + 1 or rpms.shape[1:] != state.rpm.shape:
        raise ValueError(f"rpms must have shape [T, {', '.join(map(str, state.rpm.shape))}] (one RPM command per "
                         f"control step), got {rpms.shape}")
    return _rollout(step, params, state, rpms)


@functools.partial(jax.jit, static_argnums=0)
def _rollout(step: StepFn, params: DroneParams, state: DroneState, rpms: jax.Array) -> DroneState:
    def body(s, rpm):
        s = step(params, s, rpm)
        return s, s

    return jax.lax.scan(body, state, rpms)[1]


def shard_worlds(tree, axis: int = 0, devices=None):
    """Spread the world axis of every array in ``tree`` over devices, for a step or rollout to run on all of them.

    Each leaf is placed with a `jax.sharding.NamedSharding` over a 1-D mesh ``("worlds",)``: device k holds a
    contiguous slice of the worlds. A jitted `make_step` step or `rollout` on such arrays runs on every device at
    once, each on its own slice (worlds do not interact, so no data moves between devices), and returns arrays
    sharded the same way. Shared, unbatched params need no sharding; per-world params are sharded like the state.
    On a CPU host, start Python with ``XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`` (set before
    ``jax`` is imported) to get one device per core; on GPUs the devices are the GPUs.

    Args:
        tree: a pytree of arrays whose axis ``axis`` is the world axis, e.g. a DroneState f[W, D, ...], an RPM
            command f[W, D, 4] (``axis=0``) or a rollout's commands f[T, W, D, 4] (``axis=1``).
        axis: the world axis of every leaf.
        devices: the devices to use, default ``jax.devices()``.

    Returns:
        The same pytree with its leaves sharded over ``devices``.

    Raises:
        ValueError: if a leaf lacks ``axis`` or its size there is not a multiple of the number of devices.
    """
    devices = list(jax.devices() if devices is None else devices)
    mesh = jax.sharding.Mesh(np.array(devices), ("worlds",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(*[None] * axis, "worlds"))

    def put(x):
        x = jnp.asarray(x)
        if x.ndim <= axis or x.shape[axis] % len(devices):
            raise ValueError(f"shard_worlds: a leaf of shape {x.shape} has no world axis {axis} whose size is a "
                             f"multiple of the {len(devices)} devices")
        return jax.device_put(x, sharding)

    return jax.tree.map(put, tree)
