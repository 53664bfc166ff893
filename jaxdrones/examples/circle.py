"""The paper's first example: Crazyflies tracking a circle with the DSL PID controller (``jaxdrones fly``).

Reproduces gym-pybullet-drones ``examples/pid.py`` (facts sheet §13) on the jaxdrones physics (the explicit
model, optionally with drag, ground effect and downwash):

* drone i starts at (R cos(2πi/6 + π/2), R sin(2πi/6 + π/2) − R, H + i·H_STEP) with R = 0.3 m, H = 0.1 m,
  H_STEP = 0.05 m, and rpy = (0, 0, i·(π/2)/N);
* NUM_WP = 10·ctrl_freq way-points WP_k = (R cos(2πk/NUM_WP + π/2) + x_0, R sin(2πk/NUM_WP + π/2) − R + y_0) on
  one circle (period 10 s); drone i starts at index ⌊i·NUM_WP/6⌋ mod NUM_WP and advances one index per control
  step, at its own start altitude and with its start rpy as the target;
* 240 Hz physics, 48 Hz control, 12 s; the first control step applies 0 RPM, then each step applies the PID
  command computed from the state reached by the previous one.

The whole flight is one jitted ``lax.scan``.

Tracking metrics (``result["metrics"]``), each an RMS over all control steps with t ≥ ``settle_s`` (default 1 s,
which leaves out the take-off transient: the drones start at rest while their way-points already move, and the
first PID call sees the derivative spike of the non-zero initial yaw):

* ``waypoint``: ‖p(t_k) − WP(t_k)‖, the 3-D distance to the way-point commanded at t_k (the moving target);
* ``cross_track``: the 3-D distance from p(t_k) to the nearest point of the drone's reference circle (at its
  target altitude), i.e. the error regardless of the lag along the path.

Without velocity feed-forward the PID lags its moving way-point by about half a second (≈ 9 cm at 0.19 m/s, as
the facts sheet reports for the original), while staying within millimetres of the path. With ``feedforward``
(the default), the way-point's velocity is passed as ``target_vel`` and the lag almost disappears.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones.control.pid import PIDGains, pid_control, pid_init
from jaxdrones.params import MODELS, load_params
from jaxdrones.rotations import quat_to_euler
from jaxdrones.sim import SimConfig, make_step
from jaxdrones.state import init_state

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


def circle_setup(num_drones: int, ctrl_freq: int = 48) -> dict:
    """Start poses and way-points of the paper's example (facts §13), as float64 NumPy arrays.

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
    waypoints = np.stack([RADIUS * np.cos(2 * np.pi * k / num_wp + np.pi / 2) + x0,
                          RADIUS * np.sin(2 * np.pi * k / num_wp + np.pi / 2) - RADIUS + y0], -1)
    wp_start = np.array([int((j * num_wp / 6) % num_wp) for j in range(num_drones)])
    return dict(init_pos=init_pos, init_rpy=init_rpy, waypoints=waypoints, wp_start=wp_start,
                center=np.array([x0, y0 - RADIUS]), num_wp=num_wp)


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


@functools.lru_cache(maxsize=8)
def _simulator(config: SimConfig):
    """The jitted closed loop for a config: zero RPM for the first step, then PID commands (one scan)."""
    step = make_step(config)

    @jax.jit
    def simulate(params, gains, state, target_pos, target_vel, target_rpy, feedforward):
        def body(carry, targets):
            sim_state, pid_state, action = carry
            sim_state = step(params, sim_state, action)
            pos_k, vel_k = targets
            rpm, pid_state = pid_control(params, gains, pid_state, sim_state, pos_k, target_vel=feedforward * vel_k,
                                         target_rpy=target_rpy, ctrl_dt=config.ctrl_dt)
            return (sim_state, pid_state, rpm), (sim_state, rpm)

        carry = (state, pid_init(state), jnp.zeros_like(state.rpm))
        _, (states, rpms) = jax.lax.scan(body, carry, (target_pos, target_vel))
        return states, rpms

    return simulate


def fly_circle(num_drones: int = 4, duration_s: float = 12.0, model: str = "cf2x", drag: bool = False,
               ground_effect: bool = False, downwash: bool = False, *, feedforward: bool = DEFAULT_FEEDFORWARD,
               settle_s: float = DEFAULT_SETTLE_S, sim_freq: int = 240, ctrl_freq: int = 48,
               gains: PIDGains | None = None) -> dict:
    """Fly the paper's circle example and measure how well it tracks.

    Args:
        num_drones: number of drones N ≥ 1 (the paper's script defaults to 3, its README shows 4).
        duration_s: flight time, s (the paper: 12 s). Rounded down to whole control steps.
        model: airframe name or URDF path. The PID gains are tuned for the Crazyflies (``cf2x``, ``cf2p``); other
            airframes are accepted but will not fly well with them.
        drag, ground_effect, downwash: aerodynamic effects of the physics (facts §6).
        feedforward: pass the way-point's velocity as the PID's ``target_vel`` (the original passes 0).
        settle_s: initial transient, s, excluded from the metrics.
        sim_freq: physics rate, Hz (240).
        ctrl_freq: control rate, Hz (48); a divisor of ``sim_freq``.
        gains: PID gains; default `PIDGains.dsl`.

    Returns:
        dict of NumPy arrays and values: ``times`` f[T] s (time of each state, (k+1)/ctrl_freq); ``pos``, ``vel``
        f[T, N, 3] (world), ``quat`` f[T, N, 4], ``rpy`` f[T, N, 3] rad, ``ang_vel`` f[T, N, 3] rad/s (body) after
        each control step; ``rpm`` f[T, N, 4] RPM applied during the step that ends at ``times``; ``rpm_cmd``
        f[T, N, 4] the PID command computed at ``times`` (applied next); ``target_pos``, ``target_vel`` f[T, N, 3]
        the way-point commanded at ``times``; ``waypoint_err``, ``cross_track_err`` f[T, N] m; ``metrics``
        (RMS errors per drone and overall, see the module docstring); ``setup`` (`circle_setup`); ``settings``;
        ``wall_s`` (seconds for the call, compilation included).

    Raises:
        ValueError: non-positive ``num_drones``, ``duration_s`` shorter than one control step, a negative
            ``settle_s`` or one that leaves no samples, an unknown model, or invalid rates.
    """
    if isinstance(num_drones, bool) or not isinstance(num_drones, (int, np.integer)) or num_drones < 1:
        raise ValueError(f"num_drones must be a positive integer, got {num_drones!r}")
    config = SimConfig(n_drones=int(num_drones), sim_freq=sim_freq, ctrl_freq=ctrl_freq, drag=drag,
                       ground_effect=ground_effect, downwash=downwash)
    if not math.isfinite(duration_s) or duration_s * ctrl_freq < 1:
        raise ValueError(f"duration_s must be at least one control step (1/{ctrl_freq} s), got {duration_s!r}")
    n_steps = int(duration_s * ctrl_freq + 1e-9)
    if not math.isfinite(settle_s) or settle_s < 0 or settle_s >= n_steps / ctrl_freq:
        raise ValueError(f"settle_s must be in [0, {n_steps / ctrl_freq}) s (the flight time), got {settle_s!r}")

    start = time.perf_counter()
    params = load_params(model)
    gains = PIDGains.dsl() if gains is None else gains
    setup = circle_setup(config.n_drones, ctrl_freq)
    target_pos, target_vel = circle_targets(setup, n_steps, ctrl_freq)
    state = init_state(config, pos=setup["init_pos"], rpy=setup["init_rpy"])
    dtype = state.pos.dtype
    states, rpm_cmd = _simulator(config)(params, gains, state, jnp.asarray(target_pos, dtype),
                                         jnp.asarray(target_vel, dtype), jnp.asarray(setup["init_rpy"], dtype),
                                         jnp.asarray(float(feedforward), dtype))
    rpy = quat_to_euler(states.quat)
    out = {k: np.asarray(v) for k, v in dict(pos=states.pos, quat=states.quat, vel=states.vel, rpy=rpy,
                                             ang_vel=states.ang_vel, rpm=states.rpm, rpm_cmd=rpm_cmd).items()}
    wall_s = time.perf_counter() - start

    times = np.arange(1, n_steps + 1) / ctrl_freq
    waypoint_err = np.linalg.norm(out["pos"] - target_pos, axis=-1)
    radial = np.linalg.norm(out["pos"][..., :2] - setup["center"], axis=-1) - RADIUS
    cross_track_err = np.hypot(radial, out["pos"][..., 2] - setup["init_pos"][:, 2])
    keep = times >= settle_s - 1e-9
    out.update(
        times=times, target_pos=target_pos, target_vel=target_vel, waypoint_err=waypoint_err,
        cross_track_err=cross_track_err, setup=setup, wall_s=wall_s,
        metrics=tracking_metrics(waypoint_err[keep], cross_track_err[keep], settle_s),
        settings=dict(num_drones=config.n_drones, duration_s=n_steps / ctrl_freq, model=str(model), drag=drag,
                      ground_effect=ground_effect, downwash=downwash, feedforward=bool(feedforward),
                      settle_s=settle_s, sim_freq=sim_freq, ctrl_freq=ctrl_freq, dtype=str(dtype)),
    )
    return out


def tracking_metrics(waypoint_err: np.ndarray, cross_track_err: np.ndarray, settle_s: float) -> dict:
    """RMS and maximum of f[T, N] errors in m, per drone and overall (RMS over all drones and samples)."""

    def rms(e, axis=None):
        return np.sqrt(np.mean(np.square(e), axis=axis))

    return {
        "definition": (f"RMS over control steps with t >= {settle_s:g} s of the 3-D distance to the moving way-point "
                       "(waypoint) and to the nearest point of the drone's reference circle (cross_track), m"),
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
    from jaxdrones.plotting import plot_flight as _plot

    s, m = result["settings"], result["metrics"]
    title = (f"Circle tracking: {s['num_drones']} × {s['model']}, DSL PID at {s['ctrl_freq']} Hz, physics "
             f"{s['sim_freq']} Hz, feed-forward {'on' if s['feedforward'] else 'off'}")
    effects = [name for name in ("drag", "ground_effect", "downwash") if s[name]]
    note = (f"RMS for t ≥ {m['settle_s']:g} s: to the moving way-point {100 * m['waypoint_rms_m']:.2f} cm, "
            f"to the circle (cross-track) {100 * m['cross_track_rms_m']:.2f} cm; effects: "
            f"{', '.join(effects) or 'none'}")
    return _plot(result, path, title=title, note=note, mark_t=m["settle_s"])


def register(subparsers) -> None:
    """Add the ``fly`` subcommand (the circle example) to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "fly", help="fly the paper's PID circle example and plot it",
        description="Fly N Crazyflies around a circle with the DSL PID controller (the paper's first example), "
                    "save a plot and metrics.json in a new run folder, and print the RMS tracking errors.")
    parser.add_argument("--num-drones", type=int, default=4, help="number of drones (default 4)")
    parser.add_argument("--duration", type=float, default=12.0, help="flight time in s (default 12)")
    parser.add_argument("--model", default="cf2x", help=f"airframe: one of {', '.join(MODELS)} or a URDF path")
    parser.add_argument("--drag", action="store_true", help="rotor drag")
    parser.add_argument("--ground-effect", action="store_true", help="ground effect")
    parser.add_argument("--downwash", action="store_true", help="downwash between drones")
    parser.add_argument("--feedforward", action=argparse.BooleanOptionalAction, default=DEFAULT_FEEDFORWARD,
                        help="pass the way-point velocity as the PID's target velocity "
                             f"(default {'on' if DEFAULT_FEEDFORWARD else 'off'}; the original passes 0)")
    parser.add_argument("--settle", type=float, default=DEFAULT_SETTLE_S,
                        help=f"initial transient excluded from the metrics, s (default {DEFAULT_SETTLE_S:g})")
    parser.add_argument("--out", default="runs/fly", help="output folder (default runs/fly; a numbered sibling "
                                                          "is used if it exists, unless --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace the contents of an existing --out")
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``fly`` subcommand; returns the exit status."""
    from jaxdrones.runs import new_run_dir

    try:
        result = fly_circle(args.num_drones, args.duration, args.model, args.drag, args.ground_effect,
                            args.downwash, feedforward=args.feedforward, settle_s=args.settle)
    except ValueError as err:
        print(f"jaxdrones fly: error: {err}")
        return 2
    out = new_run_dir(args.out, overwrite=args.overwrite)
    plot_path = plot_flight(result, os.path.join(out, "flight.png"))
    m = result["metrics"]
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump({"settings": result["settings"], "metrics": m, "wall_s": result["wall_s"]}, f, indent=2)
    np.savez_compressed(os.path.join(out, "flight.npz"), **{k: result[k] for k in (
        "times", "pos", "quat", "vel", "rpy", "ang_vel", "rpm", "rpm_cmd", "target_pos", "target_vel")})
    s = result["settings"]
    print(f"{s['num_drones']} × {s['model']}, {s['duration_s']:g} s, feed-forward "
          f"{'on' if s['feedforward'] else 'off'}: simulated in {result['wall_s']:.2f} s (compilation included)")
    print(f"RMS tracking error for t ≥ {m['settle_s']:g} s (cm):  to the moving way-point | to the circle path")
    for d, (w, c) in enumerate(zip(m["waypoint_rms_per_drone_m"], m["cross_track_rms_per_drone_m"])):
        print(f"  drone {d}: {100 * w:8.3f} | {100 * c:8.3f}")
    print(f"  overall: {100 * m['waypoint_rms_m']:8.3f} | {100 * m['cross_track_rms_m']:8.3f}")
    print(f"saved {plot_path}, {os.path.join(out, 'metrics.json')} and {os.path.join(out, 'flight.npz')}")
    return 0
