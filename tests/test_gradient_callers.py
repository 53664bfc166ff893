"""The three ways of differentiating through the simulator agree with each other and with finite differences:
`jd.rollout`, a user's own ``lax.scan`` over the step that `jd.make_step` returns, and ``lax.scan`` over the hover
env's ``step`` (vmapped over worlds, open-loop normalised RPM actions), through 20 control steps of 3 tilted,
moving drones in ground effect with drag on. Also: `split` and `join`, which every caller goes through, are exact
(bit for bit, NaN, infinities and signed zeros included) whichever way they compute the components."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdrones as jd
from jaxdrones.envs.actions import RPM_ACTION_SCALE
from jaxdrones.envs.base import world_axes
from jaxdrones.rotations import join, split

pytestmark = pytest.mark.unit

STEPS, WORLDS = 20, 3
CALLERS = ("rollout", "rollout_stored", "user_scan", "env_step")


def _case(dtype, adjoint: bool = True):
    """The env, its start state (the drones put where the test wants them), its params and the actions;
    ``adjoint``: the physics' hand-written adjoint (`jaxdrones.SimConfig.adjoint`) or JAX's derived derivatives."""
    env = jd.make("hover", ctrl_freq=240, drag=True, ground_effect=True, adjoint=adjoint)
    rng = np.random.default_rng(3)
    config = env.config.sim
    sim = jd.init_state(
        config,
        pos=np.c_[rng.uniform(-0.5, 0.5, (WORLDS, 2)), rng.uniform(0.06, 0.2, WORLDS)][:, None],
        rpy=rng.uniform(-0.2, 0.2, (WORLDS, 1, 3)),
        vel=rng.uniform(-0.3, 0.3, (WORLDS, 1, 3)),
        ang_vel=rng.uniform(-0.5, 0.5, (WORLDS, 1, 3)),
    )
    axes = world_axes(env.shared_params is not None)
    start = jax.vmap(env.reset, out_axes=axes)(jax.random.split(jax.random.key(0), WORLDS)).replace(sim=sim)
    actions = jnp.asarray(rng.uniform(-0.6, 0.6, (STEPS, WORLDS, 1, 4)), dtype)
    return env, start, axes, actions


def _losses(env, start, axes):
    """loss(actions, pos, vel, quat, ang_vel) of each caller: the squared distance to (0, 0, 1) m, the squared
    velocities and body rates and the quaternion's vector part, averaged over steps and worlds."""
    params = start.params
    step = jd.make_step(env.config.sim)
    env_step = jax.vmap(env.step, in_axes=(axes, 0), out_axes=axes)

    def loss_of(pos, vel, quat, ang_vel):
        return (
            jnp.mean(jnp.sum(pos.at[..., 2].add(-1.0) ** 2, -1))
            + 0.1 * jnp.mean(vel**2)
            + 0.01 * jnp.mean(ang_vel**2)
            + jnp.mean(quat[..., :3] ** 2)
        )

    def commands(actions):
        return jnp.broadcast_to(params.hover_rpm[..., None], actions.shape) * (1.0 + RPM_ACTION_SCALE * actions)

    def state(pos, vel, quat, ang_vel):
        return start.sim.replace(pos=pos, vel=vel, quat=quat, ang_vel=ang_vel)

    def rollout(remat):
        def loss(actions, *s):
            out = jd.rollout(step, params, state(*s), commands(actions), remat=remat)
            return loss_of(out.pos, out.vel, out.quat, out.ang_vel)

        return loss

    def user_scan(actions, *s):
        def body(sim, rpm):
            sim = step(params, sim, rpm)
            return sim, (sim.pos, sim.vel, sim.quat, sim.ang_vel)

        return loss_of(*jax.lax.scan(body, state(*s), commands(actions))[1])

    def through_env(actions, *s):
        def body(env_state, action):
            env_state = env_step(env_state, action)
            sim = env_state.sim
            return env_state, (sim.pos, sim.vel, sim.quat, sim.ang_vel)

        return loss_of(*jax.lax.scan(body, start.replace(sim=state(*s)), actions)[1])

    return {"rollout": rollout(True), "rollout_stored": rollout(False), "user_scan": user_scan, "env_step": through_env}


def _args(start, actions):
    sim = start.sim
    return (actions, sim.pos, sim.vel, sim.quat, sim.ang_vel)


@pytest.mark.slow
def test_gradients_of_rollout_user_scan_and_env_step_agree(x64):
    """float64: the same loss and the same gradients w.r.t. the actions and the initial pos, vel, quat and ang_vel,
    whichever caller; the drones stay off the ground (contact is not smooth) but feel ground effect."""
    env, start, axes, actions = _case(jnp.float64)
    losses = _losses(env, start, axes)
    args = _args(start, actions)
    assert start.sim.pos.dtype == jnp.float64
    values, grads = {}, {}
    for name in CALLERS:
        values[name], grads[name] = jax.jit(jax.value_and_grad(losses[name], argnums=tuple(range(5))))(*args)
    for name in CALLERS[1:]:
        np.testing.assert_allclose(values[name], values["rollout"], rtol=1e-12)
        for g, ref in zip(grads[name], grads["rollout"], strict=True):
            np.testing.assert_allclose(g, ref, rtol=1e-9, atol=1e-12)
    assert all(np.any(np.asarray(g) != 0) for g in grads["rollout"])
    out = jd.rollout(
        jd.make_step(env.config.sim),
        start.params,
        start.sim,
        jnp.broadcast_to(start.params.hover_rpm[..., None], actions.shape) * (1.0 + RPM_ACTION_SCALE * actions),
    )
    assert not bool(out.ground_contact.any()) and float(out.pos[..., 2].min()) < 0.2  # in ground effect


@pytest.mark.parametrize(
    "caller, adjoint",
    [
        ("user_scan", False),
        pytest.param("user_scan", True, marks=pytest.mark.slow),
        pytest.param("env_step", False, marks=pytest.mark.slow),
        ("env_step", True),
    ],
)
def test_user_scan_and_env_step_gradients_match_finite_differences(x64, caller, adjoint):
    """check_grads (float64, order 1) through the user's scan and through the env: reverse mode with the
    hand-written adjoint (it has no forward mode), forward and reverse mode with JAX's derived derivatives."""
    env, start, axes, actions = _case(jnp.float64, adjoint)
    loss = jax.jit(_losses(env, start, axes)[caller])
    modes = ("rev",) if adjoint else ("fwd", "rev")
    check_grads(loss, _args(start, actions), order=1, modes=modes, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.slow
def test_gradients_of_the_callers_agree_in_float32():
    """float32, as the callers run by default (on CPU the components are computed by integer matrix products and
    the steps rematerialised): the gradients agree within float32 rounding."""
    env, start, axes, actions = _case(jnp.float32)
    losses = _losses(env, start, axes)
    args = _args(start, actions)
    grads = {name: jax.jit(jax.grad(losses[name], argnums=tuple(range(5))))(*args) for name in CALLERS}
    for name in CALLERS[1:]:
        for g, ref in zip(grads[name], grads["rollout"], strict=True):
            assert g.dtype == jnp.float32
            np.testing.assert_allclose(g, ref, rtol=2e-3, atol=2e-5 * float(jnp.max(jnp.abs(ref))))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("contiguous", [False, True])
def test_split_and_join_are_exact(x64, dtype, contiguous):
    """Bit for bit, NaN payloads, infinities, signed zeros and subnormals included, under jit and vmap; their
    derivatives are those of the identity, in forward and reverse mode."""
    tiny = np.finfo(dtype).smallest_subnormal
    x = np.array([[[1.5, -0.0, np.nan], [np.inf, tiny, -3.25]], [[0.0, -np.inf, 7.0], [-tiny, 1e30, -1e-30]]], dtype)
    x[0, 0, 2] = np.frombuffer(
        np.array(
            0x7FC00123 if dtype == np.float32 else 0x7FF8000000000123, np.uint32 if dtype == np.float32 else np.uint64
        ).tobytes(),
        dtype,
    )[0]
    bits = np.uint32 if dtype == np.float32 else np.uint64

    def identity(a):
        return join(split(a, contiguous), contiguous)

    for f in (identity, jax.jit(identity), jax.vmap(identity)):
        np.testing.assert_array_equal(np.asarray(f(jnp.asarray(x))).view(bits), x.view(bits))
    parts = jax.jit(lambda a: split(a, contiguous))(jnp.asarray(x))
    for i, part in enumerate(parts):
        np.testing.assert_array_equal(np.asarray(part).view(bits), x[..., i].view(bits))
    y = jnp.asarray(np.arange(6, dtype=dtype).reshape(2, 3))
    jac = jax.jacrev(identity)(y)
    np.testing.assert_array_equal(jac, jax.jacfwd(identity)(y))
    np.testing.assert_array_equal(jac.reshape(6, 6), np.eye(6))
    expected = np.zeros((2, 2, 3), dtype)
    expected[[0, 1], [0, 1], 1] = 1  # d y[:, 1] / d y
    for jacobian in (jax.jacfwd, jax.jacrev):
        np.testing.assert_array_equal(jacobian(lambda a: split(a, contiguous)[1])(y), expected)
