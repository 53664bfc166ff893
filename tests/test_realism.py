"""Sim-to-real options of the physics core: first-order motor dynamics (`SimConfig.motor_dynamics`) against the
analytic first-order response, and the step's `Disturbance` (external force, torque, wind through the drag)
against hand-derived accelerations; their derivatives through the hand-written adjoint against JAX's derived
ones; bad input at the boundary."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones.state import Disturbance

TAU_UP, TAU_DOWN = 0.0555, 0.249  # L2F / RLtools' Crazyflie (rl-tools l2f/parameters/dynamics/crazyflie.h)


def _lagged(params=None):
    params = jd.load_params("cf2x") if params is None else params
    dtype = params.mass.dtype
    return params.replace(motor_tau_up=jnp.asarray(TAU_UP, dtype), motor_tau_down=jnp.asarray(TAU_DOWN, dtype))


@pytest.mark.parametrize("ctrl_freq", [240, 30])
def test_motor_step_response_is_first_order(x64, ctrl_freq):
    """A step up from 0 to hover RPM and, from there, a step down to half of it: each motor's speed at every control
    step is c + (ω0 - c)·exp(-t/τ) with the rising, then the falling time constant, within 1e-9 relative (the
    update is the exact solution over each substep; the acceptance bound is 1 %)."""
    params = _lagged()
    config = jd.SimConfig(motor_dynamics=True, ctrl_freq=ctrl_freq)
    step = jd.make_step(config)
    state = jd.init_state(config, pos=[[0.0, 0.0, 2.0]])
    hover = float(params.hover_rpm)
    n = ctrl_freq // 3  # a third of a second
    t = np.arange(1, n + 1) / ctrl_freq
    up, down = [], []
    for _ in range(n):
        state = step(params, state, jnp.full((1, 4), hover))
        up.append(np.asarray(state.rpm[0]))
    for _ in range(n):
        state = step(params, state, jnp.full((1, 4), 0.5 * hover))
        down.append(np.asarray(state.rpm[0]))
    expect_up = hover * (1 - np.exp(-t / TAU_UP))
    expect_down = 0.5 * hover + (expect_up[-1] - 0.5 * hover) * np.exp(-t / TAU_DOWN)
    np.testing.assert_allclose(np.asarray(up), np.repeat(expect_up[:, None], 4, 1), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(down), np.repeat(expect_down[:, None], 4, 1), rtol=1e-9)
    assert up[0][0] < 0.5 * hover, "the motors lag: after one step they are far from the command"


def test_motor_dynamics_thrust_uses_the_actual_speed(x64):
    """At one substep per control step from rest on the ground at full command, the vertical acceleration over
    the first substep is 4 kf ω1² / m - g with ω1 the lagged speed, not the command."""
    params = _lagged()
    config = jd.SimConfig(motor_dynamics=True)
    state = jd.init_state(config, pos=[[0.0, 0.0, 1.0]])
    command = float(params.max_rpm)
    out = jd.make_step(config)(params, state, jnp.full((1, 4), command))
    omega = command * (1 - np.exp(-config.dt / TAU_UP))
    acc = 4 * float(params.kf) * omega**2 / float(params.mass) - float(params.gravity)
    np.testing.assert_allclose(float(out.vel[0, 2]), acc * config.dt, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.rpm[0]), omega, rtol=1e-12)


def test_instant_motors_match_the_paper_step(x64):
    """With time constants of 0 the motor-dynamics path gives the paper's step (drag on, so that the previous
    substep's speed matters) to rounding."""
    params = jd.load_params("cf2x")
    base = jd.SimConfig(ctrl_freq=30, drag=True, ground_effect=True)
    rng = np.random.default_rng(0)
    state = jd.init_state(base, pos=[[0.1, -0.2, 0.05]], vel=rng.normal(size=(1, 3)), rpm=[[1e4, 1.2e4, 1.4e4, 9e3]])
    rpm = float(params.hover_rpm) * (1 + 0.1 * rng.normal(size=(1, 4)))
    a = jd.make_step(base)(params, state, rpm)
    b = jd.make_step(dataclasses.replace(base, motor_dynamics=True))(params, state, rpm)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-13, atol=1e-15)


def test_disturbance_force_torque_and_wind(x64):
    """Hand-derived: at hover RPM, level and at rest, one substep of Euler gives Δv = dt F/m from a world force,
    Δω = dt J⁻¹ τ from a body torque (no gyroscopic term at rest), and Δv = dt Ω C w / m from a wind w with drag
    (Ω the previous substep's summed speeds in rad/s)."""
    params = jd.load_params("cf2x")
    config = jd.SimConfig(drag=True)
    hover = float(params.hover_rpm)
    state = jd.init_state(config, pos=[[0.0, 0.0, 1.0]], rpm=np.full((1, 4), hover))
    rpm = np.full((1, 4), hover)
    step = jd.make_step(config)
    force, torque, wind = np.array([[0.01, -0.02, 0.03]]), np.array([[1e-5, -2e-5, 3e-6]]), np.array([[1.0, -2.0, 0.5]])
    dt, m = config.dt, float(params.mass)
    out = step(params, state, rpm, Disturbance(force=force))
    np.testing.assert_allclose(np.asarray(out.vel), dt * force / m, rtol=1e-9, atol=1e-15)
    out = step(params, state, rpm, Disturbance(torque=torque))
    np.testing.assert_allclose(np.asarray(out.ang_vel), dt * torque @ np.asarray(params.inertia_inv).T, rtol=1e-9)
    out = step(params, state, rpm, Disturbance(wind=wind))
    omega = 4 * hover * 2 * np.pi / 60
    np.testing.assert_allclose(
        np.asarray(out.vel), dt * omega * np.asarray(params.drag_coeff) * wind / m, rtol=1e-9, atol=1e-15
    )


@pytest.mark.parametrize(
    "downwash, substeps, with_params",
    [
        ("paper", 1, False),
        pytest.param("paper", 1, True, marks=pytest.mark.slow),
        pytest.param("per_rotor", 4, False, marks=pytest.mark.slow),
    ],
)
def test_adjoint_with_motor_dynamics_and_disturbance(x64, downwash, substeps, with_params):
    """The hand-written adjoint with every core option on (motor dynamics, force, torque, wind, drag, ground
    effect, either downwash model) agrees with JAX's derived derivative within 1e-10 relative: for the state, the
    command and the disturbance with the params closed over (the rule's hand-written pass runs), and with
    ``with_params`` for the params too, the time constants included (the rule falls back to JAX's derived pass)."""
    n, worlds = 3, 4
    config = jd.SimConfig(
        n_drones=n,
        sim_freq=240 * substeps,
        ctrl_freq=240,
        drag=True,
        ground_effect=True,
        downwash=downwash,
        motor_dynamics=True,
    )
    params = _lagged()
    rng = np.random.default_rng(3)
    hover = float(params.hover_rpm)
    heights = np.array([0.1, 0.4, 0.7])[:, None] + rng.uniform(-0.02, 0.02, (worlds, n, 1))  # stacked: downwash acts
    pos = np.concatenate([rng.uniform(-0.04, 0.04, (worlds, n, 2)), heights], -1)
    state = jd.init_state(
        config,
        pos=pos,
        vel=rng.normal(size=(worlds, n, 3)),
        ang_vel=rng.normal(size=(worlds, n, 3)),
        rpm=hover * (1 + 0.1 * rng.normal(size=(worlds, n, 4))),
    )
    rpm = jnp.asarray(hover * (1 + 0.2 * rng.normal(size=(worlds, n, 4))))
    dist = Disturbance(
        force=jnp.asarray(0.02 * rng.normal(size=(worlds, n, 3))),
        torque=jnp.asarray(3e-5 * rng.normal(size=(worlds, n, 3))),
        wind=jnp.asarray(rng.normal(size=(worlds, n, 3))),
    )
    results = []
    for use in (False, True):
        step = jd.make_step(dataclasses.replace(config, adjoint=use))
        if with_params:
            results.append(jax.vjp(lambda s, r, d, p, step=step: step(p, s, r, d), state, rpm, dist, params))
        else:
            results.append(jax.vjp(lambda s, r, d, step=step: step(params, s, r, d), state, rpm, dist))
    (out_ref, vjp_ref), (out, vjp) = results
    for a, b in zip(jax.tree.leaves(out_ref), jax.tree.leaves(out), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-14)
    ct = jax.tree.map(
        lambda x: (
            np.zeros(x.shape, jax.dtypes.float0)
            if x.dtype == jnp.int32
            else jnp.asarray(rng.normal(size=x.shape), x.dtype)
        ),
        out_ref,
    )
    checked = set()
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(vjp_ref(ct)), jax.tree.leaves(vjp(ct)), strict=True):
        if a.dtype == jax.dtypes.float0:
            continue
        scale = float(jnp.max(jnp.abs(a)))
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-12 * scale, err_msg=jax.tree_util.keystr(path))
        if scale > 0:
            checked.add(jax.tree_util.keystr(path))
    names = ("pos", "quat", "vel", "ang_vel", "rpm", "force", "torque", "wind")
    for name in names + (("motor_tau_up", "motor_tau_down") if with_params else ()):
        assert any(name in p for p in checked), f"no nonzero cotangent for {name}: {sorted(checked)}"
    assert "[1]" in checked, "the command's cotangent"


def test_core_bad_input():
    params = jd.load_params("cf2x")
    config = jd.SimConfig()
    state = jd.init_state(config)
    step = jd.make_step(config)
    rpm = np.zeros((1, 4))
    with pytest.raises(ValueError, match="motor_dynamics must be True or False"):
        jd.SimConfig(motor_dynamics="yes")
    with pytest.raises(ValueError, match="needs SimConfig\\(drag=True\\)"):
        step(params, state, rpm, Disturbance(wind=np.zeros((1, 3))))
    with pytest.raises(ValueError, match="disturbance.force must broadcast"):
        step(params, state, rpm, Disturbance(force=np.zeros((2, 3))))
    with pytest.raises(ValueError, match="disturbance.torque contains NaN"):
        step(params, state, rpm, Disturbance(torque=np.full((1, 3), np.nan)))
    with pytest.raises(ValueError, match="must be a jaxdrones.Disturbance"):
        step(params, state, rpm, {"force": np.zeros((1, 3))})
    lagged = jd.make_step(jd.SimConfig(motor_dynamics=True))
    for bad in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="motor_tau_down must be finite time constants >= 0"):
            lagged(params.replace(motor_tau_down=jnp.asarray(bad)), state, rpm)


@pytest.mark.parametrize("bad", ["-0.1", "nan", "fast"])
def test_urdf_motor_time_constant_must_be_a_number_at_least_zero(tmp_path, bad):
    text = open(jd.params.model_path("cf2x")).read().replace("<properties ", f'<properties motor_tau_up="{bad}" ', 1)
    path = tmp_path / "lagged.urdf"
    path.write_text(text)
    with pytest.raises(ValueError, match="motor_tau_up"):
        jd.load_params(str(path))


def test_urdf_motor_time_constants_are_read(tmp_path):
    text = (
        open(jd.params.model_path("cf2x"))
        .read()
        .replace("<properties ", '<properties motor_tau_up="0.05" motor_tau_down="0.2" ', 1)
    )
    path = tmp_path / "lagged.urdf"
    path.write_text(text)
    params = jd.load_params(str(path))
    assert float(params.motor_tau_up) == pytest.approx(0.05) and float(params.motor_tau_down) == pytest.approx(0.2)
    assert float(jd.load_params("cf2x").motor_tau_up) == 0.0


@pytest.mark.pybullet
def test_pybullet_backend_follows_motor_dynamics_and_disturbance(x64):
    """The PyBullet backend with motor dynamics, a force, a torque and a wind (drag on) tracks the JAX core over
    half a second at the default rates (within 2 mm and 2e-3 RPM relative; Bullet integrates the rigid body its
    own way), under jit too."""
    pytest.importorskip("pybullet")
    params = _lagged()
    config = jd.SimConfig(ctrl_freq=30, drag=True, motor_dynamics=True)
    state = jd.init_state(config, pos=[[0.0, 0.0, 1.0]])
    dist = Disturbance(
        force=np.array([[0.01, 0.0, 0.0]]), torque=np.array([[0.0, 1e-6, 0.0]]), wind=np.array([[0.0, 1.0, 0.0]])
    )
    rpm = np.full((1, 4), 1.02 * float(params.hover_rpm))
    jax_step = jd.make_step(config)
    with jd.make_step(config, backend="pybullet") as bullet:
        a = b = c = state
        jitted = jax.jit(lambda p, s, r, d: bullet(p, s, r, d))
        for _ in range(15):
            a = jax_step(params, a, rpm, dist)
            b = bullet(params, b, rpm, dist)
            c = jitted(params, c, rpm, dist)
    np.testing.assert_allclose(np.asarray(b.rpm), np.asarray(a.rpm), rtol=2e-3)
    np.testing.assert_allclose(np.asarray(b.pos), np.asarray(a.pos), atol=2e-3)
    np.testing.assert_allclose(np.asarray(c.pos), np.asarray(b.pos), atol=1e-9)
    moved = np.asarray(a.pos - state.pos)[0]
    assert moved[0] > 5e-3 and moved[1] > 5e-3, f"the force (+x) and the wind (+y) push the drone: {moved}"


# -- the env options (jaxdrones.realism) ----------------------------------------------------------------------------

from jaxdrones.realism import PRESETS, Realism, RealismModel, dryden_psd  # noqa: E402

pytestmark = pytest.mark.unit


def _rollout(env, actions, key=0):
    """The states and observations of ``env`` driven by ``actions`` f[T, D, n_act] from a reset with ``key``."""
    state = env.reset(jax.random.key(key))

    def body(s, a):
        s = env.step(s, a)
        return s, (s.sim, s.obs)

    return jax.lax.scan(body, state, actions)[1]


@pytest.mark.parametrize("k", [1, 3])
def test_action_delay_shifts_the_response_by_k_steps(k):
    """With an action delay of k control steps the drone flies exactly the trajectory of the undelayed env fed
    k zero actions first (the buffer's start) and then the same actions."""
    start = dict(init_pos=[[0.0, 0.0, 1.0]])
    delayed, plain = jd.make("hover", action_delay=k, **start), jd.make("hover", **start)
    actions = jnp.asarray(np.random.default_rng(0).uniform(-0.5, 0.5, (40, 1, 4)), jnp.float32)
    shifted = jnp.concatenate([jnp.zeros((k, 1, 4)), actions[:-k]])
    a, _ = jax.jit(lambda x: _rollout(delayed, x))(actions)
    b, _ = jax.jit(lambda x: _rollout(plain, x))(shifted)
    np.testing.assert_array_equal(np.asarray(a.pos), np.asarray(b.pos))
    np.testing.assert_array_equal(np.asarray(a.rpm), np.asarray(b.rpm))
    assert float(jnp.abs(a.pos[-1] - a.pos[0]).max()) > 1e-3, "the actions move the drone"


@pytest.mark.parametrize("k", [1, 2])
def test_observation_delay_shifts_the_observation_by_k_steps(k):
    """With an observation delay of k steps the observation after step t is the undelayed one after step t - k
    (the start's before that); the physics is untouched."""
    start = dict(init_pos=[[0.0, 0.0, 1.0]])
    delayed, plain = jd.make("hover", obs_delay=k, **start), jd.make("hover", **start)
    actions = jnp.asarray(np.random.default_rng(1).uniform(-0.5, 0.5, (30, 1, 4)), jnp.float32)
    (sa, oa), (sb, ob) = (jax.jit(lambda x, e=e: _rollout(e, x))(actions) for e in (delayed, plain))
    np.testing.assert_array_equal(np.asarray(sa.pos), np.asarray(sb.pos))
    first = plain.reset(jax.random.key(0)).obs
    expected = jnp.concatenate([jnp.broadcast_to(first, (k,) + first.shape), ob[:-k]])
    np.testing.assert_allclose(np.asarray(oa), np.asarray(expected), rtol=0, atol=1e-6)


def _observe_many(realism, n_worlds=4000, steps=3):
    """Many worlds' observed states minus the true one (a level drone at rest): the errors f[W, T, 4, 3] (position,
    attitude as a rotation vector, velocity, body rates)."""
    model = RealismModel(realism, 1, 4, 1 / 30)
    sim = jd.init_state(jd.SimConfig(), pos=[[0.0, 0.0, 1.0]])

    def world(key):
        state = model.reset(key, sim, jnp.float32)
        errors = []
        for _ in range(steps):
            seen, state = model.observe(state, sim)
            rotvec = 2 * seen.quat[0, :3] * jnp.sign(seen.quat[0, 3])  # small angles: 2·(x, y, z) of the quaternion
            errors.append(jnp.stack([seen.pos[0] - sim.pos[0], rotvec, seen.vel[0], seen.ang_vel[0]]))
        return jnp.stack(errors)

    return np.asarray(jax.jit(jax.vmap(world))(jax.random.split(jax.random.key(7), n_worlds)), np.float64)


def test_observation_noise_statistics():
    """The crazyflie preset's noise: zero mean and the preset's σ per quantity and axis, within sampling error
    (4000 worlds × 3 steps: the mean within 4 σ/√n, the standard deviation within 5 %), independent between
    steps (correlation below 0.05)."""
    realism = PRESETS["crazyflie"]
    errors = _observe_many(realism)
    sigma = np.array(
        [realism.obs_noise_pos[0], realism.obs_noise_att[0], realism.obs_noise_vel[0], realism.obs_noise_ang_vel[0]]
    )
    n = errors.shape[0] * errors.shape[1]
    flat = errors.reshape(n, 4, 3)
    assert np.all(np.abs(flat.mean(0)) < 4 * sigma[:, None] / np.sqrt(n))
    np.testing.assert_allclose(flat.std(0), np.broadcast_to(sigma[:, None], (4, 3)), rtol=0.05)
    corr = np.corrcoef(errors[:, 0, 0, 0], errors[:, 1, 0, 0])[0, 1]
    assert abs(corr) < 0.05


def test_observation_bias_is_held_over_the_episode():
    """A bias of σ 0.01 m: constant within an episode (equal at every step without noise), N(0, σ²) across
    episodes (standard deviation within 5 %)."""
    errors = _observe_many(Realism(obs_bias_pos=0.01), steps=3)
    np.testing.assert_array_equal(errors[:, 0], errors[:, 2])
    np.testing.assert_allclose(errors[:, 0, 0].std(0), 0.01, rtol=0.05)
    assert np.all(errors[:, :, 1:] == 0)


def _disturbances(realism, n_worlds, steps, ctrl_freq=30):
    """The disturbances of ``steps`` control steps of ``n_worlds`` worlds (one drone at rest): force f[W, T, 3],
    torque f[W, T, 3] and wind f[W, T, 3]."""
    model = RealismModel(realism, 1, 4, 1 / ctrl_freq)
    sim = jd.init_state(jd.SimConfig(), pos=[[0.0, 0.0, 1.0]])

    def world(key):
        def body(state, _):
            d, state = model.disturbance(state, sim)
            zero = jnp.zeros((3,))
            pick = lambda x: zero if x is None else x[0]  # noqa: E731
            return state, (pick(d.force), pick(d.torque), pick(d.wind))

        return jax.lax.scan(body, model.reset(key, sim, jnp.float32), None, length=steps)[1]

    out = jax.jit(jax.vmap(world))(jax.random.split(jax.random.key(3), n_worlds))
    return [np.asarray(x, np.float64) for x in out]


def test_dryden_spectra_match_the_model():
    """Dryden turbulence (σ 1 m/s, 2 m altitude, 5 m/s mean wind): the one-sided spectra of the longitudinal,
    lateral and vertical components (Welch, 256 worlds × 4096 steps at 30 Hz) are within 10 % of the model's,
    2 Φ(2πf), at 0.1, 0.3 and 1 Hz; their variances within 10 % of σ_u² and σ_w²."""
    from scipy.signal import welch

    from jaxdrones.realism import dryden_constants

    realism = Realism(turbulence=1.0, wind_speed=5.0)
    _, _, wind = _disturbances(realism, 256, 4096)
    mean = wind.mean(axis=1, keepdims=True)
    along_axis = mean[..., :2] / np.linalg.norm(mean[..., :2], axis=-1, keepdims=True)
    gust = wind - mean
    u = np.sum(gust[..., :2] * along_axis, -1)
    v = gust[..., 0] * -along_axis[..., 1] + gust[..., 1] * along_axis[..., 0]
    w = gust[..., 2]
    (sigma_u, sigma_w), (tau_u, tau_w) = (tuple(map(float, x)) for x in dryden_constants(1.0, 2.0, 5.0))
    for name, x, sigma, tau, longitudinal in (
        ("u", u, sigma_u, tau_u, True),
        ("v", v, sigma_u, tau_u, False),
        ("w", w, sigma_w, tau_w, False),
    ):
        freqs, psd = welch(x, fs=30.0, nperseg=1024, axis=-1)
        psd = psd.mean(0)
        for f in (0.1, 0.3, 1.0):
            i = int(np.argmin(np.abs(freqs - f)))
            model = 2 * dryden_psd(2 * np.pi * freqs[i], sigma, tau, longitudinal)
            assert abs(psd[i] / model - 1) < 0.10, f"{name} at {freqs[i]:.3f} Hz: {psd[i]:.4g} vs {model:.4g}"
        assert abs(x.var() / sigma**2 - 1) < 0.10, f"{name}: variance {x.var():.4g} vs {sigma**2:.4g}"


@pytest.mark.parametrize("hold", [0.0, 0.5, math.inf])
def test_disturbance_statistics(hold):
    """Force and torque: N(0, σ²) per axis (standard deviation within 5 %); redrawn at every step (hold 0: lag-1
    correlation below 0.05), held for exponential durations of mean 0.5 s (mean run within 15 %), or for the
    whole episode (inf)."""
    realism = Realism(disturbance_force=0.0132, disturbance_torque=2.65e-5, disturbance_hold=hold)
    force, torque, wind = _disturbances(realism, 2000, 60)
    assert np.all(wind == 0)
    np.testing.assert_allclose(force.reshape(-1, 3).std(0), 0.0132, rtol=0.05)
    np.testing.assert_allclose(torque[:, 0].std(0), 2.65e-5, rtol=0.05)
    changes = np.mean(force[:, 1:, 0] != force[:, :-1, 0])
    if hold == 0:
        assert changes == 1.0
        assert abs(np.corrcoef(force[:, 1:, 0].ravel(), force[:, :-1, 0].ravel())[0, 1]) < 0.05
    elif math.isinf(hold):
        assert changes == 0.0
        np.testing.assert_allclose(force[:, 0].std(0), 0.0132, rtol=0.05)
    else:
        mean_run = (1 / 30) / changes
        assert abs(mean_run / hold - 1) < 0.15, f"mean hold {mean_run:.3f} s"


def test_gusts_follow_their_shape_and_rate():
    """Discrete 1 − cosine gusts of 2 m/s peak, 1 s long, at 0.2 per s: the wind's speed never exceeds the peak,
    reaches it, and gusts start at the given rate within 15 % (allowing for one gust at a time)."""
    realism = Realism(gust_speed=2.0, gust_rate=0.2, gust_duration=1.0)
    _, _, wind = _disturbances(realism, 500, 600)
    speed = np.linalg.norm(wind, axis=-1)
    assert speed.max() <= 2.0 + 1e-5 and speed.max() > 1.99
    starts = np.sum((speed[:, 1:] > 0) & (speed[:, :-1] == 0))
    busy = np.mean(speed > 0)
    rate = starts / (500 * 600 / 30 * (1 - busy))
    assert abs(rate / 0.2 - 1) < 0.15, rate


@pytest.mark.slow
def test_env_gradients_with_every_option(x64):
    """Float64 `check_grads` (reverse mode, against finite differences) of a 20-step rollout's loss w.r.t. the
    actions, with every option on: motor lag, both delays, noise and bias, constant wind, gusts, turbulence and
    disturbances (the noise is drawn from the state's key, so the rollout is a deterministic function)."""
    from jax.test_util import check_grads

    realism = Realism(
        motor_tau_up=0.06,
        motor_tau_down=0.2,
        action_delay=1,
        obs_delay=1,
        obs_noise_pos=0.001,
        obs_noise_att=0.001,
        obs_noise_vel=0.002,
        obs_noise_ang_vel=0.002,
        obs_bias_pos=0.001,
        wind_speed=1.0,
        gust_speed=1.0,
        gust_rate=1.0,
        turbulence=0.5,
        disturbance_force=0.01,
        disturbance_torque=1e-5,
        disturbance_hold=0.2,
    )
    env = jd.make("hover", realism=realism, init_pos=[[0.0, 0.0, 1.0]])
    state = env.reset(jax.random.key(0))
    weights = jnp.asarray(np.random.default_rng(0).normal(size=(env.observation_size, 4)) * 0.01)

    def loss(offsets):
        def body(s, offset):
            s = env.step(s, jnp.tanh(s.obs @ weights) * 0.3 + offset)
            return s, jnp.sum(env.loss(s))

        return jnp.sum(jax.lax.scan(body, state, offsets)[1])

    offsets = jnp.asarray(np.random.default_rng(1).uniform(-0.2, 0.2, (20, 1, 4)))
    check_grads(jax.jit(loss), (offsets,), order=1, modes=["rev"], eps=1e-6, atol=1e-6, rtol=1e-5)


def test_presets_and_options():
    """The preset turns on motor dynamics with L2F's 0.15 s and draws no delays; options override it; wind turns
    drag on; a range of time constants makes the params per episode."""
    env = jd.make("hover", realism="crazyflie")
    assert env.config.sim.motor_dynamics and not env.config.sim.drag
    assert float(env.params.motor_tau_up[0]) == pytest.approx(0.15) and env.shared_params is not None
    env = jd.make("hover", realism="crazyflie", turbulence=0.5, motor_tau_up=(0.1, 0.2))
    assert env.config.sim.drag and env.shared_params is None
    state = env.reset(jax.random.key(0))
    assert 0.1 <= float(state.params.motor_tau_up[0]) <= 0.2
    assert env.config.realism.obs_noise_pos == (0.001, 0.001)
    harsh = PRESETS["crazyflie_harsh"]
    assert harsh.motor_tau_up == (0.3, 0.3) and harsh.obs_noise_vel == (0.004, 0.004) and harsh.turbulence == (1.0, 1.0)
    assert jd.make("hover").config.realism is None


def test_motors_start_turning_where_they_have_dynamics():
    """With the preset's motor lag an episode starts with each drone's motors at its hover RPM: from a level start at
    rest (the preset's random force off), ten control steps at the hover action lose no height, where stopped motors
    (``start_rpm="zero"``, a take-off from rest) sink the drone tens of cm while they spin up. Without motor
    dynamics the state's RPM starts at 0, as in the paper's physics."""

    def height_lost(**options):
        env = jd.make("hover", realism="crazyflie", init_pos=[[0.0, 0.0, 1.0]], disturbance_force=0.0, **options)
        state = env.reset(jax.random.key(0))
        hover = jnp.zeros((1, env.action_size))
        end = jax.jit(lambda s: jax.lax.fori_loop(0, 10, lambda _, s: env.step(s, hover), s))(state)
        return state, float(state.sim.pos[0, 2] - end.sim.pos[0, 2])

    state, lost = height_lost()
    np.testing.assert_allclose(state.sim.rpm, np.broadcast_to(state.params.hover_rpm[:, None], (1, 4)), rtol=1e-6)
    assert abs(lost) < 0.01
    state, lost = height_lost(start_rpm="zero")
    assert np.all(state.sim.rpm == 0) and lost > 0.2
    assert np.all(jd.make("hover").reset(jax.random.key(0)).sim.rpm == 0)
    with pytest.raises(ValueError, match="unknown start_rpm 'idle'"):
        jd.make("hover", start_rpm="idle")


@pytest.mark.parametrize(
    "options, match",
    [
        ({"realism": "crazyfly"}, "did you mean 'crazyflie'"),
        ({"realism": {"action_dealy": 1}}, "did you mean 'action_delay'"),
        ({"motor_tau_up": -0.1}, "motor_tau_up must be finite, >= 0"),
        ({"motor_tau_down": math.nan}, "motor_tau_down must be finite"),
        ({"obs_noise_pos": math.inf}, "obs_noise_pos must be finite"),
        ({"action_delay": 1.5}, "action_delay must be an integer"),
        ({"obs_delay": -1}, "obs_delay must be finite, >= 0"),
        ({"wind_speed": (2.0, 1.0)}, "low <= high"),
        ({"turbulence": "strong"}, "turbulence must be a number"),
        ({"disturbance_force": True}, "disturbance_force must be a number"),
        ({"realism": 3}, "realism must be None, a preset name"),
    ],
)
def test_realism_bad_input(options, match):
    with pytest.raises(ValueError, match=match):
        jd.make("hover", **options)


def test_gymnasium_ids_and_command_line_take_the_options():
    """The gymnasium ids pass the options to `jd.make`; ``jaxdrones train``'s --realism and --realism-set become the
    config's realism (plain data, recorded with the run), and malformed settings are refused."""
    import gymnasium as gym

    from jaxdrones.cli.train import realism_options

    env = gym.make("jaxdrones/Hover-v0", realism="crazyflie", action_delay=1)
    assert env.unwrapped.env.config.realism.action_delay == (1, 1)
    assert env.reset(seed=0)[0].shape == (21,)
    assert realism_options(None, []) is None and realism_options("crazyflie", []) == "crazyflie"
    options = realism_options("crazyflie", ["action_delay=1", "motor_tau_up=0.05,0.2", "disturbance_hold=inf"])
    assert options == {
        "preset": "crazyflie",
        "action_delay": 1,
        "motor_tau_up": (0.05, 0.2),
        "disturbance_hold": math.inf,
    }
    assert jd.make("hover", realism=options).config.realism.motor_tau_up == (0.05, 0.2)
    for bad in ("action_delay", "turbulence=strong", "wind_speed=1,2,3"):
        with pytest.raises(ValueError, match="--realism-set takes NAME=VALUE"):
            realism_options(None, [bad])
