"""jaxdrones.symbolic: the CasADi model against the JAX core, value for value and derivative for derivative."""

from __future__ import annotations

import dataclasses
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones import dynamics, symbolic
from jaxdrones.rotations import quat_to_euler, split

cs = pytest.importorskip("casadi", reason="casadi is not installed (the casadi extra)")

N = 1000
CONFIGS = {
    "euler_drag_ground": jd.SimConfig(ctrl_freq=30, drag=True, ground_effect=True),
    "euler_motor_dynamics": jd.SimConfig(ctrl_freq=30, drag=True, ground_effect=True, motor_dynamics=True),
    "rk4_drag_ground": jd.SimConfig(ctrl_freq=48, integrator="rk4", drag=True, ground_effect=True),
    "paper_default": jd.SimConfig(),
}


def crazyflie(config: jd.SimConfig) -> jd.DroneParams:
    """cf2x, with L2F's motor time constants (0.0555 s rising, 0.249 s falling) where the config has motor lag."""
    params = jd.load_params("cf2x")
    if config.motor_dynamics:
        params = params.replace(motor_tau_up=jnp.asarray(0.0555), motor_tau_down=jnp.asarray(0.249))
    return params


def random_states(rng, params, n: int, rotor_state: bool, near_level: bool = False):
    """(x f64[n, 13 or 17], u f64[n, 4]): positions 0-30 cm up (in ground effect, some touching), half the attitudes
    near level and half uniform, speeds ~1 m/s, rates ~3 rad/s, RPM commands from -10 % to 120 % of max (clipped)."""
    max_rpm = float(params.max_rpm)
    pos = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(0.0, 0.3, n)]
    quat = rng.normal(size=(n, 4))
    level = np.arange(n) < n // 2 if not near_level else np.ones(n, bool)
    quat[level] = np.c_[0.1 * rng.normal(size=(level.sum(), 3)), np.ones(level.sum())]
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    x = np.c_[pos, quat, rng.normal(0, 1, (n, 3)), rng.normal(0, 3, (n, 3))]
    if rotor_state:
        x = np.c_[x, rng.uniform(0, 1.2 * max_rpm, (n, 4))]
    return x, rng.uniform(-0.1, 1.2, (n, 4)) * max_rpm


def jax_step_of_vectors(config: jd.SimConfig, params):
    """The JAX core's step on crazyflow-ordered state vectors f64[..., 17] and commands f64[..., 4]."""
    step = jd.make_step(config)

    def f(x, u):
        state = jd.DroneState(
            pos=x[..., None, 0:3],
            quat=x[..., None, 3:7],
            vel=x[..., None, 7:10],
            ang_vel=x[..., None, 10:13],
            rpm=x[..., None, 13:17],
            contact=jnp.zeros(x.shape[:-1] + (1,), jnp.int32),
        )
        out = step(params, state, u[..., None, :])
        return jnp.concatenate([out.pos, out.quat, out.vel, out.ang_vel, out.rpm], -1)[..., 0, :]

    return f


def with_rotors(x, params):
    """A 13-entry state padded with rotor speeds (unused by configs without drag or motor lag)."""
    return x if x.shape[-1] == 17 else np.c_[x, np.zeros((len(x), 4))]


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_discrete_step_equals_the_jax_step(x64, rng, name):
    config = CONFIGS[name]
    params = crazyflie(config)
    step = symbolic.discrete_step(params, config)
    rotor_state = step.size1_in(0) == 17
    assert rotor_state == bool(config.drag or config.motor_dynamics)
    x, u = random_states(rng, params, N, rotor_state)
    symbolic_next = np.asarray(step.map(N)(x.T, u.T)).T
    jax_next = np.asarray(jax_step_of_vectors(config, params)(jnp.asarray(with_rotors(x, params)), jnp.asarray(u)))
    touched = jax_next[:, 2] <= 0.5 * float(params.collision_height)
    assert 0 < touched.sum() < N  # some states go through the ground contact, most do not
    np.testing.assert_allclose(symbolic_next, jax_next[:, : symbolic_next.shape[1]], rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name", ["euler_drag_ground", "euler_motor_dynamics"])
def test_discrete_jacobians_equal_jacfwd(x64, rng, name):
    config = dataclasses.replace(CONFIGS[name], adjoint=False)  # the hand-written adjoint has no forward mode
    params = crazyflie(config)
    model = symbolic.SymbolicModel(params, config)
    n = 200
    x, u = random_states(rng, params, n, True, near_level=True)
    x[:, 2] = rng.uniform(0.05, 0.3, n)  # above the ground: away from the contact's kink
    u = rng.uniform(0.3, 0.95, (n, 4)) * float(params.max_rpm)  # inside the clip
    # Level drones at rest: no rate, four equal rotor speeds and commands, so no torque. The step holds the attitude,
    # and both derivatives are the first-order update's (a level hover is not a stationary point of a controller).
    x[:10, 3:7], x[:10, 10:13], u[:10] = [0.0, 0.0, 0.0, 1.0], 0.0, u[:10, :1]
    x[:10, 13:17] = u[:10]
    dfdx, dfdu = (np.asarray(j).reshape(17, n, -1).transpose(1, 0, 2) for j in model.dfd_func.map(n)(x.T, u.T))
    jac_x, jac_u = jax.jit(jax.vmap(jax.jacfwd(jax_step_of_vectors(config, params), argnums=(0, 1))))(
        jnp.asarray(x), jnp.asarray(u)
    )
    np.testing.assert_allclose(dfdx, jac_x, rtol=1e-8, atol=1e-8)
    max_rpm = float(params.max_rpm)  # the input Jacobian per unit of full-scale command
    np.testing.assert_allclose(dfdu * max_rpm, np.asarray(jac_u) * max_rpm, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("name", ["euler_drag_ground", "euler_motor_dynamics"])
def test_continuous_dynamics_equal_the_core_accelerations(x64, rng, name):
    config = CONFIGS[name]
    params = crazyflie(config)
    f = symbolic.continuous_dynamics(params, config)
    x, u = random_states(rng, params, N, True)
    xdot = np.asarray(f.map(N)(x.T, u.T)).T
    rpm = np.clip(u, 0, float(params.max_rpm))
    speeds = x[:, 13:17] if config.motor_dynamics else rpm
    kin = dynamics.Kinematics(*(split(jnp.asarray(x[:, None, a:b])) for a, b in ((0, 3), (3, 7), (7, 10), (10, 13))))
    speeds_c = split(jnp.asarray(speeds[:, None]))
    acc, ang_acc = dynamics.accelerations_c(
        params, dynamics.Effects(config.drag, config.ground_effect), kin, dynamics.motors_c(params, speeds_c), speeds_c
    )
    np.testing.assert_allclose(xdot[:, 0:3], x[:, 7:10], rtol=1e-12)
    np.testing.assert_allclose(xdot[:, 7:10], np.stack([a[:, 0] for a in acc], -1), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(xdot[:, 10:13], np.stack([a[:, 0] for a in ang_acc], -1), rtol=1e-10, atol=1e-9)
    q, w = x[:, 3:7], x[:, 10:13]  # q̇ = ½ q ⊗ (ω, 0), by the Hamilton product written out
    expected = 0.5 * np.stack(
        [
            q[:, 3] * w[:, 0] + q[:, 1] * w[:, 2] - q[:, 2] * w[:, 1],
            q[:, 3] * w[:, 1] - q[:, 0] * w[:, 2] + q[:, 2] * w[:, 0],
            q[:, 3] * w[:, 2] + q[:, 0] * w[:, 1] - q[:, 1] * w[:, 0],
            -q[:, 0] * w[:, 0] - q[:, 1] * w[:, 1] - q[:, 2] * w[:, 2],
        ],
        -1,
    )
    np.testing.assert_allclose(xdot[:, 3:7], expected, rtol=1e-12, atol=1e-15)
    if config.motor_dynamics:  # τ ṙpm = cmd - rpm, τ by the sign of the error
        error = rpm - x[:, 13:17]
        tau = np.where(error > 0, float(params.motor_tau_up), float(params.motor_tau_down))
        np.testing.assert_allclose(xdot[:, 13:17], error / tau, rtol=1e-12)
    else:
        assert np.all(xdot[:, 13:17] == 0)


def test_hover_is_an_equilibrium_and_the_model_has_safe_control_gyms_shape(x64):
    params = jd.load_params("cf2x")
    config = jd.SimConfig(ctrl_freq=30)
    model = symbolic.SymbolicModel(params, config)
    assert (model.nx, model.nu, model.ny, model.dt) == (13, 4, 16, 1 / 30)
    x_eq = model.x_eq
    assert x_eq[2] == 1.0  # 1 m up, out of ground contact
    np.testing.assert_allclose(np.asarray(model.fc_func(x_eq, model.u_eq)), 0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(model.fd_func(x0=x_eq, p=model.u_eq)["xf"]).ravel(), x_eq, atol=1e-12)
    dfdx, dfdu = (np.asarray(j) for j in model.df_func(x_eq, model.u_eq))
    assert dfdx.shape == (13, 13) and dfdu.shape == (13, 4)
    np.testing.assert_allclose(dfdx[0:3, 7:10], np.eye(3))  # ṗ = v
    # Equal RPM increments raise the thrust only: d(az)/d(rpm_i) = 2 kf rpm / m for each motor.
    np.testing.assert_allclose(dfdu[9], 2 * float(params.kf) * float(params.hover_rpm) / float(params.mass), rtol=1e-12)
    q, r = np.diag(np.arange(1.0, 14.0)), 1e-8 * np.eye(4)
    x = x_eq + 0.1
    loss = model.loss(x=x, u=model.u_eq + 100, Xr=x_eq, Ur=model.u_eq, Q=q, R=r)
    assert float(loss["l"]) == pytest.approx(0.5 * 0.01 * np.arange(1.0, 14.0).sum() + 0.5 * 1e-8 * 4 * 100**2)
    np.testing.assert_allclose(np.asarray(loss["l_xx"]), q)


def test_observation_is_the_papers_kin(x64, rng):
    params = jd.load_params("cf2x")
    x, _ = random_states(rng, params, N, False)
    x[:5, 3:7] = [
        [0.5, 0.5, 0.5, 0.5],
        [0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)],
        [0.0, -np.sqrt(0.5), 0.0, np.sqrt(0.5)],
        [0.0, 0.0, 0.0, 1.0],
        [1.0, 0.0, 0.0, 0.0],
    ]  # gimbal lock at pitch ±π/2, level, upside down
    y = np.asarray(symbolic.observation().map(N)(x.T)).T
    assert y.shape == (N, 16)
    np.testing.assert_array_equal(y[:, 0:7], x[:, 0:7])
    np.testing.assert_array_equal(y[:, 10:16], x[:, 7:13])
    np.testing.assert_allclose(y[:, 7:10], np.asarray(quat_to_euler(jnp.asarray(x[:, 3:7]))), atol=1e-12)


@pytest.mark.parametrize("rotor", [False, True])
def test_crazyflow_signature_with_our_parameters_equals_our_model(x64, rng, rotor):
    """`symbolic_dynamics(...)` as crazyflow's, fed `crazyflow_params`: the paper's model (no drag or ground
    effect), with the rotor speeds as state (L2F's motor lag) or the commands applied directly."""
    config = jd.SimConfig(motor_dynamics=rotor)
    params = crazyflie(config)
    x_dot, x_sym, u_sym, y_sym = symbolic.symbolic_dynamics(model_rotor_vel=rotor, **symbolic.crazyflow_params(params))
    assert (x_sym.shape[0], u_sym.shape[0], y_sym.shape[0]) == (17 if rotor else 13, 4, 7)
    theirs = cs.Function("f", [x_sym, u_sym], [x_dot]).map(N)
    ours = symbolic.continuous_dynamics(params, config, rotor_state=rotor).map(N)
    x, u = random_states(rng, params, N, rotor)
    u = np.clip(u, 0, float(params.max_rpm))  # crazyflow's model does not clip
    np.testing.assert_allclose(np.asarray(theirs(x.T, u.T)), np.asarray(ours(x.T, u.T)), rtol=1e-10, atol=1e-12)


def test_crazyflow_disturbance_states(x64):
    """``model_dist_f`` / ``model_dist_t`` append a world force and torque to the state, acting on the body."""
    params = jd.load_params("cf2x")
    x_dot, x_sym, u_sym, _ = symbolic.symbolic_dynamics(False, True, True, **symbolic.crazyflow_params(params))
    assert x_sym.shape[0] == x_dot.shape[0] == 19
    f = cs.Function("f", [x_sym, u_sym], [x_dot])
    force, torque = np.array([0.01, -0.02, 0.03]), np.array([1e-5, 2e-5, -3e-5])
    hover = np.r_[0, 0, 1, 0, 0, 0, 1, np.zeros(6)]
    xdot = np.asarray(f(np.r_[hover, force, torque], np.full(4, float(params.hover_rpm)))).ravel()
    np.testing.assert_allclose(xdot[7:10], force / float(params.mass), atol=1e-12)  # level: world = body
    np.testing.assert_allclose(xdot[10:13], np.asarray(params.inertia_inv) @ torque, rtol=1e-12)
    np.testing.assert_array_equal(xdot[13:19], 0)


def test_bad_input(monkeypatch):
    params = jd.load_params("cf2x")
    with pytest.raises(ValueError, match="one drone"):
        symbolic.discrete_step(jax.tree.map(lambda v: jnp.stack([v, v]), params), jd.SimConfig())
    with pytest.raises(ValueError, match="DroneParams"):
        symbolic.SymbolicModel({"mass": 0.027})
    with pytest.raises(ValueError, match="SimConfig"):
        symbolic.discrete_step(params, {"ctrl_freq": 30})
    with pytest.raises(ValueError, match="smooth kinks"):
        symbolic.discrete_step(params, jd.SimConfig(kinks="smooth"))
    with pytest.raises(ValueError, match="rotor_state must be True"):
        symbolic.continuous_dynamics(params, jd.SimConfig(drag=True), rotor_state=False)
    with pytest.raises(ValueError, match="positive motor time constants"):
        symbolic.continuous_dynamics(params, jd.SimConfig(motor_dynamics=True))
    with pytest.raises(ValueError, match="not finite"):
        symbolic.discrete_step(params.replace(kf=jnp.asarray(np.nan)), jd.SimConfig())
    monkeypatch.setitem(sys.modules, "casadi", None)
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'jaxdrones\[casadi\]'"):
        symbolic.SymbolicModel(params)
