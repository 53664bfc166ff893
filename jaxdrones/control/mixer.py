"""Wrench allocation: the motor mixer of the explicit dynamics, the paper's NNLS conversion, and a body-rate loop.

A quadrotor's four motor speeds set a body wrench (collective thrust T along body +z and the body torques τx, τy,
τz). The map is linear in the squared speeds s = rpm², ``wrench = A s``, with A = `allocation_matrix`, built from
the same constants and signs as `jaxdrones.physics.dynamics` (docs/physics.md §2, §3.1). Its inverse with the
constraint s ≥ 0 is the paper's DYN action conversion (docs/physics.md §10.3,
``paper:gym_pybullet_drones/utils/utils.py:58-133``): solve A s = b; if a squared speed comes out negative, take the
non-negative least-squares (NNLS) solution instead; rpm = √s. `nnls_rpm_squared` solves that NNLS problem exactly,
batched and jittable, by enumerating the 16 passive sets of the 4-motor problem.

`mixer_matrix` is the PID controller's mixer (PWM units), derived from the airframe as the original's
DSLPIDControl writes it (docs/physics.md §12.1).

`body_rate_control` closes a proportional body-rate loop with gyroscopic feed-forward on top, for the collective
thrust and body rates (CTBR) interface of real flight stacks (PX4, Betaflight).

All functions are pure and broadcast over leading axes ``[..., D]``; `DroneParams` may carry batch axes that
broadcast against them (per drone ``[D]``, ``[W, D]``, or per world ``[W, 1]``). Motor speeds are in RPM
(rev/min), as in the paper and its URDFs; thrust is in N, torques in N·m, body frame (x forward, y left, z up).
"""

from __future__ import annotations

import functools
import itertools
import operator

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.typing import DTypeLike
from numpy.typing import ArrayLike

from jaxdrones.physics.params import DroneParams, align_params, params_batch_shape

#: The 16 passive sets of the 4-motor NNLS problem, bool[16, 4] (True = the motor's s_i is free, False = held at
#: 0). Row 0 is the empty set (s = 0, always feasible).
_PASSIVE_SETS = np.array(list(itertools.product((False, True), repeat=4)))


@struct.dataclass
class RateGains:
    """Gains of the body-rate loop τ = J K (ω* − ω) + ω × (J ω) (see `body_rate_control`).

    Attributes:
        k_rate: f[..., 3] 1/s, the diagonal of K for the body axes (x, y, z): the inverse time constants of the
            first-order rate response ω̇ = K (ω* − ω). Broadcasts against the drones' ``[..., D, 3]``: f[3] for one
            gain set, f[W, 1, 3] or f[W, D, 3] per world or per drone.
    """

    k_rate: jax.Array

    @classmethod
    def flightmare(cls, dtype: DTypeLike | None = None) -> RateGains:
        """K = diag(16.6, 16.6, 5.0) 1/s, in JAX's default float or ``dtype``.

        Source: the simple low-level controller of the Flightmare simulator (uzh-rpg/flightmare,
        ``flightlib/include/flightlib/controller/lowlevel_controller_simple.hpp``, ``Kinv_ang_vel_tau_``), whose
        ``run`` computes the same law, ``J * Kinv_ang_vel_tau_ * omega_err + omega.cross(J * omega)``
        (``flightlib/src/controller/lowlevel_controller_simple.cpp``), then allocates with B⁻¹ and clamps the
        thrusts. Time constants 60 ms (roll, pitch) and 200 ms (yaw).

        Flightmare evaluates the loop at every integration step (at most 2.5 ms, ``flightlib/src/objects/
        quadrotor.cpp``), behind first-order motors. Here it runs at the control rate f_c with its output held over
        the physics substeps, so each axis's rate error is multiplied by about 1 − k/f_c per control step: at
        30 Hz by 0.45 (roll, pitch) and 0.83 (yaw). That is without overshoot for f_c ≥ k (16.6 Hz roll/pitch,
        5 Hz yaw) and stable for f_c > k/2; `tests/test_mixer.py` checks the response at 30 Hz.
        """
        dtype = jnp.result_type(float) if dtype is None else dtype
        return cls(k_rate=jnp.asarray((16.6, 16.6, 5.0), dtype=dtype))


def allocation_matrix(params: DroneParams) -> jax.Array:
    """The motor mixer of the explicit dynamics: wrench = A @ rpm², exactly as `jaxdrones.physics.dynamics` computes it.

    Rows (docs/physics.md §3.1, ``main:BA:838-855``): collective thrust T = kf Σ rpm_i²;
    (τx, τy) = kf · torque_arm @ rpm² (the explicit model's lever arms: L/√2 along each diagonal for an x frame, L
    along each axis for a + frame);
    τz = −km Σ spin_i rpm_i² (`dynamics.yaw_torque_c`: a counter-clockwise motor, spin +1, pushes the body
    clockwise).

    Args:
        params: DroneParams, possibly batched (``kf``, ``km`` f[...], ``torque_arm`` f[..., 2, 4] m,
            ``prop_spin`` f[..., 4]).

    Returns:
        f[..., 4, 4]: rows T (N), τx, τy, τz (N·m), body frame; columns motors 0-3, per RPM².

    Raises:
        ValueError: if ``params`` is not a `DroneParams` or its fields disagree on the batch shape.
    """
    _check_params(params)
    params_batch_shape(params)
    return _allocation_matrix(params)


def _allocation_matrix(params: DroneParams) -> jax.Array:
    kf = params.kf[..., None]
    rows = (
        kf * jnp.ones_like(params.prop_spin),
        kf * params.torque_arm[..., 0, :],
        kf * params.torque_arm[..., 1, :],
        -params.km[..., None] * params.prop_spin,
    )
    return jnp.stack(rows, axis=-2)


def wrench_scale(params: DroneParams) -> jax.Array:
    """Row weights of the NNLS problem, the original's (docs/physics.md §10.3): (1/kf, 1/(kf L), 1/(kf L), 1/km).

    They turn the wrench (N, N·m, N·m, N·m) into RPM² and the rows of `allocation_matrix` into numbers of order
    one (for the shipped models: (1, 1, 1, 1), the ±1/√2 or 0/±1 lever-arm signs, and −spin), so that float32
    suffices.

    Returns:
        f[..., 4] in 1/N, 1/(N·m), 1/(N·m), 1/(N·m) times RPM², with the params' batch shape.

    Raises:
        ValueError: as `allocation_matrix`.
    """
    _check_params(params)
    params_batch_shape(params)
    return _wrench_scale(params)


def _wrench_scale(params: DroneParams) -> jax.Array:
    arm = 1.0 / (params.kf * params.arm)
    return jnp.stack([1.0 / params.kf, arm, arm, 1.0 / params.km], axis=-1)


def nnls_rpm_squared(params: DroneParams, wrench: ArrayLike) -> jax.Array:
    """Squared motor speeds for a desired wrench: the paper's DYN conversion (docs/physics.md §10.3), solved exactly.

    Minimises ‖W (A s − wrench)‖₂ over s ≥ 0, where A = `allocation_matrix` and W = diag(`wrench_scale`) =
    diag(1/kf, 1/(kf L), 1/(kf L), 1/km): the Euclidean norm of the residual measured in RPM², the norm the
    original's ``scipy.optimize.nnls(A', b)`` minimises with its scaled matrix A' = W A and target b = W wrench.
    When the wrench is reachable with non-negative squared speeds (s = A⁻¹ wrench ≥ 0), this is that exact
    solution, as in the original; otherwise it is the least-squares compromise, some motors at 0. There is no upper
    limit (the original has none either; `jaxdrones.sim.make_step` clips the RPM to ``max_rpm``).

    Exact for the 4×4 problem: the restricted least-squares solution of each of the 16 passive sets is computed
    (masked normal equations, an unrolled LDLᵀ solve), and the one that satisfies the optimality (KKT) conditions
    is returned: its free squared speeds are ≥ 0, and no motor held at 0 could lower the residual by speeding up
    (the residual's gradient with respect to its s_i is ≥ 0). For a full-rank A the problem is strictly convex,
    so exactly one passive set (the optimum's support) satisfies them, up to ties between sets giving the same
    point; the candidate with the smallest violation is taken, which is robust to round-off. No iterations and no
    data-dependent control flow: it runs under ``jit``, ``vmap`` and ``grad``. Gradients are those of the selected
    passive set's solution, exact wherever the active set does not change. A non-finite wrench gives NaN.

    Args:
        params: DroneParams, possibly batched; its batch shape broadcasts against ``wrench``'s leading axes.
        wrench: f[..., 4] (T N, τx N·m, τy N·m, τz N·m), body frame.

    Returns:
        f[..., 4] RPM², s ≥ 0, one per motor; leading shape: ``wrench``'s broadcast with the params' batch shape.

    Raises:
        ValueError: if ``wrench`` is not f[..., 4] or ``params`` does not broadcast against its leading shape.
    """
    wrench, params = _prepare(params, wrench, min_ndim=1, name="nnls_rpm_squared")
    return _nnls_rpm_squared(params, wrench)


def wrench_to_rpm(params: DroneParams, wrench: ArrayLike) -> jax.Array:
    """Motor speeds for a desired wrench: rpm = √s with s = `nnls_rpm_squared` (the paper's DYN action).

    Not clipped to ``max_rpm`` (the step clips). The square root is safe at 0: a motor at 0 RPM gets a zero, not
    an infinite or NaN, gradient.

    Args:
        params: DroneParams, possibly batched (per drone ``[D]``, ``[W, D]``, per world ``[W, 1]``).
        wrench: f[..., D, 4] (T N, τx N·m, τy N·m, τz N·m), body frame.

    Returns:
        f[..., D, 4] RPM.

    Raises:
        ValueError: if ``wrench`` is not f[..., D, 4] or ``params`` does not broadcast against its leading shape.
    """
    wrench, params = _prepare(params, wrench, min_ndim=2, name="wrench_to_rpm")
    return _wrench_to_rpm(params, wrench)


def body_rate_torque(
    params: DroneParams, ang_vel: ArrayLike, rate_cmd: ArrayLike, gains: RateGains | None = None
) -> jax.Array:
    """Body torque of a proportional body-rate loop with gyroscopic feed-forward: τ = J K (ω* − ω) + ω × (J ω).

    With this torque the rigid body's Euler equation J ω̇ = τ − ω × (J ω) becomes ω̇ = K (ω* − ω): each body rate
    approaches its command as a first-order system with time constant 1/k. The law is the simple low-level
    controller of the Flightmare simulator (uzh-rpg/flightmare, ``flightlib/src/controller/
    lowlevel_controller_simple.cpp``); the default gains are theirs (`RateGains.flightmare`).

    Args:
        params: DroneParams (``inertia`` f[..., 3, 3] kg·m², body frame), possibly batched.
        ang_vel: f[..., D, 3] rad/s, body frame, the measured angular velocity ω.
        rate_cmd: f[..., D, 3] rad/s, body frame, the commanded rates ω* (broadcastable to ``ang_vel``).
        gains: RateGains; default `RateGains.flightmare`.

    Returns:
        f[..., D, 3] N·m, body frame.

    Raises:
        ValueError: on wrong shapes (see `body_rate_control`) or a ``gains`` that is not a RateGains.
    """
    ang_vel, rate_cmd, _, gains, params = _prepare_rates(params, ang_vel, rate_cmd, None, gains, "body_rate_torque")
    return _body_rate_torque(params, ang_vel, rate_cmd, gains)


def body_rate_control(
    params: DroneParams, ang_vel: ArrayLike, rate_cmd: ArrayLike, thrust: ArrayLike, gains: RateGains | None = None
) -> jax.Array:
    """Collective thrust and body rates (CTBR) to motor speeds: `body_rate_torque`, then `wrench_to_rpm`.

    The interface of real flight stacks (PX4's rate setpoint with collective thrust, Betaflight's acro mode): the
    caller commands the thrust along body +z and the body rates; this loop computes the torque
    τ = J K (ω* − ω) + ω × (J ω) and allocates (thrust, τ) to the motors with the exact NNLS mixer. It is
    memoryless (no integral term), so it can run at the control rate with its output held over the physics
    substeps; `RateGains.flightmare` discusses the rates at which that is stable.

    Args:
        params: DroneParams, possibly batched (per drone ``[D]``, ``[W, D]``, per world ``[W, 1]``).
        ang_vel: f[..., D, 3] rad/s, body frame, the measured angular velocity (``DroneState.ang_vel``).
        rate_cmd: f[..., D, 3] rad/s, body frame, the commanded body rates (broadcastable to ``ang_vel``).
        thrust: f[..., D] N, the commanded collective thrust along body +z (broadcastable to ``ang_vel[..., 0]``;
            ``params.weight`` hovers).
        gains: RateGains; default `RateGains.flightmare`.

    Returns:
        f[..., D, 4] RPM, not clipped to ``max_rpm`` (the step clips); leading shape: ``ang_vel``'s broadcast with
        the params' batch shape.

    Raises:
        ValueError: if ``ang_vel`` is not f[..., D, 3], ``rate_cmd`` or ``thrust`` does not broadcast to it, ``gains``
            is not a RateGains or its ``k_rate`` is not f[..., 3], or ``params`` does not broadcast against the
            drones' leading shape.
    """
    ang_vel, rate_cmd, thrust, gains, params = _prepare_rates(
        params, ang_vel, rate_cmd, thrust, gains, "body_rate_control"
    )
    return _body_rate_control(params, ang_vel, rate_cmd, thrust, gains)


@jax.jit
def _nnls_rpm_squared(params: DroneParams, wrench: jax.Array) -> jax.Array:
    """`nnls_rpm_squared` on validated inputs (params of ``wrench``'s batch rank, see `_broadcast_params`)."""
    scale = _wrench_scale(params).astype(wrench.dtype)
    matrix = _allocation_matrix(params).astype(wrench.dtype) * scale[..., :, None]
    target = wrench * scale
    s = _nnls4(matrix, target)
    finite = jnp.all(jnp.isfinite(target), axis=-1, keepdims=True)
    return jnp.where(finite, s, jnp.nan)


@jax.jit
def _wrench_to_rpm(params: DroneParams, wrench: jax.Array) -> jax.Array:
    return _safe_sqrt(_nnls_rpm_squared(params, wrench))


@jax.jit
def _body_rate_torque(params, ang_vel, rate_cmd, gains):
    inertia = params.inertia.astype(ang_vel.dtype)
    feedback = (inertia @ (gains.k_rate * (rate_cmd - ang_vel))[..., None])[..., 0]
    momentum = (inertia @ ang_vel[..., None])[..., 0]
    return feedback + jnp.cross(ang_vel, momentum)


@jax.jit
def _body_rate_control(params, ang_vel, rate_cmd, thrust, gains):
    torque = _body_rate_torque(params, ang_vel, rate_cmd, gains)
    return _wrench_to_rpm(params, jnp.concatenate([thrust[..., None], torque], axis=-1))


def _nnls4(matrix: jax.Array, target: jax.Array) -> jax.Array:
    """argmin_{s ≥ 0} ‖matrix s − target‖₂ for a full-rank f[..., 4, 4] matrix and f[..., 4] target, by passive sets.

    For each passive set P (``_PASSIVE_SETS``), the masked normal equations M x = r with M_ij = (AᵀA)_ij for
    i, j ∈ P, M_ii = 1 for i ∉ P (0 elsewhere) and r_i = (Aᵀb)_i for i ∈ P, 0 otherwise, give the least-squares
    solution restricted to P (zeros outside it). M is symmetric positive definite, so an LDLᵀ solve needs no
    pivoting.

    The optimum is the candidate that satisfies the KKT conditions x_i ≥ 0 (i ∈ P) and w_i = (Aᵀ(b − A x))_i ≤ 0
    (i ∉ P); the candidate with the smallest violation max_i(−x_i for i ∈ P, w_i for i ∉ P) is returned. Unlike a
    comparison of residual norms, which are quadratic in a squared speed near 0, these are linear in it, so float32
    tells the candidates apart to its own resolution. ``matrix``'s and ``target``'s leading axes are of equal rank and
    broadcast (size-1 axes).

    The arithmetic runs on the 16 entries of the 4×4 matrices as separate arrays with the candidates on a leading
    axis, f[16, ...], which XLA fuses into a few vectorised loops.
    """
    lead = (1,) * (matrix.ndim - 2)
    a = [[matrix[None, ..., k, i] for i in range(4)] for k in range(4)]  # a[k][i]: f[1, ...]
    b = [target[None, ..., k] for k in range(4)]
    gram = [[_sum(a[k][i] * a[k][j] for k in range(4)) for j in range(4)] for i in range(4)]
    rhs = [_sum(a[k][i] * b[k] for k in range(4)) for i in range(4)]
    passive = [jnp.asarray(_PASSIVE_SETS[:, i]).reshape((16,) + lead) for i in range(4)]
    normal = [[jnp.where(passive[i] & passive[j], gram[i][j], float(i == j)) for j in range(4)] for i in range(4)]
    x = _spd_solve4(normal, [jnp.where(passive[i], rhs[i], 0.0) for i in range(4)])
    x = [jnp.where(passive[i], x[i], 0.0) for i in range(4)]  # f[16, ...]
    dual = [rhs[i] - _sum(gram[i][j] * x[j] for j in range(4)) for i in range(4)]
    violation = [jnp.where(passive[i], -x[i], dual[i]) for i in range(4)]
    violation = jnp.maximum(jnp.maximum(violation[0], violation[1]), jnp.maximum(violation[2], violation[3]))
    best = jnp.argmin(jnp.where(jnp.isnan(violation), jnp.inf, violation), axis=0)
    chosen = jnp.arange(16).reshape((16,) + lead) == best[None]
    return jnp.stack([jnp.sum(jnp.where(chosen, xi, 0.0), axis=0) for xi in x], axis=-1)


def _spd_solve4(m: list, r: list) -> list:
    """Solve m x = r for symmetric positive-definite 4×4 systems given entry by entry, by an unrolled LDLᵀ.

    ``m[i][j]`` and ``r[i]`` are arrays of one shape (or broadcastable); returns ``x`` as a list of 4 arrays.
    """
    n = len(r)
    low = [[None] * n for _ in range(n)]
    diag = [None] * n
    for j in range(n):
        diag[j] = m[j][j] - _sum(low[j][k] ** 2 * diag[k] for k in range(j))
        for i in range(j + 1, n):
            low[i][j] = (m[i][j] - _sum(low[i][k] * low[j][k] * diag[k] for k in range(j))) / diag[j]
    y = []
    for i in range(n):
        y.append(r[i] - _sum(low[i][k] * y[k] for k in range(i)))
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = y[i] / diag[i] - _sum(low[k][i] * x[k] for k in range(i + 1, n))
    return x


def _sum(terms):
    """Sum of an iterable of arrays; 0 for none."""
    terms = list(terms)
    return functools.reduce(operator.add, terms) if terms else 0.0


def _safe_sqrt(s: jax.Array) -> jax.Array:
    """√s for s ≥ 0, with a zero (not infinite) gradient at s = 0; NaN stays NaN."""
    positive = s > 0
    root = jnp.sqrt(jnp.where(positive, s, 1.0))
    return jnp.where(positive, root, jnp.where(jnp.isnan(s), s, 0.0))


def _check_params(params) -> None:
    if not isinstance(params, DroneParams):
        raise ValueError(f"expected DroneParams (see jaxdrones.load_params), got {type(params).__name__}")


def _float_array(value, params: DroneParams, what: str) -> jax.Array:
    value = jnp.asarray(value)
    if (
        not (jnp.issubdtype(value.dtype, jnp.floating) or jnp.issubdtype(value.dtype, jnp.integer))
        or value.dtype == bool
    ):
        raise ValueError(f"{what} must be a real (float or int) array, got dtype {value.dtype}")
    return value.astype(jnp.result_type(params.kf.dtype, value.dtype, float))


def _broadcast_params(params: DroneParams, lead: tuple[int, ...], name: str) -> tuple[tuple[int, ...], DroneParams]:
    """The drones' leading shape broadcast with the params' batch shape, and params of that batch rank.

    Singleton axes are prepended to the params' leaves, so that their sizes broadcast against that shape without
    implicit rank promotion; nothing is copied.
    """
    batch = params_batch_shape(params)
    try:
        full = tuple(np.broadcast_shapes(batch, lead))
    except ValueError:
        raise ValueError(
            f"{name}: params have batch shape {batch}, which does not broadcast against the drones' "
            f"leading shape {lead} (batched params are right-aligned with the drone axis: per-drone "
            f"[D] or [W, D], per-world [W, 1])"
        ) from None
    return full, align_params(params, len(full))


def _prepare(params: DroneParams, wrench, min_ndim: int, name: str) -> tuple[jax.Array, DroneParams]:
    """Validate ``wrench`` f[..., 4] (at least ``min_ndim`` axes) and broadcast it and ``params`` together."""
    _check_params(params)
    wrench = _float_array(wrench, params, f"{name}: wrench")
    if wrench.ndim < min_ndim or wrench.shape[-1] != 4:
        expected = "[..., D, 4]" if min_ndim > 1 else "[..., 4]"
        raise ValueError(f"{name}: wrench must have shape {expected} (thrust N, τx, τy, τz N·m), got {wrench.shape}")
    lead, params = _broadcast_params(params, tuple(wrench.shape[:-1]), name)
    return jnp.broadcast_to(wrench, lead + (4,)), params


def _prepare_rates(params, ang_vel, rate_cmd, thrust, gains, name: str):
    """Validate and broadcast the inputs of `body_rate_control` / `body_rate_torque` (``thrust`` may be None)."""
    _check_params(params)
    gains = RateGains.flightmare() if gains is None else gains
    if not isinstance(gains, RateGains):
        raise ValueError(f"{name}: gains must be a RateGains (e.g. RateGains.flightmare()), got {type(gains).__name__}")
    ang_vel = _float_array(ang_vel, params, f"{name}: ang_vel")
    if ang_vel.ndim < 2 or ang_vel.shape[-1] != 3:
        raise ValueError(f"{name}: ang_vel must have shape [..., D, 3] (rad/s, body frame), got {ang_vel.shape}")
    shape = tuple(ang_vel.shape)
    rate_cmd = _float_array(rate_cmd, params, f"{name}: rate_cmd")
    k_rate = _float_array(gains.k_rate, params, f"{name}: gains.k_rate")
    for what, value in (("rate_cmd", rate_cmd), ("gains.k_rate", k_rate)):
        if value.ndim < 1 or value.shape[-1] != 3 or not _broadcasts(value.shape, shape):
            raise ValueError(
                f"{name}: {what} must broadcast to ang_vel's shape {shape} ([..., D, 3]), got {value.shape}"
            )
    if thrust is not None:
        thrust = _float_array(thrust, params, f"{name}: thrust")
        if not _broadcasts(thrust.shape, shape[:-1]):
            raise ValueError(
                f"{name}: thrust must broadcast to the drones' leading shape {shape[:-1]} ([..., D], N), "
                f"got {thrust.shape}"
            )
    lead, params = _broadcast_params(params, shape[:-1], name)
    dtype = jnp.result_type(ang_vel.dtype, rate_cmd.dtype, k_rate.dtype, *(() if thrust is None else (thrust.dtype,)))
    ang_vel = jnp.broadcast_to(ang_vel.astype(dtype), lead + (3,))
    rate_cmd = jnp.broadcast_to(rate_cmd.astype(dtype), lead + (3,))
    gains = RateGains(k_rate=jnp.broadcast_to(k_rate.astype(dtype), lead + (3,)))
    if thrust is not None:
        thrust = jnp.broadcast_to(thrust.astype(dtype), lead)
    return ang_vel, rate_cmd, thrust, gains, params


def _broadcasts(shape, target) -> bool:
    """Whether ``shape`` broadcasts to ``target`` without enlarging it."""
    try:
        return tuple(np.broadcast_shapes(tuple(shape), tuple(target))) == tuple(target)
    except ValueError:
        return False


def mixer_matrix(params: DroneParams) -> jax.Array:
    """The controller's mixer, derived from the airframe: pwm = thrust + M @ (τ_roll, τ_pitch, τ_yaw).

    Roll/pitch columns: sign(torque_arm)ᵀ, scaled so each column's absolute values sum to 2 (½ per motor for an x
    frame, 1 for the two active motors of a + frame); yaw column: −prop_spin. This gives exactly the original's
    matrices (docs/physics.md §12.1): cf2x (main) [[−½,−½,−1],[−½,½,1],[½,½,−1],[½,−½,1]] and cf2p
    [[0,−1,−1],[1,0,1],[0,1,−1],[−1,0,1]]; for the racer, its mirrored spins and motor order.

    Args:
        params: DroneParams, possibly batched (``torque_arm`` f[..., 2, 4] m, ``prop_spin`` f[..., 4]).

    Returns:
        f[..., 4, 3] (rows: motors 0-3; columns: roll, pitch, yaw), dimensionless.
    """
    arm = params.torque_arm
    tol = 1e-6 * jnp.max(jnp.abs(arm), axis=(-2, -1), keepdims=True)
    sign = jnp.where(jnp.abs(arm) > tol, jnp.sign(arm), 0.0)
    count = jnp.maximum(jnp.sum(jnp.abs(sign), axis=-1, keepdims=True), 1.0)
    roll_pitch = jnp.swapaxes(2.0 * sign / count, -1, -2)
    lead = jnp.broadcast_shapes(roll_pitch.shape[:-2], params.prop_spin.shape[:-1])
    yaw = jnp.broadcast_to(-params.prop_spin[..., None], lead + (4, 1))
    return jnp.concatenate([jnp.broadcast_to(roll_pitch, lead + (4, 2)), yaw], axis=-1)
