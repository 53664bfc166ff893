"""The closed loop shared by the control examples: physics step, then controller, in one jitted ``lax.scan``; and
the scaffolding around it that every example shares (checking a flight's settings, flying the DSL PID to way-points
as the original scripts do, the settings a result records).

Every example of the paper (§V-A: circle, velocity, ground effect, downwash) runs the same loop as the original
scripts (``examples/pid.py``, ``velocity.py``, ``groundeffect.py``, ``downwash.py``): each control step applies
the command held in the carry for ``sim_freq // ctrl_freq`` physics substeps, then the controller computes the
next command from the state reached. Only the controller and its per-step inputs differ between examples, so the
loop takes the controller as a function:

    control(params, gains, pid_state, state, x_k, fixed, ctrl_dt) -> (rpm f[D, 4] RPM, pid_state)

where ``x_k`` is the example's input of control step k (a pytree sliced from the scan's ``xs``, e.g. a way-point
or a velocity command), ``fixed`` a pytree of inputs constant over the flight, and ``ctrl_dt`` the control
period in s. Controllers are module-level functions (hashable), so the JAX backend compiles one loop per
(config, controller) pair and reuses it (`jax_closed_loop`).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from jaxdrones._validate import check_choice, is_real
from jaxdrones.control.pid import PIDGains, PIDState, pid_control, pid_init
from jaxdrones.physics.params import DroneParams, load_params
from jaxdrones.physics.rotations import quat_to_euler
from jaxdrones.physics.state import DroneState, init_state
from jaxdrones.sim import SimConfig, StepFn, make_step

#: Physics backends of the examples (`jaxdrones.sim.make_step`).
BACKENDS = ("jax", "pybullet")
#: The examples' arguments that are `SimConfig` fields of the same name.
PHYSICS_ARGUMENTS = ("sim_freq", "ctrl_freq", "drag", "ground_effect", "downwash")
#: Labels of the two runs of an effect's example: with the effect and without it (`effect_configs`, `on_off`).
RUNS = ("on", "off")
#: Fields of a flight record (`flight_arrays`), each with a leading time axis.
FLIGHT_KEYS = ("times", "pos", "quat", "vel", "rpy", "ang_vel", "rpm", "rpm_cmd", "contact")

Control = Callable[[DroneParams, PIDGains, PIDState, DroneState, Any, Any, float], tuple[jax.Array, PIDState]]
#: The loop's carry: (drone state, controller state, RPM command f[..., D, 4] to apply in the next step).
Carry = tuple[DroneState, PIDState, jax.Array]


def track_position(
    params: DroneParams,
    gains: PIDGains,
    pid_state: PIDState,
    state: DroneState,
    x_k: tuple[jax.Array, jax.Array],
    fixed: tuple[jax.Array, jax.Array],
    ctrl_dt: float,
) -> tuple[jax.Array, PIDState]:
    """Position tracking with the DSL PID (the controller of the circle, ground-effect and downwash examples).

    Args:
        params, gains, pid_state, state: as for `jaxdrones.control.pid.pid_control`.
        x_k: (target_pos f[D, 3] m, target_vel f[D, 3] m/s), world frame, of this control step.
        fixed: (target_rpy f[D, 3] rad, feedforward f[] 0 or 1): the target attitude (only its yaw is used) and
            whether ``target_vel`` is passed to the PID (the original scripts pass 0).
        ctrl_dt: control period, s.

    Returns:
        (rpm f[D, 4] in RPM, new PIDState).
    """
    target_pos, target_vel = x_k
    target_rpy, feedforward = fixed
    return pid_control(
        params,
        gains,
        pid_state,
        state,
        target_pos,
        target_vel=feedforward * target_vel,
        target_rpy=target_rpy,
        ctrl_dt=ctrl_dt,
    )


def closed_loop(step: StepFn, control: Control) -> Callable:
    """The jitted closed loop over a run of control steps for a step function (either backend).

    Args:
        step: ``step(params, state, rpm) -> state`` from `jaxdrones.sim.make_step`, with a ``config`` attribute.
        control: the controller, see the module docstring.

    Returns:
        ``simulate(params, gains, carry, xs, fixed, x_first=None) -> (carry, (states, rpm_cmd))``: a ``lax.scan``
        over the leading axis T of every leaf of ``xs``; ``states`` is the `DroneState` after each step (leaves
        [T, ...]) and ``rpm_cmd`` f[T, D, 4] the command computed from it (applied in the next step). The first
        step applies the carry's command, or, given ``x_first`` (an input like one of ``xs``), the controller's
        command for it computed from the carry's state (as the original's VEL environment converts its first
        action). Call it on consecutive slices of ``xs`` to pause in between (e.g. to render a video frame); the
        pieces give the same flight as one call.
    """
    ctrl_dt = step.config.ctrl_dt

    @jax.jit
    def simulate(params, gains, carry, xs, fixed, x_first=None):
        def body(carry, x_k):
            state, pid_state, rpm = carry
            state = step(params, state, rpm)
            rpm, pid_state = control(params, gains, pid_state, state, x_k, fixed, ctrl_dt)
            return (state, pid_state, rpm), (state, rpm)

        if x_first is not None:
            state, pid_state, _ = carry
            rpm, pid_state = control(params, gains, pid_state, state, x_first, fixed, ctrl_dt)
            carry = (state, pid_state, rpm)
        return jax.lax.scan(body, carry, xs)

    return simulate


@functools.lru_cache(maxsize=16)
def jax_closed_loop(config: SimConfig, control: Control) -> Callable:
    """`closed_loop` on the JAX backend for a config and controller, built (and compiled) once per pair."""
    return closed_loop(make_step(config), control)


def initial_carry(state: DroneState, rpm: ArrayLike | None = None) -> Carry:
    """The loop's first carry: the start state, a zeroed `PIDState`, and the first step's RPM command f[..., D, 4]
    (default 0 RPM, as the original scripts apply on their first ``env.step``)."""
    first = jnp.zeros_like(state.rpm) if rpm is None else jnp.asarray(rpm, state.rpm.dtype)
    return state, pid_init(state), first


def run_closed_loop(
    config: SimConfig,
    control: Control,
    params: DroneParams,
    gains: PIDGains,
    carry: Carry,
    xs: Any,
    fixed: Any,
    backend: str = "jax",
    x_first: Any = None,
    **options: Any,
) -> tuple[DroneState, jax.Array]:
    """Fly one closed loop to the end on a backend; the PyBullet worlds are closed afterwards.

    Args:
        config: SimConfig of the flight.
        control: the controller (see the module docstring).
        params, gains: drone params and PID gains.
        carry: the first carry (`initial_carry`).
        xs: pytree of per-step inputs, leaves with a leading axis T (the number of control steps).
        fixed: pytree of constant inputs.
        backend: ``"jax"`` or ``"pybullet"``.
        x_first: optional input of the first step's command (see `closed_loop`); default: the carry's command.
        **options: PyBullet backend options (e.g. ``obstacles``), see `jaxdrones.sim.make_step`.

    Returns:
        (states, rpm_cmd): the `DroneState` after each step (leaves [T, ...]) and the commands f[T, D, 4] RPM
        computed from them.
    """
    if backend == "jax":
        if options:
            raise ValueError(f"the jax backend takes no options, got {sorted(options)} (they are PyBullet's)")
        _, out = jax_closed_loop(config, control)(params, gains, carry, xs, fixed, x_first)
        return out
    step = make_step(config, backend="pybullet", **options)
    try:
        _, out = closed_loop(step, control)(params, gains, carry, xs, fixed, x_first)
        return jax.block_until_ready(out)  # the host callbacks must finish before the worlds are closed
    finally:
        step.close()


def flight_arrays(states: DroneState, rpm_cmd: ArrayLike, ctrl_freq: int) -> dict:
    """A flight as NumPy arrays, one row per control step.

    Returns:
        dict with ``times`` f[T] s (the time of each state, (k + 1)/ctrl_freq); ``pos``, ``vel`` f[T, D, 3] (m,
        m/s, world frame), ``quat`` f[T, D, 4] (x, y, z, w), ``rpy`` f[T, D, 3] rad, ``ang_vel`` f[T, D, 3] rad/s
        (body frame) after each step; ``rpm`` f[T, D, 4] RPM applied during the step that ends at ``times``;
        ``rpm_cmd`` f[T, D, 4] the command computed at ``times`` (applied next); ``contact`` i32[T, D]
        (`DroneState.contact`).
    """
    fields = {
        "pos": states.pos,
        "quat": states.quat,
        "vel": states.vel,
        "rpy": quat_to_euler(states.quat),
        "ang_vel": states.ang_vel,
        "rpm": states.rpm,
        "rpm_cmd": rpm_cmd,
        "contact": states.contact,
    }
    out = {k: np.asarray(v) for k, v in fields.items()}
    out["times"] = np.arange(1, out["pos"].shape[0] + 1) / ctrl_freq
    return out


def check_steps(duration_s: float, ctrl_freq: int) -> int:
    """The number of whole control steps in ``duration_s`` (rounded down).

    Raises:
        ValueError: if ``duration_s`` is not finite or shorter than one control step.
    """
    if not (is_real(duration_s) and math.isfinite(duration_s) and duration_s * ctrl_freq >= 1):
        raise ValueError(f"duration_s must be at least one control step (1/{ctrl_freq} s), got {duration_s!r}")
    return int(duration_s * ctrl_freq + 1e-9)


def check_backend(backend: str) -> None:
    """Raises ValueError unless ``backend`` is one of `BACKENDS`."""
    check_choice("backend", backend, BACKENDS)


def bind_arguments(fly: Callable, args: tuple, kwargs: dict) -> dict:
    """The arguments that ``fly(*args, **kwargs)`` would bind, by name, with ``fly``'s defaults for the rest: how an
    example's ``check`` takes exactly its ``fly``'s arguments, whose signature is their one home.

    Raises:
        TypeError: an argument ``fly`` does not take, or one given twice (as the call would).
    """
    bound = inspect.signature(fly).bind(*args, **kwargs)
    bound.apply_defaults()
    return bound.arguments


def check_flight_settings(arguments: dict, **physics: Any) -> tuple[SimConfig, int, DroneParams]:
    """An example's physics, length and airframe, each checked: the first step of every example's ``check``.

    Args:
        arguments: the example's arguments (`bind_arguments`): ``duration_s`` (flight time, s, `check_steps`),
            ``model`` (airframe name or URDF path, `jaxdrones.physics.params.load_params`), ``backend`` (one of
            `BACKENDS`), and those of `PHYSICS_ARGUMENTS` the example takes.
        **physics: further `SimConfig` fields the example sets itself (``n_drones``).

    Returns:
        (config, n_steps, params): the `SimConfig`, the whole control steps in ``duration_s`` and the airframe's
        `DroneParams`.

    Raises:
        ValueError: invalid physics settings or rates (`SimConfig`), a ``duration_s`` shorter than one control step,
            an unknown backend or model.
    """
    config = SimConfig(**{k: arguments[k] for k in PHYSICS_ARGUMENTS if k in arguments}, **physics)
    n_steps = check_steps(arguments["duration_s"], config.ctrl_freq)
    check_backend(arguments["backend"])
    return config, n_steps, load_params(arguments["model"])


def fly_to_waypoints(
    config: SimConfig,
    params: DroneParams,
    gains: PIDGains,
    start_pos: ArrayLike,
    target_pos: ArrayLike,
    backend: str = "jax",
) -> dict:
    """The DSL PID flown to a way-point per control step as the original ground-effect and downwash scripts fly it:
    from rest at ``start_pos`` f[D, 3] m, 0 RPM in the first step, no target velocity, a level target attitude.

    Args:
        config, params, gains: the physics, the airframe and the PID gains.
        start_pos: f[D, 3] m, world frame.
        target_pos: f[T, D, 3] m, world frame: the way-point commanded after each of the T control steps.
        backend: ``"jax"`` or ``"pybullet"``.

    Returns:
        The flight (`flight_arrays`).
    """
    state = init_state(config, pos=np.asarray(start_pos))
    dtype = state.pos.dtype
    target_pos = jnp.asarray(target_pos, dtype)
    xs = (target_pos, jnp.zeros_like(target_pos))
    fixed = (jnp.zeros(target_pos.shape[1:], dtype), jnp.asarray(0.0, dtype))
    states, rpm_cmd = run_closed_loop(config, track_position, params, gains, initial_carry(state), xs, fixed, backend)
    return flight_arrays(states, rpm_cmd, config.ctrl_freq)


def flight_settings(example: str, config: SimConfig, flight: dict, model: str, backend: str, **more: Any) -> dict:
    """The settings a flight's result records (``result["settings"]``, saved in ``metrics.json``).

    Args:
        example: the example's name.
        config: the flight's physics (of an example flown with and without an effect, the run with it).
        flight: the flight (`flight_arrays`), whose length and float type are recorded.
        model, backend: the airframe and the backend flown.
        **more: the example's own settings.

    Returns:
        dict: ``example``, ``num_drones``, ``duration_s`` (s), ``model``, the aerodynamic effects (``drag``,
        ``ground_effect``, ``downwash``), ``more``, the rates ``sim_freq`` and ``ctrl_freq`` (Hz), ``dtype`` and
        ``backend``.
    """
    return {
        "example": example,
        "num_drones": config.n_drones,
        "duration_s": len(flight["times"]) / config.ctrl_freq,
        "model": str(model),
        "drag": config.drag,
        "ground_effect": config.ground_effect,
        "downwash": config.downwash,
        **more,
        "sim_freq": config.sim_freq,
        "ctrl_freq": config.ctrl_freq,
        "dtype": str(flight["pos"].dtype),
        "backend": backend,
    }


def run_arrays(runs: dict) -> dict:
    """The flights of an example flown more than once (label → `flight_arrays`) as one dict of arrays for
    ``flight.npz``: each run's arrays but the times (which they share) as ``{label}_{key}``, e.g. ``on_pos``."""
    return {f"{label}_{k}": run[k] for label, run in runs.items() for k in FLIGHT_KEYS if k != "times"}


def pid_title(settings: dict) -> str:
    """The words of a plot's title that name the controller, the rates and the backend of a flight's settings (the
    JAX backend where they name none, as results saved before they recorded it)."""
    backend = settings.get("backend", "jax")
    return f"DSL PID at {settings['ctrl_freq']} Hz, physics {settings['sim_freq']} Hz ({backend})"


def effect_configs(config: SimConfig, effect: str, value: Any = True) -> dict[str, SimConfig]:
    """The physics of an effect's example flown twice (`RUNS`): ``config`` with its `SimConfig` field ``effect`` set
    to ``value`` (``"on"``) and to False (``"off"``)."""
    return {label: dataclasses.replace(config, **{effect: v}) for label, v in zip(RUNS, (value, False), strict=True)}


def on_off(on: float, off: float) -> dict:
    """A figure of the two runs of an effect's example (with it and without) and their difference on − off."""
    return {"on": on, "off": off, "difference": on - off}
