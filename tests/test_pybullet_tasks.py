"""The tasks on the PyBullet backend: the PID circle and a trained hover policy give the same results as on the JAX
backend, vision observations (rendered every k control steps, held in between) and ``jaxdrones fly --backend
pybullet`` with its video.

Measured (float32): the circle (4 drones, 4 s, among the example's obstacles) tracks with RMS errors 0.87 / 0.75 cm
(way-point / cross-track) on JAX and 1.01 / 0.87 cm on PyBullet. The two flights agree to 1e-7 m over the first
10 control steps (in float64, to 1e-11 m over the first second); after that the closed loop itself amplifies
rounding: on the JAX backend alone, moving the start by 1e-12 m (float64) changes the positions by 5.6 mm at 2 s.
So the tolerances are on the RMS errors: 3 mm apart overall, 5 mm per drone.
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from optional import needs

needs("pybullet")
pytestmark = pytest.mark.pybullet

import jaxdrones as jd  # noqa: E402
from jaxdrones.cameras import EYE_MARGIN  # noqa: E402
from jaxdrones.cli import main  # noqa: E402
from jaxdrones.envs.observations import kinematic_obs  # noqa: E402
from jaxdrones.examples import circle  # noqa: E402
from jaxdrones.io.runs import MARKER  # noqa: E402
from jaxdrones.scene import Obstacle  # noqa: E402

#: How far apart the RMS tracking errors of the two backends may be, overall and per drone, m. The two float32
#: flights agree to 1e-6 m for their first 10 steps, then the closed loop amplifies the engines' different round-off
#: (they differ by 1e-4 m after about 30 steps and up to 2 cm later): per-drone RMS errors of about 1 cm were seen
#: to differ by up to 6.4 mm, the overall ones by up to 2.4 mm.
CIRCLE_RMS_TOLERANCE_M = 0.004
CIRCLE_RMS_PER_DRONE_TOLERANCE_M = 0.008
#: How far apart the two backends' mean hover errors over the last second may be, m.
HOVER_TOLERANCE_M = 0.003


# ------------------------------------------------------------------------------------------------------------------
# (a) The PID circle on both backends
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def circles():
    """The 4-drone circle for 4 s on JAX, and on PyBullet among the example's obstacles."""
    return {
        "jax": circle.fly_circle(num_drones=4, duration_s=4.0),
        "pybullet": circle.fly_circle(num_drones=4, duration_s=4.0, backend="pybullet", obstacles=True),
    }


def test_circle_tracks_alike_on_both_backends(circles):
    jx, pb = circles["jax"], circles["pybullet"]
    print(
        f"\nMEASURED circle, 4 drones, 4 s: waypoint RMS jax {jx['metrics']['waypoint_rms_m'] * 100:.2f} cm, "
        f"pybullet among obstacles {pb['metrics']['waypoint_rms_m'] * 100:.2f} cm; cross-track "
        f"{jx['metrics']['cross_track_rms_m'] * 100:.2f} / {pb['metrics']['cross_track_rms_m'] * 100:.2f} cm"
    )
    assert pb["pos"].shape == jx["pos"].shape == (192, 4, 3) and np.all(np.isfinite(pb["pos"]))
    # The same model: step by step, the flights start identical to float32 rounding.
    np.testing.assert_allclose(pb["pos"][:10], jx["pos"][:10], atol=1e-6)
    np.testing.assert_allclose(pb["rpm"][:10], jx["rpm"][:10], rtol=1e-5)
    for name in ("waypoint_rms_m", "cross_track_rms_m"):
        assert pb["metrics"][name] < 0.02 and jx["metrics"][name] < 0.02, (name, pb["metrics"], jx["metrics"])
        assert abs(pb["metrics"][name] - jx["metrics"][name]) < CIRCLE_RMS_TOLERANCE_M, name
    np.testing.assert_allclose(
        pb["metrics"]["waypoint_rms_per_drone_m"],
        jx["metrics"]["waypoint_rms_per_drone_m"],
        atol=CIRCLE_RMS_PER_DRONE_TOLERANCE_M,
    )
    # Among the obstacles, placed around the circle: no drone touches anything.
    contacts = pb["contacts"]
    assert contacts["modelled"] == ["ground", "obstacle", "drone"]
    assert not contacts["collided"] and contacts["first_collision_s"] is None
    assert contacts["obstacle_steps"] == contacts["drone_steps"] == contacts["ground_steps"] == [0] * 4
    assert len(pb["settings"]["obstacles"]) == 4 and pb["settings"]["backend"] == "pybullet"
    assert jx["contacts"]["modelled"] == ["ground"] and not jx["contacts"]["collided"]


def test_circle_reports_collisions():
    """A post on drone 0's path (it passes (-0.145, -0.038) m at t ≈ 0.8 s) is hit, and the contact reported."""
    from jaxdrones.scene import Obstacle

    post = Obstacle("box", size=(0.05, 0.05, 0.2), pos=(-0.145, -0.038, 0.1))
    result = circle.fly_circle(num_drones=2, duration_s=1.5, settle_s=0.0, backend="pybullet", obstacles=[post])
    contacts = result["contacts"]
    assert contacts["collided"] and contacts["obstacle_steps"][0] > 0 and contacts["obstacle_steps"][1] == 0
    assert 0.3 < contacts["first_collision_s"] < 1.0
    assert np.any(result["contact"][:, 0] & 2) and not np.any(result["contact"][:, 1])


def test_circle_backend_options_are_checked():
    with pytest.raises(ValueError, match="unknown backend 'mujoco'"):
        circle.fly_circle(duration_s=1.0, settle_s=0.0, backend="mujoco")
    for option in (dict(obstacles=True), dict(gui=True), dict(video="x.mp4")):
        with pytest.raises(ValueError, match="needs backend='pybullet'"):
            circle.fly_circle(duration_s=1.0, settle_s=0.0, **option)
    with pytest.raises(ValueError, match="ending in one of"):
        circle.fly_circle(duration_s=1.0, settle_s=0.0, backend="pybullet", video="x.avi")
    with pytest.raises(ValueError, match="video_size"):
        circle.fly_circle(duration_s=1.0, settle_s=0.0, backend="pybullet", video="x.mp4", video_size=(0, 10))


# ------------------------------------------------------------------------------------------------------------------
# (b) A trained hover policy runs unchanged on both backends
# ------------------------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_trained_hover_policy_flies_alike_on_both_backends():
    """APG through the JAX env (the paper's 1-D hover, the trainer's hover settings: 0.6 M env steps, about 20 s on
    2 cores), then the same policy from the same 16 start states on the JAX and PyBullet envs.

    Measured: mean distance to the target over the last second 0.42 mm on both backends, at the last step 0.42 mm
    on both. The first control step agrees to 1e-7 m, but a trained policy amplifies any difference (on the JAX env
    alone, moving the start by 1e-6 m can change positions by centimetres within an episode), so the backends are
    compared on the statistics, not episode by episode.
    """
    from jaxdrones.training import rollout_policy, trainers
    from jaxdrones.training.recipes import recipe

    setting = {"action_type": "one_d_rpm", "obs_type": "kin"}  # the paper's 1-D setting
    env_jax = jd.make("hover", **setting)
    apg = trainers.get("apg")
    policy = apg.make_policy(*apg.train(env_jax, recipe("hover", "cpu", setting, "apg").config))
    keys = jax.random.split(jax.random.key(1), 16)
    runs = {}
    with jd.make("hover", action_type="one_d_rpm", obs_type="kin", backend="pybullet") as env_pb:
        for name, env in (("jax", env_jax), ("pybullet", env_pb)):
            episodes = jax.jit(jax.vmap(lambda k, env=env: rollout_policy(env, policy, k)))(keys)
            runs[name] = {
                "terminated": np.asarray(episodes.terminated),
                "truncated": np.asarray(episodes.truncated),
                "distance": np.asarray(episodes.metrics["distance"]),
                "pos": np.asarray(episodes.sim.pos[:, :, 0]),
            }
    jx, pb = runs["jax"], runs["pybullet"]
    last = slice(-env_jax.config.sim.ctrl_freq, None)
    print(
        f"\nMEASURED hover policy, {len(keys)} starts: mean distance over the last second jax "
        f"{jx['distance'][:, last].mean() * 1e3:.1f} mm, pybullet {pb['distance'][:, last].mean() * 1e3:.1f} mm; "
        f"final {jx['distance'][:, -1].mean() * 1e3:.1f} / {pb['distance'][:, -1].mean() * 1e3:.1f} mm"
    )
    np.testing.assert_array_equal(pb["pos"][:, 0], jx["pos"][:, 0])  # the same reset
    np.testing.assert_allclose(pb["pos"][:, 1], jx["pos"][:, 1], atol=1e-6)  # the same first step
    last_second = slice(-env_jax.config.sim.ctrl_freq, None)
    for run in (jx, pb):
        assert not run["terminated"].any() and run["truncated"][:, -1].all()
        assert run["distance"][:, last_second].mean() < 0.02 and run["distance"][:, -1].mean() < 0.03
    assert abs(pb["distance"][:, last_second].mean() - jx["distance"][:, last_second].mean()) < HOVER_TOLERANCE_M


def test_hover_env_agrees_step_by_step():
    """The env on both backends, jitted and vmapped, under a PD altitude hold: the same states (float32 rounding)."""

    def pd_hold(obs):
        return jnp.clip(-2.0 * (obs[:, 2:3] - 1.0) - 2.0 * obs[:, 8:9], -1.0, 1.0)

    keys = jax.random.split(jax.random.key(0), 4)
    out = {}
    for backend in ("jax", "pybullet"):
        with jd.make("hover", action_type="one_d_rpm", backend=backend) as env:

            def episode(k, env=env):
                def body(s, _):
                    s = env.step(s, pd_hold(s.obs))
                    return s, s.sim.pos[0]

                return jax.lax.scan(body, env.reset(k), None, length=60)[1]

            out[backend] = np.asarray(jax.jit(jax.vmap(episode))(keys))
    np.testing.assert_allclose(out["pybullet"], out["jax"], atol=2e-5)


# ------------------------------------------------------------------------------------------------------------------
# (c) Vision observations
# ------------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def vision_env():
    """Hover on PyBullet among the obstacles with all three images at 48 Hz control: a render every 2 steps."""
    env = jd.make(
        "hover",
        action_type="one_d_rpm",
        backend="pybullet",
        obstacles=True,
        vision=("rgb", "depth", "seg"),
        ctrl_freq=48,
        init_pos=[[0.0, 0.0, 0.5]],
    )
    yield env
    env.close()


def test_camera_rate_is_decoupled_from_control():
    for ctrl_freq, period in ((30, 1), (48, 2), (240, 10), (80, 3)):
        cfg = jd.envs.HoverConfig(sim={"ctrl_freq": ctrl_freq})
        assert cfg.camera_period == period and cfg.camera_rate == pytest.approx(ctrl_freq / period)
    assert jd.envs.HoverConfig(sim={"ctrl_freq": 30}, camera_freq=10).camera_period == 3


def test_vision_obs_shapes_and_render_schedule(vision_env):
    env = vision_env
    assert env.config.camera_period == 2
    spec = env.observation_spec
    assert {k: (v.shape, np.dtype(v.dtype)) for k, v in spec.items()} == {
        "state": ((1, 21), np.dtype(np.float32)),
        "rgb": ((1, 48, 64, 4), np.dtype(np.uint8)),
        "depth": ((1, 48, 64), np.dtype(np.float32)),
        "seg": ((1, 48, 64), np.dtype(np.int32)),
    }
    n = 3
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    state = reset(jax.random.split(jax.random.key(0), n))
    climb = jnp.ones((n, 1, 1))
    history = [state.obs]
    for _ in range(6):
        state = step(state, climb)
        history.append(state.obs)
    for obs in history:
        for name, s in spec.items():
            assert obs[name].shape == (n,) + s.shape and obs[name].dtype == s.dtype, name
    np.testing.assert_allclose(history[-1]["state"][..., :12], kinematic_obs(state.sim), rtol=1e-6, atol=1e-7)
    for k in range(1, 7):  # steps 2, 4, 6 render (the drones climb, so the ground recedes); 1, 3, 5 hold
        same = [np.array_equal(history[k][name], history[k - 1][name]) for name in ("rgb", "depth", "seg")]
        if k % 2:
            assert all(same), k
        else:
            assert not same[1], k
            assert np.all(history[k]["depth"][:, 0, -1, 32] > history[k - 1]["depth"][:, 0, -1, 32]), k

    # Unbatched under jit (lax.cond skips the render), and eagerly: the same schedule.
    single = jax.jit(env.step)
    s = env.reset(jax.random.key(0))
    s1 = single(s, jnp.ones((1, 1)))
    s2 = env.step(s1, jnp.ones((1, 1)))
    assert np.array_equal(s1.obs["depth"], s.obs["depth"]) and not np.array_equal(s2.obs["depth"], s1.obs["depth"])


def test_depth_and_segmentation_see_the_ground_and_obstacles(vision_env):
    """At reset the drone is level at (0, 0, 0.5) m looking along +x: sky above the horizon, the ground below at
    the depth of the ground plane, and the first obstacle (a box whose front face is at x = 0.625 m) to the right."""
    env = vision_env
    obs = env.reset(jax.random.key(0)).obs
    depth, seg = np.asarray(obs["depth"][0]), np.asarray(obs["seg"][0])
    ids = env._step.body_ids(0)
    h, width = 48, 64
    f = (h / 2) / np.tan(np.radians(30.0))  # focal length, pixels (60° vertical field of view)
    straight = slice(20, 44)  # columns ahead, clear of the obstacles
    # Above the horizon: nothing but sky (depth = far = 100 m, seg -1).
    assert np.all(seg[: h // 2, straight] == -1) and np.allclose(depth[: h // 2, straight], 100.0, rtol=1e-3)
    # Below: the ground, at depth z·f / (pixels below the image centre), the same along each row. (TinyRenderer
    # reads row j at the ray through j + 1 rather than the pixel centre j + 0.5: allow either.)
    rows = np.arange(30, h)
    assert np.all(seg[rows][:, straight] == ids["ground"])
    near, far = 0.5 * f / (rows + 1.0 - h / 2), 0.5 * f / (rows + 0.5 - h / 2)
    assert np.all((depth[rows, 32] > 0.995 * near) & (depth[rows, 32] < 1.005 * far)), depth[rows, 32]
    np.testing.assert_allclose(depth[rows][:, straight], depth[rows, 32:33] * np.ones((1, 24)), rtol=1e-3)
    assert np.all(np.diff(depth[rows, 32]) < 0)
    # The box, right of centre: its front face at x = 0.625 m, seen from the eye just ahead of the drone.
    box = seg == ids["obstacles"][0]
    assert box.sum() > 50 and np.all(np.nonzero(box)[1] > width // 2)
    eye_x = float(env.params.collision_radius[0]) + EYE_MARGIN
    assert np.median(depth[box]) == pytest.approx(0.625 - eye_x, rel=0.03)
    # The RGB image is opaque and not uniform.
    rgb = np.asarray(obs["rgb"][0])
    assert np.all(rgb[..., 3] == 255) and rgb[..., :3].std() > 5


def test_vision_options_are_checked():
    with pytest.raises(ValueError, match="only seen by its cameras"):
        jd.make("hover", obstacles=[Obstacle("box")])  # the jax backend: obstacles without cameras do nothing
    with pytest.raises(ValueError, match="URDF mesh"):
        jd.make("hover", obstacles=True, vision=("depth",))  # the paper's scene has a duck mesh
    with pytest.raises(ValueError, match="renderer needs backend='pybullet'"):
        jd.make("hover", vision=("depth",), renderer="egl")
    with pytest.raises(ValueError, match="vision must hold distinct names"):
        jd.make("hover", backend="pybullet", vision=("rgb", "dep"))
    with pytest.raises(ValueError, match="vision must be a tuple"):
        jd.make("hover", backend="pybullet", vision="rgb")
    with pytest.raises(ValueError, match="camera_freq"):
        jd.make("hover", backend="pybullet", vision=("rgb",), camera_freq=0.0)
    with pytest.raises(ValueError, match="image_size"):
        jd.make("hover", backend="pybullet", vision=("rgb",), image_size=(64,))
    for fov in (0.0, 180.0, float("nan"), "60"):
        with pytest.raises(ValueError, match=r"camera_fov .* in \(0, 180\)"):
            jd.make("hover", vision=("depth",), camera_fov=fov)
    for k in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match="frame_stack must be a positive integer"):
            jd.make("hover", vision=("depth",), frame_stack=k)
    with pytest.raises(ValueError, match="frame_stack=2 stacks camera frames: it needs vision"):
        jd.make("hover", frame_stack=2)
    with pytest.raises(ValueError, match="unknown backend 'bullet'"):
        jd.make("hover", backend="bullet")
    with pytest.raises(ValueError, match="unknown renderer 'gl'"):
        jd.make("hover", backend="pybullet", renderer="gl")


def test_frame_stack_on_pybullet():
    """``frame_stack=2`` on the PyBullet backend: the reset's capture twice, then after one camera period the reset's
    capture first and the new one last."""
    env = jd.make(
        "hover",
        backend="pybullet",
        vision=("depth", "seg"),
        frame_stack=2,
        image_size=(16, 12),
        ctrl_freq=30,
        camera_freq=15,
    )
    state = env.reset(jax.random.key(0))
    first = np.asarray(state.obs["depth"][0, 1])
    assert state.obs["depth"].shape == (1, 2, 12, 16) and state.obs["seg"].shape == (1, 2, 12, 16)
    np.testing.assert_array_equal(np.asarray(state.obs["depth"][0, 0]), first)
    for _ in range(2):
        state = env.step(state, jnp.full((1, 4), 0.5))
    np.testing.assert_array_equal(np.asarray(state.obs["depth"][0, 0]), first)
    assert not np.array_equal(np.asarray(state.obs["depth"][0, 1]), first)  # climbing: the ground further away
    env.close()


def test_gymnasium_on_pybullet_with_vision():
    import gymnasium as gym

    env = gym.make("jaxdrones/Hover-v0", backend="pybullet", vision=("depth",), image_size=(32, 24))
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"state", "depth"} and obs["depth"].shape == (24, 32) and obs["depth"].dtype == np.float32
    assert env.observation_space.contains(obs)
    obs, reward, terminated, truncated, _ = env.step(np.zeros(4, np.float32))
    assert env.observation_space.contains(obs) and np.isfinite(reward) and not terminated
    env.close()


# ------------------------------------------------------------------------------------------------------------------
# (d) jaxdrones fly --backend pybullet --obstacles
# ------------------------------------------------------------------------------------------------------------------


def test_fly_cli_pybullet_writes_a_video(tmp_path, capsys):
    import imageio.v2 as imageio

    out = tmp_path / "fly"
    args = [
        "fly",
        "--backend",
        "pybullet",
        "--obstacles",
        "--num-drones",
        "2",
        "--duration",
        "1.5",
        "--settle",
        "0.5",
        "--video-size",
        "160x120",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "on pybullet" in printed and "contacts with obstacles or other drones: none" in printed
    assert sorted(os.listdir(out)) == [MARKER, "flight.mp4", "flight.npz", "flight.png", "metrics.json"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["settings"]["backend"] == "pybullet" and len(metrics["settings"]["obstacles"]) == 4
    assert metrics["contacts"]["collided"] is False
    assert metrics["video"] == "flight.mp4"  # inside the run folder, wherever it is moved
    assert metrics["video_frames"] == 1 + 72 // 2  # 1.5 s at 48 Hz control, a frame every 2 steps, plus the start
    reader = imageio.get_reader(out / "flight.mp4")
    try:
        assert reader.count_frames() == metrics["video_frames"]
        assert reader.get_data(0).shape == (120, 160, 3)
        assert reader.get_meta_data()["fps"] == pytest.approx(24.0)
    finally:
        reader.close()

    # A GIF at another rate, and an existing video file is never replaced.
    assert main(args[:-1] + [str(tmp_path / "gif"), "--video", "clip.gif", "--fps", "12"]) == 0
    assert json.loads((tmp_path / "gif" / "metrics.json").read_text())["video_frames"] == 1 + 72 // 4
    assert (tmp_path / "gif" / "clip.gif").read_bytes().startswith(b"GIF8")
    existing = tmp_path / "mine.mp4"
    existing.write_bytes(b"not a video")
    assert main(args[:-1] + [str(tmp_path / "bad"), "--video", str(existing)]) == 2
    assert "exists" in capsys.readouterr().err
    assert existing.read_bytes() == b"not a video" and not (tmp_path / "bad").exists()


def test_fly_cli_rejects_pybullet_options_on_jax_and_gui_without_display(tmp_path, capsys, monkeypatch):
    assert main(["fly", "--obstacles", "--out", str(tmp_path / "a")]) == 2
    assert "needs backend='pybullet'" in capsys.readouterr().err
    assert main(["fly", "--video", "v.mp4", "--out", str(tmp_path / "b")]) == 2
    assert "needs --backend pybullet" in capsys.readouterr().err
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert main(["fly", "--backend", "pybullet", "--gui", "--out", str(tmp_path / "c")]) == 2
    assert "needs a display" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in "abc")
