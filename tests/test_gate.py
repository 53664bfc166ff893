"""``fly_thru_gate`` with ``gate_pose="random"`` (`jaxdrones.envs.tasks.gate.GatePass`): the gate drawn per episode
and seen only through the camera, passing, missing and hitting it, a policy that knows the gate against one that
flies straight, and bad settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones import cameras
from jaxdrones.envs.tasks.gate import GATE_OPENING_HALF_X


@pytest.fixture(scope="module")
def env():
    """The env ``jaxdrones train fly_thru_gate --vision depth`` trains in."""
    from jaxdrones.training.recipes import recipe

    env = jd.make("fly_thru_gate", **recipe("fly_thru_gate", "cpu", {"vision": ("depth",)}).env)
    assert env.config.gate_pose == "random" and env.config.image_size == (64, 48)
    return env


def at(state, local):
    """``state`` with the drone at ``local`` (the gate's frame: x along the architrave, y across, z up), at rest."""
    pos = state.task.data["gate_pos"] + state.task.data["gate_rot"] @ jnp.asarray(local, jnp.float32)
    return state.replace(sim=state.sim.replace(pos=pos[None], vel=jnp.zeros((1, 3))))


def test_the_gate_is_drawn_per_episode_and_only_the_camera_sees_it(env):
    assert type(env.task).__name__ == "GatePass" and env.observation_size == 21  # the kinematic state alone
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 8))
    gate = np.asarray(states.task.data["gate_pos"])
    lo, hi = env.config.gate_distance
    assert np.all((gate[:, 0] >= lo) & (gate[:, 0] <= hi)) and np.all(np.abs(gate[:, 1]) <= env.config.gate_offset)
    assert len(np.unique(gate[:, 0])) == 8  # every world its own gate
    boxes = np.asarray(states.task.scene.box.pos)  # the columns and the architrave, in the gate's frame
    local = np.einsum("wni,wij->wnj", boxes - gate[:, None], np.asarray(states.task.data["gate_rot"]))
    np.testing.assert_allclose(local[0], [[-0.3, 0.0, 0.245], [0.3, 0.0, 0.245], [0.0, 0.0, 0.55]], atol=1e-6)
    seg = cameras.render(
        cameras.CameraSpec(), states.task.scene, env.params, states.sim.pos, states.sim.quat, kinds=("seg",)
    )["seg"]
    assert all(
        np.isin([1, 2, 3], np.asarray(seg[w])).all() for w in range(8)
    )  # each world's camera sees its gate (64 × 48)


def test_passing_missing_and_hitting_the_gate(env):
    state = jax.jit(env.reset)(jax.random.key(1))
    step = jax.jit(env.step)
    hold = jnp.zeros((1, 3))
    before = step(at(state, [0.0, 0.5, 0.25]), hold)
    assert not bool(before.terminated) and float(before.metrics["failure"]) == 1.0
    through = step(at(state, [0.0, -0.05, 0.25]), hold)  # just beyond the plane, inside the opening
    assert bool(through.terminated) and float(through.metrics["failure"]) == 0.0
    assert float(through.metrics["crash"]) == 0.0 and float(through.reward[0]) > 5.0  # reached, weight 10
    missed = step(at(state, [GATE_OPENING_HALF_X + 0.3, -0.05, 0.25]), hold)  # beyond, beside the column
    assert bool(missed.terminated) and float(missed.metrics["missed"]) == 1.0
    assert float(missed.metrics["failure"]) == 1.0 and float(missed.reward[0]) < -5.0
    hit = step(at(state, [0.3, 0.03, 0.25]), hold)  # in the column's face
    assert bool(hit.terminated) and float(hit.metrics["collision"]) == 1.0 and float(hit.metrics["failure"]) == 1.0


def fly(env, policy: str, n: int = 64) -> float:
    """Success rate of ``n`` episodes of a policy that knows the gate (an approach point 0.4 m before the opening,
    then through it) or flies straight ahead."""

    def episode(key):
        def body(state, _):
            if policy == "knows":
                local = (state.sim.pos - state.task.data["gate_pos"][None]) @ state.task.data["gate_rot"]
                before = state.task.data["gate_pos"] + state.task.data["gate_rot"] @ jnp.asarray([0.0, 0.4, 0.25])
                aim = jnp.where(local[:, 1:2] > 0.45, before, state.task.target)
                d = aim - state.sim.pos
            else:
                d = jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0]), state.sim.pos.shape)
            action = d / jnp.maximum(jnp.max(jnp.abs(d), -1, keepdims=True), 1e-6)
            done = state.terminated | state.truncated
            return jax.tree.map(lambda a, b: jnp.where(done, a, b), state, env.step(state, action)), None

        return jax.lax.scan(body, env.reset(key), None, length=env.episode_length)[0].metrics["failure"]

    return 1.0 - float(jnp.mean(jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(2), n))))


def test_the_image_carries_what_the_policy_needs(env):
    """Knowing the gate's pose, every episode passes; flying straight, with the gate unseen, about half do (the
    gate's offset and yaw put its columns in the way)."""
    assert fly(env, "knows") >= 0.95
    assert fly(env, "straight") <= 0.7


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(gate_pose="moving"), "gate_pose"),
        (dict(gate_pose="random", backend="pybullet", vision=("depth",)), "backend='jax'"),
        (dict(gate_pose="random"), "vision"),
        (dict(gate_pose="random", vision=("depth",), gate_distance=(0.5, 2.0)), "gate_distance"),
        (dict(gate_pose="random", vision=("depth",), gate_yaw=-0.1), "gate_yaw"),
    ],
)
def test_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jd.make("fly_thru_gate", **kwargs)
