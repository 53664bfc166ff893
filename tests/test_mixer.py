"""The wrench mixer (allocation matrix, exact NNLS against scipy) and the body-rate loop closed with the step.

Figures worth knowing are printed with the prefix ``MEASURED`` (see them with ``pytest -s``).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.optimize import nnls

import jaxdrones as jd
from jaxdrones import dynamics
from jaxdrones.control import (
    RateGains,
    allocation_matrix,
    body_rate_control,
    body_rate_torque,
    nnls_rpm_squared,
    wrench_scale,
    wrench_to_rpm,
)
from jaxdrones.rotations import join, split

pytestmark = pytest.mark.unit

MODELS = ("cf2x", "cf2p", "racer")
#: Agreement with scipy.optimize.nnls, relative to the largest entry of scipy's solution, over 1,000 targets per
#: model. float64: measured at most 3e-15 on RPM² and 4e-15 on RPM. float32 (scipy still in float64): measured at
#: most 4e-7 on RPM² and 7e-7 on RPM (the square root amplifies the error of a squared speed near 0).
F64_RTOL = 1e-12
F32_RTOL_SQUARED = 2e-6
F32_RTOL_RPM = 1e-5
#: The scaled allocation matrices W A (rows T, τx, τy, τz) that docs/physics.md §3.1 and §10.3 give: cf2x with main's
#: motor order (the paper's matrix is for its own order), cf2p exactly the paper's, racer with its mirrored spins.
SCALED = {
    "cf2x": [
        [1, 1, 1, 1],
        [-1 / math.sqrt(2), -1 / math.sqrt(2), 1 / math.sqrt(2), 1 / math.sqrt(2)],
        [-1 / math.sqrt(2), 1 / math.sqrt(2), 1 / math.sqrt(2), -1 / math.sqrt(2)],
        [-1, 1, -1, 1],
    ],
    "cf2p": [[1, 1, 1, 1], [0, 1, 0, -1], [-1, 0, 1, 0], [-1, 1, -1, 1]],
    "racer": [
        [1, 1, 1, 1],
        [1 / math.sqrt(2), 1 / math.sqrt(2), -1 / math.sqrt(2), -1 / math.sqrt(2)],
        [-1 / math.sqrt(2), 1 / math.sqrt(2), 1 / math.sqrt(2), -1 / math.sqrt(2)],
        [1, -1, 1, -1],
    ],
}


@pytest.fixture
def strict_ranks():
    """Implicit rank promotion raises inside the test (for tests that call only the mixer's functions)."""
    with jax.numpy_rank_promotion("raise"):
        yield


@functools.cache
def stepper(config: jd.SimConfig):
    """One step function per config, so that its jit cache is reused across tests."""
    return jd.make_step(config)


def stacked_params(names) -> jd.DroneParams:
    """Params of several models stacked along leading axes shaped like ``names`` (a nested list)."""
    arr = np.asarray(names)
    flat = [jd.load_params(n) for n in arr.ravel()]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *flat)
    return jax.tree.map(lambda x: x.reshape(arr.shape + x.shape[1:]), stacked)


def scaled_system(params: jd.DroneParams) -> tuple[np.ndarray, np.ndarray]:
    """Host-side (W A, W) in float64 for unbatched params, written from the params' fields in NumPy.

    The matrix and row weights that the original hands to scipy's nnls (docs/physics.md §10.3).
    """
    kf, km, arm = (float(getattr(params, name)) for name in ("kf", "km", "arm"))
    torque_arm, spin = np.asarray(params.torque_arm, np.float64), np.asarray(params.prop_spin, np.float64)
    matrix = np.stack([kf * np.ones(4), kf * torque_arm[0], kf * torque_arm[1], -km * spin])
    weights = np.array([1 / kf, 1 / (kf * arm), 1 / (kf * arm), 1 / km])
    return weights[:, None] * matrix, weights


def random_targets(params: jd.DroneParams, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Feasible and infeasible wrenches, f64[n, 4] each, checked with the unconstrained solution s = A⁻¹ b.

    Feasible: thrust in [0.25, 1]·max_thrust with torques up to 5 % of the maxima (the paper's DYN action range),
    plus wrenches of squared speeds drawn uniformly in [0, max_rpm²]⁴. Infeasible: thrust in [0, max_thrust] with
    torques of 0.5-3 times the maxima (about 95 % of those are infeasible; the first n are kept).
    """
    matrix, weights = scaled_system(params)
    limits = np.array([float(params.max_xy_torque)] * 2 + [float(params.max_z_torque)])
    max_thrust = float(params.max_thrust)
    half = n // 2
    dyn = np.column_stack([rng.uniform(0.25, 1.0, half) * max_thrust, 0.05 * limits * rng.uniform(-1, 1, (half, 3))])
    squares = rng.uniform(0, float(params.max_rpm) ** 2, (n - half, 4))
    feasible = np.concatenate([dyn, squares @ (matrix / weights[:, None]).T])
    sign = rng.choice([-1.0, 1.0], (2 * n, 3))
    infeasible = np.column_stack([rng.uniform(0, max_thrust, 2 * n), sign * limits * rng.uniform(0.5, 3.0, (2 * n, 3))])
    free = np.linalg.solve(matrix, (weights * feasible).T).T
    assert np.all(free >= 0), "the 'feasible' targets must be reachable with non-negative squared speeds"
    free = np.linalg.solve(matrix, (weights * infeasible).T).T
    infeasible = infeasible[np.any(free < 0, axis=-1)][:n]
    assert len(infeasible) == n
    return feasible, infeasible


def scipy_nnls(params: jd.DroneParams, wrenches: np.ndarray) -> np.ndarray:
    """scipy.optimize.nnls on the original's scaled problem, one target at a time (float64)."""
    matrix, weights = scaled_system(params)
    return np.stack([nnls(matrix, weights * w)[0] for w in wrenches])


def max_rel_err(actual, expected) -> float:
    """Maximum over targets of max_i |actual_i - expected_i| / max_i |expected_i|."""
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    return float(np.max(np.max(np.abs(actual - expected), axis=-1) / np.max(np.abs(expected), axis=-1)))


# ------------------------------------------------------------------------------------------------- allocation


@pytest.mark.parametrize("model", MODELS)
def test_allocation_matrix_is_the_dynamics_mixer(model, x64, rng):
    """Thrust and body torques of `jaxdrones.dynamics` for random RPMs equal allocation_matrix @ rpm²."""
    params = jd.load_params(model)
    rpm = rng.uniform(0, float(params.max_rpm), (200, 4))
    motors = dynamics.motors_c(params, split(jnp.asarray(rpm)))
    thrust = sum(motors.thrust[1:], motors.thrust[0])
    torque = join(dynamics.body_torque_c(params, motors.thrust, motors.yaw_torque))
    expected = np.column_stack([np.asarray(thrust), np.asarray(torque)])
    wrench = np.asarray(allocation_matrix(params)) @ (rpm**2).T
    column_scale = np.abs(expected).max(axis=0)
    np.testing.assert_allclose(wrench.T / column_scale, expected / column_scale, rtol=0, atol=1e-13)
    matrix = np.asarray(wrench_scale(params))[:, None] * np.asarray(allocation_matrix(params))
    np.testing.assert_allclose(matrix, SCALED[model], atol=1e-12)
    np.testing.assert_allclose(matrix, scaled_system(params)[0], atol=1e-15)


def test_allocation_matrix_batched_params(x64, strict_ranks):
    """Params batched [W, D] give [W, D, 4, 4], each that of its model."""
    names = [["cf2x", "cf2p", "racer"], ["racer", "cf2x", "cf2x"]]
    batched = allocation_matrix(stacked_params(names))
    assert batched.shape == (2, 3, 4, 4)
    for w, row in enumerate(names):
        for d, name in enumerate(row):
            np.testing.assert_array_equal(batched[w, d], allocation_matrix(jd.load_params(name)))
    assert wrench_scale(stacked_params(names)).shape == (2, 3, 4)


# ------------------------------------------------------------------------------------------------------ NNLS


@pytest.mark.parametrize("model", MODELS)
def test_nnls_matches_scipy_float64(model, x64, rng, strict_ranks):
    """1,000 targets (500 feasible, 500 infeasible) against scipy.optimize.nnls with the same scaled matrix.

    Feasible ones are also the unconstrained solution A⁻¹ b (the original's first branch); infeasible ones leave
    at least one motor at exactly 0.
    """
    params = jd.load_params(model)
    feasible, infeasible = random_targets(params, rng, 500)
    for name, targets in (("feasible", feasible), ("infeasible", infeasible)):
        expected = scipy_nnls(params, targets)
        squared = nnls_rpm_squared(params, targets)
        rpm = wrench_to_rpm(params, targets[:, None, :])[:, 0]
        assert squared.dtype == jnp.float64 and rpm.shape == (len(targets), 4)
        err_sq, err_rpm = max_rel_err(squared, expected), max_rel_err(rpm, np.sqrt(expected))
        print(f"MEASURED {model} float64 {name} ({len(targets)}): RPM² rel err {err_sq:.1e}, RPM {err_rpm:.1e}")
        assert err_sq < F64_RTOL and err_rpm < F64_RTOL
        if name == "feasible":
            matrix, weights = scaled_system(params)
            assert max_rel_err(squared, np.linalg.solve(matrix, (weights * targets).T).T) < F64_RTOL
        else:
            assert np.all(np.min(np.asarray(squared), axis=-1) == 0.0)


@pytest.mark.parametrize("model", MODELS)
def test_nnls_matches_scipy_float32(model, rng, strict_ranks):
    """The same 1,000 targets in float32 (scipy in float64): agreement within the stated float32 tolerances."""
    params = jd.load_params(model)
    assert params.kf.dtype == jnp.float32
    feasible, infeasible = random_targets(params, rng, 500)
    targets = np.concatenate([feasible, infeasible])
    expected = scipy_nnls(params, targets)
    squared = nnls_rpm_squared(params, targets)
    rpm = wrench_to_rpm(params, targets[:, None, :])[:, 0]
    assert squared.dtype == jnp.float32
    err_sq, err_rpm = max_rel_err(squared, expected), max_rel_err(rpm, np.sqrt(expected))
    print(f"MEASURED {model} float32 ({len(targets)} targets): RPM² rel err {err_sq:.1e}, RPM {err_rpm:.1e}")
    assert err_sq < F32_RTOL_SQUARED and err_rpm < F32_RTOL_RPM


def test_jit_vmap_and_batched_params(x64, rng, strict_ranks):
    """Under jit as eager; vmap over worlds as the batched call; params [W, D] and [W, 1] broadcast."""
    names = [["cf2x", "cf2p", "racer"], ["racer", "cf2x", "cf2p"]]
    params = stacked_params(names)
    wrench = np.stack(
        [
            [
                np.concatenate(
                    [
                        [rng.uniform(0.2, 1.0) * float(params.max_thrust[w, d])],
                        rng.uniform(-1, 1, 3) * 0.3 * float(params.max_z_torque[w, d]),
                    ]
                )
                for d in range(3)
            ]
            for w in range(2)
        ]
    )
    batched = wrench_to_rpm(params, wrench)
    assert batched.shape == (2, 3, 4)
    for w, row in enumerate(names):
        for d, name in enumerate(row):
            np.testing.assert_allclose(
                batched[w, d], wrench_to_rpm(jd.load_params(name), wrench[w, d][None])[0], rtol=1e-14
            )
    np.testing.assert_array_equal(jax.jit(wrench_to_rpm)(params, wrench), batched)
    np.testing.assert_allclose(jax.vmap(wrench_to_rpm)(params, wrench), batched, rtol=1e-14)
    per_world = stacked_params([["racer"], ["cf2x"]])
    racer_then_cf2x = wrench_to_rpm(per_world, np.broadcast_to(wrench[:, :1], (2, 3, 4)))
    assert racer_then_cf2x.shape == (2, 3, 4)
    np.testing.assert_allclose(
        racer_then_cf2x[0, 2], wrench_to_rpm(jd.load_params("racer"), wrench[:1, 0])[0], rtol=1e-14
    )
    lone = nnls_rpm_squared(jd.load_params("cf2x"), wrench[0, 0])
    assert lone.shape == (4,)


@pytest.mark.slow
def test_gradients(x64, strict_ranks):
    """Gradients of the mixer and the body-rate loop (float64).

    check_grads of the squared speeds wrt the wrench and kf at a feasible and an infeasible target (where the
    active set is fixed); the Jacobian of the RPM is A⁻¹ / (2 rpm) for the feasible target, and finite, zero in the
    row of the motor at 0, for the infeasible one; check_grads of the body-rate loop wrt the measured and commanded
    rates.
    """
    params = jd.load_params("cf2x")
    weight, max_xy = float(params.weight), float(params.max_xy_torque)
    feasible = jnp.array([1.2 * weight, 0.02 * max_xy, -0.03 * max_xy, 0.01 * float(params.max_z_torque)])
    infeasible = jnp.array([0.5 * weight, 0.9 * max_xy, -0.2 * max_xy, 0.0])
    targets = jnp.stack([feasible, infeasible])

    def squared(u, c):
        return nnls_rpm_squared(params.replace(kf=params.kf * c), targets * u) / params.hover_rpm**2

    check_grads(
        squared, (jnp.ones((2, 4)), jnp.array(1.0)), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-7, rtol=1e-7
    )

    rpm = wrench_to_rpm(params, targets)
    assert float(jnp.min(rpm[0])) > 0 and float(jnp.min(rpm[1])) == 0.0
    jac = jax.jacrev(lambda w: wrench_to_rpm(params, w))(targets)  # [2, 4, 2, 4]
    inverse = np.linalg.inv(np.asarray(allocation_matrix(params)))
    np.testing.assert_allclose(jac[0, :, 0], inverse / (2 * np.asarray(rpm[0]))[:, None], rtol=1e-10)
    np.testing.assert_array_equal(jac[0, :, 1], 0.0)
    assert np.all(np.isfinite(jac))
    np.testing.assert_array_equal(jac[1][np.asarray(rpm[1]) == 0], 0.0)

    ang_vel, rate_cmd = jnp.array([[0.5, -0.3, 0.2], [0.0, 0.1, -0.4]]), jnp.array([[0.2, 0.1, 0.0], [-0.3, 0.0, 0.6]])
    check_grads(
        lambda w, c: body_rate_control(params, w, c, params.weight * jnp.ones(2)) / params.hover_rpm,
        (ang_vel, rate_cmd),
        order=1,
        modes=("rev",),
        eps=1e-6,
        atol=1e-7,
        rtol=1e-7,
    )


def test_non_finite_wrench_gives_nan(strict_ranks):
    """A NaN or inf in the wrench gives NaN for that drone only (the envs detect NaN), not a silent 0."""
    params = jd.load_params("cf2x")
    wrench = jnp.array([[float(params.weight), 0, 0, 0], [jnp.nan, 0, 0, 0], [0.1, jnp.inf, 0, 0]])
    rpm = wrench_to_rpm(params, wrench)
    assert np.all(np.isfinite(rpm[0])) and np.all(np.isnan(rpm[1:]))


def test_bad_input_raises(strict_ranks):
    """Clear ValueErrors at the entry points for wrong types and shapes."""
    params = jd.load_params("cf2x")
    per_drone = stacked_params(["cf2x", "cf2p", "racer"])
    cases = [
        (nnls_rpm_squared, (params, np.zeros(3)), "wrench must have shape"),
        (wrench_to_rpm, (params, np.zeros(4)), r"\[\.\.\., D, 4\]"),
        (wrench_to_rpm, (per_drone, np.zeros((2, 4))), "does not broadcast"),
        (wrench_to_rpm, ({"kf": 1.0}, np.zeros((1, 4))), "expected DroneParams"),
        (wrench_to_rpm, (params, np.zeros((1, 4), bool)), "real"),
        (allocation_matrix, (object(),), "expected DroneParams"),
        (body_rate_control, (params, np.zeros(3), np.zeros(3), 0.3), "ang_vel must have shape"),
        (body_rate_control, (params, np.zeros((2, 3)), np.zeros((3, 3)), 0.3), "rate_cmd must broadcast"),
        (body_rate_control, (params, np.zeros((2, 3)), np.zeros(3), np.zeros(3)), "thrust must broadcast"),
        (body_rate_control, (params, np.zeros((2, 3)), np.zeros(3), 0.3, {"k_rate": 1.0}), "RateGains"),
        (body_rate_control, (params, np.zeros((2, 3)), np.zeros(3), 0.3, RateGains(jnp.ones(2))), "k_rate"),
        (body_rate_torque, (per_drone, np.zeros((2, 3)), np.zeros(3)), "does not broadcast"),
    ]
    for fn, args, match in cases:
        with pytest.raises(ValueError, match=match):
            fn(*args)


# --------------------------------------------------------------------------------------------- body-rate loop


@pytest.mark.parametrize("model", MODELS)
def test_body_rate_loop_gives_first_order_rate_dynamics(model, x64, rng):
    """With the loop's RPMs, the dynamics' angular acceleration is K (ω* − ω) and the thrust the command.

    τ = J K (ω* − ω) + ω × (J ω) cancels the gyroscopic term of Euler's equation, checked through
    `dynamics.accelerations_c` for 50 drones with random rates, reachable commands and thrusts near hover.
    """
    params = jd.load_params(model)
    gains = RateGains.flightmare()
    n = 50
    ang_vel = rng.uniform(-3, 3, (n, 3))
    rate_cmd = ang_vel + rng.uniform(-1, 1, (n, 3))  # rate errors the motors can correct without saturating
    thrust = float(params.weight) * rng.uniform(0.8, 1.5, n)
    inertia = np.asarray(params.inertia)
    expected_torque = (np.asarray(gains.k_rate) * (rate_cmd - ang_vel)) @ inertia.T + np.cross(
        ang_vel, ang_vel @ inertia.T
    )
    np.testing.assert_allclose(body_rate_torque(params, ang_vel, rate_cmd), expected_torque, rtol=1e-12)
    with jax.numpy_rank_promotion("raise"):
        rpm = body_rate_control(params, ang_vel, rate_cmd, thrust, gains)
    assert rpm.shape == (n, 4) and 0 < float(jnp.min(rpm)) and float(jnp.max(rpm)) < float(params.max_rpm)
    quat = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (n, 4))
    kin = dynamics.Kinematics(split(jnp.zeros((n, 3))), split(quat), split(jnp.zeros((n, 3))), split(ang_vel))
    motors = dynamics.motors_c(params, split(rpm))
    acc, ang_acc = dynamics.accelerations_c(params, dynamics.Effects(), kin, motors, split(rpm))
    np.testing.assert_allclose(join(ang_acc), np.asarray(gains.k_rate) * (rate_cmd - ang_vel), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(acc[2]) + float(params.gravity), thrust / float(params.mass), rtol=1e-12)


#: Control rate of the closed-loop tests, Hz (physics at 240 Hz, 8 substeps per command), and their length.
CTRL_FREQ = 30
LOOP_STEPS = 60


@jax.jit
def _rate_loop(params, state, rate_cmd, thrust):
    """LOOP_STEPS control steps of the body-rate loop closed with the step; the states' fields and the RPMs."""
    step = stepper(jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=CTRL_FREQ))

    def control_step(state, _):
        rpm = body_rate_control(params, state.ang_vel, rate_cmd, thrust)
        state = step(params, state, rpm)
        return state, (state.ang_vel[0], state.quat[0], state.pos[0], rpm[0])

    return jax.lax.scan(control_step, state, None, length=LOOP_STEPS)[1]


def run_rate_loop(model: str, rate_cmd, ang_vel0=(0.0, 0.0, 0.0), rpy0=(0.0, 0.0, 0.0)):
    """Close the body-rate loop with the step at CTRL_FREQ over 240 Hz physics, the command held over the substeps.

    LOOP_STEPS control steps of one drone with hover thrust, starting at 100 m (far from the ground).
    Returns the body rates f[T + 1, 3] (the start included), quaternions f[T + 1, 4], positions f[T + 1, 3] and
    the commanded RPMs f[T, 4]. One compilation serves every model (their params have the same shapes).
    """
    config = jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=CTRL_FREQ)
    params = jd.load_params(model)
    state = jd.init_state(config, pos=[[0.0, 0.0, 100.0]], rpy=[rpy0], ang_vel=[ang_vel0])
    rate_cmd = jnp.asarray([rate_cmd], dtype=state.pos.dtype)
    rates, quats, pos, rpms = _rate_loop(params, state, rate_cmd, jnp.full((1,), params.weight))

    def prepend(first, rest):
        return np.concatenate([np.asarray(first)[None], np.asarray(rest)])

    return prepend(state.ang_vel[0], rates), prepend(state.quat[0], quats), prepend(state.pos[0], pos), np.asarray(rpms)


@pytest.mark.parametrize("model", MODELS)
def test_rate_step_is_tracked_at_30_hz(model):
    """A step of the commanded body rates is tracked, controller at 30 Hz over 240 Hz physics.

    The rates follow the discrete first-order response e_n = (1 − k/30)ⁿ e_0 of each axis within 2 % of the step,
    never overshoot by more than 1 %, and are within 1 % of the command after 1 s; no motor saturates.
    """
    command = np.array([1.0, -0.6, 0.8])
    params = jd.load_params(model)
    rates, _, _, rpms = run_rate_loop(model, command)
    rates, rpms = rates[: CTRL_FREQ + 1], rpms[:CTRL_FREQ]  # the first second
    k = np.asarray(RateGains.flightmare().k_rate, np.float64)
    n = np.arange(len(rates))[:, None]
    predicted = command * (1 - (1 - k / CTRL_FREQ) ** n)
    deviation = np.max(np.abs(rates - predicted)) / np.max(np.abs(command))
    overshoot = np.max((rates - command) * np.sign(command)) / np.max(np.abs(command))
    final = np.max(np.abs(rates[-1] - command)) / np.max(np.abs(command))
    print(
        f"MEASURED {model} rate step at 30 Hz: max deviation from first order {deviation:.1e}, overshoot "
        f"{overshoot:.1e}, error after 1 s {final:.1e} (of the step)"
    )
    assert deviation < 0.02 and overshoot < 0.01 and final < 0.01
    assert np.max(rpms) < float(params.max_rpm) and np.min(rpms) > 0


@pytest.mark.parametrize("model", MODELS)
def test_hover_thrust_and_zero_rates_hold_attitude(model):
    """Zero rates and hover thrust at 30 Hz hold the attitude.

    A tilted drone keeps its attitude for 2 s, a level one its position; a tumbling one (rates of up to 2 rad/s)
    is brought to rest at the first-order rate.
    """
    rpy0 = (0.3, -0.2, 1.0)
    rates, quats, _, _ = run_rate_loop(model, (0.0, 0.0, 0.0), rpy0=rpy0)
    drift = float(np.max(np.abs(quats - quats[0])))
    print(
        f"MEASURED {model} zero rates, hover thrust, tilted: quaternion drift {drift:.1e} in 2 s, "
        f"max rate {np.max(np.abs(rates)):.1e} rad/s"
    )
    assert drift < 1e-5 and np.max(np.abs(rates)) < 1e-4

    _, quats, pos, _ = run_rate_loop(model, (0.0, 0.0, 0.0))
    assert np.max(np.abs(pos - pos[0])) < 1e-4 and np.max(np.abs(quats - quats[0])) < 1e-5

    ang_vel0 = np.array([2.0, -1.0, 0.5])
    rates, _, _, _ = run_rate_loop(model, (0.0, 0.0, 0.0), ang_vel0=tuple(ang_vel0))
    k = np.asarray(RateGains.flightmare().k_rate, np.float64)
    predicted = ang_vel0 * (1 - k / CTRL_FREQ) ** np.arange(len(rates))[:, None]
    assert np.max(np.abs(rates - predicted)) < 0.02 * np.max(np.abs(ang_vel0))
    assert np.max(np.abs(rates[-1])) < 1e-3
