"""System identification: fit `DroneParams` fields so that the simulator reproduces recorded flight.

A quadrotor is open-loop unstable: replayed open loop for seconds, any wrong guess diverges and the loss is
useless. `fit` therefore uses multiple shooting: the record is cut into windows of a few control steps, each
window is simulated from the *observed* state at its start under the recorded commands, and the loss sums the
windows' residuals (Bock and Plitt, "A multiple shooting algorithm for direct solution of optimal control problems",
IFAC 1984). The fitted fields are parameterised as log-ratios to their initial guess and optimised with optax's
L-BFGS; the report gives a Gauss-Newton standard error for each fitted value.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from jaxdrones.config import SimConfig
from jaxdrones.params import DroneParams, with_derived
from jaxdrones.sim import make_step, rollout
from jaxdrones.state import DroneState

#: Default measurement noise (standard deviations) that scales each residual: position m, velocity m/s, attitude
#: (quaternion components, about rad/2), body rate rad/s.
NOISE = {"pos": 1e-3, "vel": 1e-2, "quat": 5e-3, "ang_vel": 0.1}
#: `DroneParams` fields that `fit` may fit (the others are derived from them, or geometry).
FITTABLE = ("mass", "kf", "km", "drag_coeff", "inertia", "gnd_eff_coeff", "dw_coeff")


def _apply(params0: DroneParams, theta: dict) -> DroneParams:
    """``params0`` with each fitted field scaled by exp(θ), the derived fields recomputed."""
    return with_derived(params0.replace(**{f: getattr(params0, f) * jnp.exp(t) for f, t in theta.items()}))


def _residuals(step, params0, noise, starts, rpm_windows, observed_windows):
    """The scaled residuals of every window, as a function of the log-ratios θ (field -> array)."""

    def residuals(theta):
        params = _apply(params0, theta)
        predicted = jax.vmap(lambda s, r: rollout(step, params, s, r))(starts, rpm_windows)
        # q and −q are the same attitude: compare with the observed quaternion's sign.
        sign = jnp.sign(jnp.sum(predicted.quat * observed_windows.quat, axis=-1, keepdims=True))
        parts = [(predicted.pos - observed_windows.pos) / noise["pos"],
                 (predicted.vel - observed_windows.vel) / noise["vel"],
                 (sign * predicted.quat - observed_windows.quat) / noise["quat"],
                 (predicted.ang_vel - observed_windows.ang_vel) / noise["ang_vel"]]
        return jnp.concatenate([jnp.ravel(p) for p in parts])

    return residuals


def _check(init_state, rpms, observed, fields, window):
    unknown = [f for f in fields if f not in FITTABLE]
    if not fields or unknown:
        raise ValueError(f"fields must name DroneParams fields from {FITTABLE}, got {tuple(fields)!r}")
    rpms = jnp.asarray(rpms)
    if rpms.ndim != init_state.rpm.ndim + 1 or rpms.shape[1:] != init_state.rpm.shape:
        raise ValueError(f"rpms must have shape [T, {', '.join(map(str, init_state.rpm.shape))}], got {rpms.shape}")
    for name in ("pos", "quat", "vel", "ang_vel", "rpm"):
        value, expected = getattr(observed, name), (rpms.shape[0],) + getattr(init_state, name).shape
        if value.shape != expected:
            raise ValueError(f"observed.{name} must have shape [T, ...] = {expected} (the state after each of the T "
                             f"commands, as rollout returns it), got {value.shape}")
        if not bool(jnp.all(jnp.isfinite(value))):
            raise ValueError(f"observed.{name} contains NaN or inf")
    if not (isinstance(window, int) and 1 <= window <= rpms.shape[0]):
        raise ValueError(f"window must be an integer in [1, T={rpms.shape[0]}] control steps, got {window!r}")
    return rpms


def fit(config: SimConfig, params0: DroneParams, init_state: DroneState, rpms, observed: DroneState,
        fields=("kf", "km", "drag_coeff"), *, window: int = 10, noise: dict | None = None,
        iterations: int = 100) -> tuple[DroneParams, dict]:
    """Fit the named fields of ``params0`` to recorded flight by multiple shooting.

    Args:
        config: the `SimConfig` of the record (rates and effects).
        params0: the initial guess (also the value of every field not fitted), unbatched or [D].
        init_state: the state before the first command, DroneState f[D, ...].
        rpms: f[T, D, 4] RPM, the recorded commands, one per control step.
        observed: DroneState with leading time axis [T, D, ...], the state after each command (as `rollout`
            returns it), measured.
        fields: `DroneParams` fields to fit (from `FITTABLE`); each element of an array field is fitted.
        window: control steps per shooting window.
        noise: measurement noise standard deviations that scale the residuals, keys of `NOISE` (default `NOISE`).
        iterations: L-BFGS iterations.

    Returns:
        ``(params, report)``: the fitted params (derived fields recomputed, `jaxdrones.params.with_derived`) and a
        dict with ``loss`` (the loss after each iteration: mean squared residual in noise units), ``estimates``
        (field -> fitted value), ``initial`` (field -> initial guess), ``std`` (field -> Gauss-Newton standard
        error of the fitted value, from the residuals' scatter; inf where the data do not determine it),
        ``windows`` and ``window``.

    Raises:
        ValueError: an unknown field, ``rpms`` or ``observed`` of the wrong shape, a non-finite observation, a
            window outside [1, T].
    """
    import optax

    rpms = _check(init_state, rpms, observed, tuple(fields), window)
    noise = {**NOISE, **(noise or {})}
    n = (rpms.shape[0] // window) * window
    before = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest[:n - 1]]), init_state, observed)
    starts = jax.tree.map(lambda x: x[::window], before)
    windows = lambda x: x[:n].reshape((n // window, window) + x.shape[1:])  # noqa: E731
    residuals = _residuals(make_step(config), params0, noise, starts, windows(rpms), jax.tree.map(windows, observed))
    theta = {f: jnp.zeros_like(getattr(params0, f)) for f in fields}
    loss = lambda t: jnp.mean(residuals(t) ** 2)  # noqa: E731
    solver = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(loss)

    @jax.jit
    def iterate(theta, state):
        value, grad = value_and_grad(theta, state=state)
        updates, state = solver.update(grad, state, theta, value=value, grad=grad, value_fn=loss)
        return optax.apply_updates(theta, updates), state, value

    state, curve = solver.init(theta), []
    for _ in range(iterations):
        theta, state, value = iterate(theta, state)
        curve.append(float(value))
    curve.append(float(loss(theta)))
    params = _apply(params0, theta)
    return params, {"loss": curve, "estimates": {f: np.asarray(getattr(params, f)) for f in fields},
                    "initial": {f: np.asarray(getattr(params0, f)) for f in fields},
                    "std": _standard_errors(residuals, theta, params, fields), "windows": n // window, "window": window}


def _standard_errors(residuals, theta, params, fields) -> dict:
    """Gauss-Newton standard errors: cov(θ) = s² (JᵀJ)⁻¹ with s² the residuals' mean square per degree of freedom;
    a fitted value p·exp(θ) has standard error p·σ_θ."""
    flat, unravel = jax.flatten_util.ravel_pytree(theta)
    jac = np.asarray(jax.jacfwd(lambda x: residuals(unravel(x)))(flat), np.float64)
    r = np.asarray(residuals(theta), np.float64)
    dof = max(r.size - flat.size, 1)
    info = jac.T @ jac
    with np.errstate(divide="ignore", invalid="ignore"):
        if np.linalg.cond(info) > 1e12:
            sigma = np.full(flat.size, np.inf)
        else:
            sigma = np.sqrt(np.diag(np.linalg.inv(info)) * (r @ r) / dof)
    sigma = unravel(jnp.asarray(sigma, flat.dtype))
    return {f: np.asarray(getattr(params, f)) * np.asarray(sigma[f]) for f in fields}


@dataclasses.dataclass(frozen=True)
class Flight:
    """A recorded flight: ``init_state`` (DroneState [D, ...]), ``rpms`` f[T, D, 4] RPM and ``observed`` (DroneState
    [T, D, ...]), as `fit` takes them."""

    init_state: DroneState
    rpms: jax.Array
    observed: DroneState


def excitation_flight(config: SimConfig, params: DroneParams, duration_s: float = 5.0) -> Flight:
    """Closed-loop flight for identification: the DSL PID (`jaxdrones.control.pid`) flies one drone from hover at
    (0, 0, 1) m along x = 0.5 sin(0.8 t), y = 0.4 sin(1.6 t), z = 1 + 0.3 sin(1.2 t) m with yaw 1.0 sin(0.7 t)
    rad (climbs, turns and yaw at up to about 1 m/s), the commands and states recorded.

    Raises:
        ValueError: a config with other than one drone.
    """
    from jaxdrones.control import pid
    from jaxdrones.state import init_state

    if config.n_drones != 1:
        raise ValueError(f"excitation_flight flies one drone, got n_drones={config.n_drones}")
    step = make_step(config)
    gains = pid.PIDGains.dsl(params.mass.dtype)
    state0 = init_state(config, pos=[[0.0, 0.0, 1.0]])
    state0 = state0.replace(rpm=jnp.full_like(state0.rpm, params.hover_rpm))
    steps = int(round(duration_s * config.ctrl_freq))

    def body(carry, t):
        state, ctrl = carry
        target = jnp.stack([0.5 * jnp.sin(0.8 * t), 0.4 * jnp.sin(1.6 * t), 1.0 + 0.3 * jnp.sin(1.2 * t)])
        yaw = jnp.stack([0.0, 0.0, 1.0 * jnp.sin(0.7 * t)])
        rpm, ctrl = pid.pid_control(params, gains, ctrl, state, target[None], target_rpy=yaw[None],
                                    ctrl_dt=config.ctrl_dt)
        state = step(params, state, rpm)
        return (state, ctrl), (rpm, state)

    times = jnp.arange(1, steps + 1) * config.ctrl_dt
    _, (rpms, states) = jax.lax.scan(body, (state0, pid.pid_init(state0)), times)
    return Flight(state0, rpms, states)
