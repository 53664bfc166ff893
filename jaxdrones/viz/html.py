"""The flight viewer: a `jaxdrones.viz.Flight` as one self-contained HTML file that plays offline (viser's scene
serializer and static client; the ``viewer`` extra)."""

from __future__ import annotations

import dataclasses
import math
import os
import socket

import numpy as np

from jaxdrones._validate import check_real
from jaxdrones.io.runs import write_file
from jaxdrones.viz.flight import (
    Colors,
    Flight,
    View,
    check_target,
    drone_colours,
    drone_palette,
    resolve_view,
    wxyz,
    wxyz_from_rotmat,
)

#: What installs viser (the HTML viewer's only optional dependency): the ``viewer`` extra, from a clone of the project.
VIEWER_INSTALL = 'pip install ".[viewer]" from a clone of jaxdrones, or pip install viser "websockets<17"'
#: The HTML viewer's initial vertical field of view, degrees.
VIEW_FOV = 50.0


def _primitives(scene, world: int) -> list[tuple]:
    """The valid primitives of world ``world`` of a `Flight.scene`: (shape, centre, rotation, size, rgb) with
    `jaxdrones.cameras.Primitives`' size convention (half extents; radius; radius and half length)."""
    if scene is None:
        return []
    out = []
    for shape in ("box", "sphere", "cylinder", "capsule"):
        p = getattr(scene, shape)
        if p.valid.ndim == 2:  # one scene per world: this world's
            p = type(p)(**{f.name: getattr(p, f.name)[world] for f in dataclasses.fields(p)})
        out += [(shape, p.pos[i], p.rot[i], p.size[i], p.rgb[i]) for i in np.flatnonzero(p.valid)]
    return out


def _drone_mesh(arm: float) -> tuple[np.ndarray, np.ndarray]:
    """A quadrotor of arm length ``arm`` m as one triangle mesh (vertices f[V, 3] m, body frame; faces i32[F, 3]):
    a square plate, four rotor disks on the diagonals (the cf2x's X layout) and a nose along body +x that shows the
    heading."""
    side = 1.13 * arm  # `jaxdrones.sensors.camera.BODY_SIDE_PER_ARM`, as the cameras draw the plate
    d = arm / math.sqrt(2)
    parts = [
        _prism(4, (side / 2, side / 2, 0.006), (0.0, 0.0, 0.0)),
        _prism(4, (0.45 * arm, 0.125 * arm, 0.006), (side / 2 + 0.3 * arm, 0.0, 0.0)),
    ]
    parts += [_prism(20, (0.58 * arm, 0.58 * arm, 0.002), (sx * d, sy * d, 0.008)) for sx in (1, -1) for sy in (1, -1)]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts]).astype(np.float32)
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)]).astype(np.int32)
    return vertices, faces


def _prism(sections: int, half: tuple[float, float, float], centre: tuple[float, float, float]):
    """A closed right prism along z over a regular polygon of ``sections`` sides (4: a box, its sides along x and y;
    more: a cylinder), half extents ``half`` m, at ``centre``: (vertices f[2n + 2, 3], faces i[4n, 3]), each face
    wound counter-clockwise seen from outside."""
    n = sections
    angle = 2 * np.pi * (np.arange(n) + 0.5) / n
    scale = np.sqrt(2) if n == 4 else 1.0  # the square's corners at (±hx, ±hy)
    ring = np.stack([scale * np.cos(angle) * half[0], scale * np.sin(angle) * half[1]], -1)
    bottom, top = np.c_[ring, -np.full(n, half[2])], np.c_[ring, np.full(n, half[2])]
    vertices = np.concatenate([bottom, top, [[0.0, 0.0, -half[2]], [0.0, 0.0, half[2]]]]) + np.asarray(centre)
    i, j = np.arange(n), (np.arange(n) + 1) % n
    faces = np.concatenate(
        [
            np.stack([i, j, j + n], -1),  # the sides, counter-clockwise from outside
            np.stack([i, j + n, i + n], -1),
            np.stack([np.full(n, 2 * n), j, i], -1),  # the bottom cap, seen from below
            np.stack([np.full(n, 2 * n + 1), i + n, j + n], -1),  # the top cap, seen from above
        ]
    )
    return vertices, faces


def _world_offsets(flight: Flight, spacing: float | None) -> np.ndarray:
    """f[W, 3]: where each world is drawn, m: all at the origin (``spacing`` 0), or on a square grid of that pitch."""
    n = flight.n_worlds
    if spacing is None:
        per_world = flight.scene is not None and flight.scene.box.pos.ndim == 3 and n > 1
        if not per_world:
            return np.zeros((n, 3))
        span = float(np.ptp(flight.pos[..., :2], axis=(0, 2)).max())
        reach = [
            np.abs(c[:2] - flight.pos[0, w, :, :2].mean(0)).max() + 2 * np.max(s)
            for w in range(n)
            for _, c, _, s, _ in _primitives(flight.scene, w)
        ]
        spacing = 2 * max([span, *reach]) + 1.0
    cols = math.ceil(math.sqrt(n))
    w = np.arange(n)
    return np.stack([(w % cols) * spacing, -(w // cols) * spacing, np.zeros(n)], -1)


def _viser():
    """Import viser, or raise one ModuleNotFoundError that names the extra to install."""
    try:
        import viser
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(f"the flight viewer needs viser: {VIEWER_INSTALL}", name="viser") from err
    return viser


def viewer_available() -> bool:
    """Whether viser (the ``viewer`` extra) is installed, so that `write_html` can run."""
    import importlib.util

    return importlib.util.find_spec("viser") is not None


def write_html(
    path: str | os.PathLike,
    flight: Flight,
    *,
    overwrite: bool = False,
    trail_s: float | None = 2.0,
    max_fps: float = 30.0,
    spacing: float | None = None,
    camera: View | None = None,
    drone_scale: float = 1.0,
    colors: Colors | None = None,
    dark_mode: bool = False,
) -> str:
    """Write ``flight`` as one self-contained HTML file that plays offline (from ``file://``, no server).

    The file is viser's static client with the recorded scene embedded (no URL is fetched): the ground grid, the
    scene's boxes, spheres, cylinders and capsules, the drones as small quadrotors (a nose marks body +x) in a colour
    per drone index, or per world for flights of one drone (`DRONE_COLORS`), their trails, and with
    ``flight.images`` a panel per drone of world 0 (`MAX_PANELS` at most) showing its camera frames beside the
    flight, facing the initial view. The page has play/pause (also the space bar), a time slider, playback speed and
    a view to orbit, pan and zoom. Worlds are drawn at the same place unless the scene differs per world, where they
    are laid out on a grid (see ``spacing``).

    Args:
        path: the file to write (``.html``); parent folders are created.
        flight: the `Flight`.
        overwrite: replace an existing page that `write_html` wrote (`GENERATOR`; otherwise FileExistsError, and
            ValueError for any other file, which is kept).
        trail_s: how far back each trail reaches, s; None: the whole flight; 0: no trails.
        max_fps: the recording's frame rate at most, Hz: frames are skipped to stay at or below it (the time axis
            is kept: playback runs at real time).
        spacing: the pitch, m, of the grid the worlds are laid out on; 0: all at the origin; None: at the origin
            unless the scene is per world, then a pitch that keeps the worlds apart.
        camera: the initial view, ``(position, look_at)`` in m (world frame), z up, `VIEW_FOV` vertically; None:
            from the front left and above, framing the drones' paths.
        drone_scale: draw the drones this many times their size (> 0), e.g. to see small drones in a large arena.
        colors: RGB 0-255 per drone index (per world with one drone), a sequence of (r, g, b), cycled; default
            `DRONE_COLORS`.
        dark_mode: the viewer's dark theme.

    Returns:
        The path written.

    Raises:
        TypeError: ``flight`` is not a `Flight`.
        ModuleNotFoundError: viser is not installed (`VIEWER_INSTALL`).
        FileExistsError: ``path`` exists and not ``overwrite``.
        ValueError: ``overwrite`` of a file `write_html` did not write, or a bad option.
        ValueError: a bad option (a negative trail, a frame rate or scale that is not positive, a camera that is not
            two points, colours that are not RGB triples).
    """
    if not isinstance(flight, Flight):
        raise TypeError(
            f"flight must be a jaxdrones.viz.Flight (e.g. Flight(pos, quat, dt)), got {type(flight).__name__}"
        )
    path = os.fspath(path)
    check_target(path, overwrite, GENERATOR.encode())
    if trail_s is not None:
        check_real("trail_s", trail_s, 0, what="None or a finite number of seconds")
    for name, value in (("max_fps", max_fps), ("drone_scale", drone_scale)):
        check_real(name, value, 0, low_open=True, what="a finite number")
    if spacing is not None:
        check_real("spacing", spacing, 0, what="None or a finite number of metres")
    palette = drone_palette(colors)
    offsets = _world_offsets(flight, spacing)
    eye, target = resolve_view(flight, offsets, camera)
    viser = _viser()
    html = _record(viser, flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode)
    folder = os.path.dirname(path)
    if folder:
        os.makedirs(folder, exist_ok=True)
    html = html.replace("<head>", f"<head>{GENERATOR}", 1) if "<head>" in html else GENERATOR + html
    write_file(path, html)
    return path


#: The mark of every page `write_html` writes: ``overwrite`` replaces only a page that holds it.
GENERATOR = '<meta name="generator" content="jaxdrones flight viewer">'


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _record(viser, flight: Flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode) -> str:
    """Build the scene in a viser server bound to localhost (no client ever connects), record the frames with its
    scene serializer and return the static client with the recording embedded."""
    import rich  # viser's: it prints its banner on start and a line on stop through rich's console

    console, was_quiet = rich.get_console(), rich.get_console().quiet
    console.quiet = True  # silent in a terminal and in a notebook's cell; the stop's line comes from the server's
    try:  # thread, which `stop` joins
        server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
        try:
            return _build(server, flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode)
        finally:
            server.stop()
    finally:
        console.quiet = was_quiet


def _build(server, flight: Flight, offsets, eye, target, trail_s, max_fps, drone_scale, palette, dark_mode) -> str:
    scene = server.scene
    scene.set_up_direction("+z")
    n_w, n_d = flight.n_worlds, flight.n_drones
    pos = flight.pos + offsets[None, :, None, :]  # [T, W, D, 3]
    n = n_w * n_d
    colours = drone_colours(palette, n_w, n_d).reshape(n, 3)
    corners = [pos.reshape(-1, 3), target[None]]
    corners += [
        (c + offsets[w] + np.abs(r) @ h)[None] for w in range(n_w) for _, c, r, h, _ in _primitives(flight.scene, w)
    ]
    corners += [
        (c + offsets[w] - np.abs(r) @ h)[None] for w in range(n_w) for _, c, r, h, _ in _primitives(flight.scene, w)
    ]
    lo, hi = np.concatenate(corners).min(0) - 0.5, np.concatenate(corners).max(0) + 0.5
    size = float(np.ceil(max(hi[0] - lo[0], hi[1] - lo[1], 2.0)))
    scene.add_grid(
        "/ground",
        width=size,
        height=size,
        plane="xy",
        cell_size=0.25,
        section_size=1.0,
        position=(float(round((lo[0] + hi[0]) / 2)), float(round((lo[1] + hi[1]) / 2)), 0.0),
        shadow_opacity=0.0,
    )
    for w in range(n_w):
        if w > 0 and (flight.scene is None or flight.scene.box.pos.ndim == 2) and not np.any(offsets[w]):
            break  # one scene for all worlds drawn at one place: once
        for k, (shape, centre, rot, half, rgb) in enumerate(_primitives(flight.scene, w)):
            _add_primitive(
                scene,
                f"/scene/w{w}/{shape}{k}",
                shape,
                centre + offsets[w],
                rot,
                half,
                tuple(int(c) for c in np.round(255 * np.clip(rgb, 0, 1))),
            )
    vertices, faces = _drone_mesh(flight.arm * drone_scale)
    drones = scene.add_batched_meshes_simple(
        "/drones",
        vertices,
        faces,
        batched_wxyzs=wxyz(flight.quat[0]).reshape(n, 4),
        batched_positions=pos[0].reshape(n, 3),
        batched_colors=colours,
        lod="off",
        material="toon3",
        cast_shadow=False,
        receive_shadow=False,
    )  # toon: saturated colours under viser's bright default lights
    server.initial_camera.position = tuple(eye)
    server.initial_camera.look_at = tuple(target)
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.fov = math.radians(VIEW_FOV)
    panels = _add_panels(scene, flight, eye, target, lo, hi)
    stride = max(1, math.ceil(1.0 / (flight.dt * max_fps)))
    frames = list(range(0, flight.n_frames, stride))
    if frames[-1] != flight.n_frames - 1:
        frames.append(flight.n_frames - 1)
    keep = None if trail_s is None else math.ceil(trail_s / (stride * flight.dt))
    serializer = server.get_scene_serializer()
    trails = []
    for i, t in enumerate(frames):
        if i > 0:
            serializer.insert_sleep((t - frames[i - 1]) * flight.dt)
            drones.batched_positions = pos[t].reshape(n, 3)
            drones.batched_wxyzs = wxyz(flight.quat[t]).reshape(n, 4)
            if keep != 0:
                segment = np.stack([pos[frames[i - 1]], pos[t]], axis=-2).reshape(n, 2, 3)
                trails.append(
                    scene.add_line_segments(
                        f"/trails/{i}",
                        segment,
                        colors=np.repeat(colours[:, None], 2, 1),
                        thickness=1.5,
                        thickness_units="screen",
                    )
                )
                if keep is not None and len(trails) > keep:
                    trails.pop(0).remove()
        for d, panel in enumerate(panels):
            if i == 0 or not np.array_equal(flight.images[t, 0, d], flight.images[frames[i - 1], 0, d]):
                panel.image = flight.images[t, 0, d]
    if len(frames) == 1:  # a single frame: a still scene
        serializer.insert_sleep(flight.dt)
    return serializer.as_html(dark_mode=dark_mode)


def _add_primitive(scene, name: str, shape: str, centre, rot, half, rgb) -> None:
    """One obstacle (`jaxdrones.cameras.Primitives` conventions) as a viser shape."""
    quat = wxyz_from_rotmat(rot)
    centre = tuple(float(c) for c in centre)
    if shape == "box":
        scene.add_box(name, color=rgb, dimensions=tuple(2 * float(h) for h in half), wxyz=quat, position=centre)
    elif shape == "sphere":
        scene.add_icosphere(name, radius=float(half[0]), color=rgb, position=centre)
    elif shape == "cylinder":
        scene.add_cylinder(
            name, radius=float(half[0]), height=2 * float(half[1]), color=rgb, wxyz=quat, position=centre
        )
    else:
        import trimesh

        mesh = trimesh.creation.capsule(height=2 * float(half[1]), radius=float(half[0]))  # along z, centred
        scene.add_mesh_simple(
            name,
            np.asarray(mesh.vertices, np.float32),
            np.asarray(mesh.faces, np.int32),
            color=rgb,
            wxyz=quat,
            position=centre,
        )


#: Camera panels drawn at most (world 0's first drones).
MAX_PANELS = 4


def _add_panels(scene, flight: Flight, eye, target, lo, hi) -> list:
    """Image panels for world 0's drones' camera frames: upright, facing the initial view, in a column beside the
    flight (to its right as seen from the initial view)."""
    if flight.images is None:
        return []
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= max(np.linalg.norm(right), 1e-9)
    up = np.cross(right, forward)
    rot = np.stack([right, -up, forward], axis=1)  # the image plane's x right, y down, z away from the viewer
    quat = wxyz_from_rotmat(rot)
    h, w = flight.images.shape[3:5]
    extent = float(np.linalg.norm(hi - lo))
    height = max(0.5 * extent / MAX_PANELS, 0.15)
    width = height * w / h
    centre = (lo + hi) / 2
    half = float(np.abs(right) @ (hi - lo)) / 2  # the box [lo, hi]'s half extent along the view's right
    panels = []
    count = min(flight.n_drones, MAX_PANELS)
    middle = centre + right * (half + 0.2 + width / 2)
    middle[2] = target[2]
    middle[2] = max(middle[2], 1.1 * height * count / 2 + 0.05)  # the lowest panel above the ground
    for d in range(count):
        centre = middle + up * (height * 1.1 * ((count - 1) / 2 - d))
        panels.append(
            scene.add_image(
                f"/cameras/drone{d}",
                flight.images[0, 0, d],
                width,
                height,
                format="png",
                wxyz=quat,
                position=tuple(centre),
                cast_shadow=False,
                receive_shadow=False,
            )
        )
    return panels


#: Evaluation episodes ``jaxdrones view`` flies by default, and ``jaxdrones train`` shows in its flight.html.
VIEW_EPISODES = 4
