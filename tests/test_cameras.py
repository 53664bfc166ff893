"""The JAX cameras (`jaxdrones.cameras`): hand-derived images, the PyBullet backend's cameras on shared scenes,
batching, gradients against finite differences, and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

import jaxdrones as jd
from jaxdrones import cameras
from jaxdrones.envs.observations import DEPTH_SCALE, policy_input
from jaxdrones.scene import Obstacle
from jaxdrones.sensors import raycast

PARAMS = jd.load_params("cf2x")
LEVEL = [[0.0, 0.0, 0.0]]


def pose(pos, rpy, dtype=np.float32):
    config = jd.SimConfig(n_drones=len(pos))
    state = jd.init_state(config, pos=np.asarray(pos, np.float64), rpy=np.asarray(rpy, np.float64))
    return jnp.asarray(state.pos, dtype), jnp.asarray(state.quat, dtype)


def render(obstacles, pos, rpy, spec=cameras.CameraSpec(), **kwargs):
    return jax.jit(lambda p, q: cameras.render(spec, cameras.make_scene(obstacles), PARAMS, p, q, **kwargs))(
        *pose(pos, rpy)
    )


def test_hand_derived_box_ground_and_sky():
    """A level drone 1 m up, a 0.5 m cube 2 m ahead: the centre pixels see its face at 2 − 0.25 − eye offset, the
    ground and sky split at the horizon, and row r of the ground lies at depth 1 / ((r + ½ − H/2) / f)."""
    box = Obstacle("box", size=(0.5, 0.5, 0.5), pos=(2.0, 0.0, 1.0), rgba=(1.0, 0.0, 0.0, 1.0))
    spec = cameras.CameraSpec()
    img = render([box], [[0.0, 0.0, 1.0]], LEVEL)
    eye = float(PARAMS.collision_radius) + cameras.EYE_MARGIN
    face = 2.0 - 0.25 - eye
    assert img["depth"].shape == (1, 48, 64) and img["seg"].dtype == jnp.int32 and img["rgb"].shape == (1, 48, 64, 3)
    depth, seg = np.asarray(img["depth"][0]), np.asarray(img["seg"][0])
    np.testing.assert_allclose(depth[23:25, 31:33], face, rtol=1e-6)
    # The face covers the pixels whose centre ray meets the 0.5 m square at that depth (pinhole model).
    f = spec.focal
    right = (np.arange(64) + 0.5 - 32) * face / f
    up = (24 - np.arange(48) - 0.5) * face / f
    expected = (np.abs(up)[:, None] <= 0.25) & (np.abs(right)[None, :] <= 0.25)
    np.testing.assert_array_equal(seg == 1, expected)
    ground_rows = np.arange(24, 48)
    np.testing.assert_allclose(depth[ground_rows, 0], 1.0 / ((ground_rows + 0.5 - 24) / f), rtol=1e-5)
    assert np.all(seg[:24, 0] == -1) and np.all(depth[:24, 0] == spec.far) and np.all(seg[24:, 0] == 0)
    rgb = np.asarray(img["rgb"][0])
    assert rgb[24, 32, 0] > 50 and rgb[24, 32, 1] == 0 and np.all(rgb[0, 0] == 0)  # red face, black sky


def test_near_plane_and_own_body():
    """Geometry nearer than the near plane is clipped, and a drone never sees its own plate or propellers even
    looking down its own body."""
    spec = cameras.CameraSpec(mount_pos=(0.0, 0.0, 0.1), mount_rpy=(0.0, np.pi / 2, 0.0))  # looks down
    img = render([], [[0.0, 0.0, 1.0]], LEVEL, spec=spec)
    assert np.all(np.asarray(img["seg"]) == 0)  # only the ground, never drone 1 (its own id)
    np.testing.assert_allclose(np.asarray(img["depth"])[0, 23:25, 31:33], 1.1, rtol=1e-5)
    clipped = render(
        [Obstacle("box", size=(0.2, 0.2, 0.2), pos=(0.1, 0.0, 1.0))],
        [[0.0, 0.0, 1.0]],
        LEVEL,
        spec=cameras.CameraSpec(near=0.5),
    )
    assert not np.any(np.asarray(clipped["seg"]) == 1)


def _cross_scenes():
    gate = [Obstacle("box", size=(0.05, 0.05, 0.5), pos=(x, -1.0, 0.25)) for x in (-0.3, 0.3)]
    gate.append(Obstacle("box", size=(0.65, 0.05, 0.05), pos=(0.0, -1.0, 0.525)))
    return {
        "box and sphere": (
            [
                Obstacle("box", size=(0.4, 0.3, 0.6), pos=(1.5, 0.2, 0.8), rpy=(0, 0, 0.4)),
                Obstacle("sphere", size=(0.25,), pos=(1.2, -0.6, 1.1)),
            ],
            [[0, 0, 1.0]],
            LEVEL,
        ),
        "cylinder and capsule, tilted drone": (
            [
                Obstacle("cylinder", size=(0.2, 1.0), pos=(1.4, 0.4, 0.7), rpy=(0.3, 0, 0)),
                Obstacle("capsule", size=(0.15, 0.6), pos=(1.0, -0.5, 1.0), rpy=(0, 1.2, 0.3)),
            ],
            [[0, 0, 1.0]],
            [[0.2, -0.25, 0.1]],
        ),
        "three drones": (
            [],
            [[0, 0, 1.0], [0.6, 0.05, 1.02], [0.9, -0.2, 0.95]],
            [[0, 0, 0], [0.1, 0.2, 2.0], [0, 0, 3.0]],
        ),
        "the paper's gate": (gate, [[0, 0, 0.4]], [[0, 0, -np.pi / 2]]),
        "every shape, two tilted drones": (
            [
                Obstacle("box", size=(0.3, 0.3, 0.3), pos=(1.0, 0.0, 0.3)),
                Obstacle("cylinder", size=(0.1, 0.8), pos=(-1.0, 0.3, 0.4)),
                Obstacle("sphere", size=(0.2,), pos=(0.1, 1.2, 0.6)),
                Obstacle("capsule", size=(0.1, 0.5), pos=(0.0, -1.2, 0.5), rpy=(1.5, 0, 0)),
            ],
            [[0, 0, 0.6], [0.2, 0.3, 0.7]],
            [[0, 0.35, 0.2], [-0.3, 0.1, 1.8]],
        ),
    }


@pytest.mark.slow
@pytest.mark.pybullet
@pytest.mark.parametrize("name", list(_cross_scenes()))
def test_matches_the_pybullet_backend(name):
    """Against the PyBullet backend's onboard cameras (EGL renderer, which samples pixel centres as the pinhole
    model does): segmentation ids equal on ≥ 99 % of pixels, the differences only at silhouette edges (a pixel
    whose 3 × 3 neighbourhood sees one id in both images always agrees); depth within 1 cm away from edges on flat
    surfaces (boxes, the drones' plates and the ground up to 5 m), and within 3 cm on spheres, cylinders and
    capsules, which Bullet draws as tessellated meshes lying inside the true surface (measured: 2.7 cm on a
    0.25 m sphere, 8 mm on cylinders and capsules)."""
    obstacles, pos, rpy = _cross_scenes()[name]
    config = jd.SimConfig(n_drones=len(pos))
    state = jax.tree.map(np.asarray, jd.init_state(config, pos=np.asarray(pos, float), rpy=np.asarray(rpy, float)))
    with jd.make_step(config, backend="pybullet", obstacles=obstacles, renderer="egl") as step:
        ref = step.camera_images(PARAMS, state)
        ids = step.body_ids()
    ours = {
        -1: -1,
        ids["ground"]: 0,
        **{b: k + 1 for k, b in enumerate(ids["obstacles"])},
        **{b: len(obstacles) + 1 + d for d, b in enumerate(ids["drones"])},
    }
    ref_seg = np.vectorize(lambda v: ours[int(v)])(ref["seg"])
    img = render(obstacles, pos, rpy)
    seg, depth = np.asarray(img["seg"]), np.asarray(img["depth"])
    for d in range(len(pos)):
        same = seg[d] == ref_seg[d]
        assert same.mean() >= 0.99, (d, same.mean())
        interior = (minimum_filter(seg[d], 3) == maximum_filter(seg[d], 3)) & (
            minimum_filter(ref_seg[d], 3) == maximum_filter(ref_seg[d], 3)
        )
        assert np.all(same[interior])
        curved = [k + 1 for k, o in enumerate(obstacles) if o.shape != "box"]
        hit = interior & same & (seg[d] >= 0)
        err = np.abs(depth[d] - ref["depth"][d])
        flat = hit & ~np.isin(seg[d], curved) & (depth[d] < 5.0)
        assert flat.sum() > 100 and err[flat].max() < 0.01, err[flat].max()
        if np.any(hit & np.isin(seg[d], curved)):
            assert err[hit & np.isin(seg[d], curved)].max() < 0.03


def test_batched_scenes_and_worlds():
    """A scene per world (the same capacity, other obstacles) under vmap gives each world's unbatched render."""
    a = cameras.make_scene([Obstacle("box", size=(0.3, 0.3, 0.3), pos=(1.0, 0.0, 1.0))], capacity=2)
    b = cameras.make_scene(
        [
            Obstacle("sphere", size=(0.2,), pos=(1.0, 0.2, 1.0)),
            Obstacle("box", size=(0.3, 0.3, 0.3), pos=(1.0, -0.3, 1.0)),
        ],
        capacity=2,
    )
    both = jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)
    p, q = pose([[0, 0, 1.0], [0.3, 0.0, 1.0]], [[0, 0, 0], [0, 0.1, 0]])
    spec = cameras.CameraSpec(width=32, height=24)
    batched = jax.jit(jax.vmap(lambda s, p, q: cameras.render(spec, s, PARAMS, p, q)))(
        both, jnp.stack([p, p + 0.1]), jnp.stack([q, q])
    )
    for w, (scene, shift) in enumerate(((a, 0.0), (b, 0.1))):
        single = cameras.render(spec, scene, PARAMS, p + shift, q)
        np.testing.assert_allclose(np.asarray(batched["depth"][w]), np.asarray(single["depth"]), rtol=1e-5)
        for k in ("seg", "rgb"):
            np.testing.assert_array_equal(np.asarray(batched[k][w]), np.asarray(single[k]))
    assert {1, 2} <= set(np.unique(np.asarray(batched["seg"][1])))  # world 1 sees its sphere and its box


def test_depth_gradient_matches_finite_differences(x64):
    """d depth / d (drone position, obstacle position) in float64, away from silhouette edges, against central
    differences."""
    spec = cameras.CameraSpec(width=16, height=12)
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), PARAMS)
    p0, q0 = pose([[0.0, 0.0, 1.0]], [[0.05, -0.1, 0.2]], np.float64)
    weights = jnp.asarray(np.random.default_rng(0).uniform(size=(1, 12, 16)))

    @jax.jit
    def loss(shift, centre):
        obstacles = [
            Obstacle("box", size=(0.5, 0.6, 0.7), pos=(2.0, 0.1, 1.0), rpy=(0.1, 0.2, 0.3)),
            Obstacle("sphere", size=(0.2,), pos=(1.2, -0.5, 1.2)),
            Obstacle("cylinder", size=(0.15, 0.8), pos=(1.5, 0.6, 0.8), rpy=(0.4, 0.0, 0.0)),
            Obstacle("capsule", size=(0.1, 0.4), pos=(1.0, 0.0, 0.3), rpy=(0.0, 1.4, 0.0)),
        ]
        scene = cameras.make_scene(obstacles, dtype=jnp.float64)
        scene = scene.replace(box=scene.box.replace(pos=scene.box.pos.at[0].set(centre)))
        depth = cameras.render(spec, scene, params, p0 + shift[None], q0, kinds=("depth",))["depth"]
        return jnp.sum(jnp.where(depth < spec.far, depth, 0.0) * weights)

    shift, centre = jnp.zeros(3), jnp.asarray([2.0, 0.1, 1.0])
    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(shift, centre)
    h = 1e-6
    for arg, g in zip((0, 1), grads, strict=True):
        for i in range(3):
            e = jnp.zeros(3).at[i].set(h)
            args_p = [shift, centre]
            args_m = [shift, centre]
            args_p[arg], args_m[arg] = args_p[arg] + e, args_m[arg] - e
            fd = (loss(*args_p) - loss(*args_m)) / (2 * h)
            np.testing.assert_allclose(g[i], fd, rtol=1e-5, atol=1e-6)
    assert np.all(np.abs(np.asarray(grads[1])) > 0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"width": 0}, "width"),
        ({"height": 9000}, "height"),
        ({"fov": 0.0}, "fov"),
        ({"fov": 180.0}, "fov"),
        ({"near": 2.0, "far": 1.0}, "near"),
        ({"far": -1.0}, "far"),
        ({"mount_pos": (0.0, 1.0)}, "mount_pos"),
    ],
)
def test_bad_camera_spec(kwargs, match):
    with pytest.raises(ValueError, match=match):
        cameras.CameraSpec(**kwargs)


def test_bad_scene_and_input():
    with pytest.raises(ValueError, match="URDF mesh.*backend='pybullet'"):
        cameras.make_scene([Obstacle("urdf", urdf="duck_vhacd.urdf")])
    with pytest.raises(ValueError, match="more than its capacity"):
        cameras.make_scene([Obstacle("box")] * 3, capacity=2)
    scene = cameras.make_scene([])
    p, q = pose([[0, 0, 1.0]], LEVEL)
    with pytest.raises(ValueError, match="kinds"):
        cameras.render(cameras.CameraSpec(), scene, PARAMS, p, q, kinds=("normals",))
    with pytest.raises(ValueError, match=r"pos f\[..., D, 3\]"):
        cameras.render(cameras.CameraSpec(), scene, PARAMS, p[..., :2], q)


@pytest.mark.slow
@pytest.mark.pybullet
@pytest.mark.parametrize("fov", [60.0, 100.0])
def test_env_images_match_across_backends(fov):
    """The same task and options on both backends (the gate of fly_thru_gate, a tilted start; the paper's field of
    view and a wider one) give the same images: segmentation ids on ≥ 99 % of pixels, depth within 1 cm on the
    gate's boxes away from their edges."""
    states = {}
    for backend in ("jax", "pybullet"):
        extra = {"renderer": "egl"} if backend == "pybullet" else {}
        env = jd.make(
            "fly_thru_gate",
            backend=backend,
            vision=("depth", "seg"),
            init_pos=[[0.05, -0.45, 0.45]],
            init_rpy=[[0.1, -0.05, -1.5]],
            camera_fov=fov,
            **extra,
        )
        states[backend] = env.reset(jax.random.key(0)).obs
        env.close()
    seg_j, seg_p = np.asarray(states["jax"]["seg"][0]), np.asarray(states["pybullet"]["seg"][0])
    assert (seg_j == seg_p).mean() >= 0.99 and set(np.unique(seg_j)) >= {0, 1, 2, 3}
    interior = (minimum_filter(seg_j, 3) == maximum_filter(seg_j, 3)) & (seg_j >= 1) & (seg_j == seg_p)
    depth_j, depth_p = np.asarray(states["jax"]["depth"][0]), np.asarray(states["pybullet"]["depth"][0])
    assert interior.sum() > 20 and np.abs(depth_j - depth_p)[interior].max() < 0.01


def test_env_vision_on_the_jax_backend_is_batched_and_held_between_captures():
    """vision on the JAX backend: a dict observation of the stacked shapes, rendered under jit(vmap), held between
    two captures (camera_freq below ctrl_freq) and depth differentiable w.r.t. the drone's state."""
    env = jd.make("fly_thru_gate", vision=("rgb", "depth", "seg"), ctrl_freq=30, camera_freq=10, image_size=(32, 24))
    assert env.config.camera_period == 3
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    state = reset(jax.random.split(jax.random.key(0), 4))
    assert state.obs["rgb"].shape == (4, 1, 24, 32, 4) and state.obs["depth"].dtype == jnp.float32
    assert np.all(np.asarray(state.obs["rgb"][..., 3]) == 255)
    first = state.obs["depth"]
    up = jnp.ones((4, 1, 4)) * 0.3
    state = step(state, up)
    np.testing.assert_array_equal(np.asarray(state.obs["depth"]), np.asarray(first))  # held
    state = step(step(state, up), up)  # step 3: a capture
    assert not np.array_equal(np.asarray(state.obs["depth"]), np.asarray(first))

    def mean_depth(z):
        sim = state.sim.replace(pos=state.sim.pos.at[..., 2].add(z))
        return jnp.mean(env._render(state.task.scene, state.params, sim, jnp.ones((4,), bool), state.obs)["depth"])

    slope = jax.jit(jax.grad(mean_depth))(0.0)
    assert np.isfinite(slope) and slope != 0.0


def test_frame_stack_holds_the_last_captures_oldest_first():
    """``frame_stack=3``: each image gains a frame axis holding the last 3 captures, oldest first, the reset's
    capture repeated until 3 have been taken: the frames are those of the same env without a stack, one capture
    period apart; `policy_input` puts the drones then their frames along the channels; the gymnasium space has the
    frame axis."""
    kwargs = dict(vision=("rgb", "depth"), ctrl_freq=30, camera_freq=15, image_size=(16, 12), n_drones=2)
    plain, stacked = jd.make("multi_hover", **kwargs), jd.make("multi_hover", frame_stack=3, **kwargs)
    assert stacked.observation_spec["depth"].shape == (2, 3, 12, 16)
    assert stacked.observation_spec["rgb"].shape == (2, 3, 12, 16, 4)
    key = jax.random.key(0)
    a, b = jax.jit(plain.reset)(key), jax.jit(stacked.reset)(key)
    for k in range(3):  # the reset's capture, three times
        np.testing.assert_array_equal(np.asarray(b.obs["depth"][:, k]), np.asarray(a.obs["depth"]))
    captures = [a.obs]
    step_a, step_b = jax.jit(plain.step), jax.jit(stacked.step)
    turn = jnp.tile(jnp.asarray([[0.2, 0.1, 0.3, -0.5]]), (2, 1))
    for t in range(1, 7):
        a, b = step_a(a, turn), step_b(b, turn)
        if t % 2 == 0:
            captures.append(a.obs)
        expected = ([captures[0]] * 3 + captures[1:])[-3:]  # the last three captures, oldest first
        for name in ("depth", "rgb"):
            np.testing.assert_array_equal(
                np.asarray(b.obs[name]), np.stack([np.asarray(c[name]) for c in expected], axis=1)
            )
    assert len({np.asarray(c["depth"]).tobytes() for c in captures}) == len(captures)  # every capture new
    seen = policy_input(b.obs)
    assert seen["pixels/depth"].shape == (12, 16, 6) and seen["pixels/rgb"].shape == (12, 16, 18)
    np.testing.assert_allclose(
        np.asarray(seen["pixels/depth"][..., 4]),  # drone 1, frame 1
        np.clip(np.asarray(b.obs["depth"][1, 1]) / DEPTH_SCALE, 0, 1),
        rtol=1e-6,
    )
    import gymnasium as gym

    env = gym.make("jaxdrones/Hover-v0", vision=("depth",), frame_stack=4, image_size=(16, 12))
    obs, _ = env.reset(seed=0)
    assert obs["depth"].shape == (4, 12, 16) and env.observation_space.contains(obs)
    env.close()


def test_scenes_larger_than_one_step_trace_as_unrolled(monkeypatch):
    """A scene of 10 primitives (scanned `SLOTS_PER_STEP` = 2 slots at a time: boxes and spheres in two steps, one
    padded) and two drones per world gives the images of every slot traced at once, and without RGB (packed keys) the
    same; the drones see each other (ids 11 and 12) but not themselves."""
    monkeypatch.setattr(raycast, "SLOTS_PER_STEP", 2)
    rng = np.random.default_rng(0)
    obstacles = [
        Obstacle(
            ("box", "sphere", "cylinder", "capsule")[k % 4],
            size=(0.2, 0.3, 0.4) if k % 4 == 0 else (0.2,) if k % 4 == 1 else (0.1, 0.5),
            pos=(float(rng.uniform(0.8, 3)), float(rng.uniform(-2, 2)), float(rng.uniform(0.2, 1.5))),
            rpy=tuple(float(a) for a in rng.uniform(-0.5, 0.5, 3)),
        )
        for k in range(10)
    ]
    scene = cameras.make_scene(obstacles)
    p, q = pose([[0.0, 0.0, 1.0], [0.6, 0.05, 0.92]], [[0.0, 0.0, 0.0], [0.0, 0.0, np.pi]])
    spec = cameras.CameraSpec(width=32, height=24)
    scanned = jax.jit(lambda p, q: cameras.render(spec, scene, PARAMS, p, q))(p, q)
    monkeypatch.setattr(raycast, "SLOTS_PER_STEP", 100)
    unrolled = jax.jit(lambda p, q: cameras.render(spec, scene, PARAMS, p, q))(p, q)
    np.testing.assert_allclose(np.asarray(scanned["depth"]), np.asarray(unrolled["depth"]), rtol=1e-5)
    for k in ("seg", "rgb"):  # compiled apart, float rounding may differ, never what a pixel sees
        np.testing.assert_array_equal(np.asarray(scanned[k]), np.asarray(unrolled[k]))
    seg = np.asarray(scanned["seg"])
    assert 12 in seg[0] and 11 in seg[1] and 11 not in seg[0] and 12 not in seg[1]
    # Without RGB, the nearest hits as packed keys: the same ids, depth rounded by less than 2^(b − 24) of itself
    # for 10 + 2 × 5 primitives, the ground and "nothing" (b = 5 bits for the slots).
    packed = jax.jit(lambda p, q: cameras.render(spec, scene, PARAMS, p, q, kinds=("depth", "seg")))(p, q)
    np.testing.assert_array_equal(np.asarray(packed["seg"]), seg)
    packed_depth, depth = np.asarray(packed["depth"]), np.asarray(unrolled["depth"])
    # Two programs, each with its own float32 rounding of the hits (3.8e-5 relative seen in 4 of 1536 pixels on jax
    # 0.12 with LLVM's optimisation level 0): the bound holds for nearly every pixel, the rounding for all.
    assert np.isclose(packed_depth, depth, rtol=2.0 ** (5 - 24), atol=0).mean() > 0.99
    np.testing.assert_allclose(packed_depth, depth, rtol=1e-4)
    assert np.any(packed_depth != depth)  # it is the packed path
