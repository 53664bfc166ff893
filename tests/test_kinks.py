"""`SimConfig.kinks`: the smooth treatment of each kink agrees with central finite differences across it (float64),
is C¹ and equals the original outside its band; straight-through keeps the original's forward pass; the exact
default is left as it was (the physics tests check it against the original)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdrones as jd
from jaxdrones.kinks import Kinks

pytestmark = pytest.mark.unit

P = jd.load_params("cf2x")
REST = 0.5 * float(P.collision_height)


def _one_step(kinks, n_drones=1, **effects):
    """``f(pos, vel, quat, ang_vel, rpm) -> state``: one 240 Hz control step of the JAX core."""
    config = jd.SimConfig(n_drones=n_drones, sim_freq=240, ctrl_freq=240, kinks=kinks, **effects)
    step = jd.make_step(config)
    state0 = jd.init_state(config, rpm=float(P.hover_rpm) * np.ones((n_drones, 4)))
    return lambda **fields: step(
        P, state0.replace(**{k: v for k, v in fields.items() if k != "rpm"}), fields.get("rpm", state0.rpm)
    )


def _rpm_clip(kinks):
    step = _one_step(kinks)
    # The 4 motors' command x; the result mixes thrust (vz) and the yaw torque (ω_z).
    return lambda x: (lambda s: s.vel[0, 2] + 1e-3 * s.ang_vel[0, 2])(step(rpm=jnp.stack([x, x, x, 0.5 * x])[None]))


def _contact_height(kinks):
    step = _one_step(kinks)

    def f(z):  # hover thrust: no net acceleration; landing at 0.1 m/s, sliding and spinning
        s = step(
            pos=jnp.stack([0.0, 0.0, z])[None],
            vel=jnp.asarray([[0.1, -0.2, -0.1]]),
            ang_vel=jnp.asarray([[0.3, 0.2, -0.1]]),
        )
        return s.pos[0, 2] + jnp.sum(s.vel) + jnp.sum(s.ang_vel)

    return f


def _contact_speed(kinks):
    step = _one_step(kinks)

    def f(vz):  # on the ground (2 bands below the rest height), moving up or down
        s = step(pos=jnp.asarray([[0.0, 0.0, REST - 2 * kinks.height]]), vel=jnp.stack([0.0, 0.0, vz])[None])
        return s.vel[0, 2] + s.pos[0, 2]

    return f


def _ground_effect_height(kinks):
    step = _one_step(kinks, ground_effect=True)
    return lambda z: step(pos=jnp.stack([0.0, 0.0, z])[None]).vel[0, 2]


def _ground_effect_attitude(kinks, axis):
    step = _one_step(kinks, ground_effect=True)

    def f(angle):  # rolled or pitched about 90°, 0.2 m up: the ground effect turns off
        quat = jnp.zeros(4).at[axis].set(jnp.sin(angle / 2)).at[3].set(jnp.cos(angle / 2))
        s = step(pos=jnp.asarray([[0.0, 0.0, 0.2]]), quat=quat[None])
        return jnp.sum(s.vel) + 1e-2 * jnp.sum(s.ang_vel)

    return f


def _downwash(kinks, variable):
    step = _one_step(kinks, n_drones=2, downwash=True)

    def f(x):  # the upper drone Δz above, or d away horizontally 30 m above (where the wake is widest)
        upper = jnp.stack([0.05, 0.0, 1.0 + x]) if variable == "dz" else jnp.stack([x, 0.0, 31.0])
        return step(pos=jnp.stack([jnp.asarray([0.0, 0.0, 1.0]), upper])).vel[0, 2]

    return f


#: kink -> (f(kinks) -> scalar function of x, the kink's x, the band's half-width in x).
KINKS = {
    "rpm_clip_max": (_rpm_clip, float(P.max_rpm), lambda k: k.rpm),
    "rpm_clip_zero": (_rpm_clip, 0.0, lambda k: k.rpm),
    "contact_height": (_contact_height, REST + 0.1 / 240, lambda k: k.height),
    "contact_speed": (_contact_speed, 0.0, lambda k: k.speed),
    "ground_effect_height": (_ground_effect_height, float(P.gnd_eff_h_clip), lambda k: k.height),
    "ground_effect_roll": (lambda k: _ground_effect_attitude(k, 0), math.pi / 2, lambda k: k.attitude),
    "ground_effect_pitch": (lambda k: _ground_effect_attitude(k, 1), math.asin(0.99999), lambda k: k.attitude),
    "downwash_onset": (lambda k: _downwash(k, "dz"), 0.01, lambda k: k.downwash),
    "downwash_cutoff": (lambda k: _downwash(k, "d"), 10.0, lambda k: k.downwash),
}
#: The kinks whose checks compile longest (10-11 s each on 2 cores): in the ``slow`` tier, the others ``fast``.
SLOW_KINKS = ("ground_effect_height", "downwash_onset", "downwash_cutoff")


def _grads_and_central_differences(f, xs, eps):
    grads = np.asarray(jax.jit(jax.vmap(jax.grad(f)))(jnp.asarray(xs)))
    values = jax.jit(jax.vmap(f))
    fd = (np.asarray(values(jnp.asarray(xs + eps))) - np.asarray(values(jnp.asarray(xs - eps)))) / (2 * eps)
    return grads, fd


@pytest.mark.parametrize("kink", [pytest.param(k, marks=pytest.mark.slow) if k in SLOW_KINKS else k for k in KINKS])
def test_smooth_treatment_agrees_with_finite_differences_across_its_kink(kink, x64):
    make_f, center, band = KINKS[kink]
    kinks = Kinks("smooth")
    width = band(kinks)
    f, f_exact = make_f(kinks), make_f(Kinks("exact"))
    # 41 points across the band, the kink and both edges among them.
    xs = center + width * np.linspace(-2.0, 2.0, 41)
    grads, fd = _grads_and_central_differences(f, xs, eps=1e-5 * width)
    scale = np.abs(fd).max()
    assert scale > 0 and np.all(np.isfinite(grads))
    # Central differences are off by O(eps / band) where the second derivative jumps (at the band's edges).
    np.testing.assert_allclose(grads, fd, rtol=1e-5, atol=2e-5 * scale, err_msg=kink)
    # C¹: the derivative moves by less than a fraction of its range between neighbouring points 0.1 band apart.
    assert np.abs(np.diff(grads)).max() < 0.3 * (np.ptp(grads) + 1e-12), kink
    # The original outside the band (the downwash onset's band is Δz ∈ [0, 2w]; near 90° pitch the band of
    # |R[2,0]| < 0.99999 spans 0.14 rad).
    if kink != "ground_effect_pitch":
        outside = jnp.asarray(center + width * np.array([-3.0, 3.0]))
        np.testing.assert_allclose(jax.vmap(f)(outside), jax.vmap(f_exact)(outside), rtol=1e-12, atol=1e-15)
    # Whereas the original's derivative jumps there, or its value does: no derivative on either side matches the
    # secant across the kink.
    left, right = center - width, center + width
    g_left, g_right = (float(jax.grad(f_exact)(jnp.asarray(x))) for x in (left, right))
    secant = float(f_exact(jnp.asarray(right)) - f_exact(jnp.asarray(left))) / (right - left)
    assert min(abs(secant - g_left), abs(secant - g_right)) > 0.05 * scale, (kink, secant, g_left, g_right)


@pytest.mark.slow
def test_straight_through_keeps_the_forward_pass_and_passes_the_gradient_through(x64):
    exact, straight = Kinks("exact"), Kinks("straight_through")
    for make_f, center, band in KINKS.values():
        xs = jnp.asarray(center + band(exact) * np.linspace(-3.0, 3.0, 13))
        # The same values up to float64 rounding (the two functions compile apart: 4e-15 relative seen).
        np.testing.assert_allclose(jax.vmap(make_f(straight))(xs), jax.vmap(make_f(exact))(xs), rtol=1e-13, atol=0)

    # A saturated command still moves the thrust, at the slope it has at max_rpm (the clipped command's).
    def vz_after(kinks):
        step = _one_step(kinks)
        return lambda x: step(rpm=jnp.full((1, 4), x)).vel[0, 2]

    above, below = (float(jax.grad(vz_after(straight))(jnp.asarray(P.max_rpm * s))) for s in (1.05, 0.999999))
    assert float(jax.grad(vz_after(exact))(jnp.asarray(P.max_rpm * 1.05))) == 0.0
    assert above > 0 and abs(above / below - 1) < 1e-5
    # Below the ground, the height passes through the contact with slope 1.
    config = jd.SimConfig(kinks="straight_through")
    step = jd.make_step(config)
    state0 = jd.init_state(config, rpm=float(P.hover_rpm) * np.ones((1, 4)))
    z_after = lambda z: step(P, state0.replace(pos=jnp.stack([0.0, 0.0, z])[None]), state0.rpm).pos[0, 2]  # noqa: E731
    assert float(z_after(REST - 0.005)) == REST and float(jax.grad(z_after)(REST - 0.005)) == pytest.approx(1.0)


@pytest.mark.slow
def test_check_grads_rollout_with_smooth_kinks_through_contact_and_saturation(x64):
    """check_grads through 20 steps of smooth physics in which drones saturate, land and sit in each other's
    downwash, with every effect on."""
    config = jd.SimConfig(
        n_drones=2, sim_freq=240, ctrl_freq=240, drag=True, ground_effect=True, downwash=True, kinks="smooth"
    )
    step = jd.make_step(config)
    state0 = jd.init_state(
        config,
        pos=[[0.0, 0.0, REST + 2e-4], [0.05, 0.0, 0.15]],
        vel=[[0.1, 0.0, -0.05], [0.0, 0.0, 0.0]],
        rpm=float(P.hover_rpm) * np.ones((2, 4)),
    )
    rng = np.random.default_rng(0)
    rpms = jnp.asarray(P.max_rpm * rng.uniform(0.2, 1.01, (20, 2, 4)))
    out = jd.rollout(step, P, state0, rpms)
    assert bool(out.ground_contact[:, 0].any()) and float(rpms.max()) > float(P.max_rpm)

    def f(rpms, pos, vel):
        out = jd.rollout(step, P, state0.replace(pos=pos, vel=vel), rpms)
        return jnp.concatenate([out.pos[-1].ravel(), out.vel[::5].ravel()])

    check_grads(
        jax.jit(f), (rpms, state0.pos, state0.vel), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-5
    )


def test_kinks_bad_input():
    with pytest.raises(ValueError, match="Kinks.mode must be one of"):
        jd.SimConfig(kinks="soft")
    with pytest.raises(ValueError, match="Kinks.height .* must be a number > 0"):
        Kinks("smooth", height=0.0)
    with pytest.raises(ValueError, match="SimConfig.kinks must be a jaxdrones.kinks.Kinks"):
        jd.SimConfig(kinks=3)
    assert jd.SimConfig(kinks="smooth") == jd.SimConfig(kinks=Kinks("smooth"))


@pytest.mark.pybullet
def test_pybullet_backend_steps_exact_kinks_only():
    with pytest.raises(ValueError, match="kinks must be 'exact'"):
        jd.make_step(jd.SimConfig(kinks="smooth"), backend="pybullet")
