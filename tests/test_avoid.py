"""The ``avoid`` task: obstacles drawn per episode in the task params, collisions from the scene's distance
function, its success metric, its policy input and bad settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrones as jd
from jaxdrones import cameras
from jaxdrones.envs.observations import DEPTH_SCALE, policy_input
from jaxdrones.scene import Obstacle


def test_distance_is_each_shapes_signed_distance():
    """Hand-derived distances to a box, a sphere, a cylinder and a lying capsule, outside and inside."""
    scene = cameras.make_scene(
        [
            Obstacle("box", size=(1.0, 2.0, 3.0), pos=(5.0, 0.0, 0.0)),
            Obstacle("sphere", size=(0.5,), pos=(0.0, 5.0, 0.0)),
            Obstacle("cylinder", size=(0.2, 2.0), pos=(0.0, 0.0, 5.0)),
            Obstacle("capsule", size=(0.1, 1.0), pos=(-5.0, 0.0, 0.0), rpy=(np.pi / 2, 0.0, 0.0)),
        ]
    )
    points = jnp.array(
        [[3.0, 0, 0], [5, 0, 0], [0, 6, 0], [0, 0.5, 5], [0, 0, 7], [-5, 0, 1.0], [-5, 0.2, 0], [4.0, 2.0, 0.0]]
    )
    expected = [
        1.5,  # to the box's x face at 4.5
        -0.5,  # its centre, 0.5 inside its nearest face
        0.5,
        0.3,  # sphere of radius 0.5; cylinder side, radius 0.2
        1.0,  # above the cylinder's top at z = 6
        0.9,  # 1 m from the capsule's axis (along y after the roll), radius 0.1
        -0.1,  # on its axis
        np.hypot(0.5, 1.0),
    ]  # to the box's edge at (4.5, 1)
    np.testing.assert_allclose(np.asarray(cameras.distance(scene, points)), expected, atol=1e-6)
    empty = cameras.make_scene([], capacity=2)
    assert np.all(np.isinf(np.asarray(cameras.distance(empty, points))))


@pytest.fixture(scope="module")
def env():
    return jd.make("avoid")  # its own camera: a 64 × 16 depth strip, 144° across


def test_avoid_draws_a_field_per_episode_that_only_the_camera_sees(env):
    reset = jax.jit(jax.vmap(env.reset))
    states = reset(jax.random.split(jax.random.key(0), 4))
    scene = states.task.scene
    assert scene.cylinder.pos.shape == (4, 12, 3) and scene.box.pos.shape == (4, 4, 3)
    assert np.all(np.asarray(scene.cylinder.valid)) and np.all(np.asarray(scene.box.valid))
    pos = np.asarray(scene.cylinder.pos)
    assert not np.allclose(pos[0], pos[1])  # every world its own field
    (x_low, x_high), side = env.config.field_x, env.config.field_y
    assert np.all((pos[..., 0] >= x_low) & (pos[..., 0] <= x_high) & (np.abs(pos[..., 1]) <= side))
    again = reset(jax.random.split(jax.random.key(1), 4)).task.scene.cylinder.pos
    assert not np.allclose(np.asarray(again), pos)  # and every episode
    # The state observation is the kinematics and the goal offset only: 21 + 3 entries; the depth image sees the
    # obstacles (ids 1..16; the ground is 0).
    assert states.obs["state"].shape == (4, 1, 24) and states.obs["depth"].shape == (4, 1, 16, 64)
    np.testing.assert_allclose(
        np.asarray(states.obs["state"][:, 0, 21:]),
        np.asarray(states.task.target[:, 0] - states.sim.pos[:, 0]),
        atol=1e-6,
    )
    spec = cameras.CameraSpec(*env.config.image_size, fov=env.config.camera_fov)  # the env's own camera
    seg = cameras.render(spec, scene, env.params, states.sim.pos, states.sim.quat, kinds=("seg",))["seg"]
    assert np.any(np.asarray(seg) >= 1)


def test_collision_terminates_and_the_goal_succeeds(env):
    state = jax.jit(env.reset)(jax.random.key(3))
    step = jax.jit(env.step)
    hold = jnp.zeros((1, 3))
    centre = state.task.scene.cylinder.pos[0]
    inside = state.replace(sim=state.sim.replace(pos=jnp.asarray([[centre[0], centre[1], 1.0]])))
    hit = step(inside, hold)
    assert bool(hit.terminated) and float(hit.metrics["collision"]) == 1.0 and float(hit.metrics["failure"]) == 1.0
    assert float(hit.reward[0]) < -5.0  # the crash term, weight −10
    goal = state.replace(sim=state.sim.replace(pos=state.task.target))
    there = step(goal, hold)  # the episode ends at its goal: terminated, a success, not a crash
    assert bool(there.terminated) and float(there.metrics["failure"]) == 0.0
    assert float(there.metrics["crash"]) == 0.0 and float(there.metrics["collision"]) == 0.0
    assert float(there.reward[0]) > 5.0  # the reached term, weight 10
    near = state.replace(sim=state.sim.replace(pos=state.task.target - jnp.asarray([[0.7, 0.0, 0.0]])))
    assert not bool(step(near, hold).terminated)  # 0.7 m short of the goal (radius 0.5 m): flying on
    side = state.replace(sim=state.sim.replace(pos=jnp.asarray([[0.5, env.config.field_y + 0.7, 1.0]])))
    assert bool(step(side, hold).terminated)  # left the field's side


def test_policy_input_and_the_brax_view(env):
    state = jax.jit(env.reset)(jax.random.key(0))
    seen = policy_input(state.obs)
    assert set(seen) == {"state", "pixels/depth"} and seen["pixels/depth"].shape == (16, 64, 1)
    np.testing.assert_allclose(
        np.asarray(seen["pixels/depth"][..., 0]),
        np.clip(np.asarray(state.obs["depth"][0]) / DEPTH_SCALE, 0, 1),
        rtol=1e-6,
    )
    from jaxdrones.adapters.brax import BraxEnv

    assert BraxEnv(env).observation_size == {"state": (24,), "pixels/depth": (16, 64, 1)}
    rgb = jd.make("avoid", image_size=(32, 24), vision=("rgb", "depth", "seg"))
    seen = policy_input(jax.jit(rgb.reset)(jax.random.key(0)).obs)
    assert set(seen) == {"state", "pixels/depth", "pixels/rgb"} and seen["pixels/rgb"].shape == (24, 32, 3)
    assert float(seen["pixels/rgb"].max()) <= 1.0


def test_flying_straight_at_the_goal_mostly_fails(env):
    """A policy that cannot see, flying straight at the goal, reaches it in about a sixth of the episodes (15 % of
    these 128; the rest collide): a policy that does better reads its depth image."""

    def episode(key):
        def body(state, _):
            d = state.task.target - state.sim.pos
            action = d / jnp.max(jnp.abs(d), -1, keepdims=True)
            done = state.terminated | state.truncated
            return jax.tree.map(lambda a, b: jnp.where(done, a, b), state, env.step(state, action)), None

        return jax.lax.scan(body, env.reset(key), None, length=env.episode_length)[0].metrics

    metrics = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(2), 128))
    success, collided = 1 - float(jnp.mean(metrics["failure"])), float(jnp.mean(metrics["collision"]))
    assert 0.05 <= success <= 0.35 and collided >= 0.6, (success, collided)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(backend="pybullet"), "backend='jax'"),
        (dict(field_x=(0.1, 3.0)), "clear"),
        (dict(field_x=(4.0, 1.0)), "low <= high"),
        (dict(n_cylinders=-1), "n_cylinders"),
        (dict(goal_radius=float("nan")), "goal_radius"),
    ],
)
def test_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jd.make("avoid", **kwargs)


def test_brax_vision_networks_act_on_the_camera_observation(env):
    """The trainer's networks for an env with cameras (brax's vision PPO networks with the config's CNN): a policy
    of freshly initialised parameters acts on `policy_input` of the env's dict observation, as the evaluation
    runs it (`jaxdrones.training.evaluation.act`)."""
    from brax.training.acme import running_statistics

    from jaxdrones.training import brax_ppo
    from jaxdrones.training.evaluation import act
    from jaxdrones.training.recipes import recipe

    config = recipe("avoid", "cpu").config
    networks = brax_ppo.make_network(config, env)
    state = jax.jit(env.reset)(jax.random.key(0))
    seen = policy_input(state.obs)
    normalizer = running_statistics.init_state({"state": jax.ShapeDtypeStruct(seen["state"].shape, jnp.float32)})
    params = (
        normalizer,
        networks.policy_network.init(jax.random.key(1)),
        networks.value_network.init(jax.random.key(2)),
    )
    conv = [k for k in params[1]["params"] if "CNN" in k or "Conv" in k]
    assert conv, sorted(params[1]["params"])  # the image goes through convolutions
    policy = brax_ppo.make_policy(networks, params)
    action = jax.jit(lambda o, k: act(env, policy, o, k))(state.obs, jax.random.key(3))
    assert action.shape == (1, 3) and np.all(np.isfinite(np.asarray(action)))
    assert np.all(np.abs(np.asarray(action)) <= 1.0)


def test_scene_clearances_map_the_obstacles_around_the_drone(env):
    """The privileged observation: the clearance at the drone and at 16 bearings × 5 distances around it (and at
    avoid's own 8 × 3), hand-derived for one cylinder 1 m ahead."""
    from jaxdrones.envs.tasks.avoid import scene_clearances

    bearings, distances = 16, (0.25, 0.5, 0.75, 1.0, 1.5)

    state = jax.jit(env.reset)(jax.random.key(0))
    scene = cameras.make_scene(
        [Obstacle("cylinder", size=(0.1, 4.0), pos=(1.0, 0.0, 2.0))], capacity={"cylinder": 12, "box": 4}
    )
    task = state.task.replace(scene=scene)
    sim = state.sim.replace(pos=jnp.asarray([[0.0, 0.0, 1.0]]))
    radius = float(task.data["collision_radius"][0])
    got = np.asarray(scene_clearances(task, sim, bearings, distances))
    assert got.shape == (1, 1 + bearings * len(distances))
    np.testing.assert_allclose(got[0, 0], 1.0 - 0.1 - radius, atol=1e-6)  # at the drone: 0.9 m to the surface
    ahead = got[0, 1:].reshape(bearings, len(distances))[0]  # bearing 0, along +x
    expected = np.clip([abs(1.0 - r) - 0.1 - radius for r in distances], -1, 1)
    np.testing.assert_allclose(ahead, expected, atol=1e-6)
    behind = got[0, 1:].reshape(bearings, len(distances))[8]  # bearing π: 1 + r from the axis
    np.testing.assert_allclose(behind, np.clip([1.0 + r - 0.1 - radius for r in distances], -1, 1), atol=1e-6)
    # avoid's critic reads 8 bearings × 0.25, 0.5, 1 m: the same map at those points.
    own = np.asarray(env.privileged(state.replace(task=task, sim=sim)))
    assert (env.task.clearance_bearings, env.task.clearance_ranges) == (8, (0.25, 0.5, 1.0))
    coarse = got[0, 1:].reshape(bearings, len(distances))[::2][:, [0, 1, 3]]  # every other bearing, those distances
    np.testing.assert_allclose(own, np.concatenate([got[:, :1], coarse.reshape(1, -1)], axis=1), atol=1e-6)


def test_the_brax_view_with_a_privileged_critic(env):
    """``BraxEnv(privileged=True)`` adds the task's privileged observation; the asymmetric critic reads it and the
    state, not the image, and the policy reads the image and the state, not it."""
    from brax.training.acme import running_statistics

    from jaxdrones.adapters.brax import BraxEnv
    from jaxdrones.training.encoders import make_ppo_networks_vision

    brax_env = BraxEnv(env, privileged=True)
    assert brax_env.observation_size == {"state": (24,), "pixels/depth": (16, 64, 1), "privileged_state": (25,)}
    state = jax.jit(brax_env.reset)(jax.random.key(0))
    np.testing.assert_allclose(
        np.asarray(state.obs["privileged_state"]), np.asarray(env.privileged(state.pipeline_state)).reshape(-1)
    )
    stepped = jax.jit(brax_env.step)(state, jnp.zeros(3))
    np.testing.assert_allclose(
        np.asarray(stepped.obs["privileged_state"]), np.asarray(env.privileged(stepped.pipeline_state)).reshape(-1)
    )
    nets = make_ppo_networks_vision(
        brax_env.observation_size, 3, running_statistics.normalize, value_obs_key="privileged_state"
    )
    stats = running_statistics.init_state(
        {k: jax.ShapeDtypeStruct(v, jnp.float32) for k, v in brax_env.observation_size.items() if k[:7] != "pixels/"}
    )
    value = jax.jit(nets.value_network.init)(jax.random.key(1))  # jitted: one program, not one per operation
    assert not [k for k in value["params"] if "CNN" in k]  # no convolutions in the critic
    policy = jax.jit(nets.policy_network.init)(jax.random.key(2))
    obs = state.obs
    blank = {**obs, "pixels/depth": jnp.zeros_like(obs["pixels/depth"])}
    moved = {**obs, "privileged_state": obs["privileged_state"] + 1.0}
    value_apply, policy_apply = jax.jit(nets.value_network.apply), jax.jit(nets.policy_network.apply)
    v = lambda o: float(value_apply(stats, value, o))
    p = lambda o: np.asarray(policy_apply(stats, policy, o))
    assert v(blank) == v(obs) and v(moved) != v(obs)
    assert not np.allclose(p(blank), p(obs)) and np.array_equal(p(moved), p(obs))
    # The trainer's config: the asymmetric critic where the env has a privileged observation, the usual one elsewhere.
    from jaxdrones.training import brax_ppo
    from jaxdrones.training.recipes import recipe

    config = recipe("avoid", "cpu").config
    assert config.privileged_critic
    value = jax.eval_shape(brax_ppo.make_network(config, env).value_network.init, jax.random.key(0))
    assert not [k for k in value["params"] if "CNN" in k]
    hover = jd.make("hover", vision=("depth",), image_size=(32, 24))
    value = jax.eval_shape(brax_ppo.make_network(config, hover).value_network.init, jax.random.key(0))
    assert [k for k in value["params"] if "CNN" in k]
    with pytest.raises(ValueError, match="value_obs_key 'privileged_state' is not a key"):
        make_ppo_networks_vision(BraxEnv(env).observation_size, 3, value_obs_key="privileged_state")
    with pytest.raises(ValueError, match="privileged"):
        BraxEnv(jd.make("hover"), privileged=True)  # no camera
    with pytest.raises(ValueError, match="privileged"):
        BraxEnv(jd.make("hover", vision=("depth",), image_size=(32, 24)), privileged=True)  # no privileged obs
