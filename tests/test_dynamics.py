"""Physics of the JAX step: agreement with an independent NumPy re-derivation, physical checks, aerodynamic
effects, gradients, invariances and the RK4 integrator.

Figures worth knowing are printed with the prefix ``MEASURED`` (see them with ``pytest -s``). Section numbers (§)
refer to docs/physics.md.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_dyn as ref
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxdrones as jd
from jaxdrones import aerodynamics
from jaxdrones.adjoint import supported as adjoint_supported
from jaxdrones.rotations import quat_mul, quat_to_rotmat

pytestmark = pytest.mark.unit

MODELS = ("cf2x", "cf2p", "racer")
PATTERNS = ("hover", "climb", "roll", "pitch", "yaw", "random")
#: Relative tolerance of the JAX step against the NumPy reference (float64).
REF_RTOL = 1e-6
#: High start, so that the ground plane (z clamp at collision_height / 2) is never reached.
START = (0.3, -0.2, 100.0)


@functools.cache
def stepper(config: jd.SimConfig):
    """One step function per config, so that its jit cache is reused across tests."""
    return jd.make_step(config)


def rel_err(actual, expected) -> float:
    """max |actual - expected| / max(|expected|, 1), elementwise."""
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    return float(np.max(np.abs(actual - expected) / np.maximum(np.abs(expected), 1.0)))


def rpm_sequence(model: str, pattern: str, n_steps: int, rng: np.random.Generator) -> np.ndarray:
    """f64[T, 4] RPM commands for a named pattern, around the model's hover RPM (§1.1)."""
    hover = ref.AIRFRAMES[model].hover_rpm
    if pattern == "hover":
        rpm = np.full(4, hover)
    elif pattern == "climb":
        rpm = np.full(4, 1.1 * hover)
    elif pattern in ("roll", "pitch", "yaw"):
        rpm = hover * (1 + 0.01 * np.array(ref.POSITIVE_TORQUE_PATTERNS[model][pattern], dtype=np.float64))
    elif pattern == "random":
        return hover * (1 + 0.05 * rng.uniform(-1, 1, (n_steps, 4)))
    else:
        raise KeyError(pattern)
    return np.broadcast_to(rpm, (n_steps, 4)).copy()


def initial_conditions(pattern: str, rng: np.random.Generator) -> dict:
    """Start pose and rates: at rest and level (with some yaw) except for 'random', which starts tumbling."""
    if pattern == "random":
        return dict(
            pos=[START], rpy=[rng.uniform(-0.5, 0.5, 3)], vel=[rng.uniform(-1, 1, 3)], ang_vel=[rng.uniform(-2, 2, 3)]
        )
    return dict(pos=[START], rpy=[[0.0, 0.0, 0.4]], vel=[[0.0, 0.0, 0.0]], ang_vel=[[0.0, 0.0, 0.0]])


def euler_matrix(rpy) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (§0.4)."""
    r, p, y = rpy
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def compare_with_reference(model: str, pattern: str, ctrl_freq: int, n_physics: int, seed: int) -> dict:
    """Run the JAX step and the NumPy reference from the same state; return the relative error of each field."""
    rng = np.random.default_rng(seed)
    n_sub = 240 // ctrl_freq
    config = jd.SimConfig(n_drones=1, sim_freq=240, ctrl_freq=ctrl_freq, integrator="euler")
    params = jd.load_params(model)
    ic = initial_conditions(pattern, rng)
    rpms = rpm_sequence(model, pattern, n_physics // n_sub, rng)
    state = jd.init_state(config, **ic)
    assert state.pos.dtype == jnp.float64
    # The start quaternion is built by init_state from rpy; check it against PyBullet's Euler convention (§0.4).
    np.testing.assert_allclose(ref.rotmat(np.asarray(state.quat[0])), euler_matrix(ic["rpy"][0]), atol=1e-15)

    out = jd.rollout(stepper(config), params, state, rpms[:, None, :])
    expected = ref.simulate(
        ref.AIRFRAMES[model],
        np.asarray(state.pos[0]),
        np.asarray(state.quat[0]),
        np.asarray(state.vel[0]),
        np.asarray(state.ang_vel[0]),
        rpms,
        240,
        ctrl_freq,
    )
    errors = {name: rel_err(getattr(out, name)[:, 0], expected[name]) for name in expected}
    assert expected["pos"][:, 2].min() > 1.0, "the reference run must stay clear of the ground"
    print(
        f"MEASURED reference {model:5s} {pattern:6s} ctrl={ctrl_freq:3d} Hz: "
        + " ".join(f"{k}={v:.1e}" for k, v in errors.items())
    )
    return errors


# ------------------------------------------------------------------------------------------------------------------
# 1. Agreement with the NumPy re-derivation of the paper code's explicit dynamics (§3.1, §4)
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("model", MODELS)
def test_euler_matches_numpy_reference(model, pattern, x64):
    errors = compare_with_reference(model, pattern, ctrl_freq=240, n_physics=480, seed=1)
    assert max(errors.values()) < REF_RTOL, errors


@pytest.mark.parametrize("pattern", ["random", "roll"])
@pytest.mark.parametrize("model", MODELS)
def test_euler_matches_numpy_reference_with_substeps(model, pattern, x64):
    """ctrl_freq = 48 Hz: 5 physics substeps per control step with the action held."""
    errors = compare_with_reference(model, pattern, ctrl_freq=48, n_physics=480, seed=2)
    assert max(errors.values()) < REF_RTOL, errors


@pytest.mark.parametrize("model", MODELS)
def test_out_of_range_rpm_is_clipped_like_the_reference(model, x64, rng):
    """RPM outside [0, max_rpm] is clipped (§9), before the dynamics and in the stored ``state.rpm``."""
    config = jd.SimConfig()
    params = jd.load_params(model)
    frame = ref.AIRFRAMES[model]
    rpms = frame.hover_rpm * rng.uniform(-0.5, 2.5, (480, 4))
    assert (rpms < 0).any() and (rpms > frame.max_rpm).any()
    state = jd.init_state(config, pos=[START])
    out = jd.rollout(stepper(config), params, state, rpms[:, None, :])
    np.testing.assert_allclose(out.rpm[:, 0], np.clip(rpms, 0, frame.max_rpm), rtol=1e-15)
    expected = ref.simulate(
        frame, np.asarray(state.pos[0]), np.asarray(state.quat[0]), np.zeros(3), np.zeros(3), rpms, 240, 240
    )
    errors = {name: rel_err(getattr(out, name)[:, 0], expected[name]) for name in expected}
    assert max(errors.values()) < REF_RTOL, errors


def test_held_action_equals_repeated_action(x64, rng):
    """A 48 Hz step (5 substeps) equals five 240 Hz steps with the same RPM (no drag, so the RPM lag is moot)."""
    params = jd.load_params("cf2x")
    fast, slow = jd.SimConfig(sim_freq=240, ctrl_freq=240), jd.SimConfig(sim_freq=240, ctrl_freq=48)
    state = jd.init_state(fast, pos=[START], rpy=[[0.1, -0.2, 0.3]], ang_vel=[[1.0, -0.5, 0.2]])
    rpms = float(params.hover_rpm) * (1 + 0.05 * rng.uniform(-1, 1, (20, 1, 4)))
    out_slow = jd.rollout(stepper(slow), params, state, rpms)
    out_fast = jd.rollout(stepper(fast), params, state, np.repeat(rpms, 5, axis=0))
    for name in ("pos", "quat", "vel", "ang_vel", "rpm"):
        np.testing.assert_allclose(getattr(out_slow, name), getattr(out_fast, name)[4::5], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "options",
    [
        {},
        pytest.param({"n_drones": 2, "drag": True, "ground_effect": True, "downwash": True}, marks=pytest.mark.slow),
        pytest.param({"motor_dynamics": True, "kinks": "smooth", "ground_effect": True}, marks=pytest.mark.slow),
    ],
    ids=["default", "aero", "motors-smooth"],
)
def test_unrolled_substeps_equal_the_loop(options, rng):
    """`SimConfig.unroll_substeps` writes the substeps out instead of looping over them: the same states over a
    rollout, and the same gradient w.r.t. the commands, in float32 (to 1e-5: XLA may fuse the arithmetic
    differently); by default a loop; None, the per-device choice, loops on the CPU only."""
    base = jd.SimConfig(sim_freq=240, ctrl_freq=80, **options)  # 3 substeps (the envs' 8 take longer to compile)
    assert base.unroll_substeps is False and base.substep_unroll == 1
    per_device = dataclasses.replace(base, unroll_substeps=None)
    assert per_device.substep_unroll == (1 if jax.default_backend() == "cpu" else 3)
    params = jd.load_params("cf2x")
    d = base.n_drones
    state = jd.init_state(
        base,
        pos=[[0.0, 0.0, 0.05 + 0.3 * k] for k in range(d)],
        rpy=[[0.1, -0.2, 0.3]] * d,
        ang_vel=[[1.0, -0.5, 0.2]] * d,
    )
    rpms = jnp.asarray(float(params.hover_rpm) * (1 + 0.05 * rng.uniform(-1, 1, (3, d, 4))), jnp.float32)

    def loss(config, rpms):
        out = jd.rollout(jd.make_step(config), params, state, rpms)
        return jnp.sum(out.pos[-1] ** 2) + jnp.sum(out.vel**2), out

    results = {}
    for unroll in (False, True):
        config = dataclasses.replace(base, unroll_substeps=unroll)
        assert config.substep_unroll == (3 if unroll else 1)
        (_, out), grad = jax.value_and_grad(functools.partial(loss, config), has_aux=True)(rpms)
        results[unroll] = (out, grad)
    (loop, grad_loop), (unrolled, grad_unrolled) = results[False], results[True]
    for name in ("pos", "quat", "vel", "ang_vel", "rpm"):
        np.testing.assert_allclose(getattr(unrolled, name), getattr(loop, name), rtol=1e-5, atol=1e-5)
    scale = float(jnp.max(jnp.abs(grad_loop)))
    np.testing.assert_allclose(grad_unrolled / scale, grad_loop / scale, rtol=1e-5, atol=1e-5)


def test_quaternion_update_tiny_rate_is_a_no_op(x64):
    """|ω| ≤ 1e-8 leaves q bit-identical (numpy isclose in the original, §4.6); slightly above, q moves."""
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    step = stepper(config)
    hover = np.full((1, 4), float(params.hover_rpm))
    quat = np.array([[0.1, -0.2, 0.3, 0.9]])
    quat /= np.linalg.norm(quat)
    still = jd.init_state(config, pos=[START], quat=quat, ang_vel=[[3e-9, -2e-9, 5e-9]])
    out = step(params, still, hover)
    np.testing.assert_array_equal(out.quat, still.quat)
    moving = jd.init_state(config, pos=[START], quat=quat, ang_vel=[[3e-6, -2e-6, 5e-6]])
    out = step(params, moving, hover)
    assert np.any(np.asarray(out.quat) != np.asarray(moving.quat))
    expected = ref.integrate_quat(np.asarray(moving.quat[0]), np.asarray(moving.ang_vel[0]), config.dt)
    np.testing.assert_allclose(out.quat[0], expected / np.linalg.norm(expected), rtol=0, atol=1e-15)


# ------------------------------------------------------------------------------------------------------------------
# 2. Physical checks
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", MODELS)
def test_hover_rpm_gives_zero_acceleration(model, x64):
    config = jd.SimConfig()
    params = jd.load_params(model)
    state = jd.init_state(config, pos=[START], rpy=[[0.0, 0.0, 1.1]])
    rpms = np.full((240, 1, 4), float(params.hover_rpm))
    out = jd.rollout(stepper(config), params, state, rpms)
    acc = np.asarray(out.vel[0, 0]) / config.dt
    print(f"MEASURED hover {model}: |a| after one step = {np.abs(acc).max():.1e} m/s²")
    assert np.abs(acc).max() < 1e-13 * params.gravity
    # Symmetric RPM: no torque beyond round-off (XLA may contract the yaw sum into FMAs, ~1e-16 relative).
    assert np.abs(np.asarray(out.ang_vel)).max() < 1e-12
    # |ω| stays far below 1e-8 rad/s, so the quaternion update is the no-op: q is bit-identical.
    np.testing.assert_array_equal(out.quat, np.broadcast_to(state.quat, out.quat.shape))
    np.testing.assert_allclose(out.pos[-1], state.pos, rtol=0, atol=1e-12)


def test_free_fall_and_rest_on_ground(x64):
    """Zero RPM: v_z = -g t and the semi-implicit position z_n = z0 - g dt² n(n+1)/2, then resting on the ground."""
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    dt, g, z0 = config.dt, float(params.gravity), 1.0
    state = jd.init_state(config, pos=[[0.5, -0.5, z0]])
    out = jd.rollout(stepper(config), params, state, np.zeros((240, 1, 4)))
    n = np.arange(1, 241)
    z_free = z0 - g * dt**2 * n * (n + 1) / 2
    airborne = z_free >= 0.5 * float(params.collision_height)
    assert 50 < airborne.sum() < 240
    np.testing.assert_allclose(out.vel[airborne, 0, 2], -g * n[airborne] * dt, rtol=1e-13)
    np.testing.assert_allclose(out.pos[airborne, 0, 2], z_free[airborne], rtol=1e-13)
    np.testing.assert_array_equal(out.pos[:, 0, :2], np.broadcast_to(state.pos[0, :2], (240, 2)))
    np.testing.assert_array_equal(out.ground_contact[airborne], False)
    # After the first step that would go below the resting height: on the ground, at rest, in contact.
    landed = ~airborne
    np.testing.assert_array_equal(out.ground_contact[landed], True)
    np.testing.assert_array_equal(out.pos[landed, 0, 2], 0.5 * params.collision_height)
    np.testing.assert_array_equal(out.vel[landed], 0.0)
    np.testing.assert_array_equal(out.ang_vel[landed], 0.0)
    assert float(out.pos[-1, 0, 2]) == pytest.approx(0.0125, rel=1e-12)


def test_ground_contact_keeps_upward_velocity(x64):
    """A drone below its resting height that climbs keeps its upward velocity (the rule is max(v_z, 0))."""
    config = jd.SimConfig()
    params = jd.load_params("cf2x")
    state = jd.init_state(config, pos=[[0.0, 0.0, 0.0125]], vel=[[0.3, 0.2, -0.5]])
    out = stepper(config)(params, state, np.full((1, 4), float(params.max_rpm)))
    assert bool(out.ground_contact[0])
    np.testing.assert_array_equal(out.vel[0, :2], 0.0)
    assert float(out.pos[0, 2]) == 0.5 * float(params.collision_height)
    climb = jd.init_state(config, pos=[[0.0, 0.0, 0.0125]], vel=[[0.0, 0.0, 1.0]])
    out = stepper(config)(params, climb, np.full((1, 4), float(params.max_rpm)))
    assert not bool(out.ground_contact[0]) and float(out.vel[0, 2]) > 1.0


@pytest.mark.parametrize("axis", ["roll", "pitch", "yaw"])
@pytest.mark.parametrize("model", MODELS)
def test_positive_torque_patterns(model, axis, x64):
    """§2: raising the + motors and lowering the - motors spins the body positively about that axis."""
    config = jd.SimConfig()
    params = jd.load_params(model)
    pattern = np.array(ref.POSITIVE_TORQUE_PATTERNS[model][axis], dtype=np.float64)
    rpm = float(params.hover_rpm) * (1 + 0.01 * pattern)
    out = stepper(config)(params, jd.init_state(config, pos=[START]), rpm[None])
    w = np.asarray(out.ang_vel[0])
    k = "roll pitch yaw".split().index(axis)
    assert w[k] > 0, w
    assert np.all(np.abs(np.delete(w, k)) < 0.01 * w[k]), w


#: Body-frame motor positions (x, y) of §2, and whether the motor spins CCW seen from above (yaw reaction -).
MOTOR_XY = {
    "cf2x": [(0.028, -0.028), (-0.028, -0.028), (-0.028, 0.028), (0.028, 0.028)],
    "cf2p": [(0.0397, 0), (0, 0.0397), (-0.0397, 0), (0, -0.0397)],
    "racer": [(0.085, 0.0675), (-0.085, 0.0675), (-0.085, -0.0675), (0.085, -0.0675)],
}
MOTOR_CCW = {
    "cf2x": (True, False, True, False),
    "cf2p": (True, False, True, False),
    "racer": (False, True, False, True),
}


@pytest.mark.parametrize("model", MODELS)
def test_single_motor_torque_signs(model, x64):
    """Raising motor i alone: τx has the sign of its y, τy the sign of -x, τz is - for CCW and + for CW motors."""
    config = jd.SimConfig()
    params = jd.load_params(model)
    state = jd.init_state(config, pos=[START])
    step = stepper(config)
    for i, ((x, y), ccw) in enumerate(zip(MOTOR_XY[model], MOTOR_CCW[model], strict=True)):
        rpm = np.full((1, 4), float(params.hover_rpm))
        rpm[0, i] *= 1.02
        w = np.asarray(step(params, state, rpm).ang_vel[0])
        assert np.sign(w[0]) == np.sign(y) and np.sign(w[1]) == np.sign(-x), (i, w)
        assert np.sign(w[2]) == (-1 if ccw else 1), (i, w)


def test_quaternion_norm_over_1e5_steps_float32(key):
    """10⁵ physics steps of a tumbling drone in float32: |q| stays 1 ± 1e-6 at every recorded step."""
    config = jd.SimConfig(sim_freq=12000, ctrl_freq=240)
    assert config.n_substeps == 50
    params = jd.load_params("cf2x")
    assert params.mass.dtype == jnp.float32
    state = jd.init_state(config, pos=[[0.0, 0.0, 1000.0]], rpy=[[0.4, -0.3, 2.0]], ang_vel=[[10.0, -7.0, 4.0]])
    rpms = params.hover_rpm * (1 + 0.1 * jax.random.uniform(key, (2000, 1, 4), minval=-1.0, maxval=1.0))
    out = jd.rollout(stepper(config), params, state, rpms)
    assert out.quat.dtype == jnp.float32
    norm = np.linalg.norm(np.asarray(out.quat, np.float64), axis=-1)
    drift = np.abs(norm - 1).max()
    print(f"MEASURED quaternion |norm - 1| over 1e5 float32 steps: {drift:.1e}")
    assert drift <= 1e-6
    # It really tumbled: the attitude visited many orientations and did not hit the ground.
    assert np.ptp(np.asarray(out.quat[:, 0]), axis=0).min() > 1.0
    assert not bool(out.ground_contact.any())
    assert np.all(np.isfinite(np.asarray(out.pos)))


# ------------------------------------------------------------------------------------------------------------------
# 2b. Aerodynamic effects (§6), unit checks on jaxdrones.aerodynamics plus whole-step checks
# ------------------------------------------------------------------------------------------------------------------


def _gain(params, z, rpy=(0.0, 0.0, 0.0)):
    """Ground-effect gain g_i / f_i of each propeller for a drone at height z (m)."""
    quat = jd.init_state(jd.SimConfig(), rpy=[rpy]).quat
    thrust = jnp.full((1, 4), 0.1)
    extra = aerodynamics.ground_effect_thrust(params, jnp.array([[0.0, 0.0, z]]), quat_to_rotmat(quat), thrust)
    return np.asarray(extra[0] / thrust[0])


@pytest.mark.parametrize("model", MODELS)
def test_ground_effect_far_and_clip(model, x64):
    params = jd.load_params(model)
    frame = ref.AIRFRAMES[model]
    far = _gain(params, 10.0)
    np.testing.assert_allclose(far, frame.gnd_eff_coeff * (frame.prop_radius / 40.0) ** 2, rtol=1e-12)
    assert far.max() < 2e-4 if model == "racer" else far.max() < 1e-5
    np.testing.assert_allclose(_gain(params, 1000.0), 1e-4 * far, rtol=1e-10)  # ∝ 1/h², no cut-off
    # At and below the clip height the gain is exactly 4/15 (§1.1).
    clip = float(params.gnd_eff_h_clip)
    for z in (clip, 0.5 * clip, 0.0125, -1.0):
        np.testing.assert_allclose(_gain(params, z), 4 / 15, rtol=1e-13)
    # No ground effect upside down or on the side (|roll| or |pitch| ≥ π/2).
    np.testing.assert_array_equal(_gain(params, 0.05, (np.pi / 2 + 0.1, 0.0, 0.0)), 0.0)
    np.testing.assert_array_equal(_gain(params, 0.05, (np.pi, 0.0, 0.0)), 0.0)
    assert _gain(params, 0.05, (np.pi / 2 - 0.1, 0.0, 0.0)).min() > 0


def test_ground_effect_on_just_short_of_gimbal_lock(x64):
    """Control for the test below: at pitch 90° - 0.57° PyBullet's Euler angles do not snap, the effect is on."""
    params = jd.load_params("cf2x")
    assert _gain(params, 0.05, (0.0, np.pi / 2 - 0.01, 0.0)).min() > 0


def test_ground_effect_off_in_gimbal_snap_band(x64):
    """§6.1: the effect is applied only if |roll| < π/2 and |pitch| < π/2 with the rpy *as PyBullet reports it*;
    within ~0.26° of pitch ±90° (|sin pitch| ≥ 0.99999) PyBullet snaps pitch to exactly ±π/2 (§0.4), so the original
    applies no ground effect there. jaxdrones gates on R[2,2] > 0 and |R[2,0]| < 0.99999, the same condition."""
    params = jd.load_params("cf2x")
    rpy = (0.0, np.pi / 2 - 0.002, 0.0)
    quat = np.asarray(jd.init_state(jd.SimConfig(), rpy=[rpy]).quat[0])
    x, y, z, w = quat
    assert -2 * (x * z - w * y) >= 0.99999  # PyBullet would report pitch = +π/2 exactly
    np.testing.assert_array_equal(_gain(params, 0.05, rpy), 0.0)


def test_ground_effect_whole_step(x64):
    """Whole step at hover RPM: on the ground the thrust gain is 4/15; at 10 m the extra lift is negligible;
    a tilted drone near the ground gets a restoring torque (its lower propellers push harder)."""
    params = jd.load_params("cf2x")
    g = float(params.gravity)
    on, off = jd.SimConfig(ground_effect=True), jd.SimConfig()
    hover = np.full((1, 4), float(params.hover_rpm))
    ground = jd.init_state(on, pos=[[0.0, 0.0, 0.0125]])
    out = stepper(on)(params, ground, hover)
    np.testing.assert_allclose(out.vel[0, 2] / on.dt, g * 4 / 15, rtol=1e-12)
    high = jd.init_state(on, pos=[[0.0, 0.0, 10.0]])
    a_on = float(stepper(on)(params, high, hover).vel[0, 2]) / on.dt
    a_off = float(stepper(off)(params, high, hover).vel[0, 2]) / on.dt
    assert abs(a_off) < 1e-12 and 0 < a_on < 1e-5 * g
    tilted = jd.init_state(on, pos=[[0.0, 0.0, 0.05]], rpy=[[0.2, 0.0, 0.0]])
    assert float(stepper(on)(params, tilted, hover).ang_vel[0, 0]) < 0
    assert float(stepper(off)(params, tilted, hover).ang_vel[0, 0]) == 0.0


def test_downwash_unit():
    params = jd.load_params("cf2x")
    radius = float(params.prop_radius)

    downwash = jax.jit(aerodynamics.downwash_force)

    def force(*positions):
        return np.asarray(downwash(params, jnp.array(positions, dtype=jnp.float32)))

    # §6.3 magnitudes, directly below: 0.303 N at Δz = 0.5 m, 0.0758 N at Δz = 1 m; the upper drone feels 0.
    np.testing.assert_allclose(force([0, 0, 0.5], [0, 0, 1.0]), [-0.303, 0.0], rtol=2e-3)
    np.testing.assert_allclose(force([0, 0, 0.0], [0, 0, 1.0]), [-0.0758, 0.0], rtol=2e-3)
    np.testing.assert_allclose(force([0, 0, 0.0], [0, 0, 1.0])[0], -2267.18 * (radius / 4) ** 2, rtol=1e-6)
    # Equal heights: exactly zero, however close.
    np.testing.assert_array_equal(force([0, 0, 1.0], [0.05, 0, 1.0]), 0.0)
    # Far horizontally: negligible just inside 10 m, exactly zero beyond.
    assert np.abs(force([0, 0, 0.0], [9.99, 0, 1.0])).max() < 1e-12
    np.testing.assert_array_equal(force([0, 0, 0.0], [10.01, 0, 1.0]), 0.0)
    # Very high above: tiny compared with the weight (0.26 N), and ∝ 1/Δz².
    f1, f2 = force([0, 0, 0.0], [0, 0, 1000.0])[0], force([0, 0, 0.0], [0, 0, 2000.0])[0]
    assert -1e-6 * float(params.weight) < f1 < 0 and f1 / f2 == pytest.approx(4.0, rel=1e-5)
    # With Δz = 63 m the Gaussian is wide (β ≈ 10 m): the 10 m cut-off is what makes the force vanish.
    inside, outside = force([0, 0, 0.0], [9.99, 0, 63.0])[0], force([0, 0, 0.0], [10.0, 0, 63.0])[0]
    assert inside < -1e-6 and outside == 0.0
    # β = 0 at Δz = 0.6875 m: zero off-axis, the d → 0 limit (-α, finite) on the axis.
    assert force([0, 0, 0.0], [0.01, 0, 0.6875])[0] == 0.0
    np.testing.assert_allclose(
        force([0, 0, 0.0], [0, 0, 0.6875])[0], -2267.18 * (radius / (4 * 0.6875)) ** 2, rtol=1e-5
    )
    # Several drones above add up.
    three = force([0, 0, 0.0], [0.05, 0, 0.8], [-0.03, 0.02, 1.3])
    pair_a = force([0, 0, 0.0], [0.05, 0, 0.8])[0]
    pair_b = force([0, 0, 0.0], [-0.03, 0.02, 1.3])[0]
    np.testing.assert_allclose(three[0], pair_a + pair_b, rtol=1e-6)
    assert three[0] < pair_a < 0 and three[2] == 0.0
    np.testing.assert_allclose(three[1], force([0.05, 0, 0.8], [-0.03, 0.02, 1.3])[0], rtol=1e-6)


def test_downwash_whole_step(x64):
    """Only the lower drone is pushed, along its body -z, by exactly dt·F/m in one step."""
    params = jd.load_params("cf2x")
    on, off = jd.SimConfig(n_drones=2, downwash=True), jd.SimConfig(n_drones=2)
    pos = [[0.0, 0.0, 50.0], [0.05, 0.0, 50.5]]
    state = jd.init_state(on, pos=pos, rpy=[[0.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
    rpm = np.full((2, 4), float(params.hover_rpm))
    a, b = stepper(on)(params, state, rpm), stepper(off)(params, state, rpm)
    np.testing.assert_array_equal(a.vel[1], b.vel[1])
    f = float(aerodynamics.downwash_force(params, jnp.array(pos))[0])
    body_z = ref.rotmat(np.asarray(state.quat[0]))[:, 2]
    np.testing.assert_allclose(a.vel[0] - b.vel[0], on.dt * f / float(params.mass) * body_z, rtol=1e-9, atol=1e-15)
    assert float(a.vel[0, 2]) < float(b.vel[0, 2])


def _swarm(rng, side=16, spacing=0.5):
    """A side×side grid, `spacing` m apart, at random heights between 0.5 and 1.5 m, with a little jitter."""
    xy = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2) * spacing
    xy = xy + rng.uniform(-0.05, 0.05, xy.shape)
    return np.concatenate([xy, rng.uniform(0.5, 1.5, (len(xy), 1))], -1)


@pytest.mark.slow
def test_downwash_cell_list(x64, rng):
    """The cell list finds every drone within the radius (no duplicates); with it and a 1 m cut-off, the downwash
    of a 256-drone swarm 0.5 m apart equals the all-pairs force with that cut-off, and the original's (10 m) to
    1e-12 of the weight. A cell holding more drones than its capacity loses some."""
    from jaxdrones.neighbors import cell_candidates

    params = jd.load_params("cf2x")
    pos = _swarm(rng)
    cand = np.asarray(cell_candidates(jnp.asarray(pos[:, 0]), jnp.asarray(pos[:, 1]), 1.0, 8))
    assert cand.shape == (256, 72)
    dist = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1)
    for i in range(256):
        listed = [j for j in cand[i] if j != i]
        assert len(listed) == len(set(listed)) and set(np.flatnonzero(dist[i] < 1.0)) - {i} <= set(listed)
    pos = jnp.asarray(pos)
    full = aerodynamics.downwash_force(params, pos)
    assert float(jnp.min(full)) < -1e-3 * float(params.weight)  # the swarm has real downwash
    near = aerodynamics.downwash_force(params, pos, neighbors=jnp.asarray(cand), cutoff=1.0)
    np.testing.assert_allclose(near, aerodynamics.downwash_force(params, pos, cutoff=1.0), rtol=1e-12)
    np.testing.assert_allclose(near, full, rtol=0, atol=1e-12 * float(params.weight))
    # 20 drones stacked in one cell, capacity 8: the top ones' downwash on the bottom one is partly missed.
    column = jnp.asarray(np.stack([0.01 * np.arange(20), np.zeros(20), 0.5 + 0.5 * np.arange(20)], -1))
    short = cell_candidates(column[:, 0], column[:, 1], 1.0, 8)
    assert float(aerodynamics.downwash_force(params, column, neighbors=short, cutoff=1.0)[0]) > float(
        aerodynamics.downwash_force(params, column, cutoff=1.0)[0]
    )


@pytest.mark.slow
def test_downwash_radius_step_matches_all_pairs(x64, rng):
    """SimConfig(downwash_radius=1): the control step of 256 drones (its neighbour list held over 8 substeps)
    gives the all-pairs step's state to 1e-12, in a batch of worlds; gradients flow through it; bad values are
    refused."""
    params = jd.load_params("cf2x")
    pos = np.stack([_swarm(rng) for _ in range(2)])
    configs = [jd.SimConfig(n_drones=256, ctrl_freq=30, downwash=True, downwash_radius=r) for r in (None, 1.0)]
    assert configs[1].effects.downwash_neighbors(tuple(jnp.asarray(pos[..., k]) for k in range(3))).shape == (
        2,
        256,
        72,
    )
    state = jd.init_state(configs[0], pos=pos)
    rpm = jnp.full((2, 256, 4), float(params.hover_rpm))
    full, near = (stepper(c)(params, state, rpm) for c in configs)
    off = stepper(jd.SimConfig(n_drones=256, ctrl_freq=30))(params, state, rpm)
    assert float(jnp.max(jnp.abs(full.vel - off.vel))) > 1e-4
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(near), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    loss = lambda p: jnp.sum(stepper(configs[1])(params, state.replace(pos=p), rpm).vel[..., 2])  # noqa: E731
    grad = jax.grad(loss)(state.pos)
    assert bool(jnp.all(jnp.isfinite(grad))) and float(jnp.max(jnp.abs(grad[..., 2]))) > 0
    for bad in (0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="downwash_radius"):
            jd.SimConfig(n_drones=4, downwash_radius=bad)
    with pytest.raises(ValueError, match="cell_capacity"):
        jd.SimConfig(n_drones=4, cell_capacity=0)


def test_drag_opposes_velocity(rng):
    params = jd.load_params("cf2x")
    vel = rng.normal(size=(256, 1, 3)) * rng.uniform(0.01, 10, (256, 1, 1))
    rpm_prev = rng.uniform(100.0, float(params.max_rpm), (256, 1, 4))
    drag = np.asarray(aerodynamics.drag_force(params, jnp.asarray(vel), jnp.asarray(rpm_prev)), np.float64)
    assert np.all(np.sum(drag * vel, axis=-1) < 0)
    # §6.2: world-axis coefficients, F = -Ω diag(c_xy, c_xy, c_z) v.
    omega = rpm_prev.sum(-1, keepdims=True) * 2 * np.pi / 60
    np.testing.assert_allclose(drag, -omega * np.array([9.1785e-7, 9.1785e-7, 10.311e-7]) * vel, rtol=1e-5)
    zero = aerodynamics.drag_force(params, jnp.asarray(vel), jnp.zeros((256, 1, 4)))
    np.testing.assert_array_equal(zero, 0.0)
    # Magnitude at hover (§6.2): about -6.25e-3 N per m/s vertically.
    hover = jnp.full((1, 4), params.hover_rpm)
    fz = float(aerodynamics.drag_force(params, jnp.array([[0.0, 0.0, 1.0]]), hover)[0, 2])
    assert fz == pytest.approx(-6.25e-3, rel=2e-3)


def test_drag_uses_previous_substep_rpm(x64):
    """§6.2: the first substep of a control step uses the previous step's RPM (zero after init_state); the
    other substeps use the new one. Level hover with v = (1, 0, 0): v_x = (1 - dt Ω c_xy / m)^(n_substeps - 1)."""
    params = jd.load_params("cf2x")
    config = jd.SimConfig(sim_freq=240, ctrl_freq=48, drag=True)
    state = jd.init_state(config, pos=[START], vel=[[1.0, 0.0, 0.0]])
    rpm = np.full((1, 4), float(params.hover_rpm))
    out = stepper(config)(params, state, rpm)
    decay = 1 - config.dt * 4 * float(params.hover_rpm) * 2 * np.pi / 60 * 9.1785e-7 / float(params.mass)
    np.testing.assert_allclose(out.vel[0, 0], decay**4, rtol=1e-12)
    np.testing.assert_array_equal(out.rpm, rpm)
    out2 = stepper(config)(params, out, rpm)
    np.testing.assert_allclose(out2.vel[0, 0], decay**9, rtol=1e-12)
    # Without drag the velocity is kept.
    nodrag = stepper(jd.SimConfig(sim_freq=240, ctrl_freq=48))(params, state, rpm)
    np.testing.assert_allclose(nodrag.vel[0, 0], 1.0, rtol=1e-14)


# ------------------------------------------------------------------------------------------------------------------
# 3. Gradients
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "integrator, adjoint",
    [
        ("euler", True),
        pytest.param("euler", False, marks=pytest.mark.slow),
        pytest.param("rk4", True, marks=pytest.mark.slow),
    ],
)
def test_check_grads_full_step(integrator, adjoint, x64):
    """check_grads (float64, order 1) through a 2-substep step of 3 drones with all effects on, w.r.t. pos, vel,
    quat, ang_vel, the previous RPM (drag), the RPM command, mass, kf and km: reverse mode through the hand-written
    adjoint (`jaxdrones.adjoint`, which has no forward mode), forward and reverse mode through JAX's derived ones.

    Drones sit at 0.15-0.75 m (props above the ground-effect clip, 0.0378 m, and above the contact height),
    offset horizontally by ~0.1 m at different heights (downwash active), with RPM inside (0, max_rpm)."""
    config = jd.SimConfig(
        n_drones=3,
        sim_freq=240,
        ctrl_freq=120,
        drag=True,
        ground_effect=True,
        downwash=True,
        integrator=integrator,
        adjoint=adjoint,
    )
    step = jd.make_step(config)
    p0 = jd.load_params("cf2x")
    assert p0.mass.dtype == jnp.float64
    hover = float(p0.hover_rpm)
    rng = np.random.default_rng(4)
    state0 = jd.init_state(
        config,
        pos=[[0.0, 0.0, 0.15], [0.1, 0.02, 0.45], [-0.03, 0.1, 0.75]],
        rpy=rng.uniform(-0.2, 0.2, (3, 3)),
        vel=rng.uniform(-0.5, 0.5, (3, 3)),
        ang_vel=rng.uniform(-1, 1, (3, 3)),
        rpm=hover * (1 + 0.05 * rng.uniform(-1, 1, (3, 4))),
    )
    rpm_base = hover * (1 + 0.05 * rng.uniform(-1, 1, (3, 4)))

    def f(pos, vel, quat, ang_vel, rpm_prev_scale, rpm_scale, mass_scale, kf_scale, km_scale):
        params = p0.replace(mass=p0.mass * (1 + mass_scale), kf=p0.kf * (1 + kf_scale), km=p0.km * (1 + km_scale))
        state = state0.replace(pos=pos, vel=vel, quat=quat, ang_vel=ang_vel, rpm=state0.rpm * (1 + rpm_prev_scale))
        out = step(params, state, rpm_base * (1 + rpm_scale))
        return jnp.concatenate([out.pos.ravel(), out.quat.ravel(), out.vel.ravel(), out.ang_vel.ravel()])

    zeros34 = jnp.zeros((3, 4))
    args = (state0.pos, state0.vel, state0.quat, state0.ang_vel, zeros34, zeros34, 0.0, 0.0, 0.0)
    args = tuple(jnp.asarray(a, jnp.float64) for a in args)
    # The effects are really on at this point (the check would be vacuous otherwise).
    gain = aerodynamics.ground_effect_thrust(p0, state0.pos, quat_to_rotmat(state0.quat), jnp.ones((3, 4)))
    assert float(gain.min()) > 5e-4
    assert float(aerodynamics.downwash_force(p0, state0.pos)[1]) < -1e-3
    assert not bool(step(p0, state0, rpm_base).ground_contact.any())
    modes = ("rev",) if adjoint_supported(config) else ("fwd", "rev")
    check_grads(jax.jit(f), args, order=1, modes=modes, eps=1e-5, atol=1e-6, rtol=1e-6)


def test_closed_form_jacobians(x64):
    """At hover, d v_z / d rpm_i = dt · 2 kf rpm_i / m; with zero RPM (free fall) d z / d z0 = 1, d v_z / d mass = 0
    (reverse mode: the default step's hand-written adjoint has no forward mode)."""
    config = jd.SimConfig()
    params = jd.load_params("racer")
    step = stepper(config)
    state = jd.init_state(config, pos=[START])

    def f(rpm, z0, mass):
        out = step(params.replace(mass=mass), state.replace(pos=state.pos.at[0, 2].set(z0)), rpm)
        return jnp.stack([out.pos[0, 2], out.vel[0, 2]])

    z0, mass, dt = START[2], params.mass, config.dt
    hover = jnp.full((1, 4), params.hover_rpm)
    jac_rpm, jac_z0, jac_mass = jax.jacrev(f, argnums=(0, 1, 2))(hover, z0, mass)
    np.testing.assert_allclose(jac_rpm[1, 0], dt * 2 * params.kf * params.hover_rpm / mass, rtol=1e-12)
    np.testing.assert_allclose(jac_rpm[0, 0], dt**2 * 2 * params.kf * params.hover_rpm / mass, rtol=1e-12)
    np.testing.assert_allclose(jac_z0, [1.0, 0.0], atol=1e-15)
    # At hover the weight and the thrust both scale the acceleration: d v_z / d m = -dt T / m² = -dt g / m.
    np.testing.assert_allclose(jac_mass[1], -dt * params.gravity / mass, rtol=1e-12)
    _, jac_z0, jac_mass = jax.jacrev(f, argnums=(0, 1, 2))(jnp.zeros((1, 4)), z0, mass)
    np.testing.assert_allclose(jac_z0, [1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(jac_mass, [0.0, 0.0], atol=1e-15)


# ------------------------------------------------------------------------------------------------------------------
# 4. Invariances: jit, vmap, batched state, drone permutation, heterogeneous teams
# ------------------------------------------------------------------------------------------------------------------

ALL_EFFECTS = jd.SimConfig(n_drones=4, sim_freq=240, ctrl_freq=48, drag=True, ground_effect=True, downwash=True)


def _world_states(rng, n_worlds):
    pos = rng.uniform([-0.3, -0.3, 0.1], [0.3, 0.3, 1.2], (n_worlds, 4, 3))
    return jd.init_state(
        ALL_EFFECTS,
        pos=pos,
        rpy=rng.uniform(-0.3, 0.3, (n_worlds, 4, 3)),
        vel=rng.uniform(-1, 1, (n_worlds, 4, 3)),
        ang_vel=rng.uniform(-2, 2, (n_worlds, 4, 3)),
        rpm=rng.uniform(1e4, 2e4, (n_worlds, 4, 4)),
    )


def _assert_states_close(a, b, rtol=1e-5, atol=1e-6):
    for name in ("pos", "quat", "vel", "ang_vel", "rpm"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=rtol, atol=atol, err_msg=name)
    np.testing.assert_array_equal(a.contact, b.contact)


def test_jit_equals_eager(rng):
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    state = jax.tree.map(lambda x: x[0], _world_states(rng, 1))
    rpm = rng.uniform(1e4, 2e4, (4, 4))
    _assert_states_close(jax.jit(step)(params, state, rpm), step(params, state, rpm))


@pytest.mark.slow
def test_vmap_and_batched_state_equal_per_world(rng):
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    states = _world_states(rng, 5)
    rpms = rng.uniform(1e4, 2.1e4, (5, 4, 4)).astype(np.float32)
    batched = step(params, states, rpms)
    vmapped = jax.vmap(step, in_axes=(None, 0, 0))(params, states, rpms)
    _assert_states_close(batched, vmapped)
    for w in range(5):
        one = step(params, jax.tree.map(lambda x: x[w], states), rpms[w])
        _assert_states_close(jax.tree.map(lambda x: x[w], vmapped), one)
    # Per-world params (domain randomisation) under vmap equal per-world steps with those params.
    masses = params.mass * np.linspace(0.8, 1.2, 5, dtype=np.float32)
    world_params = jax.tree.map(lambda x: jnp.broadcast_to(x, (5,) + x.shape), params).replace(mass=masses)
    randomised = jax.vmap(step)(world_params, states, rpms)
    for w in range(5):
        one = step(params.replace(mass=masses[w]), jax.tree.map(lambda x: x[w], states), rpms[w])
        _assert_states_close(jax.tree.map(lambda x: x[w], randomised), one)
    assert not np.allclose(randomised.vel, vmapped.vel)


def test_per_world_params_with_drone_axis_equal_vmap(rng):
    """Per-world params given as [W, 1] (aligned with the state's [W, D]) equal vmap over [W] params."""
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    states = _world_states(rng, 4)
    rpms = rng.uniform(1e4, 2.1e4, (4, 4, 4)).astype(np.float32)
    masses = params.mass * np.array([0.8, 0.9, 1.1, 1.2], dtype=np.float32)
    per_world = jax.tree.map(lambda x: jnp.broadcast_to(x, (4,) + x.shape), params).replace(mass=masses)
    vmapped = jax.vmap(step)(per_world, states, rpms)
    with_drone_axis = jax.tree.map(lambda x: x[:, None], per_world)
    _assert_states_close(step(with_drone_axis, states, rpms), vmapped)


def test_per_world_params_without_drone_axis_rejected(rng):
    """Batched params are right-aligned with the state's [..., D]: [W] params with W != D cannot line up and must
    be rejected with a ValueError naming the params' shape, not an opaque broadcasting error."""
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    states = _world_states(rng, 3)  # W = 3, D = 4
    rpms = rng.uniform(1e4, 2.1e4, (3, 4, 4)).astype(np.float32)
    per_world = jax.tree.map(lambda x: jnp.broadcast_to(x, (3,) + x.shape), params)
    with pytest.raises(ValueError, match=r"params have batch shape \(3,\).*per-world params \[W, 1\]"):
        step(per_world, states, rpms)


def test_permuting_drones_permutes_outputs(rng):
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    state = jax.tree.map(lambda x: x[0], _world_states(rng, 1))
    rpm = rng.uniform(1e4, 2e4, (4, 4))
    # Downwash is really felt by some drone, so the permutation test covers the coupling.
    assert float(jnp.min(aerodynamics.downwash_force(params, state.pos))) < -1e-3
    perm = np.array([2, 0, 3, 1])
    out = step(params, state, rpm)
    out_perm = step(params, jax.tree.map(lambda x: x[perm], state), rpm[perm])
    _assert_states_close(out_perm, jax.tree.map(lambda x: x[perm], out), rtol=1e-6, atol=1e-6)


def test_heterogeneous_team_equals_individual_drones(x64, rng):
    """Params with a drone axis ([D]) fly a cf2x, a cf2p and a racer in one world (no coupling effects on)."""
    config, single = (
        jd.SimConfig(n_drones=3, drag=True, ground_effect=True),
        jd.SimConfig(drag=True, ground_effect=True),
    )
    models = [jd.load_params(m) for m in MODELS]
    team = jax.tree.map(lambda *xs: jnp.stack(xs), *models)
    state = jd.init_state(
        config,
        pos=[[0, 0, 0.3], [1, 0, 0.5], [0, 1, 2.0]],
        rpy=rng.uniform(-0.3, 0.3, (3, 3)),
        ang_vel=rng.uniform(-1, 1, (3, 3)),
        rpm=rng.uniform(1e4, 1.5e4, (3, 4)),
    )
    rpm = np.stack([float(m.hover_rpm) * (1 + 0.05 * rng.uniform(-1, 1, 4)) for m in models])
    out = stepper(config)(team, state, rpm)
    for d, model in enumerate(models):
        one = stepper(single)(model, jax.tree.map(lambda x: x[d : d + 1], state), rpm[d : d + 1])
        _assert_states_close(jax.tree.map(lambda x: x[d : d + 1], out), one, rtol=1e-12, atol=1e-14)


@settings(max_examples=15, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), seed=st.integers(0, 2**16))
def test_yaw_rotating_the_world_rotates_the_result(yaw, seed):
    """All effects on: drag is isotropic in xy, ground effect depends on height, downwash on Δz and horizontal
    distance, so rotating the whole world about z by ψ rotates the step's result (body rates unchanged)."""
    rng = np.random.default_rng(seed)
    params = jd.load_params("cf2x")
    step = stepper(ALL_EFFECTS)
    state = jax.tree.map(lambda x: x[0], _world_states(rng, 1))
    rpm = rng.uniform(1e4, 2e4, (4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    rz = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=jnp.float32)
    qz = jnp.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)], dtype=jnp.float32)

    def rotate(st_):
        return st_.replace(pos=st_.pos @ rz.T, vel=st_.vel @ rz.T, quat=quat_mul(qz, st_.quat))

    out = step(params, state, rpm)
    out_rotated = step(params, rotate(state), rpm)
    expected = rotate(out)
    np.testing.assert_allclose(out_rotated.pos, expected.pos, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out_rotated.vel, expected.vel, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out_rotated.ang_vel, out.ang_vel, rtol=1e-4, atol=1e-4)
    # q and -q are the same rotation: compare rotation matrices.
    np.testing.assert_allclose(quat_to_rotmat(out_rotated.quat), quat_to_rotmat(expected.quat), atol=1e-5)


def test_torque_free_body_conserves_energy_and_angular_momentum(x64):
    """Zero RPM: no torque, so ½ωᵀJω and the world angular momentum R J ω are conserved (RK4, 480 Hz, 2 s, an
    axisymmetric cf2x spinning about a tilted axis: the gyroscopic term is active)."""
    config = jd.SimConfig(sim_freq=480, ctrl_freq=240, integrator="rk4")
    params = jd.load_params("cf2x")
    state = jd.init_state(config, pos=[START], rpy=[[0.3, 0.2, -0.4]], ang_vel=[[3.0, -2.0, 5.0]])
    out = jd.rollout(stepper(config), params, state, np.zeros((480, 1, 4)))
    inertia = np.asarray(params.inertia)
    w = np.asarray(out.ang_vel[:, 0])
    energy = 0.5 * np.einsum("ti,ij,tj->t", w, inertia, w)
    momentum = np.einsum("tij,jk,tk->ti", np.asarray(quat_to_rotmat(out.quat[:, 0])), inertia, w)
    w0 = np.asarray(state.ang_vel[0])
    e0 = 0.5 * w0 @ inertia @ w0
    m0 = np.asarray(quat_to_rotmat(state.quat[0])) @ inertia @ w0
    e_drift = np.abs(energy / e0 - 1).max()
    m_drift = np.abs(momentum - m0).max() / np.linalg.norm(m0)
    print(f"MEASURED torque-free rk4: energy drift {e_drift:.1e}, angular momentum drift {m_drift:.1e}")
    assert e_drift < 1e-10 and m_drift < 1e-8
    assert np.ptp(w[:, 0]) > 1.0  # the body rate really precessed


# ------------------------------------------------------------------------------------------------------------------
# 7. RK4 integrator
# ------------------------------------------------------------------------------------------------------------------


def test_rk4_converges_with_fourth_order_and_agrees_with_fine_euler(x64):
    """A smooth 2 s manoeuvre (tumbling start, asymmetric constant RPM). RK4 errors against a fine RK4 solution
    shrink ~16× when dt halves; semi-implicit Euler converges to the same solution with first order (~8× for dt/8).
    """
    params = jd.load_params("cf2x")
    rpm = float(params.hover_rpm) * (1 + np.array([0.02, -0.01, 0.015, -0.005]))
    rpms = np.broadcast_to(rpm, (480, 1, 4))  # 480 control steps at 240 Hz (same shapes as the reference runs)

    def final(integrator, sim_freq):
        config = jd.SimConfig(sim_freq=sim_freq, ctrl_freq=240, integrator=integrator)
        state = jd.init_state(
            config,
            pos=[START],
            rpy=[[0.2, -0.1, 0.5]],
            vel=[[0.5, 0.0, -0.2]],
            ang_vel=[[1.0, -0.6, 0.8]],
            rpm=rpm[None],
        )
        out = jd.rollout(stepper(config), params, state, rpms)
        return np.concatenate([np.asarray(getattr(out, k)[-1, 0]) for k in ("pos", "quat", "vel", "ang_vel")])

    truth = final("rk4", 240 * 8)
    rk4 = {f: np.abs(final("rk4", f) - truth).max() for f in (240, 480)}
    euler = {f: np.abs(final("euler", f) - truth).max() for f in (240, 240 * 8)}
    print(
        f"MEASURED rk4 error vs fine rk4 (1920 Hz) after 2 s: 240 Hz {rk4[240]:.2e}, 480 Hz {rk4[480]:.2e} "
        f"(ratio {rk4[240] / rk4[480]:.1f}); euler 240 Hz {euler[240]:.2e}, 1920 Hz {euler[1920]:.2e} "
        f"(ratio {euler[240] / euler[1920]:.1f})"
    )
    assert 12 < rk4[240] / rk4[480] < 20  # fourth order: 16
    assert rk4[240] < 1e-6
    assert 6 < euler[240] / euler[1920] < 10  # first order: 8
    assert rk4[240] < 1e-3 * euler[240]


def test_quaternion_update_gradient_at_rest_is_first_order(x64):
    """At |ω| ≤ 1e-8 the update is a no-op (§4.6) but its derivative is that of q ⊗ (½dt ω, 1), so attitude
    gradients flow through a drone at rest; it matches the derivative just above the threshold."""
    from jaxdrones.rotations import quat_integrate

    quat = jnp.asarray(np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9]))
    dt = 1 / 240
    at_rest = jax.jacobian(lambda w: quat_integrate(quat, w, dt))(jnp.zeros(3))
    moving = jax.jacobian(lambda w: quat_integrate(quat, w, dt))(jnp.full(3, 1e-6))
    np.testing.assert_array_equal(quat_integrate(quat, jnp.zeros(3), dt), quat)
    assert float(jnp.max(jnp.abs(at_rest))) > 1e-3
    np.testing.assert_allclose(at_rest, moving, atol=1e-9)
    # With respect to q itself: the identity at rest, as just above the threshold (q's own derivative counted once).
    by_quat = jax.jacobian(lambda q: quat_integrate(q, jnp.zeros(3), dt))(quat)
    np.testing.assert_allclose(by_quat, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(
        by_quat, jax.jacobian(lambda q: quat_integrate(q, jnp.full(3, 1e-6), dt))(quat), atol=1e-8
    )  # off the diagonal, ½ dt |ω| = 2e-9 just above


@pytest.mark.parametrize("steps", [10, pytest.param(100, marks=pytest.mark.slow)])
def test_check_grads_rollout(steps, x64):
    """check_grads (float64, order 1, rev: the hand-written adjoint) through `jd.rollout` of 10 and 100 control
    steps of 3 drones at 240 Hz with drag, ground effect and downwash on, w.r.t. the RPM commands, the initial state
    and mass, kf, km and the drag coefficients (the rollout steps the component form, with each step rematerialised)."""
    config = jd.SimConfig(n_drones=3, sim_freq=240, ctrl_freq=240, drag=True, ground_effect=True, downwash=True)
    step = jd.make_step(config)
    p0 = jd.load_params("cf2x")
    hover = float(p0.hover_rpm)
    rng = np.random.default_rng(5)
    # 0.3 m apart horizontally: the lower drones feel the upper ones' downwash (up to 0.009 N) without falling.
    state0 = jd.init_state(
        config,
        pos=[[0.0, 0.0, 0.3], [0.3, 0.02, 0.5], [0.6, 0.1, 0.8]],
        rpy=rng.uniform(-0.2, 0.2, (3, 3)),
        vel=rng.uniform(-0.2, 0.2, (3, 3)),
        ang_vel=rng.uniform(-0.3, 0.3, (3, 3)),
        rpm=hover * np.ones((3, 4)),
    )
    rpms = jnp.asarray(hover * (1.01 + 0.01 * rng.uniform(-1, 1, (steps, 3, 4))))

    def f(rpm_scale, pos, vel, quat, ang_vel, scales):
        params = p0.replace(
            mass=p0.mass * (1 + scales[0]),
            kf=p0.kf * (1 + scales[1]),
            km=p0.km * (1 + scales[2]),
            drag_coeff=p0.drag_coeff * (1 + scales[3]),
        )
        state = state0.replace(pos=pos, vel=vel, quat=quat, ang_vel=ang_vel)
        out = jd.rollout(step, params, state, rpms * (1 + rpm_scale))
        return jnp.concatenate([out.pos[-1].ravel(), out.quat[-1].ravel(), out.vel[::7].ravel()])

    args = (jnp.zeros((steps, 3, 4)), state0.pos, state0.vel, state0.quat, state0.ang_vel, jnp.zeros(4))
    out = jd.rollout(step, p0, state0, rpms)
    # Smooth all the way: no contact, every drone in ground effect (gain > 5e-4) and the upper ones in downwash.
    assert not bool(out.ground_contact.any()) and float(out.pos[..., 2].min()) > 0.1
    gain = aerodynamics.ground_effect_thrust(p0, out.pos, quat_to_rotmat(out.quat), jnp.ones((steps, 3, 4)))
    assert float(gain.min()) > 5e-4 and float(jnp.max(aerodynamics.downwash_force(p0, out.pos))) <= 0.0
    assert float(jnp.min(aerodynamics.downwash_force(p0, out.pos))) < -1e-3
    check_grads(jax.jit(f), args, order=1, modes=("rev",), eps=1e-5, atol=1e-6, rtol=1e-5)


@pytest.mark.slow
def test_gradients_stay_finite_through_contact_flips_and_crashes():
    """10⁴ random rollouts (2 drones per world, every effect on, 60 steps of random commands from 0 to max RPM,
    starts from the ground up to 0.5 m, tilted up to 1.5 rad, spinning): the drones touch the ground, flip and crash,
    and the gradient of a loss over the whole rollout w.r.t. the commands and the initial state stays finite."""
    config = jd.SimConfig(n_drones=2, sim_freq=240, ctrl_freq=120, drag=True, ground_effect=True, downwash=True)
    step = jd.make_step(config)
    params = jd.load_params("cf2x")
    rng = np.random.default_rng(6)
    n, steps = 10_000, 60
    pos = np.concatenate([rng.uniform(-0.1, 0.1, (n, 2, 2)), rng.uniform(0.0, 0.5, (n, 2, 1))], axis=-1)
    state = jd.init_state(
        config, pos=pos, rpy=rng.uniform(-1.5, 1.5, (n, 2, 3)), ang_vel=rng.uniform(-20, 20, (n, 2, 3))
    )
    rpms = jnp.asarray(rng.uniform(0, 1, (steps, n, 2, 4)) * float(params.max_rpm), jnp.float32)

    def loss(rpms, pos, ang_vel):
        states = jd.rollout(step, params, state.replace(pos=pos, ang_vel=ang_vel), rpms)
        return jnp.mean(jnp.sum(states.pos.at[..., 2].add(-1.0) ** 2, -1)) + jnp.mean(states.quat[..., 3])

    states = jd.rollout(step, params, state, rpms)
    assert float(jnp.mean(states.ground_contact.any(axis=0))) > 0.1  # many drones touched the ground
    assert (
        float(
            jnp.mean(
                jnp.min(
                    states.quat[..., 3] ** 2
                    - states.quat[..., 0] ** 2
                    - states.quat[..., 1] ** 2
                    + states.quat[..., 2] ** 2,
                    axis=0,
                )
                < 0
            )
        )
        > 0.1
    )  # ... and many turned over
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(rpms, state.pos, state.ang_vel)
    for g in grads:
        assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.max(jnp.abs(g))) > 0
