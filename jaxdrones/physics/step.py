"""The JAX core's control step and rollouts: `JaxStep` (the physics substeps of a control step under ``lax.scan``),
`physics_substep_c` and `rollout`.

The step runs on the component form of the state (each vector a tuple of f[..., D] arrays, see
`jaxdrones.physics.rotations`): the state is split once per control step, the physics substeps are scanned on the
components, and the result is joined back, so that XLA fuses each substep into a few vectorised loops.
`jaxdrones.make_step` is the one door to this core and to the PyBullet backend.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxdrones.physics import adjoint, dynamics
from jaxdrones.physics.checks import check_disturbance, check_motor_time_constants, check_params_batch, check_rpm
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import DroneParams, align_params
from jaxdrones.physics.rotations import join, normalize_c, split
from jaxdrones.physics.state import CONTACT_GROUND, Disturbance, DroneState

StepFn = Callable[..., DroneState]  #: ``step(params, state, rpm, disturbance=None) -> state``

__all__ = ["JaxStep", "StepFn", "physics_substep_c", "rollout"]


def physics_substep_c(
    config: SimConfig,
    params: DroneParams,
    state: DroneState,
    rpm: tuple,
    motors: dynamics.Motors | None = None,
    unit_quat: bool = False,
    neighbors: jax.Array | None = None,
    disturbance: Disturbance | None = None,
) -> DroneState:
    """One physics step of ``config.dt`` with already-clipped RPM, pure and differentiable, in component form:
    ``state``'s vector fields and ``rpm`` are tuples of f[..., D] arrays (``contact`` stays i32[..., D]); ``motors``
    is ``dynamics.motors_c(params, rpm)`` when already known; ``unit_quat=True`` if ``state.quat`` is known to be of
    unit norm; ``neighbors`` the downwash's neighbour list when already chosen (see `dynamics.accelerations_c`);
    ``disturbance`` a `Disturbance` in component form (each given field a 3-tuple of f[..., D]) or None.
    ``state.rpm`` is the previous substep's (drag uses it); the result's is ``rpm``, the speeds applied.

    With ``config.adjoint`` (`SimConfig`), the Euler integrator and exact kinks (the defaults), and ``unit_quat``,
    the substep has the hand-written reverse-mode derivative of `jaxdrones.physics.adjoint` and no forward-mode one;
    other configs keep JAX's derived derivatives."""
    if motors is None:
        motors = dynamics.motors_c(params, rpm)
    kin = dynamics.Kinematics(state.pos, state.quat, state.vel, state.ang_vel)
    if unit_quat and adjoint.supported(config):
        kin, touching = adjoint.euler_substep_c(
            params, config.effects, kin, motors, state.rpm, config.dt, neighbors, disturbance
        )
    else:
        integrate = dynamics.INTEGRATORS[config.integrator]
        kin = integrate(
            params, config.effects, kin, motors, state.rpm, config.dt, unit_quat, neighbors, None, disturbance
        )
        kin, touching = dynamics.ground_contact_c(params, kin, config.kinks)
    return DroneState(*kin, rpm=rpm, contact=state.contact | jnp.where(touching, CONTACT_GROUND, 0).astype(jnp.int32))


def _split_state(state: DroneState, contiguous: bool = False) -> DroneState:
    vectors = {name: split(getattr(state, name), contiguous) for name in ("pos", "quat", "vel", "ang_vel", "rpm")}
    return DroneState(**vectors, contact=state.contact)


def _join_state(state: DroneState, contiguous: bool = False) -> DroneState:
    vectors = {name: join(getattr(state, name), contiguous) for name in ("pos", "quat", "vel", "ang_vel", "rpm")}
    return DroneState(**vectors, contact=state.contact)


def _core_step_c(config: SimConfig):
    """The control step of the JAX core in component form: ``core_c(params, state_c, rpm_c, disturbance_c) ->
    state_c`` with the state's vectors, the RPM command and the disturbance's given fields as tuples of f[..., D]
    arrays (see `jaxdrones.physics.rotations`); ``disturbance_c`` may be None."""

    def core_c(
        params: DroneParams, state: DroneState, rpm: tuple, disturbance: Disturbance | None = None
    ) -> DroneState:
        # The quaternion is normalised here once; every substep then leaves it of unit norm, so the substeps need
        # not normalise it again for their rotation matrices. The clip, the normalisation and the motors' output
        # are recomputed in the backward pass (jax.checkpoint) rather than their intermediates stored at every
        # control step of a differentiated rollout (see `_recomputed`).
        rpm, quat = _recomputed(
            lambda rpm, quat: (
                tuple(config.kinks.clip(r, 0.0, params.max_rpm, config.kinks.rpm) for r in rpm),
                normalize_c(quat),
            ),
            rpm,
            state.quat,
        )
        state = state.replace(quat=quat, contact=jnp.zeros_like(state.contact))
        # With config.downwash_radius, the neighbour list of the downwash is built once per control step.
        neighbors = config.effects.downwash_neighbors(state.pos)
        if config.motor_dynamics:
            # The motors' speeds are the state's: each substep moves them towards the command, then applies them.
            def lagged(s, _):
                speeds = dynamics.motor_response_c(params, s.rpm, rpm, config.dt)
                return physics_substep_c(config, params, s, speeds, None, True, neighbors, disturbance), None

            return jax.lax.scan(lagged, state, None, length=config.n_substeps, unroll=config.substep_unroll)[0]
        # Instant motors: their output is held over the substeps. The RPM of the previous substep, which drag
        # uses, is the state's in the first substep and the held command in the others: it is chosen per substep
        # rather than carried (and copied) through the loop.
        motors = _recomputed(lambda rpm: dynamics.motors_c(params, rpm), rpm)
        rpm_before = state.rpm

        def substep(s, first):
            rpm_prev = tuple(jnp.where(first, before, now) for before, now in zip(rpm_before, rpm, strict=True))
            s = physics_substep_c(config, params, s.replace(rpm=rpm_prev), rpm, motors, True, neighbors, disturbance)
            return s.replace(rpm=()), None

        first = jnp.arange(config.n_substeps) == 0
        state, _ = jax.lax.scan(substep, state.replace(rpm=()), first, unroll=config.substep_unroll)
        return state.replace(rpm=rpm)

    return core_c


def _recomputed(fn, *args):
    """``fn(*args)``, recomputed from ``args`` in the backward pass (``jax.checkpoint``) instead of having its
    intermediates stored: for the cheap element-wise work around the physics substeps. Under a differentiated
    ``lax.scan`` every stored intermediate becomes an array stacked over the steps, with its own writes and reads;
    the clip, the normalisation and the motors' output stored 14 of them per control step of the default
    hover env (`benchmarks/gradients/gradients.py`, caller ``default_env``)."""
    return jax.checkpoint(fn)(*args)


def _split_disturbance(disturbance: Disturbance | None, contiguous: bool = False) -> Disturbance | None:
    if disturbance is None:
        return None
    return jax.tree.map(lambda x: split(x, contiguous), disturbance)


@functools.cache
def _core_step(core_c, remat: bool):
    """The jitted control step of the JAX core on checked inputs, in array form, around `_core_step_c`'s step.

    Cached: the `JaxStep`s of one ``core_c`` (`compiled_step_c`'s, per config) share one jitted function. The state
    is split into contiguous components and joined back with ``contiguous=True``
    (`jaxdrones.physics.rotations.split`, `jaxdrones.physics.rotations.join`). With ``remat`` (a step without the
    hand-written adjoint of `jaxdrones.physics.adjoint`, whose reverse pass keeps only each substep's input) the step is
    rematerialised (``jax.checkpoint``) when differentiated: the backward pass of a scan over this step (a user's own,
    or an env's) recomputes each step from its input state, as `rollout` does, instead of storing every intermediate of
    the physics (see `benchmarks/gradients/gradients.py`: on CPU that scan's gradient is otherwise several times
    slower). None of this changes a value. The command is sliced (with its components from the product, a level drone
    given four equal commands drifted sideways by 5e-5 m in 60 steps: XLA then rounds the terms of equal and opposite
    torques differently, see `jaxdrones.physics.rotations.dot`; sliced, it stays exactly level, as on PyBullet).
    """

    def core(
        params: DroneParams, state: DroneState, rpm: jax.Array, disturbance: Disturbance | None = None
    ) -> DroneState:
        state = core_c(
            params, _split_state(state, contiguous=True), split(rpm), _split_disturbance(disturbance, contiguous=True)
        )
        return _join_state(state, contiguous=True)

    return jax.jit(jax.checkpoint(core) if remat else core)


@functools.cache
def compiled_step_c(config: SimConfig) -> Callable[..., DroneState]:
    """The control step of ``config`` in component form (`_core_step_c`), shared by every `JaxStep` of an equal
    config: an env built again (an evaluation env beside the training env, a second run in a notebook) compiles
    nothing again."""
    return _core_step_c(config)


class JaxStep:
    """The JAX core's control step ``step(params, state, rpm) -> state`` (see `make_step`).

    The backend interface, shared with `jaxdrones.backends.pybullet.PyBulletStep`: calling it steps the drones;
    ``config`` is its `SimConfig`; ``has_cameras`` says whether it renders (``camera_images``, ``render``); `close`
    releases its resources. The JAX core renders nothing and holds nothing to release.
    """

    has_cameras = False

    def __init__(self, config: SimConfig, core_c: Callable[..., DroneState] | None = None):
        self.config = config
        self._core_c = compiled_step_c(config) if core_c is None else core_c
        self._core = _core_step(self._core_c, remat=not adjoint.supported(config))

    def __call__(
        self, params: DroneParams, state: DroneState, rpm, disturbance: Disturbance | None = None
    ) -> DroneState:
        rpm = check_rpm(self.config, state, rpm)
        check_params_batch(params, state)
        params = align_params(params, state.pos.ndim - 1)
        if self.config.motor_dynamics:
            check_motor_time_constants(params)
        if disturbance is None:
            return self._core(params, state, rpm)
        return self._core(params, state, rpm, check_disturbance(self.config, state, disturbance))

    def __hash__(self) -> int:
        return hash((JaxStep, self.config, self._core_c))

    def __eq__(self, other) -> bool:
        return isinstance(other, JaxStep) and (other.config, other._core_c) == (self.config, self._core_c)

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> JaxStep:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def rollout(step: StepFn, params: DroneParams, state: DroneState, rpms: jax.Array, remat: bool = True) -> DroneState:
    """Apply ``step`` to a sequence of RPM commands under ``lax.scan``.

    Differentiated, each control step is rematerialised (``jax.checkpoint``): the backward pass recomputes a step
    from its input state rather than storing all its intermediates: a faster gradient in less memory, also with the
    hand-written adjoint (the default config); the forward pass is unchanged (`benchmarks/gradients/gradients.py`,
    docs/benchmarks.md, "Gradients").

    Args:
        step: a step function from `make_step`.
        params: DroneParams.
        state: initial DroneState with leading shape ``L`` (e.g. ``[W]`` or none).
        rpms: f[T, *L, D, 4] RPM, one command per control step.
        remat: rematerialise each step in the backward pass (see above); False stores every intermediate.

    Returns:
        DroneState whose leaves have a leading time axis ``[T, *L, ...]``: the state after each step.

    Raises:
        ValueError: if ``rpms`` is not f[T, *L, D, 4]. The commands are not checked for NaN (the scan runs under
            ``jit``): a NaN command propagates into the states from that step on.
    """
    rpms = jnp.asarray(rpms)
    if rpms.ndim != state.rpm.ndim + 1 or rpms.shape[1:] != state.rpm.shape:
        raise ValueError(
            f"rpms must have shape [T, {', '.join(map(str, state.rpm.shape))}] (one RPM command per "
            f"control step), got {rpms.shape}"
        )
    if isinstance(step, JaxStep):
        check_params_batch(params, state)
        params = align_params(params, state.pos.ndim - 1)
        return _rollout_c(step, params, state, rpms.astype(state.pos.dtype), bool(remat))
    return _rollout(step, params, state, rpms, bool(remat))


@functools.partial(jax.jit, static_argnums=(0, 4))
def _rollout(step: StepFn, params: DroneParams, state: DroneState, rpms: jax.Array, remat: bool) -> DroneState:
    return _scan_steps(step, params, state, rpms, remat)


def _scan_steps(step, params, state, rpms, remat: bool):
    """The states after each command of ``rpms`` (leading time axis), ``step`` rematerialised when ``remat``."""
    step = jax.checkpoint(step) if remat else step

    def body(s, rpm):
        s = step(params, s, rpm)
        return s, s

    return jax.lax.scan(body, state, rpms)[1]


@functools.partial(jax.jit, static_argnums=(0, 4))
def _rollout_c(step: JaxStep, params: DroneParams, state: DroneState, rpms: jax.Array, remat: bool) -> DroneState:
    """`rollout` of the JAX core in component form: the state is split once and the commands once, the scan steps
    the components, and the stacked states are joined once at the end. On CPU, splitting and joining at every
    step cost as much as the physics in the backward pass (where XLA recomputes the shared cotangents for each
    component it joins)."""
    return _join_state(_scan_steps(step._core_c, params, _split_state(state), split(rpms), remat))
