"""System identification: fit `DroneParams` fields so that the simulator reproduces recorded flight.

A quadrotor is open-loop unstable: replayed open loop for seconds, any wrong guess diverges and the loss is
useless. `fit` therefore uses multiple shooting (Bock and Plitt, "A multiple shooting algorithm for direct solution
of optimal control problems", IFAC 1984): the record is cut into windows of a few control steps, each simulated
under the recorded commands from its own start state. The start states are unknowns too, started at the
observations: the fit is the least-squares (for Gaussian noise, maximum-likelihood) estimate of the parameters and
the states together, every observation counted once in units of its noise, and the jump from where a window ends to
where the next one starts (the continuity defect) a residual on a much finer scale. A window started from the
observed state instead would carry that observation's noise through the window: 0.01 rad of attitude error tilts
the thrust as much as drag pushes at 0.5 m/s. The fitted fields are parameterised as log-ratios to their initial
guess. The problem is solved by optimistix's Levenberg-Marquardt (`optimistix.least_squares`, Rader, Lyons and
Kidger, "Optimistix: modular optimisation in JAX and Equinox", arXiv:2402.09983, 2024); the report gives a
Gauss-Newton standard error for each fitted value.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.typing import ArrayLike

from jaxdrones._validate import check_int, check_real, is_real
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import DroneParams, with_derived
from jaxdrones.physics.rotations import quat_integrate
from jaxdrones.physics.state import DroneState
from jaxdrones.sim import make_step, rollout

#: Default measurement noise (standard deviations) that scales each residual: position m, velocity m/s, attitude
#: (quaternion components, about half the angle in rad: 5e-3 for 0.01 rad), body rate rad/s.
NOISE = {"pos": 1e-3, "vel": 1e-2, "quat": 5e-3, "ang_vel": 0.1}
#: `DroneParams` fields that `fit` may fit (the others are derived from them, or geometry).
FITTABLE = ("mass", "kf", "km", "drag_coeff", "inertia", "gnd_eff_coeff", "dw_coeff")
#: The solver's relative and absolute tolerances: `fit` stops once a step moves every unknown and every residual by
#: less than ATOL + RTOL × its size.
RTOL, ATOL = 1e-8, 1e-8


def _fields(theta: jax.Array, params0: DroneParams, fields: tuple) -> dict:
    """The flat log-ratios θ (each field's elements in turn) as field -> array shaped like ``params0``'s."""
    shapes = [jnp.shape(getattr(params0, f)) for f in fields]
    parts = jnp.split(theta, np.cumsum([int(np.prod(s)) for s in shapes])[:-1])
    return {f: part.reshape(shape) for f, part, shape in zip(fields, parts, shapes, strict=True)}


def _apply(params0: DroneParams, theta: dict) -> DroneParams:
    """``params0`` with each fitted field scaled by exp(θ), the derived fields recomputed."""
    return with_derived(params0.replace(**{f: getattr(params0, f) * jnp.exp(t) for f, t in theta.items()}))


def _corrected(start: DroneState, z: jax.Array, noise: dict) -> DroneState:
    """A window's start corrected by ``z`` (f[4·D·3] in noise units, or empty: uncorrected): the position,
    velocity and body rate moved by σ·z, the attitude rotated in the body frame by the rotation vector
    2σ_quat·z rad (a quaternion component moves by about half the angle)."""
    if z.size == 0:
        return start
    pos, vel, att, ang_vel = z.reshape((4,) + start.pos.shape)
    return start.replace(
        pos=start.pos + noise["pos"] * pos,
        vel=start.vel + noise["vel"] * vel,
        quat=quat_integrate(start.quat, 2 * noise["quat"] * att, 1.0),
        ang_vel=start.ang_vel + noise["ang_vel"] * ang_vel,
    )


def _scaled(state: DroneState, observed: DroneState, noise: dict, scale: float = 1.0) -> jax.Array:
    """``state − observed`` in units of ``scale`` × the noise, flat; q and −q being the same attitude, the
    quaternion is compared with the sign of the observed one."""
    sign = jnp.sign(jnp.sum(state.quat * observed.quat, axis=-1, keepdims=True))
    parts = [
        (state.pos - observed.pos) / noise["pos"],
        (state.vel - observed.vel) / noise["vel"],
        (sign * state.quat - observed.quat) / noise["quat"],
        (state.ang_vel - observed.ang_vel) / noise["ang_vel"],
    ]
    return jnp.concatenate([jnp.ravel(p) for p in parts]) / scale


def _windows(init_state: DroneState, rpms: jax.Array, observed: DroneState, window: int) -> tuple:
    """The record cut into whole windows, each leaf with a leading window axis [W]: (start state, rpms
    [W, window, D, 4], observed [W, window, D, ...], the next window's start (the first's after the last))."""
    n = (rpms.shape[0] // window) * window
    before = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest[: n - 1]]), init_state, observed)
    starts = jax.tree.map(lambda x: x[::window], before)
    cut = lambda x: x[:n].reshape((n // window, window) + x.shape[1:])  # noqa: E731
    return starts, cut(rpms), jax.tree.map(cut, observed), jax.tree.map(lambda x: jnp.roll(x, -1, axis=0), starts)


def _window_residuals(step, params0: DroneParams, fields: tuple, noise: dict, defect: float):
    """``r(θ, z, z_next, window, joined)``: the residuals of one window, f[m]: its observations, then the
    continuity defect to the next window's start in units of ``defect`` × the noise (zero unless ``joined``).
    θ is the fitted fields' log-ratios (flat, `_fields`), ``z`` and ``z_next`` the corrections of this window's
    start and of the next one's (`_corrected`), ``window`` one window of `_windows`."""

    def residuals(theta, z, z_next, window, joined):
        start, rpms, observed, following = window
        params = _apply(params0, _fields(theta, params0, fields))
        predicted = rollout(step, params, _corrected(start, z, noise), rpms)
        end = jax.tree.map(lambda v: v[-1], predicted)
        defects = _scaled(end, _corrected(following, z_next, noise), noise, defect)
        return jnp.concatenate([_scaled(predicted, observed, noise), jnp.where(joined, defects, 0.0)])

    return residuals


def _residuals(y: tuple, args: tuple) -> jax.Array:
    """All residuals, flat: every window's (`_window_residuals`), then z[0] (the first start's own observation), at
    ``y = (θ, z)``, z f[W, c]; ``args`` is ``(params0, noise, defect, windows, joined, step, fields)``."""
    (theta, z), (params0, noise, defect, windows, joined, step, fields) = y, args
    one = _window_residuals(step, params0, fields, noise, defect)
    z_next = jnp.concatenate([z[1:], jnp.zeros_like(z[:1])])
    return jnp.concatenate(
        [jnp.ravel(jax.vmap(one, in_axes=(None, 0, 0, 0, 0))(theta, z, z_next, windows, joined)), z[0]]
    )


@functools.partial(jax.jit, static_argnames=("step", "fields"))
def _evaluate(y: tuple, problem: tuple, *, step, fields: tuple) -> tuple:
    """The residuals (`_residuals`) at ``y``, f[m], and their Jacobian with respect to θ and z, f[m, p + W·c];
    ``problem`` is `_residuals`' ``args`` without the step and fields."""
    args = problem + (step, fields)
    jac = jax.jacfwd(_residuals)(y, args)
    return _residuals(y, args), jnp.concatenate([j.reshape(len(j), -1) for j in jac], axis=1)


def _check(init_state, rpms, observed, fields, window, iterations, noise, defect):
    unknown = [f for f in fields if f not in FITTABLE]
    if not fields or unknown:
        raise ValueError(f"fields must name DroneParams fields from {FITTABLE}, got {tuple(fields)!r}")
    rpms = jnp.asarray(rpms)
    if rpms.ndim != init_state.rpm.ndim + 1 or rpms.shape[1:] != init_state.rpm.shape:
        raise ValueError(f"rpms must have shape [T, {', '.join(map(str, init_state.rpm.shape))}], got {rpms.shape}")
    for name in ("pos", "quat", "vel", "ang_vel", "rpm"):
        value, expected = getattr(observed, name), (rpms.shape[0],) + getattr(init_state, name).shape
        if value.shape != expected:
            raise ValueError(
                f"observed.{name} must have shape [T, ...] = {expected} (the state after each of the T "
                f"commands, as rollout returns it), got {value.shape}"
            )
        if not bool(jnp.all(jnp.isfinite(value))):
            raise ValueError(f"observed.{name} contains NaN or inf")
    check_int("window", window, 1, rpms.shape[0], what="control steps, at most the commands' T")
    check_int("iterations", iterations, 0)
    check_real("defect", defect, 0, low_open=True, what="a number")
    noise = {**NOISE, **(noise or {})}
    if set(noise) != set(NOISE) or not all(_positive(v) for v in noise.values()):
        raise ValueError(f"noise must map some of {tuple(NOISE)} to standard deviations > 0, got {noise!r}")
    return rpms, {k: float(v) for k, v in noise.items()}


def _positive(value) -> bool:
    """Whether ``value`` is a real number > 0."""
    return is_real(value) and value > 0


def _float64(tree):
    """``tree`` with its floating-point leaves in float64 (under ``jax.enable_x64``)."""
    floating = lambda x: jnp.issubdtype(jnp.result_type(x), jnp.floating)  # noqa: E731
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if floating(x) else x, tree)


def fit(
    config: SimConfig,
    params0: DroneParams,
    init_state: DroneState,
    rpms: ArrayLike,
    observed: DroneState,
    fields: Sequence[str] = ("kf", "km", "drag_coeff"),
    *,
    window: int = 10,
    noise: dict | None = None,
    iterations: int = 100,
    estimate_starts: bool = True,
    defect: float = 1e-3,
) -> tuple[DroneParams, dict]:
    """Fit the named fields of ``params0`` to recorded flight by multiple shooting.

    The unknowns are the fields' log-ratios θ to ``params0`` and, with ``estimate_starts``, each window's start
    state: a correction z (4 × [D, 3], in noise units) to the observed one, of its position, velocity, attitude (a
    rotation vector, 2·``noise["quat"]`` rad per unit) and body rate. The residuals, each in units of its noise,
    are every observation once (the states each window's rollout predicts, and the first start's: z itself) and
    the continuity defect between each window's end and the next window's start, in units of ``defect`` × the
    noise. They are minimised by `optimistix.LevenbergMarquardt` (tolerances `RTOL`, `ATOL`), in float64
    (``jax.enable_x64`` within the call; the inputs are cast, the fitted params returned in ``params0``'s dtype):
    the defect's scale, 1 µm for 1 mm noise, is not far above float32's rounding of a position near 1 m (6e-8 m, at
    each of a window's substeps), and in float32 the fit stalled short of the optimum for 3-s records or 12-step
    windows. Without ``estimate_starts`` each window
    starts from its observed state and only θ is fitted: exact for noise-free observations, biased by noisy ones
    (with 1 mm and 0.01 rad noise, drag off by 10-100 %).

    Args:
        config: the `SimConfig` of the record (rates and effects).
        params0: the initial guess (also the value of every field not fitted), unbatched or [D].
        init_state: the state before the first command, DroneState f[D, ...], measured.
        rpms: f[T, D, 4] RPM, the recorded commands, one per control step.
        observed: DroneState with leading time axis [T, D, ...], the state after each command (as `rollout`
            returns it), measured.
        fields: `DroneParams` fields to fit (from `FITTABLE`); each element of an array field is fitted.
        window: control steps per shooting window; the last T mod ``window`` steps are left out. Longer windows
            make the problem more nonlinear: on `excitation_flight`'s 5 s from guesses 20-30 % off (noise-free, and
            with 1 mm and 0.01 rad noise), windows of 5 steps converged in 24-35 solver steps, 10 in 11-17, 20 in
            17-18 and 48 in 12-88.
        noise: the measurement noise's standard deviations that scale the residuals, some keys of `NOISE` (which
            gives the others): ``pos`` m, ``vel`` m/s, ``quat`` (quaternion components: half the attitude's in
            rad), ``ang_vel`` rad/s.
        iterations: at most this many solver steps, accepted or rejected (``max_steps``; fewer once a step
            changes the unknowns and the residuals by less than the tolerances). The fit after the last is
            returned, converged or not.
        estimate_starts: fit each window's start state too (default); False starts each from its observation.
        defect: the continuity defect's standard deviation, as a fraction of ``noise``. Small joins the windows
            into one trajectory (the maximum-likelihood fit of a model without process noise); larger lets the
            trajectory jump at window boundaries (unmodelled disturbances), at the cost of precision.

    Returns:
        ``(params, report)``: the fitted params (derived fields recomputed, `jaxdrones.physics.params.with_derived`)
        and a dict with ``loss`` (two numbers: the loss at the initial guess and at the fit, each the mean squared
        residual in noise units), ``steps`` (the solver steps taken, accepted or rejected), ``estimates`` (field ->
        fitted value), ``initial`` (field -> initial guess), ``std`` (field -> Gauss-Newton standard error of the fitted
        value, the start states unknown too, from the residuals' scatter; inf where the data do not determine it),
        ``windows`` and ``window``.

    Raises:
        ValueError: an unknown field, ``rpms`` or ``observed`` of the wrong shape, a non-finite observation, a
            window outside [1, T], a negative number of iterations, a noise key not in `NOISE` or a standard
            deviation not > 0, a defect not > 0.
    """
    fields = tuple(fields)
    rpms, noise = _check(init_state, rpms, observed, fields, window, iterations, noise, defect)
    count = len(rpms) // window
    with jax.enable_x64(True):
        guess, windows = _float64(params0), _windows(*_float64((init_state, rpms, observed)), window)
        theta = jnp.zeros(sum(np.size(getattr(params0, f)) for f in fields), jnp.float64)
        z = jnp.zeros((count, 4 * init_state.pos.size if estimate_starts else 0), jnp.float64)
        joined = (jnp.arange(count) < count - 1) & estimate_starts
        problem = (guess, _float64(noise), jnp.float64(defect), windows, joined)
        # The fit takes forward-mode Jacobians (jax.jacfwd), which the hand-written adjoint has not.
        static = {"step": make_step(dataclasses.replace(config, adjoint=False)), "fields": fields}
        # The residuals: every observed state once, the defects that join the windows, and z[0].
        size = (count * window + int(joined.sum())) * _scaled(init_state, init_state, noise).size + z.shape[1]
        y, steps, r = (theta, z), 0, np.asarray(_evaluate((theta, z), problem, **static)[0])
        loss = [float(r @ r) / size]
        if iterations:
            solution = optx.least_squares(
                _residuals,
                optx.LevenbergMarquardt(rtol=RTOL, atol=ATOL),
                y,
                args=problem + tuple(static.values()),
                max_steps=iterations,
                throw=False,
            )
            y, steps = solution.value, int(solution.stats["num_steps"])
        r, jac = (np.asarray(a) for a in _evaluate(y, problem, **static))
        loss.append(float(r @ r) / size)
        std = _standard_errors(r, jac, len(theta), size)
        theta = np.asarray(y[0])
    dtype = jnp.result_type(getattr(params0, fields[0]))
    params = _apply(params0, _fields(jnp.asarray(theta, dtype), params0, fields))
    std = _fields(np.asarray(std), params0, fields)
    return params, {
        "loss": loss,
        "steps": steps,
        "estimates": {f: np.asarray(getattr(params, f)) for f in fields},
        "initial": {f: np.asarray(getattr(params0, f)) for f in fields},
        "std": {f: np.asarray(getattr(params, f)) * np.asarray(std[f]) for f in fields},
        "windows": count,
        "window": window,
    }


def _standard_errors(r: np.ndarray, jac: np.ndarray, p: int, size: int) -> np.ndarray:
    """θ's Gauss-Newton standard errors, f[p], from the residuals ``r`` and their Jacobian ``jac`` [m, p + W·c] (θ's
    columns first): cov(θ) = s² S⁻¹, S = H_θθ − H_θz H_zz⁻¹ H_zθ the Schur complement of H = JᵀJ (the marginal
    covariance, the start states unknown too), s² the residuals' sum of squares over the ``size`` − p − W·c
    degrees of freedom; inf for every θ when S is singular (its condition number with unit diagonal above 1e12)."""
    h = jac.T @ jac
    try:
        schur = h[:p, :p] - h[:p, p:] @ np.linalg.solve(h[p:, p:], h[p:, :p]) if len(h) > p else h[:p, :p]
    except np.linalg.LinAlgError:
        return np.full(p, np.inf)
    scale = (r @ r) / max(size - len(h), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = schur / np.sqrt(np.outer(np.diag(schur), np.diag(schur)))
        if not np.all(np.isfinite(unit)) or np.linalg.cond(unit) > 1e12:
            return np.full(p, np.inf)
    return np.sqrt(np.diag(np.linalg.inv(schur)) * scale)


def fit_forces(
    predict: Callable[[jax.Array, object], jax.Array],
    theta0: ArrayLike,
    inputs: object,
    measured: ArrayLike,
    *,
    iterations: int = 200,
) -> tuple[np.ndarray, dict]:
    """Fit the constants θ of a force model to measured forces by least squares: the aerodynamic effects held
    against the residual forces of logged flights (docs/validation.md §3).

    θ is parameterised relative to its guess, θ = θ0 (1 + u), so that every unknown u is of order one whatever the
    constant's scale (hence a zero guess is not allowed); u is found by optimistix's Levenberg-Marquardt (tolerances
    `RTOL`, `ATOL`) in float64, as in `fit`.

    Args:
        predict: ``predict(theta, inputs) -> f[N]`` the model's force for each sample (any unit, ``measured``'s),
            traceable by JAX.
        theta0: f[p] the initial guess, every entry nonzero.
        inputs: a pytree of arrays the model reads (positions, thrusts, ...), cast to float64.
        measured: f[N] the measured forces.
        iterations: at most this many solver steps.

    Returns:
        ``(theta, report)``: f64[p] the fitted constants, and a dict with ``loss`` (the mean squared residual at the
        guess and at the fit), ``rmse`` (the root of the fitted loss), ``std`` (f[p] Gauss-Newton standard errors,
        inf where the data do not determine the constants) and ``steps``.

    Raises:
        ValueError: ``theta0`` not a non-empty 1-D array of finite nonzero numbers; ``measured`` not a 1-D array of
            finite numbers; a negative number of iterations.
    """
    theta0 = np.asarray(theta0, np.float64)
    measured = np.asarray(measured, np.float64)
    if theta0.ndim != 1 or not theta0.size or not np.all(np.isfinite(theta0)) or np.any(theta0 == 0):
        raise ValueError(f"theta0 must be a 1-D array of finite nonzero numbers, got {theta0!r}")
    if measured.ndim != 1 or not np.all(np.isfinite(measured)):
        raise ValueError(f"measured must be a 1-D array of finite numbers, got shape {measured.shape}")
    check_int("iterations", iterations, low=0)
    with jax.enable_x64(True):
        data = (_float64(inputs), jnp.asarray(measured), jnp.asarray(theta0))

        def residuals(u, args):
            x, y, t0 = args
            return predict(t0 * (1 + u), x) - y

        u = jnp.zeros_like(data[2])
        r0 = np.asarray(residuals(u, data))
        steps = 0
        if iterations:
            solution = optx.least_squares(
                residuals,
                optx.LevenbergMarquardt(rtol=RTOL, atol=ATOL),
                u,
                args=data,
                max_steps=iterations,
                throw=False,
            )
            u, steps = solution.value, int(solution.stats["num_steps"])
        r = np.asarray(residuals(u, data))
        jac = np.asarray(jax.jacfwd(residuals)(u, data))
        std = _standard_errors(r, jac, len(theta0), len(r)) * np.abs(theta0)
        theta = np.asarray(data[2] * (1 + u))
    loss = [float(r0 @ r0) / len(r0), float(r @ r) / len(r)]
    return theta, {"loss": loss, "rmse": float(np.sqrt(loss[1])), "std": std, "steps": steps}


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
    from jaxdrones.physics.state import init_state

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
        rpm, ctrl = pid.pid_control(
            params, gains, ctrl, state, target[None], target_rpy=yaw[None], ctrl_dt=config.ctrl_dt
        )
        state = step(params, state, rpm)
        return (state, ctrl), (rpm, state)

    times = jnp.arange(1, steps + 1) * config.ctrl_dt
    _, (rpms, states) = jax.lax.scan(body, (state0, pid.pid_init(state0)), times)
    return Flight(state0, rpms, states)


def add_noise(
    flight: Flight, key: jax.Array, pos: float = 1e-3, att: float = 1e-2, vel: float = 0.0, ang_vel: float = 0.0
) -> Flight:
    """``flight`` as sensors would record it: independent Gaussian noise of the given standard deviations added to
    each position component (m), velocity component (m/s) and body rate component (rad/s) of ``init_state`` and
    ``observed``, and each attitude rotated in the body frame by a rotation vector with N(0, ``att``²) rad
    components (its quaternion components then have about ``att``/2 noise: `fit`'s ``noise["quat"]``). The
    commands stay exact. ``key`` is a JAX PRNG key."""

    def noisy(state: DroneState, key: jax.Array) -> DroneState:
        keys = jax.random.split(key, 4)
        normal = lambda k, std: std * jax.random.normal(k, state.pos.shape, state.pos.dtype)  # noqa: E731
        return state.replace(
            pos=state.pos + normal(keys[0], pos),
            vel=state.vel + normal(keys[1], vel),
            quat=quat_integrate(state.quat, normal(keys[2], att), 1.0),
            ang_vel=state.ang_vel + normal(keys[3], ang_vel),
        )

    first, rest = jax.random.split(key)
    return Flight(noisy(flight.init_state, first), flight.rpms, noisy(flight.observed, rest))
