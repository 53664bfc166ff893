"""Gradients through an env: a linear policy's loss over 10 control steps of the hover task, differentiated with
respect to the policy's weights (observation in, action out), is finite and agrees with central finite
differences, from a level start at rest, from a tilted one, and in the paper's 1-D setting, where the attitude stays
exactly level (there the Euler angles of the observation used to give NaN derivatives everywhere)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdrones as jd
from jaxdrones.envs import MULTI_AGENT, registered
from jaxdrones.envs.actions import FIRMWARE_ACTIONS
from jaxdrones.rotations import quat_to_euler

STEPS = 10


def policy_loss(env, state0):
    """Loss(w): minus the paper's hover reward (−d², differentiable) summed over STEPS steps of tanh(obs @ w)."""

    def loss(weights):
        def body(state, _):
            action = jnp.tanh(state.obs @ weights)
            state = env.step(state, action)
            return state, jnp.sum(state.reward)

        _, rewards = jax.lax.scan(body, state0, None, length=STEPS)
        return -jnp.sum(rewards)

    return loss


CASES = {
    "level-at-rest": dict(init_pos=[[0.0, 0.0, 0.8]]),
    "tilted": dict(init_pos=[[0.2, -0.1, 0.6]], init_rpy=[[0.3, -0.2, 2.5]]),
    "one-d-level": dict(init_pos=[[0.0, 0.0, 0.5]], action_type="one_d_rpm"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_policy_gradient_through_hover_is_finite_and_matches_finite_differences(x64, case):
    """With the paper's KIN observation (the Euler angles); the every-task test below covers the default one.
    Forward and reverse mode, so through JAX's derived derivatives of the physics (``adjoint=False``)."""
    start = CASES[case]
    env = jd.make("hover", reward="paper", obs_type="kin", adjoint=False, **start)
    state0 = env.reset(jax.random.key(0))
    if "init_rpy" not in start:  # the case that gave NaN: a level attitude, so the Euler branch sees atan2(0, 0)
        np.testing.assert_array_equal(quat_to_euler(state0.sim.quat), 0.0)
    rng = np.random.default_rng(0)
    weights = jnp.asarray(0.05 * rng.standard_normal((env.observation_size, env.action_size)))
    loss = jax.jit(policy_loss(env, state0))
    grad = jax.grad(loss)(weights)
    assert grad.dtype == jnp.float64 and np.all(np.isfinite(grad)) and np.any(grad != 0)
    check_grads(loss, (weights,), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("task", registered())
def test_policy_gradient_through_every_task_matches_finite_differences(x64, task):
    """Every registered task (its default action and observation types, the paper's reward, 3 drones for the
    multi-agent ones, one policy shared by the drones), from tilted starts: finite gradients that agree with
    finite differences. firmware_hover with ``rpm`` actions: the firmware's controller is not differentiable (its
    int16 outputs), its task and physics (1 kHz, lagging motors) are."""
    n = 3 if task in MULTI_AGENT else 1
    actions = {"action_type": "rpm"} if jd.envs.get_task(task).config_cls.action_type in FIRMWARE_ACTIONS else {}
    rng = np.random.default_rng(1)
    init_pos = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.5, 1.0, n)] + np.c_[np.arange(n), np.zeros((n, 2))]
    cameras = {"vision": ()} if task == "avoid" else {}  # a linear policy of the state (images: test_cameras.py)
    env = jd.make(
        task,
        n_drones=n,
        reward="paper",
        init_pos=init_pos,
        init_rpy=rng.uniform(-0.3, 0.3, (n, 3)),
        **cameras,
        **actions,
    )
    state0 = env.reset(jax.random.key(2))
    weights = jnp.asarray(0.05 * rng.standard_normal((env.observation_size, env.action_size)))
    loss = jax.jit(policy_loss(env, state0))
    grad = jax.grad(loss)(weights)
    assert np.all(np.isfinite(grad)) and np.any(grad != 0)
    check_grads(loss, (weights,), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-5)
