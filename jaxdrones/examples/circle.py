"""The paper's first example: Crazyflies tracking a circle with the DSL PID controller (``jaxdrones fly``).

Reproduces gym-pybullet-drones ``examples/pid.py`` (docs/physics.md §13) on the jaxdrones physics (the explicit
model, optionally with drag, ground effect and downwash):

* drone i starts at (R cos(2πi/6 + π/2), R sin(2πi/6 + π/2) − R, H + i·H_STEP) with R = 0.3 m, H = 0.1 m,
  H_STEP = 0.05 m, and rpy = (0, 0, i·(π/2)/N);
* NUM_WP = 10·ctrl_freq way-points WP_k = (R cos(2πk/NUM_WP + π/2) + x_0, R sin(2πk/NUM_WP + π/2) − R + y_0) on
  one circle (period 10 s); drone i starts at index ⌊i·NUM_WP/6⌋ mod NUM_WP and advances one index per control
  step, at its own start altitude and with its start rpy as the target;
* 240 Hz physics, 48 Hz control, 12 s; the first control step applies 0 RPM, then each step applies the PID
  command computed from the state reached by the previous one.

The whole flight is one jitted ``lax.scan`` (`jaxdrones.examples.closed_loop`, shared with the other examples of
``jaxdrones fly --example``), on either physics backend: the JAX core (default) or PyBullet
(``backend="pybullet"``, optionally among the obstacles of `jaxdrones.scene.PAPER_OBSTACLES`, placed
around the circle), where the same scan calls Bullet through a host callback. With a video (PyBullet only) or the
PyBullet GUI the scan runs in chunks of a few control steps, and a third-person frame is rendered after each
chunk; the chunks give the same flight as one scan.

Tracking metrics (``result["metrics"]``), each an RMS over all control steps with t ≥ ``settle_s`` (default 1 s,
which leaves out the take-off transient: the drones start at rest while their way-points already move, and the
first PID call sees the derivative spike of the non-zero initial yaw):

* ``waypoint``: ‖p(t_k) − WP(t_k)‖, the 3-D distance to the way-point commanded at t_k (the moving target);
* ``cross_track``: the 3-D distance from p(t_k) to the nearest point of the drone's reference circle (at its
  target altitude), i.e. the error regardless of the lag along the path.

Without velocity feed-forward the PID lags its moving way-point by about half a second (≈ 9 cm at 0.19 m/s, as
measured on the original, docs/physics.md §12.5), while staying within millimetres of the path. With ``feedforward``
(the default), the way-point's velocity is passed as ``target_vel`` and the lag almost disappears.

Contacts (``result["contacts"]``), from `DroneState.contact`: the control steps in which each drone touched the
ground, an obstacle or another drone (the JAX backend models the ground only).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_int, check_real, is_integer
from jaxdrones.backends import require_pybullet
from jaxdrones.control.pid import PIDGains
from jaxdrones.examples.closed_loop import (
    bind_arguments,
    check_flight_settings,
    closed_loop,
    flight_arrays,
    flight_settings,
    initial_carry,
    pid_title,
    run_closed_loop,
    track_position,
)
from jaxdrones.io.video import VideoWriter, video_format
from jaxdrones.physics.state import CONTACT_DRONE, CONTACT_GROUND, CONTACT_OBSTACLE, init_state
from jaxdrones.scene import Obstacle, resolve_obstacles
from jaxdrones.sim import make_step

#: Circle radius (m), first altitude (m) and altitude step between drones (m) of the paper's example (§13).
RADIUS = 0.3
HEIGHT = 0.1
HEIGHT_STEP = 0.05
#: Seconds per lap: the example has NUM_WP = 10·ctrl_freq way-points, one per control step.
LAP_S = 10
#: Whether `fly_circle` feeds the way-point velocity forward by default: it cuts the RMS error to the moving
#: way-point from ≈ 9 cm to < 1 cm and does not worsen the cross-track error (see the module docstring).
DEFAULT_FEEDFORWARD = True
#: Default length of the excluded initial transient, s.
DEFAULT_SETTLE_S = 1.0
#: Defaults of the third-person video (PyBullet backend): frame size (width, height) in pixels and frame rate, Hz.
DEFAULT_VIDEO_SIZE = (640, 480)
DEFAULT_VIDEO_FPS = 24.0
#: The video's camera: distance from the circle's centre (m), yaw and pitch (degrees), as in `PyBulletStep.render`.
VIDEO_CAMERA = dict(distance=1.7, yaw=-30.0, pitch=-35.0)


def circle_setup(num_drones: int, ctrl_freq: int = 48) -> dict:
    """Start poses and way-points of the paper's example (docs/physics.md §13), as float64 NumPy arrays.

    Returns:
        dict with ``init_pos`` f[N, 3] m, ``init_rpy`` f[N, 3] rad, ``waypoints`` f[NUM_WP, 2] m (x, y),
        ``wp_start`` int[N] (each drone's first way-point index), ``center`` f[2] m (the circle's centre) and
        ``num_wp``.
    """
    i = np.arange(num_drones)
    angle = 2 * np.pi * i / 6 + np.pi / 2
    init_pos = np.stack([RADIUS * np.cos(angle), RADIUS * np.sin(angle) - RADIUS, HEIGHT + i * HEIGHT_STEP], -1)
    init_rpy = np.stack([np.zeros(num_drones), np.zeros(num_drones), i * (np.pi / 2) / num_drones], -1)
    num_wp = ctrl_freq * LAP_S
    k = np.arange(num_wp)
    x0, y0 = init_pos[0, 0], init_pos[0, 1]
    waypoints = np.stack(
        [
            RADIUS * np.cos(2 * np.pi * k / num_wp + np.pi / 2) + x0,
            RADIUS * np.sin(2 * np.pi * k / num_wp + np.pi / 2) - RADIUS + y0,
        ],
        -1,
    )
    wp_start = np.array([int((j * num_wp / 6) % num_wp) for j in range(num_drones)])
    return dict(
        init_pos=init_pos,
        init_rpy=init_rpy,
        waypoints=waypoints,
        wp_start=wp_start,
        center=np.array([x0, y0 - RADIUS]),
        num_wp=num_wp,
    )


def circle_targets(setup: dict, n_steps: int, ctrl_freq: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Way-point position and velocity commanded at each control step, f[T, N, 3] m and m/s (world frame).

    Step k uses way-point (wp_start + k) mod NUM_WP at the drone's start altitude. The velocity is the tangent of
    the circle at that way-point for the way-points' speed (one index per control step, one lap per 10 s).
    """
    num_wp = setup["num_wp"]
    idx = (setup["wp_start"][None, :] + np.arange(n_steps)[:, None]) % num_wp
    xy = setup["waypoints"][idx]
    z = np.broadcast_to(setup["init_pos"][:, 2], idx.shape)
    theta = 2 * np.pi * idx / num_wp + np.pi / 2
    speed = RADIUS * 2 * np.pi * ctrl_freq / num_wp
    vel = np.stack([-speed * np.sin(theta), speed * np.cos(theta), np.zeros(idx.shape)], -1)
    return np.concatenate([xy, z[..., None]], -1), vel


def check_flight(*args: Any, **kwargs: Any) -> dict:
    """Validate `fly_circle`'s arguments (the same, by position or name) without flying (cheap; `fly_circle` calls
    it first).

    Returns:
        dict with ``config`` (`SimConfig`), ``n_steps``, ``params`` (`DroneParams`), ``obstacles`` (the resolved
        tuple of `jaxdrones.scene.Obstacle`) and ``video_size`` (width, height).

    Raises:
        ValueError: see `fly_circle`.
        RuntimeError: ``gui`` without a display.
        ModuleNotFoundError: ``backend="pybullet"`` without pybullet installed.
        TypeError: an argument `fly_circle` does not take.
    """
    a = bind_arguments(fly_circle, args, kwargs)
    config, n_steps, params = check_flight_settings(a, n_drones=check_int("num_drones", a["num_drones"]))
    settle_s, ctrl_freq, backend, obstacles, gui, video, video_size = (
        a[k] for k in ("settle_s", "ctrl_freq", "backend", "obstacles", "gui", "video", "video_size")
    )
    if not math.isfinite(settle_s) or settle_s < 0 or settle_s >= n_steps / ctrl_freq:
        raise ValueError(f"settle_s must be in [0, {n_steps / ctrl_freq}) s (the flight time), got {settle_s!r}")
    resolved = ()
    if backend == "jax":
        for name, value in (("obstacles", obstacles not in (None, False)), ("gui", gui), ("video", video)):
            if value:
                raise ValueError(f"{name} needs backend='pybullet' (the jax backend has no obstacles, GUI or renderer)")
    else:
        require_pybullet()
        resolved = resolve_obstacles(obstacles)
    if video is not None:
        video = os.fspath(video)
        video_format(video)
        if os.path.exists(video):
            raise ValueError(f"video file {video!r} exists; choose another name (it is never overwritten)")
    if (
        not isinstance(video_size, (tuple, list))
        or len(video_size) != 2
        or not all(is_integer(v) and 1 <= v <= 8192 for v in video_size)
    ):
        raise ValueError(f"video_size must be (width, height) in pixels, each in [1, 8192], got {video_size!r}")
    check_real("video_fps", a["video_fps"], 0, low_open=True, what="a finite frame rate in Hz")
    if gui:
        from jaxdrones.backends.pybullet import require_display

        require_display()
    return dict(
        config=config, n_steps=n_steps, params=params, obstacles=resolved, video_size=tuple(int(v) for v in video_size)
    )


def fly_circle(
    num_drones: int = 4,
    duration_s: float = 12.0,
    model: str = "cf2x",
    drag: bool = False,
    ground_effect: bool = False,
    downwash: bool = False,
    *,
    feedforward: bool = DEFAULT_FEEDFORWARD,
    settle_s: float = DEFAULT_SETTLE_S,
    sim_freq: int = 240,
    ctrl_freq: int = 48,
    gains: PIDGains | None = None,
    backend: str = "jax",
    obstacles: bool | str | Sequence[Obstacle | str | os.PathLike] | None = None,
    gui: bool = False,
    video: str | os.PathLike | None = None,
    video_size: tuple[int, int] = DEFAULT_VIDEO_SIZE,
    video_fps: float = DEFAULT_VIDEO_FPS,
    progress: bool = False,
) -> dict:
    """Fly the paper's circle example and measure how well it tracks.

    Args:
        num_drones: number of drones N ≥ 1 (the paper's script defaults to 3, its README shows 4).
        duration_s: flight time, s (the paper: 12 s). Rounded down to whole control steps.
        model: airframe name or URDF path. The PID gains are tuned for the Crazyflies (``cf2x``, ``cf2p``); other
            airframes are accepted but will not fly well with them.
        drag, ground_effect, downwash: aerodynamic effects of the physics (docs/physics.md §6).
        feedforward: pass the way-point's velocity as the PID's ``target_vel`` (the original passes 0).
        settle_s: initial transient, s, excluded from the metrics.
        sim_freq: physics rate, Hz (240).
        ctrl_freq: control rate, Hz (48); a divisor of ``sim_freq``.
        gains: PID gains; default `PIDGains.dsl`.
        backend: ``"jax"`` or ``"pybullet"`` (see `jaxdrones.sim.make_step`).
        obstacles: PyBullet only: None, True or ``"paper"`` (`jaxdrones.scene.PAPER_OBSTACLES`), or a
            sequence of `jaxdrones.scene.Obstacle` / URDF paths.
        gui: PyBullet only: show the flight in PyBullet's GUI, paced to real time (needs a display).
        video: PyBullet only: write a third-person video of the flight to this new ``.mp4`` or ``.gif`` file (see
            `jaxdrones.io.video.VideoWriter`); an existing file is never replaced.
        video_size: (width, height) of the video, pixels.
        video_fps: video frame rate asked for, Hz. A frame is rendered every k = max(1, round(ctrl_freq /
            video_fps)) control steps, so the video plays at ctrl_freq / k frames per second in real time (24 fps
            at the default 48 Hz control), independently of the physics and control rates.
        progress: show a progress bar (tqdm) while a video or GUI flight runs.

    Returns:
        dict of NumPy arrays and values: ``times`` f[T] s (time of each state, (k+1)/ctrl_freq); ``pos``, ``vel``
        f[T, N, 3] (world), ``quat`` f[T, N, 4], ``rpy`` f[T, N, 3] rad, ``ang_vel`` f[T, N, 3] rad/s (body) after
        each control step; ``rpm`` f[T, N, 4] RPM applied during the step that ends at ``times``; ``rpm_cmd``
        f[T, N, 4] the PID command computed at ``times`` (applied next); ``contact`` i32[T, N] the contact bits of
        each step (`DroneState.contact`); ``target_pos``, ``target_vel`` f[T, N, 3] the way-point commanded at
        ``times``; ``waypoint_err``, ``cross_track_err`` f[T, N] m; ``metrics`` (RMS errors per drone and overall,
        see the module docstring); ``contacts`` (`contact_metrics`); ``setup`` (`circle_setup`); ``settings``;
        ``wall_s`` (seconds for the call, compilation included); ``video`` (the file written, or None) and
        ``video_frames``.

    Raises:
        ValueError: non-positive ``num_drones``, ``duration_s`` shorter than one control step, a negative
            ``settle_s`` or one that leaves no samples, an unknown model, invalid rates, an unknown backend,
            ``obstacles``/``gui``/``video`` on the jax backend, a video name without ``.mp4``/``.gif`` or that
            exists, a bad ``video_size`` or ``video_fps``.
        RuntimeError: ``gui`` without a display.
    """
    checked = check_flight(**locals())  # every argument of this call, before anything flies
    config, n_steps, params = checked["config"], checked["n_steps"], checked["params"]

    start = time.perf_counter()
    gains = PIDGains.dsl() if gains is None else gains
    setup = circle_setup(config.n_drones, ctrl_freq)
    target_pos, target_vel = circle_targets(setup, n_steps, ctrl_freq)
    state = init_state(config, pos=setup["init_pos"], rpy=setup["init_rpy"])
    dtype = state.pos.dtype
    carry = initial_carry(state)
    inputs = (jnp.asarray(target_pos, dtype), jnp.asarray(target_vel, dtype))
    fixed = (jnp.asarray(setup["init_rpy"], dtype), jnp.asarray(float(feedforward), dtype))
    n_frames = 0
    if video is None and not gui:
        options = {} if backend == "jax" else {"obstacles": checked["obstacles"]}
        states, rpm_cmd = run_closed_loop(
            config, track_position, params, gains, carry, inputs, fixed, backend, **options
        )
    else:
        step = make_step(config, backend="pybullet", obstacles=checked["obstacles"], gui=gui)
        try:
            states, rpm_cmd, n_frames = _fly_in_chunks(
                step,
                closed_loop(step, track_position),
                params,
                gains,
                carry,
                inputs,
                fixed,
                setup,
                video=video,
                video_size=checked["video_size"],
                video_fps=video_fps,
                gui=gui,
                progress=progress,
            )
        finally:
            step.close()
    out = flight_arrays(states, rpm_cmd, ctrl_freq)
    wall_s = time.perf_counter() - start

    times = out["times"]
    waypoint_err = np.linalg.norm(out["pos"] - target_pos, axis=-1)
    radial = np.linalg.norm(out["pos"][..., :2] - setup["center"], axis=-1) - RADIUS
    cross_track_err = np.hypot(radial, out["pos"][..., 2] - setup["init_pos"][:, 2])
    keep = times >= settle_s - 1e-9
    out.update(
        target_pos=target_pos,
        target_vel=target_vel,
        waypoint_err=waypoint_err,
        cross_track_err=cross_track_err,
        setup=setup,
        wall_s=wall_s,
        metrics=tracking_metrics(waypoint_err[keep], cross_track_err[keep], settle_s),
        contacts=contact_metrics(out["contact"], times, backend),
        video=None if video is None else os.fspath(video),
        video_frames=n_frames,
        settings=flight_settings(
            "circle",
            config,
            out,
            model,
            backend,
            feedforward=bool(feedforward),
            settle_s=settle_s,
            obstacles=[_obstacle_dict(o) for o in checked["obstacles"]],
        ),
    )
    return out


def _fly_in_chunks(
    step, simulate, params, gains, carry, inputs, fixed, setup, *, video, video_size, video_fps, gui, progress
):
    """Run the closed loop in chunks of k = max(1, round(ctrl_freq / video_fps)) control steps, rendering a video
    frame of world 0 at the start and after each chunk, and pacing the flight to real time with the GUI.

    Returns:
        (states with a leading time axis [T, ...], PID commands f[T, N, 4], number of video frames).
    """
    from tqdm.auto import tqdm

    config = step.config
    chunk = max(1, int(round(config.ctrl_freq / video_fps)))
    n_steps = inputs[0].shape[0]
    center = np.array([*setup["center"], float(np.mean(setup["init_pos"][:, 2]))])
    width, height = video_size
    writer = None if video is None else VideoWriter(video, fps=config.ctrl_freq / chunk)

    def frame(state):
        if writer is not None:
            writer.append(step.render(params, state, width=width, height=height, target=center, **VIDEO_CAMERA))

    pieces = []
    t0 = time.perf_counter()
    try:
        frame(carry[0])
        with tqdm(total=n_steps, unit="step", disable=not progress, desc="flying (PyBullet)") as bar:
            for begin in range(0, n_steps, chunk):
                end = min(begin + chunk, n_steps)
                carry, piece = simulate(params, gains, carry, tuple(x[begin:end] for x in inputs), fixed)
                pieces.append(piece)
                frame(carry[0])
                if gui and begin == 0:  # the GUI's world exists from the first step on: aim its camera
                    pybullet = require_pybullet()
                    camera = VIDEO_CAMERA
                    pybullet.resetDebugVisualizerCamera(
                        camera["distance"],
                        camera["yaw"],
                        camera["pitch"],
                        center.tolist(),
                        physicsClientId=step.clients[0],
                    )
                if gui:  # real time: step k ends at (k + 1) / ctrl_freq
                    time.sleep(max(0.0, t0 + end * config.ctrl_dt - time.perf_counter()))
                bar.update(end - begin)
    finally:
        if writer is not None:
            writer.close()
    states, rpm_cmd = jax.block_until_ready(jax.tree.map(lambda *xs: jnp.concatenate(xs), *pieces))
    return states, rpm_cmd, 0 if writer is None else writer.n_frames


def _obstacle_dict(obstacle) -> dict:
    """An obstacle as JSON-ready values."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(obstacle).items()}


def contact_metrics(contact: np.ndarray, times: np.ndarray, backend: str = "pybullet") -> dict:
    """Summary of contact bits i32[T, N] (`DroneState.contact`) at ``times`` f[T] s.

    Returns:
        dict: ``ground_steps``, ``obstacle_steps``, ``drone_steps`` (per drone, the control steps in which it
        touched that), ``collided`` (any drone touched an obstacle or another drone), ``first_collision_s`` (time
        of the first such step, or None) and ``modelled`` (what the backend detects: the JAX backend the ground
        only).
    """
    contact = np.asarray(contact)
    hits = {
        name: ((contact & bit) != 0)
        for name, bit in (("ground", CONTACT_GROUND), ("obstacle", CONTACT_OBSTACLE), ("drone", CONTACT_DRONE))
    }
    collided = hits["obstacle"] | hits["drone"]
    any_step = collided.any(axis=1)
    return {
        "modelled": ["ground"] if backend == "jax" else ["ground", "obstacle", "drone"],
        **{f"{name}_steps": hit.sum(axis=0).astype(int).tolist() for name, hit in hits.items()},
        "collided": bool(any_step.any()),
        "first_collision_s": float(times[np.argmax(any_step)]) if any_step.any() else None,
    }


def tracking_metrics(waypoint_err: np.ndarray, cross_track_err: np.ndarray, settle_s: float) -> dict:
    """RMS and maximum of f[T, N] errors in m, per drone and overall (RMS over all drones and samples)."""

    def rms(e, axis=None):
        return np.sqrt(np.mean(np.square(e), axis=axis))

    return {
        "definition": (
            f"RMS over control steps with t >= {settle_s:g} s of the 3-D distance to the moving way-point "
            "(waypoint) and to the nearest point of the drone's reference circle (cross_track), m"
        ),
        "settle_s": settle_s,
        "waypoint_rms_m": float(rms(waypoint_err)),
        "cross_track_rms_m": float(rms(cross_track_err)),
        "waypoint_rms_per_drone_m": rms(waypoint_err, 0).tolist(),
        "cross_track_rms_per_drone_m": rms(cross_track_err, 0).tolist(),
        "waypoint_max_m": float(np.max(waypoint_err)),
        "cross_track_max_m": float(np.max(cross_track_err)),
    }


def plot_flight(result: dict, path: str | os.PathLike) -> str:
    """Plot a `fly_circle` result (states, references, RPM vs time) with its metrics; returns ``path``."""
    from jaxdrones.io.plotting import plot_flight as _plot

    s, m = result["settings"], result["metrics"]
    title = (
        f"Circle tracking: {s['num_drones']} × {s['model']}, {pid_title(s)}, feed-forward "
        f"{'on' if s['feedforward'] else 'off'}"
    )
    effects = [name for name in ("drag", "ground_effect", "downwash") if s[name]]
    note = (
        f"RMS for t ≥ {m['settle_s']:g} s: to the moving way-point {100 * m['waypoint_rms_m']:.2f} cm, "
        f"to the circle (cross-track) {100 * m['cross_track_rms_m']:.2f} cm; effects: "
        f"{', '.join(effects) or 'none'}"
    )
    if s.get("obstacles"):
        c = result["contacts"]
        note += f"; {len(s['obstacles'])} obstacles, " + (
            "no collision" if not c["collided"] else f"first collision at {c['first_collision_s']:.2f} s"
        )
    return _plot(result, path, title=title, note=note, mark_t=m["settle_s"])
