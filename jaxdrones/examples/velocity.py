"""The paper's velocity example: 4 Crazyflies follow step-wise velocity commands (``jaxdrones fly --example velocity``).

Reproduces gym-pybullet-drones ``examples/velocity.py`` (``pid_velocity.py`` on later commits; read at commit
d27f30d: start poses lines 65-76, command schedule 100-110, loop 119-140) on the jaxdrones physics:

* drone i starts at rest at (0.3·i, 0, 0.1) m with yaw (0, π/3, π/4, π/2)[i] rad;
* each drone is flown through the VEL action (docs/physics.md §10.1-10.2, `jaxdrones.control.velocity_control`): an
  action (vx, vy, vz, s) becomes the DSL PID's targets position = current position, yaw = current yaw and velocity =
  SPEED_LIMIT·|s|·(vx, vy, vz)/‖(vx, vy, vz)‖, with the original's SPEED_LIMIT = 3 % of the airframe's maximum
  speed (`jaxdrones.control.speed_limit`: 0.25 m/s for the Crazyflies);
* the commands (`SCHEDULE`, s = 0.99, so 0.2475 m/s) switch once per drone, drone i at (1/8 + i/6)·`PERIOD_S`,
  from (−0.5, 1, 0), (0, 1, 0), (0.2, 1, 0.2), (0, 1, 0.5) to the opposite directions; NUM_WP = PERIOD_S·ctrl_freq
  commands, one per control step, repeating after PERIOD_S = 5 s (the original's duration);
* 240 Hz physics, 48 Hz control, 5 s. As in the original, the first control step applies the zero action (hold
  the start position: the VEL action is converted by the PID inside the environment's step); control step k ≥ 1
  applies command k − 1, converted by the PID from the state reached by step k − 1.

The whole flight is one jitted ``lax.scan`` (`jaxdrones.examples.closed_loop`) on the JAX or PyBullet backend.

Tracking metric (``result["metrics"]``): per drone, the RMS over control steps of ‖v − v_cmd‖ (m/s, world frame)
between the velocity reached after the step and the velocity commanded during it, counting only the steps at least
``settle_s`` (default 0.5 s) after the drone's command last changed (the start counts as a change). The PID tracks
velocity through its D term (P and I act on the position error, which the VEL action keeps at 0), a first-order
response with time constant m/D = 0.027/0.2 ≈ 0.14 s horizontally, so 0.5 s is ≈ 3.7 time constants.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_real
from jaxdrones.control.pid import PIDGains, speed_limit, velocity_control
from jaxdrones.examples.closed_loop import (
    FLIGHT_KEYS,
    bind_arguments,
    check_flight_settings,
    flight_arrays,
    flight_settings,
    initial_carry,
    run_closed_loop,
)
from jaxdrones.physics.state import init_state

#: Start positions, m, world frame, and roll/pitch/yaw, rad, of the 4 drones (``velocity.py:65-76``).
INIT_POS = ((0.0, 0.0, 0.1), (0.3, 0.0, 0.1), (0.6, 0.0, 0.1), (0.9, 0.0, 0.1))
INIT_RPY = ((0.0, 0.0, 0.0), (0.0, 0.0, math.pi / 3), (0.0, 0.0, math.pi / 4), (0.0, 0.0, math.pi / 2))
#: Per drone: (action before the switch, action after it), each (vx, vy, vz, s) (``velocity.py:105-110``).
SCHEDULE = (
    ((-0.5, 1.0, 0.0, 0.99), (0.5, -1.0, 0.0, 0.99)),
    ((0.0, 1.0, 0.0, 0.99), (0.0, -1.0, 0.0, 0.99)),
    ((0.2, 1.0, 0.2, 0.99), (-0.2, -1.0, -0.2, 0.99)),
    ((0.0, 1.0, 0.5, 0.99), (0.0, -1.0, -0.5, 0.99)),
)
#: Period of the command schedule, s: the original's NUM_WP = ctrl_freq·duration with its default 5 s duration.
PERIOD_S = 5
#: Flight time, s, physics and control rates, Hz (the original's defaults, ``velocity.py:44-46``).
DEFAULT_DURATION_S = 5.0
SIM_FREQ = 240
CTRL_FREQ = 48
#: Time after each command change excluded from the tracking metric, s.
DEFAULT_SETTLE_S = 0.5
#: Command-line options of ``jaxdrones fly`` this example takes (besides --duration, --model, --drag, --backend,
#: --out, --overwrite, --no-progress).
CLI_OPTIONS = ("ground_effect", "downwash", "settle")
DEFAULT_OUT = "runs/velocity"


def switch_step(drone: int, num_wp: int) -> float:
    """The command index at which drone ``drone`` switches: NUM_WP/8 + drone·NUM_WP/6 (``velocity.py:107-110``);
    commands with a smaller index use the first action."""
    return num_wp / 8 + drone * num_wp / 6


def velocity_schedule(ctrl_freq: int = CTRL_FREQ) -> np.ndarray:
    """The original's command table TARGET_VEL, as f[NUM_WP, 4, 4]: command k of each drone, (vx, vy, vz, s).

    NUM_WP = PERIOD_S·ctrl_freq (240 at 48 Hz): command k is used at control step k + 1 (see the module docstring).
    """
    num_wp = PERIOD_S * ctrl_freq
    k = np.arange(num_wp)[:, None]
    before, after = (np.array([pair[j] for pair in SCHEDULE]) for j in (0, 1))
    first = k < np.array([switch_step(d, num_wp) for d in range(len(SCHEDULE))])[None, :]
    return np.where(first[..., None], before[None], after[None])


def applied_actions(n_steps: int, ctrl_freq: int = CTRL_FREQ) -> np.ndarray:
    """The VEL action applied during each control step, f[T, 4, 4]: zero in step 0, then command (k − 1) mod NUM_WP
    of `velocity_schedule` in step k."""
    schedule = velocity_schedule(ctrl_freq)
    idx = (np.arange(n_steps) - 1) % schedule.shape[0]
    actions = schedule[idx]
    actions[0] = 0.0
    return actions


def commanded_velocity(actions: np.ndarray, limit: float) -> np.ndarray:
    """The target velocity of VEL actions f[..., 4], f[..., 3] m/s (world frame): limit·|s|·unit(vx, vy, vz), 0 for
    a zero direction (the rule of `jaxdrones.control.velocity_targets`)."""
    direction = actions[..., :3]
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    unit = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
    return limit * np.abs(actions[..., 3:4]) * unit


def settled_mask(actions: np.ndarray, ctrl_freq: int, settle_s: float) -> np.ndarray:
    """bool[T, D]: whether the state after step k is at least ``settle_s`` after the drone's command last changed.

    A command that starts in step j (actions[j] differs from actions[j − 1], or j = 0) has acted for
    (k + 1 − j)/ctrl_freq s at the end of step k.
    """
    changed = np.ones(actions.shape[:2], dtype=bool)
    changed[1:] = np.any(actions[1:] != actions[:-1], axis=-1)
    steps = np.arange(actions.shape[0])[:, None]
    start = np.maximum.accumulate(np.where(changed, steps, 0), axis=0)
    return (steps + 1 - start) / ctrl_freq >= settle_s - 1e-9


def velocity_metrics(vel: np.ndarray, vel_cmd: np.ndarray, settled: np.ndarray, settle_s: float) -> dict:
    """RMS velocity tracking error over the settled samples.

    Args:
        vel, vel_cmd: f[T, D, 3] m/s, world frame: reached and commanded velocity.
        settled: bool[T, D] (`settled_mask`).
        settle_s: the settling time used, s (recorded).

    Returns:
        dict: ``rms_per_drone_mps`` (per drone), ``rms_mps`` (over all drones' settled samples), ``max_mps`` (largest
        settled error), ``rms_per_axis_mps`` (per drone, per world axis x, y, z), ``samples_per_drone``.
    """
    err = vel - vel_cmd
    norm2 = np.sum(err**2, axis=-1)
    count = settled.sum(axis=0)
    per_drone = np.sqrt(np.sum(np.where(settled, norm2, 0.0), axis=0) / np.maximum(count, 1))
    per_axis = np.sqrt(np.sum(np.where(settled[..., None], err**2, 0.0), axis=0) / np.maximum(count, 1)[:, None])
    return {
        "definition": (
            f"RMS over control steps of |v - v_cmd| (world frame, m/s), counting steps at least "
            f"{settle_s:g} s after the drone's command last changed"
        ),
        "settle_s": settle_s,
        "rms_mps": float(np.sqrt(np.sum(np.where(settled, norm2, 0.0)) / max(int(count.sum()), 1))),
        "rms_per_drone_mps": per_drone.tolist(),
        "rms_per_axis_mps": per_axis.tolist(),
        "max_mps": float(np.sqrt(np.max(np.where(settled, norm2, 0.0)))),
        "samples_per_drone": count.astype(int).tolist(),
    }


def _vel_action_control(params, gains, pid_state, state, action, limit, ctrl_dt):
    """The closed loop's controller: the VEL action ``action`` f[D, 4] through `velocity_control`."""
    return velocity_control(params, gains, pid_state, state, action, ctrl_dt=ctrl_dt, limit=limit)


def check(*args: Any, **kwargs: Any) -> dict:
    """Validate `fly`'s arguments (the same, by position or name) without flying.

    Returns:
        dict with ``config`` (`SimConfig`), ``n_steps`` and ``params`` (`DroneParams`).

    Raises:
        ValueError: see `fly`.
        TypeError: an argument `fly` does not take.
    """
    a = bind_arguments(fly, args, kwargs)
    config, n_steps, params = check_flight_settings(a, n_drones=len(INIT_POS))
    settle_s, ctrl_freq = a["settle_s"], config.ctrl_freq
    check_real("settle_s", settle_s, 0, what="a finite number of seconds")
    if not settled_mask(applied_actions(n_steps, ctrl_freq), ctrl_freq, settle_s).any(axis=0).all():
        raise ValueError(
            f"settle_s = {settle_s!r} s leaves no settled sample for some drone in a {a['duration_s']!r} s "
            f"flight; fly longer or settle for less"
        )
    return {"config": config, "n_steps": n_steps, "params": params}


def fly(
    duration_s: float = DEFAULT_DURATION_S,
    model: str = "cf2x",
    *,
    settle_s: float = DEFAULT_SETTLE_S,
    sim_freq: int = SIM_FREQ,
    ctrl_freq: int = CTRL_FREQ,
    backend: str = "jax",
    drag: bool = False,
    ground_effect: bool = False,
    downwash: bool = False,
    gains: PIDGains | None = None,
) -> dict:
    """Fly the velocity example and measure how well each drone tracks its commanded velocity.

    Args:
        duration_s: flight time, s (the original: 5 s); rounded down to whole control steps. Beyond `PERIOD_S`
            the command schedule repeats.
        model: airframe name or URDF path (the PID gains are tuned for ``cf2x``/``cf2p``).
        settle_s: time after each command change left out of the metric, s.
        sim_freq, ctrl_freq: physics and control rates, Hz (``sim_freq`` a multiple of ``ctrl_freq``).
        backend: ``"jax"`` or ``"pybullet"``.
        drag, ground_effect, downwash: aerodynamic effects of the physics (the original uses none: plain PYB).
        gains: PID gains; default `PIDGains.dsl`.

    Returns:
        dict of NumPy arrays and values: the flight (`jaxdrones.examples.closed_loop.flight_arrays`: ``times``
        f[T] s, ``pos``/``vel`` f[T, 4, 3], ``rpm`` f[T, 4, 4], ...); ``action`` f[T, 4, 4] the VEL action
        applied during each step; ``vel_cmd`` f[T, 4, 3] m/s its target velocity (world frame); ``settled``
        bool[T, 4] the samples the metric counts; ``metrics`` (`velocity_metrics`); ``settings``; ``wall_s``
        (seconds for the call, compilation included).

    Raises:
        ValueError: ``duration_s`` shorter than one control step, a negative ``settle_s`` or one that leaves a
            drone no settled sample, an unknown model, invalid rates, an unknown backend.
    """
    checked = check(**locals())  # every argument of this call, before anything flies
    config, n_steps, params = checked["config"], checked["n_steps"], checked["params"]
    start = time.perf_counter()
    gains = PIDGains.dsl() if gains is None else gains
    state = init_state(config, pos=np.array(INIT_POS), rpy=np.array(INIT_RPY))
    dtype = state.pos.dtype
    actions = applied_actions(n_steps, ctrl_freq)
    limit = jnp.asarray(speed_limit(params), dtype)
    # Step 0 applies the zero action, converted from the start state; the loop's input k is command k mod NUM_WP,
    # converted after step k and applied in step k + 1 (the last one is computed but not applied).
    schedule = velocity_schedule(ctrl_freq)
    xs = jnp.asarray(schedule[np.arange(n_steps) % schedule.shape[0]], dtype)
    states, rpm_cmd = run_closed_loop(
        config,
        _vel_action_control,
        params,
        gains,
        initial_carry(state),
        xs,
        limit,
        backend,
        x_first=jnp.asarray(actions[0], dtype),
    )
    out = flight_arrays(states, rpm_cmd, ctrl_freq)
    wall_s = time.perf_counter() - start
    vel_cmd = commanded_velocity(actions, float(limit))
    settled = settled_mask(actions, ctrl_freq, settle_s)
    out.update(
        action=actions,
        vel_cmd=vel_cmd,
        settled=settled,
        wall_s=wall_s,
        metrics=velocity_metrics(out["vel"], vel_cmd, settled, settle_s),
        settings=flight_settings(
            "velocity", config, out, model, backend, speed_limit_mps=float(limit), settle_s=settle_s
        ),
    )
    return out


def plot(result: dict, path: str | os.PathLike) -> str:
    """Plot a `fly` result: commanded vs reached velocity components of each drone against time; returns ``path``."""
    from jaxdrones.io.plotting import plot_velocity_tracking

    s, m = result["settings"], result["metrics"]
    title = (
        f"Velocity commands: {s['num_drones']} × {s['model']}, VEL action (DSL PID at {s['ctrl_freq']} Hz, "
        f"speed limit {s['speed_limit_mps']:.3g} m/s), physics {s['sim_freq']} Hz ({s['backend']})"
    )
    note = (
        f"RMS |v − v_cmd| at least {m['settle_s']:g} s after each command change (grey: excluded): "
        + ", ".join(f"drone {d} {100 * e:.2f}" for d, e in enumerate(m["rms_per_drone_mps"]))
        + " cm/s"
    )
    return plot_velocity_tracking(
        result["times"], result["vel"], result["vel_cmd"], path, settled=result["settled"], title=title, note=note
    )


def summary(result: dict) -> list[str]:
    """Lines printed by ``jaxdrones fly --example velocity``."""
    s, m = result["settings"], result["metrics"]
    lines = [
        (
            f"{s['num_drones']} × {s['model']} following velocity commands, {s['duration_s']:g} s on "
            f"{s['backend']}: simulated in {result['wall_s']:.2f} s (compilation included)"
        ),
        f"RMS velocity error at least {m['settle_s']:g} s after each command change (cm/s):",
    ]
    lines += [f"  drone {d}: {100 * e:7.3f}" for d, e in enumerate(m["rms_per_drone_mps"])]
    lines.append(f"  overall: {100 * m['rms_mps']:7.3f} (largest {100 * m['max_mps']:.3f})")
    return lines


def arrays(result: dict) -> dict:
    """The arrays saved in ``flight.npz``."""
    return {k: result[k] for k in (*FLIGHT_KEYS, "action", "vel_cmd", "settled")}
