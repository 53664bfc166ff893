"""The flight viewer (jaxdrones.viz): input checks, the HTML file (self-contained, never overwritten unasked), a
headless Chromium that opens it from file:// and shows the drones where the rollout puts them, `jaxdrones view`,
the flight.html of `jaxdrones train`, and videos through the JAX cameras."""

from __future__ import annotations

import base64
import colorsys
import io
import json
import math
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from jaxdrones import viz
from jaxdrones.scene import Obstacle
from jaxdrones.viz import Flight
from jaxdrones.viz import html as viz_html

needs_viser = pytest.mark.skipif(not viz.viewer_available(), reason=f"viser is not installed ({viz.VIEWER_INSTALL})")
DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def level(n_frames: int, positions) -> Flight:
    """Drones hovering level at fixed ``positions`` f[D, 3] for ``n_frames`` frames at 30 Hz."""
    pos = np.broadcast_to(np.asarray(positions, float), (n_frames, *np.shape(positions)))
    quat = np.zeros(pos.shape[:-1] + (4,))
    quat[..., 3] = 1.0
    return Flight(pos, quat, 1 / 30)


def circle(n_frames: int = 60, n_worlds: int = 2, n_drones: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """pos f[T, W, D, 3] on circles of 1 m at 1 m height, and level quaternions yawing along."""
    t = np.arange(n_frames)[:, None, None] / 30
    ang = t + np.arange(n_drones) * 2 * np.pi / n_drones + np.arange(n_worlds)[:, None] * 0.3
    pos = np.stack([np.cos(ang), np.sin(ang), np.ones_like(ang)], -1)
    quat = np.stack([0 * ang, 0 * ang, np.sin((ang + np.pi / 2) / 2), np.cos((ang + np.pi / 2) / 2)], -1)
    return pos, quat


# --------------------------------------------------------------------------------------------- input checks
@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"pos": np.zeros((10, 2))}, r"pos must be f\[T, \.\.\., D, 3\]"),
        ({"pos": np.zeros((10, 2, 4))}, r"pos must be f\[T, \.\.\., D, 3\]"),
        ({"quat": np.zeros((10, 2, 3))}, r"quat must be f\[T, \.\.\., D, 4\]"),
        (
            {"quat": np.ones((10, 3, 4))},
            (
                r"quat must be f\[T, \.\.\., D, 4\] with the leading axes of pos "
                r"f\[10, 2, 3\], that is f\[10, 2, 4\]"
            ),
        ),
        ({"quat": np.zeros((10, 2, 4))}, "non-zero"),
        ({"pos": np.full((10, 2, 3), np.nan)}, r"pos must be finite; entry \(0, 0, 0\) is nan"),
        ({"quat": np.full((10, 2, 4), np.inf)}, "quat must be finite"),
        ({"pos": "abc"}, "numeric array"),
        ({"dt": 0.0}, "dt must be"),
        ({"dt": float("nan")}, "dt must be"),
        ({"dt": True}, "dt must be"),
        ({"arm": -1.0}, "arm must be"),
        ({"images": np.zeros((10, 2, 48, 64, 3), np.uint8)[:, :1]}, r"images must be u8\[T, \.\.\., D, H, W, 3 or 4\]"),
        ({"images": np.zeros((10, 2, 48, 64, 2), np.uint8)}, r"images must be"),
        ({"images": np.zeros((9, 2, 48, 64), np.float32)}, r"with T, \.\.\., D = \[10, 2\]"),
        ({"scene": [Obstacle("box")], "images": np.zeros((10, 2, 48, 64, 3), np.int64)}, "images must be"),
    ],
)
def test_flight_rejects_bad_input(change, message):
    args = {"pos": np.zeros((10, 2, 3)), "quat": np.tile([0.0, 0.0, 0.0, 1.0], (10, 2, 1)), "dt": 0.02}
    args.update(change)
    with pytest.raises(ValueError, match=message):
        Flight(**args)


def test_flight_flattens_worlds_and_normalises():
    pos, quat = circle(5, 2, 3)
    flight = Flight(pos[:, None], 2 * quat[:, None], 0.1)  # worlds [1, 2]
    assert flight.pos.shape == (5, 2, 3, 3) and flight.quat.shape == (5, 2, 3, 4)
    assert (flight.n_frames, flight.n_worlds, flight.n_drones) == (5, 2, 3)
    np.testing.assert_allclose(np.linalg.norm(flight.quat, axis=-1), 1.0)
    np.testing.assert_allclose(flight.pos, pos)
    depth = np.linspace(0.1, 5.0, 5 * 2 * 3 * 4 * 6).reshape(5, 2, 3, 4, 6)
    grey = Flight(pos, quat, 0.1, images=depth).images
    assert grey.shape == (5, 2, 3, 4, 6, 3) and grey.dtype == np.uint8
    assert grey[0, 0, 0, 0, 0, 0] > grey[-1, -1, -1, -1, -1, 0]  # near is bright


def test_scene_of_obstacles_and_per_world_scenes():
    from jaxdrones.cameras import make_scene

    pos, quat = circle(4, 2, 1)
    flight = Flight(
        pos,
        quat,
        0.1,
        scene=[
            Obstacle("box", size=(0.2, 0.4, 0.6), pos=(1.0, 2.0, 0.3)),
            Obstacle("urdf", urdf=__file__, pos=(0, 0, 0)),
        ],
    )  # a mesh: not drawn
    prims = viz_html._primitives(flight.scene, 0)
    assert [p[0] for p in prims] == ["box"]
    np.testing.assert_allclose(prims[0][1], (1.0, 2.0, 0.3))
    np.testing.assert_allclose(prims[0][3], (0.1, 0.2, 0.3))  # half extents
    one = make_scene([Obstacle("sphere", size=(0.1,), pos=(0, 0, 1))])
    import jax

    two = jax.tree.map(lambda x: np.stack([x, x]), one)
    two.sphere.pos[1, 0] = (5.0, 0.0, 1.0)
    flight = Flight(pos, quat, 0.1, scene=two)
    np.testing.assert_allclose(viz_html._primitives(flight.scene, 1)[0][1], (5.0, 0.0, 1.0))
    offsets = viz_html._world_offsets(flight, None)  # one scene per world: laid out apart
    assert np.linalg.norm(offsets[1] - offsets[0]) > 2.0
    with pytest.raises(ValueError, match=r"world axes \[2\]"):
        Flight(pos, quat, 0.1, scene=jax.tree.map(lambda x: np.stack([x, x, x]), one))


def test_write_html_rejects_bad_options(tmp_path):
    flight = level(3, [[0, 0, 1]])
    for kwargs, message in [
        ({"trail_s": -1.0}, "trail_s"),
        ({"max_fps": 0}, "max_fps"),
        ({"drone_scale": float("inf")}, "drone_scale"),
        ({"spacing": -1}, "spacing"),
        ({"colors": [(300, 0, 0)]}, "colors"),
        ({"camera": ((0, 0, 1), (0, 0, 1))}, "differ"),
        ({"camera": ((0, 0), (0, 0, 1))}, "camera must be"),
    ]:
        with pytest.raises(ValueError, match=message):
            viz.write_html(tmp_path / "f.html", flight, **kwargs)
    with pytest.raises(TypeError, match="Flight"):
        viz.write_html(tmp_path / "f.html", np.zeros((3, 1, 3)))
    with pytest.raises(ValueError, match="folder"):
        viz.write_html(tmp_path, flight)
    assert not (tmp_path / "f.html").exists()


def test_missing_viser_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ModuleNotFoundError
    with pytest.raises(ModuleNotFoundError, match=re.escape('pip install ".[viewer]" from a clone')):
        viz.write_html(tmp_path / "f.html", level(3, [[0, 0, 1]]))
    assert not (tmp_path / "f.html").exists()


def test_train_without_viser_prints_how_to_get_it(tmp_path, monkeypatch, capsys):
    from jaxdrones.training import writing

    monkeypatch.setattr(viz, "viewer_available", lambda: False)
    writing._write_viewer(None, {"viewer": {}}, str(tmp_path))
    assert capsys.readouterr().out.strip() == (
        f"flight.html not written: the flight viewer needs viser ({viz.VIEWER_INSTALL})"
    )
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------- the HTML file
#: URLs a page loads: script/link/img/iframe sources, CSS url(...) and @import, fetch/import of a literal URL.
FETCHED = re.compile(
    r"""(?:<(?:script|link|img|iframe|source|video|audio)\b[^>]*\b(?:src|href)\s*=\s*["']?\s*"""
    r"""https?:|url\(\s*["']?https?:|@import\s+["']https?:|fetch\(\s*["'`]https?:|"""
    r"""import\(\s*["'`]https?:)""",
    re.IGNORECASE,
)


@needs_viser
def test_html_is_self_contained_and_never_overwritten(tmp_path):
    pos, quat = circle(90, 2, 3)
    images = np.zeros((90, 2, 3, 12, 16, 4), np.uint8)
    flight = Flight(
        pos,
        quat,
        1 / 30,
        scene=[
            Obstacle("box", pos=(0, 0, 0.1)),
            Obstacle("capsule", size=(0.1, 0.3)),
            Obstacle("cylinder", size=(0.1, 0.3)),
            Obstacle("sphere", size=(0.1,)),
        ],
        images=images,
    )
    path = tmp_path / "sub" / "flight.html"
    assert viz.write_html(path, flight) == str(path)
    html = path.read_text(encoding="utf-8")
    assert html.startswith("<!doctype html>") or html.lower().startswith("<!doctype html>")
    assert "window.__VISER_EMBED_DATA__=" in html  # the recording is in the file
    assert FETCHED.findall(html) == []
    assert 100_000 < len(html) < 3_000_000
    before = path.stat().st_mtime_ns, html
    with pytest.raises(FileExistsError, match="overwrite=True"):
        viz.write_html(path, level(2, [[0, 0, 1]]))
    assert (path.stat().st_mtime_ns, path.read_text(encoding="utf-8")) == before
    viz.write_html(path, level(2, [[0, 0, 1]]), overwrite=True)
    assert path.read_text(encoding="utf-8") != html


def test_the_url_check_finds_fetched_urls():
    assert FETCHED.findall('<script src="https://cdn.example/x.js"></script>')
    assert FETCHED.findall("<link rel=stylesheet href='http://a/b.css'>")
    assert FETCHED.findall("body{background:url(https://a/b.png)}")
    assert not FETCHED.findall('<a href="#x">see https://github.com/viser-project/viser</a>')


# --------------------------------------------------------------------------------------------- in a browser
def browse(url: str, width: int = 800, height: int = 600, wait_s: float = 6.0) -> dict:
    """Open ``url`` in headless Chromium through the DevTools protocol: its screenshot (PNG bytes), console errors
    and uncaught exceptions, the URLs it requested, its console lines, and the boxes (x, y, width, height in CSS px)
    of its canvases and of its notifications (e.g. "Software WebGL rendering detected") after ``wait_s`` seconds."""
    from websockets.sync.client import connect

    profile = tempfile.mkdtemp(prefix="jaxdrones-chromium-")
    proc = subprocess.Popen(
        [
            CHROMIUM,
            "--headless=new",
            "--no-sandbox",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--no-first-run",
            "--no-default-browser-check",
            f"--user-data-dir={profile}",
            "--remote-debugging-port=0",
            f"--window-size={width},{height}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        port_file = pathlib.Path(profile, "DevToolsActivePort")
        deadline = time.monotonic() + 60
        while not (port_file.exists() and len(port_file.read_text().split("\n")) >= 2):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("chromium did not start its DevTools server")
            time.sleep(0.1)
        port, ws_path = port_file.read_text().split("\n")[:2]
        events: list[dict] = []
        with connect(f"ws://127.0.0.1:{port}{ws_path}", max_size=None, open_timeout=30) as ws:
            ids = iter(range(1, 1 << 30))

            def call(method, session=None, **params):
                i = next(ids)
                ws.send(
                    json.dumps(
                        {"id": i, "method": method, "params": params, **({"sessionId": session} if session else {})}
                    )
                )
                while True:
                    reply = json.loads(ws.recv(timeout=60))
                    if reply.get("id") == i:
                        if "error" in reply:
                            raise RuntimeError(f"{method}: {reply['error']}")
                        return reply["result"]
                    events.append(reply)

            target = call("Target.createTarget", url="about:blank")["targetId"]
            sid = call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            for domain in ("Runtime", "Log", "Page", "Network"):
                call(f"{domain}.enable", sid)
            call(
                "Emulation.setDeviceMetricsOverride", sid, width=width, height=height, deviceScaleFactor=1, mobile=False
            )
            call("Page.navigate", sid, url=url)
            end = time.monotonic() + wait_s
            while (left := end - time.monotonic()) > 0:
                try:
                    events.append(json.loads(ws.recv(timeout=left)))
                except TimeoutError:
                    break
            png = base64.b64decode(call("Page.captureScreenshot", sid, format="png")["data"])
            boxes = call(
                "Runtime.evaluate",
                sid,
                returnByValue=True,
                expression=(
                    "JSON.stringify(['canvas', '[class*=Notification-root]'].map(s => [...document.querySelectorAll(s)]"
                    ".map(c => {const r = c.getBoundingClientRect(); return [r.x, r.y, r.width, r.height]})))"
                ),
            )["result"]["value"]
    finally:
        proc.terminate()
        proc.wait(30)
        shutil.rmtree(profile, ignore_errors=True)
    errors, requested = [], []
    for event in events:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            errors.append(" ".join(str(a.get("value", a.get("description"))) for a in params.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            errors.append(json.dumps(params["exceptionDetails"])[:500])
        elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
            errors.append(params["entry"]["text"])
        elif method == "Network.requestWillBeSent":
            requested.append(params["request"]["url"])
    logs = [
        " ".join(str(a.get("value")) for a in e["params"].get("args", []))
        for e in events
        if e.get("method") == "Runtime.consoleAPICalled"
    ]
    canvases, notices = json.loads(boxes)
    return {
        "png": png,
        "errors": errors,
        "requested": requested,
        "canvases": canvases,
        "notices": notices,
        "logs": logs,
    }


def project(points, eye, target, fov_deg: float, width: float, height: float) -> np.ndarray:
    """Pixel (column, row) of world points f[N, 3] in a pinhole view from ``eye`` towards ``target``, z up, vertical
    field of view ``fov_deg`` (three.js' PerspectiveCamera) on a width × height canvas."""
    forward = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    right = np.cross(forward, (0, 0, 1))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = np.asarray(points, float) - eye
    depth = rel @ forward
    f = (height / 2) / math.tan(math.radians(fov_deg) / 2)
    return np.stack([width / 2 + f * (rel @ right) / depth, height / 2 - f * (rel @ up) / depth], -1)


def hue_mask(rgb: np.ndarray, hue_deg: float, tol_deg: float = 14.0) -> np.ndarray:
    """bool[H, W]: saturated, not dark pixels whose hue is within ``tol_deg`` of ``hue_deg``."""
    hsv = np.asarray([colorsys.rgb_to_hsv(*p) for p in rgb.reshape(-1, 3) / 255.0]).reshape(rgb.shape)
    dist = np.abs((hsv[..., 0] * 360 - hue_deg + 180) % 360 - 180)
    return (dist < tol_deg) & (hsv[..., 1] > 0.45) & (hsv[..., 2] > 0.25)


#: The browser test's drones: position (m), colour, and its hue as drawn under viser's lights (green's shifts to
#: about 95°), far apart.
MARKERS = (
    ((-1.3, 0.2, 0.6), (0, 0, 255), 240.0),
    ((1.2, -0.3, 0.4), (0, 255, 0), 100.0),
    ((0.2, 1.4, 1.1), (255, 0, 255), 303.0),
    ((0.4, -1.2, 0.9), (255, 255, 0), 59.0),
)


@pytest.mark.slow
@needs_viser
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (Debian: apt-get install chromium)")
def test_browser_shows_the_drones_where_the_rollout_puts_them(tmp_path):
    from PIL import Image

    positions = np.array([m[0] for m in MARKERS])
    flight = level(40, positions)
    eye, target = np.array([0.5, -5.0, 3.5]), np.array([0.0, 0.0, 0.7])
    path = tmp_path / "four.html"
    viz.write_html(path, flight, camera=(eye, target), trail_s=0, drone_scale=3.0, colors=[m[1] for m in MARKERS])
    page = browse(path.resolve().as_uri())
    assert page["errors"] == [], page["errors"]
    assert any("Embedded data loaded" in line for line in page["logs"]), page["logs"]
    assert page["requested"] and all(u.startswith(("file:", "data:", "blob:")) for u in page["requested"]), page[
        "requested"
    ]
    x0, y0, w, h = max(page["canvases"], key=lambda b: b[2] * b[3])
    assert w == 800 and 500 < h <= 600  # the canvas above the playback bar
    shot = np.array(Image.open(io.BytesIO(page["png"])).convert("RGB"))
    for x, y, bw, bh in page["notices"]:  # a notice over the canvas is not the scene
        shot[max(int(y), 0) : int(y + bh) + 1, max(int(x), 0) : int(x + bw) + 1] = 255
    canvas = shot[int(y0) : int(y0 + h), int(x0) : int(x0 + w)]
    expected = project(positions, eye, target, viz.VIEW_FOV, w, h)
    rows, cols = np.mgrid[0 : canvas.shape[0], 0 : canvas.shape[1]]
    for (where, _, hue), (u, v) in zip(MARKERS, expected, strict=True):
        mask = hue_mask(canvas, hue)
        near = (cols - u) ** 2 + (rows - v) ** 2 < 35**2
        assert mask[near].sum() >= 25, (
            f"drone at {where}: {mask[near].sum()} pixels of its colour near ({u:.0f}, {v:.0f})"
        )
        assert mask[~near].sum() <= 5, f"drone at {where}: {mask[~near].sum()} pixels of its colour elsewhere"
        centre = np.array([cols[mask].mean(), rows[mask].mean()])
        assert np.linalg.norm(centre - (u, v)) < 12, f"drone at {where} drawn at {centre}, expected ({u:.0f}, {v:.0f})"


# --------------------------------------------------------------------------------------------- videos
def test_video_draws_the_drone_where_it_is(tmp_path):
    from PIL import Image

    pos = np.array([[0.0, 0.0, 1.0], [0.0, 3.0, 1.0]]) + np.linspace(0, 0.3, 6)[:, None, None] * [1, 0, 0]
    flight = Flight(pos, np.tile([0.0, 0, 0, 1], (6, 2, 1)), 1 / 30)  # drone 0 moves away along the optical axis
    eye, target = np.array([-0.8, 0.0, 1.6]), np.array([0.0, 0.0, 1.0])  # drone 0 ahead, below; drone 1 out of view
    path = viz.write_video(tmp_path / "v.gif", flight, camera=(eye, target), width=128, height=96, trail_s=0)
    gif = Image.open(path)
    assert gif.n_frames == 6 and gif.size == (128, 96)
    frame = np.asarray(gif.convert("RGB")).astype(int)
    blue = np.all(np.abs(frame - viz.DRONE_COLORS[0]) < 60, axis=-1)  # drone 0's colour, shaded
    rows, cols = np.nonzero(blue)
    assert blue.sum() >= 10 and abs(cols.mean() - 63.5) < 3 and abs(rows.mean() - 47.5) < 3  # at the image's centre
    ground = np.all(frame == 184, axis=-1)  # GROUND_RGB 0.72 (the view looks down: no sky)
    assert ground.mean() > 0.8 and not np.any(np.all(frame == viz.SKY_RGB, axis=-1))
    with pytest.raises(FileExistsError):
        viz.write_video(path, flight, camera="fixed")
    chase = viz.write_video(tmp_path / "c.mp4", flight, camera="chase", drone=1, width=32, height=24)
    assert os.path.getsize(chase) > 0


def test_video_rejects_bad_options(tmp_path):
    flight = level(3, [[0, 0, 1]])
    for kwargs, message in [
        ({"camera": "orbit"}, "camera must be one of"),
        ({"world": 1}, r"world must be an index in \[0, 1\)"),
        ({"drone": -1}, "drone must be"),
        ({"chase": (0, 0)}, "chase must be"),
        ({"width": 0}, "width"),
        ({"max_fps": 0}, "max_fps"),
    ]:
        with pytest.raises(ValueError, match=message):
            viz.write_video(tmp_path / "v.gif", flight, **kwargs)
    with pytest.raises(ValueError, match="extension"):
        viz.write_video(tmp_path / "v.avi", flight)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------- envs and runs
@pytest.mark.slow
@needs_viser
def test_flight_of_a_vision_env_with_a_gate_per_episode(tmp_path):
    import jax

    import jaxdrones as jd
    from jaxdrones.training.recipes import recipe

    env = jd.make("fly_thru_gate", **recipe("fly_thru_gate", "cpu", {"vision": ("rgb",)}).env)

    def episode(key):  # the reset state and 3 steps of a zero action
        state = env.reset(key)

        def step(s, _):
            s = env.step(s, jax.numpy.zeros((env.n_drones, env.action_size)))
            return s, s

        _, states = jax.lax.scan(step, state, None, length=3)
        return jax.tree.map(lambda a, b: jax.numpy.concatenate([a[None], b]), state, states)

    states = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(0), 2))
    flight = Flight.from_states(env, states, time_axis=1)
    assert (flight.n_frames, flight.n_worlds, flight.n_drones) == (4, 2, 1)
    assert flight.dt == pytest.approx(1 / env.config.sim.ctrl_freq)
    assert flight.images.shape == (4, 2, 1, 48, 64, 3)
    gates = [np.array([c for _, c, *_ in viz_html._primitives(flight.scene, w)]) for w in range(2)]
    assert len(gates[0]) == 3 and not np.allclose(gates[0], gates[1])  # the gate's three boxes, drawn per episode
    assert np.linalg.norm(viz_html._world_offsets(flight, None)[1]) > 2.0  # episodes side by side
    html = tmp_path / "gate.html"
    viz.write_html(html, flight)
    assert html.stat().st_size > 100_000


@pytest.mark.slow
@needs_viser
def test_train_writes_flight_html_and_view_writes_a_run(tmp_path, capsys):
    from jaxdrones.cli import main
    from jaxdrones.training import train_task
    from jaxdrones.training.apg import APGConfig

    out = str(tmp_path / "hover")
    summary = train_task(
        "hover",
        out,
        algo="apg",
        config=APGConfig(num_timesteps=16_384, num_evals=1),
        n_eval_episodes=64,
        progress=False,
    )
    assert os.path.getsize(os.path.join(out, "flight.html")) > 100_000
    assert summary["phases_s"]["viewer"] < 30
    assert main(["view", out, "--episodes", "2", "--out", str(tmp_path / "v.html")]) == 0
    assert "wrote" in capsys.readouterr().out and (tmp_path / "v.html").stat().st_size > 100_000
    assert main(["view", out, "--episodes", "2", "--out", str(tmp_path / "v.html")]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--out", str(tmp_path / "w.html")]) == 2  # no policy there
    assert "no saved policy" in capsys.readouterr().err
    assert main(["view", str(tmp_path), "--out", str(tmp_path / "w.html")]) == 2  # runs in its folders
    assert "holds no policy of its own but runs in its folders: give one of them (hover)" in capsys.readouterr().err


@pytest.mark.slow
@needs_viser
def test_docs_train_then_view_lines_run_as_written(tmp_path):
    """docs/viewer.md's ``jaxdrones train hover && jaxdrones view runs/hover --episodes 4``, in a fresh folder: the
    view replaces the run's own flight.html (the training run wrote it) with the four episodes, exit status 0, and
    the page loads its recording in a browser."""
    line = re.search(r"^jaxdrones train hover && jaxdrones view .*$", (DOCS / "viewer.md").read_text(), re.M)
    done = subprocess.run(
        ["bash", "-c", line.group(0).replace("jaxdrones ", f"{sys.executable} -m jaxdrones.cli ")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "wrote" in done.stdout and "4 evaluation episodes" in done.stdout
    html = tmp_path / "runs" / "hover" / "flight.html"
    assert html.stat().st_size > 100_000 and html.stat().st_mtime >= (html.parent / "summary.json").stat().st_mtime
    if CHROMIUM is None:
        pytest.skip("the page in a browser: chromium is not installed (Debian: apt-get install chromium)")
    page = browse(html.resolve().as_uri())
    assert page["errors"] == [], page["errors"]
    assert any("Embedded data loaded" in line for line in page["logs"]), page["logs"]
    assert max(w * h for _, _, w, h in page["canvases"]) > 300 * 300


def test_flight_data_takes_the_newest_frame_of_a_stack():
    from types import SimpleNamespace

    pos, quat = circle(3, 1, 2)
    sim = SimpleNamespace(pos=pos[:, 0], quat=quat[:, 0])  # [T, D, ...]
    stack = np.zeros((3, 2, 4, 6, 8, 4), np.uint8)  # [T, D, K, H, W, 4]
    stack[:, :, -1] = 200
    states = SimpleNamespace(sim=sim, params=SimpleNamespace(arm=np.full(2, 0.05)), task=None, obs={"rgb": stack})
    data = viz.flight_data(states)
    assert data["images"].shape == (3, 2, 6, 8, 4) and np.all(data["images"] == 200) and data["scene"] is None
    single = viz.flight_data(SimpleNamespace(**{**vars(states), "obs": {"rgb": stack[:, :, 0]}}))["images"]
    assert single.shape == (3, 2, 6, 8, 4)
    depth = viz.flight_data(SimpleNamespace(**{**vars(states), "obs": {"depth": np.ones((3, 2, 4, 6, 8))}}))["images"]
    assert depth.shape == (3, 2, 6, 8)
