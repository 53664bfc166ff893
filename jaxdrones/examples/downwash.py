"""The paper's downwash example: two Crazyflies cross above each other, with and without downwash
(``jaxdrones fly --example downwash``).

Reproduces gym-pybullet-drones ``examples/downwash.py`` (docs/physics.md §13; read at commit 0ff20a6: rates and duration
lines 27-30, start positions 47, physics mode 52, way-points 61-67) on the jaxdrones physics, flown twice, once with
``SimConfig(downwash=True)`` (the original's PYB_DW; or the per-rotor model, ``fly(downwash="per_rotor")``,
docs/physics.md §6.4) and once without:

* two cf2x start at rest at (0.5, 0, 1) m and (−0.5, 0, 0.5) m (`INIT_POS`);
* each tracks x_k = 0.5·cos(2πk/NUM_WP), y = 0, at its own start altitude, with NUM_WP = `PERIOD_S`·ctrl_freq
  way-points (period 5 s), drone 0 from index 0 and drone 1 from NUM_WP/2 (half a period apart), advancing one
  index per control step; the DSL PID gets no target velocity or attitude, as in the original;
* 240 Hz physics, 48 Hz control, 12 s; the first control step applies 0 RPM.

The way-points cross twice per period (at t = 1.25 s, 3.75 s, ...); the drones, which lag their way-points by
about half a second, pass over each other near t = 1.7 s, 4.3 s, ..., 0.5 m apart vertically, where the upper
drone's downwash pushes the lower one down: at Δz = 0.5 m the force on the lower drone reaches
c1·(R/(4Δz))² ≈ 0.30 N, more than its weight, within a Gaussian of width |c2Δz + c3| ≈ 3 cm (docs/physics.md §6.3).

Metrics (``result["metrics"]``), for each run (``on``, ``off``): a *pass* is a maximal run of control steps in
which the drones' horizontal distance is below `PASS_RADIUS_M`; the lower drone's *dip* in a pass is the largest
z_target − z over the pass and the `RECOVERY_S` after it (negative if it stayed above its target). Reported: each
pass's time (the step of least distance), each dip, the largest dip ``max_dip_m`` (on, off and their difference
on − off), and the upper drone's largest |z − z_target| over the flight (downwash acts on the lower drone only).
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from jaxdrones.control.pid import PIDGains
from jaxdrones.examples.closed_loop import (
    RUNS,
    bind_arguments,
    check_flight_settings,
    effect_configs,
    flight_settings,
    fly_to_waypoints,
    on_off,
    pid_title,
    run_arrays,
)

#: Start positions, m, world frame (``downwash.py:47``); each drone's target altitude is its start altitude.
INIT_POS = ((0.5, 0.0, 1.0), (-0.5, 0.0, 0.5))
#: Amplitude of the x way-points, m, and their period, s (``downwash.py:62-66``).
AMPLITUDE = 0.5
PERIOD_S = 5
#: Flight time, s, physics and control rates, Hz (``downwash.py:27-30``).
DEFAULT_DURATION_S = 12.0
SIM_FREQ = 240
CTRL_FREQ = 48
#: Horizontal distance, m, below which the drones count as passing over each other.
PASS_RADIUS_M = 0.1
#: Time after a pass still searched for the lower drone's dip, s (it keeps falling until the PID recovers).
RECOVERY_S = 0.5
#: Command-line options of ``jaxdrones fly`` this example takes (besides --duration, --model, --drag, --backend,
#: --out, --overwrite, --no-progress).
CLI_OPTIONS = ("ground_effect",)
DEFAULT_OUT = "runs/downwash"


def downwash_targets(n_steps: int, ctrl_freq: int = CTRL_FREQ) -> np.ndarray:
    """The way-point commanded after each control step, f[T, 2, 3] m (world frame).

    Drone j uses way-point (start_j + k) mod NUM_WP after step k, start = (0, NUM_WP/2), NUM_WP = PERIOD_S·ctrl_freq;
    way-point i is (0.5·cos(2πi/NUM_WP), 0, z_j) with z_j the drone's start altitude.
    """
    num_wp = PERIOD_S * ctrl_freq
    idx = (np.array([0, num_wp // 2])[None, :] + np.arange(n_steps)[:, None]) % num_wp
    init = np.array(INIT_POS)
    x = AMPLITUDE * np.cos(2 * np.pi * idx / num_wp)
    return np.stack([x, np.zeros_like(x), np.broadcast_to(init[:, 2], x.shape)], axis=-1)


def find_passes(pos: np.ndarray, radius: float = PASS_RADIUS_M) -> list[tuple[int, int]]:
    """The passes of two drones over each other: maximal runs of steps [first, last] with horizontal distance
    below ``radius`` (m). ``pos`` is f[T, 2, 3] m."""
    close = np.linalg.norm(pos[:, 0, :2] - pos[:, 1, :2], axis=-1) < radius
    edges = np.diff(np.concatenate([[0], close.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), (np.flatnonzero(edges == -1) - 1).tolist(), strict=True))


def dip_metrics(
    times: np.ndarray,
    pos: np.ndarray,
    target_z: np.ndarray,
    *,
    radius: float = PASS_RADIUS_M,
    recovery_s: float = RECOVERY_S,
) -> dict:
    """The lower drone's altitude dips while the other passes over it, in one run.

    Args:
        times: f[T] s; pos: f[T, 2, 3] m (world frame); target_z: f[2] m, the drones' commanded altitudes.
        radius: horizontal distance of a pass, m.
        recovery_s: time after a pass still searched for the dip, s.

    Returns:
        dict with ``lower_drone`` (index), ``pass_times_s`` (per pass, the time of least horizontal distance),
        ``dips_m`` (per pass, the largest z_target − z of the lower drone), ``max_dip_m`` (the largest dip, 0 with
        no pass) and ``upper_max_error_m`` (the upper drone's largest |z − z_target|).
    """
    lower = int(np.argmin(target_z))
    dist = np.linalg.norm(pos[:, 0, :2] - pos[:, 1, :2], axis=-1)
    below = target_z[lower] - pos[:, lower, 2]
    pass_times, dips = [], []
    for first, last in find_passes(pos, radius):
        end = int(np.searchsorted(times, times[last] + recovery_s + 1e-9))
        pass_times.append(float(times[first + int(np.argmin(dist[first : last + 1]))]))
        dips.append(float(np.max(below[first:end])))
    return {
        "lower_drone": lower,
        "pass_times_s": pass_times,
        "dips_m": dips,
        "max_dip_m": max(dips, default=0.0),
        "upper_max_error_m": float(np.max(np.abs(pos[:, 1 - lower, 2] - target_z[1 - lower]))),
    }


def check(*args: Any, **kwargs: Any) -> dict:
    """Validate `fly`'s arguments (the same, by position or name) without flying.

    Returns:
        dict with ``configs`` (``"on"`` → the physics with downwash, ``"off"`` → without it; `SimConfig`), ``n_steps``
        and ``params`` (`DroneParams`).

    Raises:
        ValueError: see `fly`.
        TypeError: an argument `fly` does not take.
    """
    a = bind_arguments(fly, args, kwargs)
    config, n_steps, params = check_flight_settings(a, n_drones=2)
    return {"configs": effect_configs(config, "downwash", config.downwash), "n_steps": n_steps, "params": params}


def fly(
    duration_s: float = DEFAULT_DURATION_S,
    model: str = "cf2x",
    *,
    sim_freq: int = SIM_FREQ,
    ctrl_freq: int = CTRL_FREQ,
    backend: str = "jax",
    drag: bool = False,
    ground_effect: bool = False,
    gains: PIDGains | None = None,
    downwash: bool | str = True,
) -> dict:
    """Fly the crossing twice, with and without downwash, and measure the lower drone's dips.

    Args:
        duration_s: flight time, s (the original: 12 s; the first pass is near 1.25 s); rounded down to whole
            control steps.
        model: airframe name or URDF path (the PID gains are tuned for ``cf2x``/``cf2p``).
        sim_freq, ctrl_freq: physics and control rates, Hz.
        backend: ``"jax"`` or ``"pybullet"``.
        drag, ground_effect: further aerodynamic effects in both runs (the original has none).
        gains: PID gains; default `PIDGains.dsl`.
        downwash: the downwash model of the ``"on"`` run (`SimConfig.downwash`): True or ``"paper"`` (the original's),
            or ``"per_rotor"``.

    Returns:
        dict: ``times`` f[T] s; ``target_pos`` f[T, 2, 3] m, the way-points commanded after each step; ``runs``:
        ``"on"`` and ``"off"`` → the flight (`jaxdrones.examples.closed_loop.flight_arrays`); ``passes``: label →
        bool[T], the steps in which the drones pass over each other; ``metrics`` (label → `dip_metrics`, and
        ``max_dip_m`` with ``on``, ``off`` and ``difference``); ``settings``; ``wall_s`` (seconds for both runs,
        compilation included).

    Raises:
        ValueError: ``duration_s`` shorter than one control step, an unknown model, invalid rates, an unknown
            backend or downwash model.
    """
    checked = check(**locals())  # every argument of this call, before anything flies
    n_steps, params = checked["n_steps"], checked["params"]
    start = time.perf_counter()
    gains = PIDGains.dsl() if gains is None else gains
    target_pos = downwash_targets(n_steps, ctrl_freq)
    target_z = np.array(INIT_POS)[:, 2]
    runs, figures, passes = {}, {}, {}
    for label, config in checked["configs"].items():
        run = runs[label] = fly_to_waypoints(config, params, gains, INIT_POS, target_pos, backend)
        figures[label] = dip_metrics(run["times"], run["pos"], target_z)
        passes[label] = np.zeros(n_steps, dtype=bool)
        for first, last in find_passes(run["pos"]):
            passes[label][first : last + 1] = True
    wall_s = time.perf_counter() - start
    return {
        "times": runs["on"]["times"],
        "target_pos": target_pos,
        "runs": runs,
        "passes": passes,
        "wall_s": wall_s,
        "metrics": {
            "definition": (
                f"lower drone's largest z_target - z while the drones are less than "
                f"{PASS_RADIUS_M:g} m apart horizontally and {RECOVERY_S:g} s after, m"
            ),
            **figures,
            "max_dip_m": on_off(figures["on"]["max_dip_m"], figures["off"]["max_dip_m"]),
        },
        "settings": flight_settings("downwash", checked["configs"]["on"], runs["on"], model, backend),
    }


def plot(result: dict, path: str | os.PathLike) -> str:
    """Plot a `fly` result: both drones' altitude in both runs against time, passes shaded; returns ``path``."""
    from jaxdrones.io.plotting import plot_altitude_comparison

    s, m = result["settings"], result["metrics"]
    title = f"Downwash: 2 × {s['model']} crossing 0.5 m apart, {pid_title(s)}"
    dip = m["max_dip_m"]
    note = (
        f"lower drone's largest dip below its target while the other passes over it (grey): "
        f"{100 * dip['on']:.2f} cm with downwash, {100 * dip['off']:.2f} cm without"
    )
    target_z = np.array(INIT_POS)[:, 2]
    labels = [f"drone {d} ({'upper' if z == target_z.max() else 'lower'}, {z:g} m)" for d, z in enumerate(target_z)]
    runs = {f"downwash {label}": run["pos"][..., 2] for label, run in result["runs"].items()}
    return plot_altitude_comparison(
        result["times"], runs, target_z, path, drone_labels=labels, shade=result["passes"]["on"], title=title, note=note
    )


def summary(result: dict) -> list[str]:
    """Lines printed by ``jaxdrones fly --example downwash``."""
    s, m = result["settings"], result["metrics"]
    lines = [
        (
            f"2 × {s['model']} crossing 0.5 m apart, {s['duration_s']:g} s on {s['backend']}, with and without "
            f"downwash: simulated in {result['wall_s']:.2f} s (compilation included)"
        )
    ]
    for label in RUNS:
        r = m[label]
        dips = ", ".join(f"{100 * d:.2f} at {t:.2f} s" for d, t in zip(r["dips_m"], r["pass_times_s"], strict=True))
        lines.append(f"  downwash {label:3s}: lower drone's dips (cm) {dips or 'none (no pass)'}")
    dip = m["max_dip_m"]
    lines.append(
        f"largest dip: {100 * dip['on']:.2f} cm with downwash, {100 * dip['off']:.2f} cm without "
        f"(difference {100 * dip['difference']:+.2f} cm)"
    )
    return lines


def arrays(result: dict) -> dict:
    """The arrays saved in ``flight.npz``: ``times``, ``target_pos`` and each run's flight as ``on_pos``, ..."""
    passes = {f"{label}_passes": steps for label, steps in result["passes"].items()}
    return {"times": result["times"], "target_pos": result["target_pos"], **run_arrays(result["runs"]), **passes}
