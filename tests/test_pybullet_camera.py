"""Onboard cameras and third-person views of the PyBullet backend, the scripted camera scene, and video files."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from optional import needs
from PIL import Image

needs("pybullet")
pytestmark = pytest.mark.pybullet

import pybullet  # noqa: E402

import jaxdrones as jd  # noqa: E402
from jaxdrones.backends import camera  # noqa: E402
from jaxdrones.examples import camera_scene as cs  # noqa: E402
from jaxdrones.io.runs import MARKER  # noqa: E402
from jaxdrones.scene import Obstacle  # noqa: E402
from jaxdrones.video import VideoWriter  # noqa: E402

W, H = 320, 240


def numpy_state(state):
    return jax.tree.map(np.asarray, state)


def pinhole_box_mask(width, height, fov, distance, half):
    """Pixels whose centre's ray hits a square of half-side ``half`` m centred on the optical axis ``distance`` m
    ahead, perpendicular to it: |(c + ½ − W/2)·Z/f| ≤ half and |(H/2 − r − ½)·Z/f| ≤ half, f = (H/2)/tan(fov/2)."""
    f = (height / 2) / np.tan(np.radians(fov) / 2)
    right = (np.arange(width) + 0.5 - width / 2) * distance / f
    up = (height / 2 - np.arange(height) - 0.5) * distance / f
    return (np.abs(up)[:, None] <= half) & (np.abs(right)[None, :] <= half)


def grow(mask, k=1):
    """Dilate a boolean mask by k pixels (Chebyshev)."""
    out = mask.copy()
    for _ in range(k):
        padded = np.pad(out, 1)
        out = np.zeros_like(out)
        for dr in (0, 1, 2):
            for dc in (0, 1, 2):
                out |= padded[dr : dr + mask.shape[0], dc : dc + mask.shape[1]]
    return out


def shrink(mask, k=1):
    return ~grow(~mask, k)


def check_scene(scene, width=W, height=H, fov=60.0, distance=cs.BOX_DISTANCE, colour_tol=3.0):
    """The box, sphere, ground and sky are where the pinhole model puts them; returns (mismatched pixels, IoU,
    max depth error on the box face in m).

    TinyRenderer shades a flat face uniformly (a brightness factor times the RGBA colour, to ±1 unit); OpenGL adds
    a specular highlight, so its colours are checked to ``colour_tol`` units."""
    ids = scene["body_ids"]
    box_id, sphere_id = ids["obstacles"]
    seg, depth, rgb = scene["seg"], scene["depth"], scene["rgb"]
    expected = pinhole_box_mask(width, height, fov, distance, cs.BOX_SIDE / 2)
    seen = seg == box_id
    # every disagreement lies on the expected outline (within one pixel of it)
    wrong = seen ^ expected
    assert not np.any(wrong & ~(grow(expected) & ~shrink(expected))), "box pixels off the pinhole footprint"
    iou = (seen & expected).sum() / (seen | expected).sum()
    assert iou > 0.8
    rows, cols = np.nonzero(seen)
    exp_rows, exp_cols = np.nonzero(expected)
    for a, b in ((rows, exp_rows), (cols, exp_cols)):
        assert abs(a.min() - b.min()) <= 1 and abs(a.max() - b.max()) <= 1
    face = shrink(expected)
    assert np.all(seg[face] == box_id)
    depth_error = float(np.max(np.abs(depth[face] - distance)))
    assert depth_error < 0.01
    # the box's colour (a lit surface: a common brightness factor times the RGBA colour)
    colour = rgb[face][:, :3].astype(np.float64)
    target = np.asarray(cs.BOX_RGBA[:3]) * 255
    k = np.sum(colour * target, -1) / np.sum(target * target)
    assert np.all((k > 0.3) & (k < 1.3))
    assert np.max(np.abs(colour - k[:, None] * target)) < colour_tol
    assert np.all(rgb[..., 3] == 255)
    # the sphere at its projected centre, left of the image centre (it is at world +y)
    eye = scene["eye"]
    rel = np.asarray(cs.SPHERE_POS) - eye
    f = (height / 2) / np.tan(np.radians(fov) / 2)
    col, row = int(width / 2 - f * rel[1] / rel[0]), int(height / 2 - f * rel[2] / rel[0])
    assert seg[row, col] == sphere_id
    # right half (no sphere there), outside the box: nothing above the horizon, the ground below it
    outside = ~grow(expected, 2)
    right = np.zeros_like(expected)
    right[:, width // 2 + 2 :] = True
    above = np.arange(height)[:, None] < height / 2 - 1
    below = np.arange(height)[:, None] > height / 2 + 2
    assert np.all(seg[right & outside & above] == -1)
    assert np.all(seg[right & outside & below] == ids["ground"])
    assert np.all(np.isin(seg, [-1, ids["ground"], box_id, sphere_id]))  # the drone does not see itself
    np.testing.assert_allclose(depth[right & outside & above], 100.0, rtol=1e-4)
    return int(wrong.sum()), float(iou), depth_error


@pytest.fixture(scope="module")
def scene():
    return cs.camera_scene(width=W, height=H)


def test_scene_matches_the_pinhole_model(scene):
    """TinyRenderer: box footprint within one pixel of the pinhole prediction, depth on its face within 1 cm (in
    fact ~1e-6 m), seg ids and colour as expected."""
    assert scene["rgb"].shape == (H, W, 4) and scene["rgb"].dtype == np.uint8
    assert scene["depth"].shape == (H, W) and scene["depth"].dtype == np.float32
    assert scene["seg"].shape == (H, W) and scene["seg"].dtype == np.int32
    wrong, iou, depth_error = check_scene(scene)
    assert depth_error < 1e-4
    print(f"tiny: {wrong} outline pixels differ, IoU {iou:.3f}, depth error {depth_error:.2e} m")


@pytest.mark.parametrize("fov, distance, size", [(90.0, 0.6, (160, 90)), (45.0, 2.0, (200, 200))])
def test_other_fov_distance_and_aspect(fov, distance, size):
    scene = cs.camera_scene(width=size[0], height=size[1], fov=fov, distance=distance)
    check_scene(scene, size[0], size[1], fov, distance)


def test_egl_renderer():
    """Bullet's OpenGL renderer through the EGL plugin (headless; here Mesa's software OpenGL if no GPU)."""
    try:
        scene = cs.camera_scene(width=W, height=H, renderer="egl")
    except RuntimeError as err:
        assert "renderer='tiny'" in str(err)  # the error names the fallback
        pytest.skip(f"EGL renderer not available on this machine: {err}")
    wrong, iou, depth_error = check_scene(scene, colour_tol=15.0)
    print(f"egl: {wrong} outline pixels differ, IoU {iou:.3f}, depth error {depth_error:.2e} m")


def test_view_and_projection_matrices_equal_pybullets(rng):
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        p, offset = rng.normal(size=3), rng.uniform(0.01, 0.2)
        R = np.array(pybullet.getMatrixFromQuaternion(q.tolist())).reshape(3, 3)
        eye = p + offset * R[:, 0]
        expected = pybullet.computeViewMatrix(eye.tolist(), (eye + R[:, 0]).tolist(), R[:, 2].tolist())
        np.testing.assert_allclose(camera.onboard_view_matrices(p, q, offset), expected, atol=1e-6)
    for fov, aspect, near, far in [(60.0, 4 / 3, 0.0397, 100.0), (90.0, 1.0, 0.01, 1000.0)]:
        np.testing.assert_allclose(
            camera.projection_matrix(fov, aspect, near, far),
            pybullet.computeProjectionMatrixFOV(fov, aspect, near, far),
            rtol=1e-6,
        )
    z = camera.projection_matrix(60.0, 1.0, 0.05, 10.0).reshape(4, 4).T @ np.array([0.0, 0.0, -2.5, 1.0])
    assert camera.zbuffer_to_depth((z[2] / z[3] + 1) / 2, 0.05, 10.0) == pytest.approx(2.5)


def test_png_files_and_no_overwrite(scene, tmp_path):
    paths = cs.save_camera_images(scene, tmp_path / "cam")
    assert set(paths) == set(cs.FILES) and all(os.path.isfile(p) for p in paths.values())
    rgb, depth, seg = (Image.open(paths[f]) for f in ("rgb.png", "depth.png", "seg.png"))
    assert rgb.size == depth.size == seg.size == (W, H)
    np.testing.assert_array_equal(np.asarray(rgb), scene["rgb"][..., :3])
    depth_mm = np.asarray(depth)
    assert depth_mm.dtype == np.uint16 and depth_mm[H // 2, W // 2] == 1000
    assert depth_mm[0, W - 1] == 0  # nothing within far
    np.testing.assert_array_equal(np.asarray(seg).astype(np.int32) - 1, scene["seg"])
    with pytest.raises(FileExistsError, match="overwrite"):
        cs.save_camera_images(scene, tmp_path / "cam")
    cs.save_camera_images(scene, tmp_path / "cam", overwrite=True)


def test_cli_camera(tmp_path, capsys):
    from jaxdrones.cli import main

    out = tmp_path / "run"
    assert main(["camera", "--out", str(out), "--width", "64", "--height", "48"]) == 0
    assert sorted(os.listdir(out)) == sorted([MARKER, *cs.FILES])
    assert Image.open(out / "rgb.png").size == (64, 48)
    assert main(["camera", "--out", str(out), "--width", "64", "--height", "48"]) == 0  # a new sibling folder
    assert sorted(os.listdir(tmp_path)) == ["run", "run-1"]
    assert main(["camera", "--out", str(out), "--distance", "-1"]) == 2
    assert "distance" in capsys.readouterr().err
    # An output folder that cannot be created: a clear error, no traceback.
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["camera", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxdrones camera: error: cannot create the output folder") and "Traceback" not in err


def two_drone_worlds(n_worlds=3):
    """[W, 2] drones: drone 1 is 1 m ahead of drone 0, both facing +x, in every world."""
    config = jd.SimConfig(n_drones=2)
    pos = np.array([[0.0, 0.0, 0.5], [1.0, 0.0, 0.5]]) + np.arange(n_worlds)[:, None, None] * [0.0, 0.0, 0.1]
    return config, jd.load_params("cf2x"), numpy_state(jd.init_state(config, pos=pos))


def test_batched_worlds_shapes_jax_and_jit():
    config, params, state = two_drone_worlds()
    with jd.make_step(config, backend="pybullet") as step:
        out = step.camera_images(params, state)  # before any step: the worlds are created here
        assert out["rgb"].shape == (3, 2, 48, 64, 4) and out["rgb"].dtype == np.uint8
        assert out["depth"].shape == (3, 2, 48, 64) and out["depth"].dtype == np.float32
        assert out["seg"].shape == (3, 2, 48, 64) and out["seg"].dtype == np.int32
        assert all(isinstance(v, np.ndarray) for v in out.values())
        for w in range(3):
            ids = step.body_ids(w)
            assert ids["drones"][1] in out["seg"][w, 0]  # drone 0 sees drone 1 ahead
            assert ids["drones"][0] not in out["seg"][w, 0]  # but not itself
            assert ids["drones"][0] not in out["seg"][w, 1]  # drone 1 looks away from drone 0
        # JAX arrays in: host images, the same
        jax_state = jax.tree.map(jnp.asarray, state)
        out_jax = step.camera_images(params, jax_state)
        assert all(isinstance(v, np.ndarray) for v in out_jax.values())
        # under jit (a host callback) and under vmap over the world axis
        out_jit = jax.jit(lambda p, s: step.camera_images(p, s))(params, jax_state)
        out_vmap = jax.jit(jax.vmap(lambda s: step.camera_images(params, s)))(jax_state)
        for key in out:
            np.testing.assert_array_equal(np.asarray(out_jax[key]), out[key])
            np.testing.assert_array_equal(np.asarray(out_jit[key]), out[key])
            np.testing.assert_array_equal(np.asarray(out_vmap[key]), out[key])
            assert out_jit[key].dtype == out[key].dtype
        # inside jit, a drone with a NaN pose reads nothing instead of raising
        bad = jax_state.replace(pos=jax_state.pos.at[1, 0, 0].set(jnp.nan))
        out_bad = jax.jit(lambda s: step.camera_images(params, s))(bad)
        assert np.all(np.asarray(out_bad["seg"][1, 0]) == -1) and np.all(np.isnan(np.asarray(out_bad["depth"][1, 0])))
        np.testing.assert_array_equal(np.asarray(out_bad["seg"][0]), out["seg"][0])


def test_camera_follows_the_body_and_leaves_the_step_unchanged():
    config = jd.SimConfig(n_drones=1, ctrl_freq=48)
    params = jd.load_params("cf2x")
    box = Obstacle("box", size=(0.2, 0.2, 0.2), pos=(0.0, 1.0, 0.5))  # 1 m to the left (world +y)
    state = numpy_state(jd.init_state(config, pos=np.array([[0.0, 0.0, 0.5]]), rpy=np.array([[0.0, 0.0, np.pi / 2]])))
    rpm = np.full((1, 4), float(params.hover_rpm))
    with jd.make_step(config, backend="pybullet", obstacles=[box]) as step:
        before = step(params, state, rpm)
        seg = step.camera_images(params, state)["seg"][0]
        assert seg[24, 32] == step.body_ids()["obstacles"][0]  # yawed 90°: the camera looks along world +y
        after = step(params, state, rpm)
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after), strict=True):
        np.testing.assert_array_equal(a, b)


def test_render():
    config, params, state = two_drone_worlds(2)
    with jd.make_step(config, backend="pybullet", obstacles=True) as step:
        frame = step.render(params, state, world=1, width=160, height=120)
        assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
        assert frame.std() > 10  # not a blank image
        frame_jax = step.render(
            params,
            jax.tree.map(jnp.asarray, state),
            world=1,
            width=160,
            height=120,
            target=(0.5, 0.0, 0.6),
            distance=2.0,
            yaw=30.0,
            pitch=-20.0,
        )
        assert isinstance(frame_jax, np.ndarray) and frame_jax.shape == (120, 160, 3)
        with pytest.raises(ValueError, match="world"):
            step.render(params, state, world=2)
        with pytest.raises(ValueError, match="distance"):
            step.render(params, state, distance=0.0)
        with pytest.raises(ValueError, match="target"):
            step.render(params, state, target=(0.0, 1.0))
        with pytest.raises(ValueError, match="outside jit"):
            jax.jit(lambda s: step.render(params, s))(jax.tree.map(jnp.asarray, state))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"width": 0}, "width"),
        ({"width": 64.0}, "width"),
        ({"height": -3}, "height"),
        ({"height": True}, "height"),
        ({"fov": 0.0}, "fov"),
        ({"fov": 180.0}, "fov"),
        ({"fov": "wide"}, "fov"),
        ({"far": -1.0}, "far"),
        ({"far": np.inf}, "far"),
        ({"near": 0.0}, "near"),
        ({"near": 200.0}, "near"),
        ({"near": np.nan}, "near"),
    ],
)
def test_bad_camera_arguments(kwargs, match):
    config, params, state = two_drone_worlds(1)
    with jd.make_step(config, backend="pybullet") as step:
        with pytest.raises(ValueError, match=match):
            step.camera_images(params, state, **kwargs)


def test_bad_states_and_closed_step():
    config, params, state = two_drone_worlds(1)
    step = jd.make_step(config, backend="pybullet")
    with pytest.raises(ValueError, match=r"\[\.\.\., 2, 3\]"):
        step.camera_images(params, state.replace(pos=state.pos[..., :1, :]))
    with pytest.raises(ValueError, match="NaN"):
        step.camera_images(params, state.replace(pos=np.full_like(state.pos, np.nan)))
    with pytest.raises(ValueError, match="zero"):
        step.camera_images(params, state.replace(quat=np.zeros_like(state.quat)))
    with pytest.raises(ValueError, match="batch shape"):
        step.camera_images(jax.tree.map(lambda x: jnp.stack([x] * 3), params), state)
    with pytest.raises(ValueError, match="created so far"):
        step.body_ids(0)
    step.close()
    with pytest.raises(RuntimeError, match="closed"):
        step.camera_images(params, state)


def test_gui_without_display_raises():
    """Without an X server, ``pybullet.connect(GUI)`` would end the process; the backend raises RuntimeError."""
    code = textwrap.dedent("""
        import os
        import jaxdrones as jd
        for display in (None, ":97"):
            os.environ.pop("DISPLAY", None)
            if display:
                os.environ["DISPLAY"] = display
            try:
                jd.make_step(jd.SimConfig(), backend="pybullet", gui=True)
            except RuntimeError as err:
                print("RuntimeError:", err)
    """)
    if sys.platform.startswith("linux"):
        result = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=300,
            env={k: v for k, v in os.environ.items() if k != "DISPLAY"},
        )
        assert result.returncode == 0, result.stderr
        lines = [line for line in result.stdout.splitlines() if line.startswith("RuntimeError")]
        assert len(lines) == 2 and "DISPLAY is not set" in lines[0] and "':97'" in lines[1]


def frames(n, h, w):
    """n smooth, distinct RGB frames (a moving colour gradient)."""
    y, x = np.mgrid[0:h, 0:w]
    return [
        np.stack([(x * 255 // w + 20 * i) % 256, y * 255 // h, np.full_like(x, 40 * i % 256)], -1).astype(np.uint8)
        for i in range(n)
    ]


# imageio-ffmpeg starts ffmpeg with fork + exec, which JAX's generic fork warning flags; nothing runs in between.
pytestmark_video = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")


@pytestmark_video
def test_video_writer_gif_and_mp4(tmp_path):
    import imageio.v2 as imageio

    video = frames(6, 48, 64)
    with VideoWriter(tmp_path / "a.gif", fps=10) as writer:
        for frame in video:
            writer.append(frame)
    assert writer.n_frames == 6
    gif = Image.open(tmp_path / "a.gif")
    assert gif.n_frames == 6 and gif.size == (64, 48) and gif.info["duration"] == 100
    with VideoWriter(tmp_path / "sub" / "a.mp4", fps=24) as writer:
        for frame in video:
            writer.append(jnp.asarray(frame))
    reader = imageio.get_reader(tmp_path / "sub" / "a.mp4")
    read = [f for f in reader]
    assert reader.get_meta_data()["fps"] == 24
    reader.close()
    assert len(read) == 6 and read[0].shape == (48, 64, 3)
    assert np.mean(np.abs(np.asarray(read[3], float) - video[3])) < 8  # lossy, but the same picture
    # odd sizes are padded to even ones for H.264
    with VideoWriter(tmp_path / "odd.mp4") as writer:
        for frame in frames(3, 45, 63):
            writer.append(frame)
    reader = imageio.get_reader(tmp_path / "odd.mp4")
    assert reader.get_data(0).shape == (46, 64, 3)
    reader.close()


@pytestmark_video
def test_video_writer_refuses_bad_input(tmp_path):
    (tmp_path / "old.mp4").write_bytes(b"keep")
    with pytest.raises(FileExistsError, match="overwrite"):
        VideoWriter(tmp_path / "old.mp4")
    with pytest.raises(ValueError, match="replaces only a file jaxdrones wrote"):  # a user's file: never replaced
        VideoWriter(tmp_path / "old.mp4", overwrite=True)
    assert (tmp_path / "old.mp4").read_bytes() == b"keep"
    for name in ("ours.mp4", "ours.gif"):  # a video jaxdrones wrote is replaced with overwrite, written whole
        for _ in range(2):
            with VideoWriter(tmp_path / name, overwrite=True) as writer:
                writer.append(frames(1, 16, 16)[0])
                assert not (tmp_path / name).exists() or (tmp_path / name).stat().st_size > 100
        assert (tmp_path / name).stat().st_size > 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.mp4", "ours.gif", "ours.mp4"]
    with pytest.raises(ValueError, match="extension"):
        VideoWriter(tmp_path / "a.avi")
    with pytest.raises(ValueError, match="fps"):
        VideoWriter(tmp_path / "a.gif", fps=0)
    with VideoWriter(tmp_path / "b.gif") as writer:
        writer.append(frames(1, 16, 16)[0])
        with pytest.raises(ValueError, match="shape"):
            writer.append(frames(1, 16, 18)[0])
        with pytest.raises(ValueError, match="uint8"):
            writer.append(np.zeros((16, 16, 3), np.float32))
        with pytest.raises(ValueError, match="uint8"):
            writer.append(np.zeros((16, 16, 4), np.uint8))
    with VideoWriter(tmp_path / "empty.gif"):
        pass
    assert not (tmp_path / "empty.gif").exists()
