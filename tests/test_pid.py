"""DSLPIDControl in JAX against an independent NumPy re-implementation of the original (tests/reference_pid.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_pid as ref
from scipy.spatial.transform import Rotation

from jaxdrones.control import mixer, pid
from jaxdrones.params import load_params
from jaxdrones.physics import rotations
from jaxdrones.state import DroneState

pytestmark = pytest.mark.unit

#: Agreement required with the float64 NumPy reference: RPM are ~1e4, so this is ~1e-13 relative.
RPM_ATOL = 1e-9
ANGLE_ATOL = 1e-12


@pytest.fixture
def rng():
    """A fixed NumPy generator for host-side test data."""
    return np.random.default_rng(0)


def _random_state(rng, lead, tilt=0.6):
    """Random poses around the origin: roll/pitch up to ``tilt`` rad, any yaw, speeds up to ~1 m/s."""
    n = int(np.prod(lead))
    rpy = np.column_stack([rng.uniform(-tilt, tilt, n), rng.uniform(-tilt, tilt, n), rng.uniform(-np.pi, np.pi, n)])
    quat = Rotation.from_euler("xyz", rpy).as_quat()  # PyBullet's convention: extrinsic x-y-z, (x, y, z, w)
    pos = rng.uniform(-1, 1, (n, 3)) + np.array([0, 0, 1.0])
    vel = rng.uniform(-1, 1, (n, 3))
    ang_vel = rng.uniform(-3, 3, (n, 3))
    return {k: v.reshape(lead + (v.shape[-1],)) for k, v in dict(pos=pos, quat=quat, vel=vel, ang_vel=ang_vel).items()}


def _drone_state(arrays, lead):
    return DroneState(
        pos=jnp.asarray(arrays["pos"]),
        quat=jnp.asarray(arrays["quat"]),
        vel=jnp.asarray(arrays["vel"]),
        ang_vel=jnp.asarray(arrays["ang_vel"]),
        rpm=jnp.zeros(lead + (4,)),
        contact=jnp.zeros(lead, dtype=jnp.int32),
    )


def _random_targets(rng, lead, scale):
    return dict(
        target_pos=rng.uniform(-scale, scale, lead + (3,)) + np.array([0, 0, 1.0]),
        target_vel=rng.uniform(-1, 1, lead + (3,)),
        target_rpy=rng.uniform(-np.pi, np.pi, lead + (3,)),
        target_rpy_rates=rng.uniform(-2, 2, lead + (3,)),
    )


@pytest.mark.parametrize("model", ["cf2x", "cf2p"])
def test_matches_reference_over_a_sequence(model):
    """Several calls from reset on a [W=2, D=3] batch: RPM, errors and the carried state match the reference.

    The calls use random (not closed-loop) states and targets, so every drone sees a non-level first attitude
    (the derivative spike after reset), yaw targets anywhere in [-π, π], and - with the large targets and long
    control periods of the later calls - the integral, torque and PWM clips.
    """
    lead = (2, 3)
    rng = np.random.default_rng(0)
    refs = [[ref.DSLPIDControl(model) for _ in range(lead[1])] for _ in range(lead[0])]
    # (ctrl_dt, target scale): ordinary 48 Hz / 240 Hz calls, then large errors and long periods to hit clips.
    schedule = [(1 / 48, 0.3), (1 / 48, 0.3), (1 / 240, 1.0), (1 / 48, 3.0), (0.5, 3.0), (0.5, 5.0), (1 / 48, 0.1)]
    saw = {"pwm_clip": False, "torque_clip": False, "z_integral_clip": False}
    with jax.enable_x64(True):
        params = load_params(model)
        gains = pid.PIDGains.dsl()
        step = jax.jit(pid.pid_compute)
        state_j = pid.pid_init(lead)
        for dt, scale in schedule:
            arrays = _random_state(rng, lead)
            targets = _random_targets(rng, lead, scale)
            rpm, state_j, info = step(
                params,
                gains,
                state_j,
                _drone_state(arrays, lead),
                **{k: jnp.asarray(v) for k, v in targets.items()},
                ctrl_dt=dt,
            )
            assert rpm.dtype == jnp.float64
            for w in range(lead[0]):
                for d in range(lead[1]):
                    c = refs[w][d]
                    r_rpm, r_pos_e, r_yaw_e = c.computeControl(
                        dt,
                        arrays["pos"][w, d],
                        arrays["quat"][w, d],
                        arrays["vel"][w, d],
                        arrays["ang_vel"][w, d],
                        targets["target_pos"][w, d],
                        target_rpy=targets["target_rpy"][w, d],
                        target_vel=targets["target_vel"][w, d],
                        target_rpy_rates=targets["target_rpy_rates"][w, d],
                    )
                    np.testing.assert_allclose(rpm[w, d], r_rpm, rtol=0, atol=RPM_ATOL)
                    np.testing.assert_allclose(info.pos_err[w, d], r_pos_e, rtol=0, atol=1e-15)
                    np.testing.assert_allclose(info.yaw_err[w, d], r_yaw_e, rtol=0, atol=ANGLE_ATOL)
                    np.testing.assert_allclose(state_j.integral_pos_e[w, d], c.integral_pos_e, rtol=0, atol=1e-14)
                    np.testing.assert_allclose(state_j.integral_rpy_e[w, d], c.integral_rpy_e, rtol=0, atol=1e-12)
                    np.testing.assert_allclose(state_j.last_rpy[w, d], c.last_rpy, rtol=0, atol=ANGLE_ATOL)
                    saw["pwm_clip"] |= bool(np.any(np.isclose(r_rpm, 9440.3) | np.isclose(r_rpm, 21666.4475)))
                    saw["z_integral_clip"] |= abs(c.integral_pos_e[2]) == 0.15
            saw["torque_clip"] |= bool(
                np.any(
                    np.abs(np.asarray(rpm) - np.asarray(rpm).mean(-1, keepdims=True))
                    > 3000 * ref.DSLPIDControl.PWM2RPM_SCALE
                )
            )
    assert all(saw.values()), saw


def test_circle_like_call_matches_reference(rng):
    """Near-hover states, the circle example's yaw targets and 48 Hz: the regime where the controller is used."""
    lead = (4,)
    with jax.enable_x64(True):
        params, gains = load_params("cf2x"), pid.PIDGains.dsl()
        refs = [ref.DSLPIDControl("cf2x") for _ in range(lead[0])]
        state_j = pid.pid_init(lead)
        target_rpy = np.zeros(lead + (3,))
        target_rpy[:, 2] = np.arange(4) * np.pi / 8
        for _ in range(5):
            arrays = _random_state(rng, lead, tilt=0.05)
            arrays["vel"] *= 0.2
            target_pos = arrays["pos"] + rng.uniform(-0.05, 0.05, lead + (3,))
            rpm, state_j = pid.pid_control(
                params, gains, state_j, _drone_state(arrays, lead), target_pos, target_rpy=target_rpy, ctrl_dt=1 / 48
            )
            for d, c in enumerate(refs):
                r_rpm, _, _ = c.computeControl(
                    1 / 48,
                    arrays["pos"][d],
                    arrays["quat"][d],
                    arrays["vel"][d],
                    arrays["ang_vel"][d],
                    target_pos[d],
                    target_rpy=target_rpy[d],
                )
                np.testing.assert_allclose(rpm[d], r_rpm, rtol=0, atol=RPM_ATOL)


def test_hover_at_target_gives_hover_pwm():
    """Level, at rest, on target: thrust PWM 38726.7 (docs/physics.md §12.2) and four equal hover-ish RPMs."""
    with jax.enable_x64(True):
        params, gains = load_params("cf2x"), pid.PIDGains.dsl()
        state = DroneState(
            pos=jnp.array([[0.0, 0, 1]]),
            quat=jnp.array([[0.0, 0, 0, 1]]),
            vel=jnp.zeros((1, 3)),
            ang_vel=jnp.zeros((1, 3)),
            rpm=jnp.zeros((1, 4)),
            contact=jnp.zeros(1, jnp.int32),
        )
        rpm, _, info = pid.pid_compute(params, gains, pid.pid_init(state), state, state.pos, ctrl_dt=1 / 48)
        np.testing.assert_allclose(info.thrust_pwm, [38726.7], atol=0.05)
        np.testing.assert_allclose(rpm, np.full((1, 4), 0.2685 * float(info.thrust_pwm[0]) + 4070.3), atol=1e-9)
        np.testing.assert_allclose(rpm, float(params.hover_rpm), atol=1e-6)


@pytest.mark.parametrize("model", ["cf2x", "cf2p"])
def test_mixer_is_the_original(model):
    np.testing.assert_array_equal(np.asarray(mixer.mixer_matrix(load_params(model))), ref.MIXERS[model])


def test_mixer_racer_follows_its_positive_torque_patterns():
    """Racer (docs/physics.md §2): roll+ raises (+,+,−,−), pitch+ (−,+,+,−), yaw+ (+,−,+,−)."""
    signs = np.sign(np.asarray(mixer.mixer_matrix(load_params("racer"))))
    np.testing.assert_array_equal(signs.T, [[1, 1, -1, -1], [-1, 1, 1, -1], [1, -1, 1, -1]])


def test_moved_helpers_keep_their_old_paths():
    """The mixer and the Euler helpers live with allocation and the rotations; the PID's module still has them."""
    assert pid.mixer_matrix is mixer.mixer_matrix
    assert pid.euler_xyz_from_rotmat is rotations.euler_xyz_from_rotmat
    assert pid.rotmat_from_euler_xyz is rotations.rotmat_from_euler_xyz


def test_mixer_batched_params():
    params = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), load_params("cf2x"), load_params("cf2p"))
    matrix = np.asarray(mixer.mixer_matrix(params))
    np.testing.assert_array_equal(matrix, np.stack([ref.MIXERS["cf2x"], ref.MIXERS["cf2p"]]))


def test_velocity_targets_match_reference(rng):
    lead = (2, 3)
    arrays = _random_state(rng, lead)
    action = rng.uniform(-1, 1, lead + (4,))
    action[0, 1, :3] = 0.0  # a zero direction gives zero velocity
    with jax.enable_x64(True):
        params = load_params("cf2x")
        limit = float(pid.speed_limit(params))
        assert limit == pytest.approx(0.25)
        pos, vel, rpy = pid.velocity_targets(_drone_state(arrays, lead), action, limit)
        for w in range(lead[0]):
            for d in range(lead[1]):
                r_pos, r_vel, r_rpy = ref.velocity_targets(
                    arrays["pos"][w, d], arrays["quat"][w, d], action[w, d], limit
                )
                np.testing.assert_allclose(pos[w, d], r_pos, atol=0)
                np.testing.assert_allclose(vel[w, d], r_vel, atol=1e-15)
                np.testing.assert_allclose(rpy[w, d], r_rpy, atol=1e-15)
        assert np.all(np.asarray(vel[0, 1]) == 0)


def test_velocity_control_matches_reference(rng):
    lead = (3,)
    with jax.enable_x64(True):
        params, gains = load_params("cf2x"), pid.PIDGains.dsl()
        refs = [ref.DSLPIDControl("cf2x") for _ in range(lead[0])]
        state_j = pid.pid_init(lead)
        for _ in range(3):
            arrays = _random_state(rng, lead, tilt=0.2)
            action = rng.uniform(-1, 1, lead + (4,))
            rpm, state_j = pid.velocity_control(
                params, gains, state_j, _drone_state(arrays, lead), action, ctrl_dt=1 / 240
            )
            for d, c in enumerate(refs):
                t_pos, t_vel, t_rpy = ref.velocity_targets(arrays["pos"][d], arrays["quat"][d], action[d], 0.25)
                r_rpm, _, _ = c.computeControl(
                    1 / 240,
                    arrays["pos"][d],
                    arrays["quat"][d],
                    arrays["vel"][d],
                    arrays["ang_vel"][d],
                    t_pos,
                    target_rpy=t_rpy,
                    target_vel=t_vel,
                )
                np.testing.assert_allclose(rpm[d], r_rpm, rtol=0, atol=RPM_ATOL)


def test_euler_xyz_matches_scipy():
    rots = Rotation.random(500, random_state=3)
    with jax.enable_x64(True):
        angles = np.asarray(rotations.euler_xyz_from_rotmat(jnp.asarray(rots.as_matrix())))
        np.testing.assert_allclose(angles, rots.as_euler("XYZ"), atol=1e-13)
        back = np.asarray(rotations.rotmat_from_euler_xyz(jnp.asarray(angles)))
        np.testing.assert_allclose(back, rots.as_matrix(), atol=1e-14)


def test_vmap_and_float32(rng):
    """vmap over worlds (traced inputs) == the batched call; float32 stays float32 and close to the reference."""
    lead = (2, 4)
    arrays = _random_state(rng, lead, tilt=0.2)
    target = rng.uniform(-0.3, 0.3, lead + (3,))
    params, gains = load_params("cf2x"), pid.PIDGains.dsl()
    state = _drone_state(arrays, lead)
    ps = pid.pid_init(state)
    rpm, new = pid.pid_control(params, gains, ps, state, target, ctrl_dt=1 / 48)
    assert rpm.dtype == jnp.float32 and rpm.shape == lead + (4,)
    per_world = jax.vmap(lambda p, s, t: pid.pid_control(params, gains, p, s, t, ctrl_dt=1 / 48))(ps, state, target)
    np.testing.assert_allclose(per_world[0], rpm, rtol=1e-6)
    ref_ctrl = [ref.DSLPIDControl("cf2x") for _ in range(4)]
    expected = [
        c.computeControl(
            1 / 48,
            arrays["pos"][0, d],
            arrays["quat"][0, d],
            arrays["vel"][0, d],
            arrays["ang_vel"][0, d],
            target[0, d],
        )[0]
        for d, c in enumerate(ref_ctrl)
    ]
    np.testing.assert_allclose(rpm[0], np.array(expected), rtol=0, atol=1.0)  # float32: ~1e-4 relative


def test_gradient_wrt_gains(rng):
    """Gains are data: the gradient of the RPM w.r.t. all gains matches a central difference (float64)."""
    lead = (2,)
    arrays = _random_state(rng, lead, tilt=0.1)
    target = arrays["pos"] + 0.1
    with jax.enable_x64(True):
        params = load_params("cf2x")
        state = _drone_state(arrays, lead)
        gains = pid.PIDGains.dsl()
        weights = jnp.asarray(rng.normal(size=lead + (4,)))

        def f(g):
            rpm = pid.pid_control(params, g, pid.pid_init(state), state, target, ctrl_dt=1 / 48)[0]
            return jnp.sum(weights * rpm)

        grad = jax.jit(jax.grad(f))(gains)
        direction = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape)) * (1 + x), gains)
        eps = 1e-6
        shifted = [jax.tree_util.tree_map(lambda g, d, s=s: g + s * eps * d, gains, direction) for s in (1, -1)]
        fd = (f(shifted[0]) - f(shifted[1])) / (2 * eps)
        analytic = sum(
            jnp.vdot(g, d)
            for g, d in zip(jax.tree_util.tree_leaves(grad), jax.tree_util.tree_leaves(direction), strict=True)
        )
        assert np.isfinite(float(analytic))
        np.testing.assert_allclose(float(analytic), float(fd), rtol=1e-5)


def test_bad_inputs_raise():
    params, gains = load_params("cf2x"), pid.PIDGains.dsl()
    state = DroneState(
        pos=jnp.zeros((4, 3)),
        quat=jnp.tile(jnp.array([0.0, 0, 0, 1]), (4, 1)),
        vel=jnp.zeros((4, 3)),
        ang_vel=jnp.zeros((4, 3)),
        rpm=jnp.zeros((4, 4)),
        contact=jnp.zeros(4, jnp.int32),
    )
    ps = pid.pid_init(state)
    with pytest.raises(ValueError, match="target_pos"):
        pid.pid_control(params, gains, ps, state, jnp.zeros((3, 3)), ctrl_dt=1 / 48)
    with pytest.raises(ValueError, match="target_pos"):
        pid.pid_control(params, gains, ps, state, jnp.zeros((4, 2)), ctrl_dt=1 / 48)
    with pytest.raises(ValueError, match="target_rpy"):
        pid.pid_control(params, gains, ps, state, jnp.zeros(3), target_rpy=jnp.zeros((4, 4)), ctrl_dt=1 / 48)
    with pytest.raises(ValueError, match="ctrl_dt"):
        pid.pid_control(params, gains, ps, state, jnp.zeros(3), ctrl_dt=0.0)
    with pytest.raises(ValueError, match="pid_state"):
        pid.pid_control(params, gains, pid.pid_init((5,)), state, jnp.zeros(3), ctrl_dt=1 / 48)
    with pytest.raises(ValueError, match="action"):
        pid.velocity_targets(state, jnp.zeros((4, 3)), 0.25)
    with pytest.raises(ValueError, match="pid_init"):
        pid.pid_init((0,))
    # A target for all drones at once broadcasts.
    rpm, _ = pid.pid_control(params, gains, ps, state, jnp.array([0.0, 0.0, 0.1]), ctrl_dt=1 / 48)
    assert rpm.shape == (4, 4)
