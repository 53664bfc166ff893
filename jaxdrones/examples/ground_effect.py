"""The paper's ground-effect example: one Crazyflie takes off with and without ground effect
(``jaxdrones fly --example ground-effect``).

Reproduces gym-pybullet-drones ``examples/groundeffect.py`` (read at commit a4cf76d: rates lines 41-43, start
line 62, target 65-71, physics mode 77-78) on the jaxdrones physics, flown twice, once with
``SimConfig(ground_effect=True)`` (the original's PYB_GND) and once without (its commented-out PYB, "for
comparison"):

* one cf2x starts at rest at (0, 0, `START_Z`) = (0, 0, 0.014) m, 1.5 mm above its resting height on the ground
  (collision half-height 0.0125 m);
* the DSL PID tracks the vertical sinusoid z_k = 0.014 + 0.15·(sin(2πk/NUM_WP) + 1) m above (0, 0), NUM_WP =
  `PERIOD_S`·ctrl_freq way-points, one per control step (period 4 s): the take-off target starts at 0.164 m and
  rises to 0.270 m at 0.5 s; the original passes no target velocity or attitude;
* 240 Hz physics and 240 Hz control (one substep per control step); the first control step applies 0 RPM.

The paper's figure shows z, vz and the four motor speeds over the first 0.5 s (`WINDOW_S`), the default flight
time here. Ground effect adds thrust kf·rpm²·C_gnd·(R/(4h))² on each propeller at height h (docs/physics.md §6.1):
near the ground the same RPM lifts more, so the drone climbs faster and the PID settles on lower motor speeds.

Metrics (``result["metrics"]``), for each run (``on``, ``off``) and their difference on − off:

* ``z_at_window_m``: the altitude at t = 0.5 s (the control step ending there);
* ``overshoot_m``: the largest z − z_target over t ≤ 0.5 s (negative if the drone stays below its target);
* ``peak_vz_mps``: the largest vertical velocity over t ≤ 0.5 s;
* ``mean_rpm_window``: the mean motor speed over t ≤ 0.5 s, RPM.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from jaxdrones.control.pid import PIDGains
from jaxdrones.examples.closed_loop import (
    bind_arguments,
    check_flight_settings,
    effect_configs,
    flight_settings,
    fly_to_waypoints,
    on_off,
    pid_title,
    run_arrays,
)

#: Start altitude, m (``groundeffect.py:62``), above (x, y) = (0, 0).
START_Z = 0.014
#: Amplitude of the target sinusoid, m, and its period, s (``groundeffect.py:66-70``).
AMPLITUDE = 0.15
PERIOD_S = 4
#: Physics and control rates, Hz (``groundeffect.py:41-42``).
SIM_FREQ = 240
CTRL_FREQ = 240
#: The paper figure's window, s: the metrics are taken over t ≤ WINDOW_S; the default flight time.
WINDOW_S = 0.5
DEFAULT_DURATION_S = WINDOW_S
#: Command-line options of ``jaxdrones fly`` this example takes (besides --duration, --model, --drag, --backend,
#: --out, --overwrite, --no-progress).
CLI_OPTIONS = ()
DEFAULT_OUT = "runs/ground-effect"


def target_altitude(n_steps: int, ctrl_freq: int = CTRL_FREQ) -> np.ndarray:
    """The altitude commanded after each control step, f[T] m: way-point k mod NUM_WP of the sinusoid
    START_Z + AMPLITUDE·(sin(2πk/NUM_WP) + 1), NUM_WP = PERIOD_S·ctrl_freq."""
    num_wp = PERIOD_S * ctrl_freq
    k = np.arange(n_steps) % num_wp
    return START_Z + AMPLITUDE * (np.sin(2 * np.pi * k / num_wp) + 1)


def takeoff_metrics(
    times: np.ndarray, z: np.ndarray, vz: np.ndarray, rpm: np.ndarray, target_z: np.ndarray, window_s: float = WINDOW_S
) -> dict:
    """Take-off figures of one run over t ≤ ``window_s``.

    Args:
        times: f[T] s; z, vz: f[T] m and m/s (world frame); rpm: f[T, 4] RPM; target_z: f[T] m (commanded after
            each step, i.e. the target the next step flies to).
        window_s: the window the metrics look at, s from the start (`WINDOW_S`, the paper's figure's 0.5 s).

    Returns:
        dict with ``z_at_window_m``, ``overshoot_m``, ``peak_vz_mps``, ``mean_rpm_window`` (see the module
        docstring).
    """
    inside = times <= window_s + 1e-9
    at = int(np.flatnonzero(inside)[-1])
    # The state after step k is compared with the target it was flying to: the one commanded after step k − 1.
    flown_to = np.concatenate([target_z[:1], target_z[:-1]])
    return {
        "z_at_window_m": float(z[at]),
        "overshoot_m": float(np.max((z - flown_to)[inside])),
        "peak_vz_mps": float(np.max(vz[inside])),
        "mean_rpm_window": float(np.mean(rpm[inside])),
    }


def compare(on: dict, off: dict) -> dict:
    """Both runs' figures and their difference on − off, per figure (`on_off`)."""
    return {k: on_off(on[k], off[k]) for k in on}


def check(*args: Any, **kwargs: Any) -> dict:
    """Validate `fly`'s arguments (the same, by position or name) without flying.

    Returns:
        dict with ``configs`` (``"on"`` → the physics with ground effect, ``"off"`` → without it; `SimConfig`),
        ``n_steps`` and ``params`` (`DroneParams`).

    Raises:
        ValueError: see `fly`.
        TypeError: an argument `fly` does not take.
    """
    a = bind_arguments(fly, args, kwargs)
    config, n_steps, params = check_flight_settings(a, n_drones=1)
    if n_steps / config.ctrl_freq < WINDOW_S - 1e-9:
        raise ValueError(f"duration_s must cover the figure's {WINDOW_S:g} s window, got {a['duration_s']!r}")
    return {"configs": effect_configs(config, "ground_effect"), "n_steps": n_steps, "params": params}


def fly(
    duration_s: float = DEFAULT_DURATION_S,
    model: str = "cf2x",
    *,
    sim_freq: int = SIM_FREQ,
    ctrl_freq: int = CTRL_FREQ,
    backend: str = "jax",
    drag: bool = False,
    gains: PIDGains | None = None,
) -> dict:
    """Fly the take-off twice, with and without ground effect, and compare.

    Args:
        duration_s: flight time, s, at least `WINDOW_S` (default 0.5 s, the paper figure's window; the original
            script flies 4 s); rounded down to whole control steps.
        model: airframe name or URDF path (the PID gains are tuned for ``cf2x``/``cf2p``).
        sim_freq, ctrl_freq: physics and control rates, Hz.
        backend: ``"jax"`` or ``"pybullet"``.
        drag: rotor drag in both runs (the original has none).
        gains: PID gains; default `PIDGains.dsl`.

    Returns:
        dict: ``times`` f[T] s; ``target_z`` f[T] m, the altitude commanded after each step; ``runs``: ``"on"`` and
        ``"off"`` → the flight (`jaxdrones.examples.closed_loop.flight_arrays`, drone axis of size 1); ``metrics``
        (``window_s`` and, per figure of `takeoff_metrics`, ``on``, ``off`` and ``difference``); ``settings``;
        ``wall_s`` (seconds for both runs, compilation included).

    Raises:
        ValueError: ``duration_s`` shorter than `WINDOW_S`, an unknown model, invalid rates, an unknown backend.
    """
    checked = check(**locals())  # every argument of this call, before anything flies
    n_steps, params = checked["n_steps"], checked["params"]
    start = time.perf_counter()
    gains = PIDGains.dsl() if gains is None else gains
    target_z = target_altitude(n_steps, ctrl_freq)
    target_pos = np.zeros((n_steps, 1, 3))
    target_pos[:, 0, 2] = target_z
    runs, figures = {}, {}
    for label, config in checked["configs"].items():
        r = runs[label] = fly_to_waypoints(config, params, gains, [[0.0, 0.0, START_Z]], target_pos, backend)
        figures[label] = takeoff_metrics(r["times"], r["pos"][:, 0, 2], r["vel"][:, 0, 2], r["rpm"][:, 0], target_z)
    wall_s = time.perf_counter() - start
    return {
        "times": runs["on"]["times"],
        "target_z": target_z,
        "runs": runs,
        "wall_s": wall_s,
        "metrics": {"window_s": WINDOW_S, **compare(figures["on"], figures["off"])},
        "settings": flight_settings(
            "ground-effect", checked["configs"]["on"], runs["on"], model, backend, start_z_m=START_Z
        ),
    }


def plot(result: dict, path: str | os.PathLike) -> str:
    """Plot a `fly` result: z, vz and the four motor speeds of both runs against time; returns ``path``."""
    from jaxdrones.io.plotting import plot_takeoff_comparison

    s, m = result["settings"], result["metrics"]
    title = f"Take-off with and without ground effect: {s['model']}, {pid_title(s)}"
    z, over = m["z_at_window_m"], m["overshoot_m"]
    note = (
        f"at t = {m['window_s']:g} s: z = {100 * z['on']:.2f} cm with ground effect, {100 * z['off']:.2f} cm "
        f"without (difference {100 * z['difference']:+.2f} cm); largest z − target up to then "
        f"{100 * over['on']:+.2f} / {100 * over['off']:+.2f} cm"
    )
    runs = {
        f"ground effect {label}": {k: v[:, 0] for k, v in run.items() if k in ("pos", "vel", "rpm")}
        for label, run in result["runs"].items()
    }
    return plot_takeoff_comparison(result["times"], runs, result["target_z"], path, title=title, note=note)


def summary(result: dict) -> list[str]:
    """Lines printed by ``jaxdrones fly --example ground-effect``."""
    s, m = result["settings"], result["metrics"]
    rows = (
        ("z at {w:g} s (cm)", "z_at_window_m", 100),
        ("largest z - target (cm)", "overshoot_m", 100),
        ("peak vz (cm/s)", "peak_vz_mps", 100),
        ("mean motor speed (RPM)", "mean_rpm_window", 1),
    )
    lines = [
        (
            f"1 × {s['model']} taking off from z = {100 * s['start_z_m']:.1f} cm, {s['duration_s']:g} s on "
            f"{s['backend']}, with and without ground effect: simulated in {result['wall_s']:.2f} s "
            f"(compilation included)"
        ),
        f"over t ≤ {m['window_s']:g} s:               with |  without | difference",
    ]
    for name, key, scale in rows:
        v = m[key]
        lines.append(
            f"  {name.format(w=m['window_s']):24s} {scale * v['on']:9.2f} | {scale * v['off']:8.2f} | "
            f"{scale * v['difference']:+9.2f}"
        )
    return lines


def arrays(result: dict) -> dict:
    """The arrays saved in ``flight.npz``: ``times``, ``target_z`` and each run's flight as ``on_pos``, ..."""
    return {"times": result["times"], "target_z": result["target_z"], **run_arrays(result["runs"])}
