"""Plots of flights and training runs, written to files (matplotlib's `matplotlib.figure.Figure`, without pyplot:
the user's backend and open figures are left alone, e.g. a notebook's inline plots)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

#: Rows of each column: (result key, column title, component labels, unit).
_GROUPS = (
    ("pos", "position (world)", ("x", "y", "z"), "m"),
    ("vel", "velocity (world)", ("vx", "vy", "vz"), "m/s"),
    ("rpy", "attitude", ("roll", "pitch", "yaw"), "rad"),
    ("ang_vel", "angular velocity (body)", ("wx", "wy", "wz"), "rad/s"),
    ("rpm", "motor speed", ("motor 0", "motor 1", "motor 2", "motor 3"), "RPM"),
)


def plot_flight(
    flight: Mapping,
    path: str | os.PathLike,
    *,
    title: str | None = None,
    note: str | None = None,
    mark_t: float | None = None,
) -> str:
    """Plot a flight of ``N`` drones: one column per quantity group, one line per drone.

    Columns: position, velocity, roll/pitch/yaw, body angular velocity, motor RPM. If ``flight`` has
    ``target_pos``, the references are drawn dashed in the position column and the position-error norm fills the
    position column's fourth row.

    Args:
        flight: mapping with ``times`` f[T] s and ``pos`` f[T, N, 3] m, ``vel`` f[T, N, 3] m/s (world frame),
            ``rpy`` f[T, N, 3] rad, ``ang_vel`` f[T, N, 3] rad/s (body frame), ``rpm`` f[T, N, 4] RPM; optional
            ``target_pos`` f[T, N, 3] m. Arrays may be NumPy or JAX.
        path: output image file (PNG, or any format matplotlib infers from the suffix); its folder must exist.
        title: figure title.
        note: text printed under the title (e.g. metrics and their definition).
        mark_t: time in s marked by a dotted vertical line on the error plot (e.g. the end of a transient that
            metrics leave out).

    Returns:
        ``path`` as a string.

    Raises:
        ValueError: if a key is missing or the shapes do not agree.
    """
    data = _check(flight)
    times, n_drones = data["times"], data["pos"].shape[1]
    colors = _colors(n_drones)
    fig, axes = _figure(4, len(_GROUPS), figsize=(4.2 * len(_GROUPS), 10), sharex=True, squeeze=False)
    for col, (key, name, labels, unit) in enumerate(_GROUPS):
        for row in range(4):
            ax = axes[row, col]
            if row >= len(labels):
                ax.set_visible(key == "pos" and "target_pos" in data)
                continue
            for d in range(n_drones):
                ax.plot(times, data[key][:, d, row], color=colors[d], lw=1.0, label=f"drone {d}")
                if key == "pos" and "target_pos" in data:
                    ax.plot(times, data["target_pos"][:, d, row], color=colors[d], lw=0.8, ls="--")
            ax.set_ylabel(f"{labels[row]} ({unit})")
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(name)
    if "target_pos" in data:
        ax = axes[3, 0]
        err = np.linalg.norm(data["pos"] - data["target_pos"], axis=-1)
        for d in range(n_drones):
            ax.plot(times, 100 * err[:, d], color=colors[d], lw=1.0)
        if mark_t is not None:
            ax.axvline(mark_t, color="k", lw=0.8, ls=":")
        ax.set_ylabel("|pos − target| (cm)")
        ax.grid(alpha=0.3)
    for col in range(len(_GROUPS)):
        for row in range(3, -1, -1):
            if axes[row, col].get_visible():
                axes[row, col].set_xlabel("time (s)")
                axes[row, col].tick_params(labelbottom=True)
                break
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title)
    if note:
        fig.text(0.5, 0.95, note, ha="center", va="top", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.94 if note else 0.97))
    path = os.fspath(path)
    fig.savefig(path, dpi=110)
    return path


def _figure(rows: int, cols: int, figsize: tuple[float, float], **kwargs):
    """A figure of ``figsize`` inches and its ``rows`` x ``cols`` axes (``Figure.subplots``' keyword arguments)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    return fig, fig.subplots(rows, cols, **kwargs)


def _colors(n: int) -> np.ndarray:
    """``n`` colours of matplotlib's ``tab10`` cycle, RGBA f[n, 4]."""
    import matplotlib

    return matplotlib.colormaps["tab10"](np.arange(n) % 10)


def _save(fig, path: str | os.PathLike, title: str | None) -> str:
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = os.fspath(path)
    fig.savefig(path, dpi=110)
    return path


def _check(flight: Mapping) -> dict:
    missing = [k for k in ("times", *(g[0] for g in _GROUPS)) if k not in flight]
    if missing:
        raise ValueError(f"plot_flight: flight lacks {missing}; expected times, pos, vel, rpy, ang_vel, rpm")
    data = {k: np.asarray(v) for k, v in flight.items() if k in ("times", "target_pos") or k in {g[0] for g in _GROUPS}}
    t = data["times"]
    if t.ndim != 1:
        raise ValueError(f"plot_flight: times must be f[T], got shape {t.shape}")
    n = data["pos"].shape[1] if data["pos"].ndim == 3 else -1
    for key, _, labels, _ in _GROUPS + (("target_pos", "", "xyz", ""),):
        if key in data and data[key].shape != (t.shape[0], n, len(labels)):
            raise ValueError(
                f"plot_flight: {key} must have shape [T={t.shape[0]}, N, {len(labels)}] with the same N "
                f"as pos, got {data[key].shape}"
            )
    return data


def plot_learning_curve(
    history: list[Mapping],
    path: str | os.PathLike,
    *,
    title: str | None = None,
    metric: str = "success_value",
    metric_label: str = "final distance (m)",
    threshold: float | None = None,
) -> str:
    """Plot evaluation return and the task's success metric against env steps.

    Args:
        history: rows with ``env_steps``, ``episode_reward`` and ``metric`` (as
            `jaxdrones.training.progress.ProgressLog` records).
        path: output image file.
        title: figure title.
        metric: the row key of the metric to plot on the right (log scale).
        metric_label: its axis label, with its unit.
        threshold: drawn as a dashed line: the value below which the task counts as solved.

    Returns:
        ``path`` as a string.
    """
    steps = np.array([row["env_steps"] for row in history], dtype=float)
    fig, (ax_r, ax_d) = _figure(1, 2, figsize=(10, 3.8))
    ax_r.plot(steps, [row["episode_reward"] for row in history], marker="o")
    ax_d.plot(steps, [row[metric] for row in history], marker="o", color="tab:red", label="evaluation")
    _curve_axes(ax_r, ax_d, metric_label, threshold)
    if threshold is not None:
        ax_d.legend(loc="upper right")
    return _save(fig, path, title)


def _curve_axes(ax_return, ax_metric, metric_label: str, threshold: float | None) -> None:
    """The axes of a learning curve: env steps (200k, 1M: no overlapping tick labels) against the evaluation return
    and the metric (log scale), with the threshold as a dashed line."""
    from matplotlib.ticker import EngFormatter

    ax_return.set_ylabel("evaluation episode return")
    ax_metric.set_ylabel(metric_label)
    ax_metric.set_yscale("log")
    if threshold is not None:
        ax_metric.axhline(threshold, color="k", linestyle="--", linewidth=1, label=f"solved below {threshold:g}")
    for ax in (ax_return, ax_metric):
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(EngFormatter())
        ax.grid(alpha=0.3)


def plot_learning_curves(
    histories: Sequence[Sequence[Mapping]],
    path: str | os.PathLike,
    *,
    groups: Sequence[str] | None = None,
    title: str | None = None,
    metric_label: str = "final distance (m)",
    threshold: float | None = None,
) -> str:
    """Plot the evaluation return and the success metric (``success_value``) of several runs (seeds) against env
    steps: each run thin, the runs' median thick, the band between their lowest and highest value; with ``groups``,
    one colour, median and band per group (e.g. a sweep's settings).

    Args:
        histories: one list of rows per run, as `plot_learning_curve` takes (the runs evaluated at the same steps).
        groups: each run's group, as its legend label (default: one group).
        path, title, metric_label, threshold: as `plot_learning_curve`.

    Returns:
        ``path`` as a string.
    """
    n = min(len(h) for h in histories)
    steps = np.array([row["env_steps"] for row in histories[0][:n]], dtype=float)
    labels = list(groups) if groups is not None else [""] * len(histories)
    names = list(dict.fromkeys(labels))
    fig, axes = _figure(1, 2, figsize=(10, 3.8))
    for ax, key, color in ((axes[0], "episode_reward", "tab:blue"), (axes[1], "success_value", "tab:red")):
        for g, name in enumerate(names):
            shade = color if len(names) == 1 else f"C{g % 10}"
            runs = [h for h, label in zip(histories, labels, strict=True) if label == name]
            values = np.array([[row[key] for row in h[:n]] for h in runs], dtype=float)
            for run in values:
                ax.plot(steps, run, color=shade, alpha=0.3, linewidth=0.8)
            band = f"{name + ': ' if name else ''}lowest to highest of the seeds"
            ax.fill_between(steps, values.min(0), values.max(0), color=shade, alpha=0.15, linewidth=0, label=band)
            legend = f"{name + ': ' if name else ''}median of {len(values)} seeds"
            ax.plot(steps, np.median(values, 0), color=shade, marker="o", label=legend)
    _curve_axes(*axes, metric_label, threshold)
    axes[1].legend(loc="upper right", fontsize="small" if len(names) > 1 else None)
    return _save(fig, path, title)


def plot_learning_curve_comparison(
    histories: Mapping[str, Sequence[Mapping]],
    path: str | os.PathLike,
    *,
    title: str | None = None,
    metric_label: str = "final distance (m)",
    threshold: float | None = None,
) -> str:
    """Plot the success metric (``success_value``) of several runs, e.g. one per trainer, on one set of axes
    against env steps (left) and against wall time (right).

    Args:
        histories: ``{label: rows}``, the rows as `plot_learning_curve` takes them with ``time_s`` too (seconds
            from the run's start to the evaluation, compilation included: `jaxdrones.training.progress.
            ProgressLog` records it, and ``progress.json`` of a run folder holds it).
        path, title, metric_label, threshold: as `plot_learning_curve`.

    Returns:
        ``path`` as a string.

    Raises:
        ValueError: no histories, or a row without ``env_steps``, ``time_s`` or ``success_value``.
    """
    if not histories:
        raise ValueError("plot_learning_curve_comparison: histories is empty; give {label: rows}")
    for label, rows in histories.items():
        if not rows or not all({"env_steps", "time_s", "success_value"} <= set(row) for row in rows):
            raise ValueError(
                f"plot_learning_curve_comparison: the rows of {label!r} must each have env_steps, time_s and "
                "success_value (as progress.json of a run folder)"
            )
    fig, (ax_steps, ax_time) = _figure(1, 2, figsize=(10, 3.8))
    for k, (label, rows) in enumerate(histories.items()):
        values = [row["success_value"] for row in rows]
        ax_steps.plot([row["env_steps"] for row in rows], values, marker="o", color=f"C{k % 10}", label=label)
        ax_time.plot([row["time_s"] for row in rows], values, marker="o", color=f"C{k % 10}", label=label)
    _curve_axes(ax_steps, ax_steps, metric_label, threshold)
    _curve_axes(ax_time, ax_time, metric_label, threshold)
    ax_time.set_xlabel("wall time from the run's start, compilation included (s)")
    ax_time.xaxis.set_major_formatter("{x:g}")
    ax_time.set_xlim(left=0)  # the time before the first evaluation: mostly compiling the programs
    ax_steps.legend(loc="upper right")
    return _save(fig, path, title)


def plot_task_flight(
    times: ArrayLike,
    pos: ArrayLike,
    ref_pos: ArrayLike,
    vel: ArrayLike,
    rpm: ArrayLike,
    path: str | os.PathLike,
    *,
    title: str | None = None,
) -> str:
    """An evaluation flight of a task: position against the task's reference, velocity and motor speeds.

    Args:
        times: f[T] s.
        pos: f[T, D, 3] m, world frame.
        ref_pos: f[T, D, 3] m, the task's reference point (drawn dashed).
        vel: f[T, D, 3] m/s, world frame.
        rpm: f[T, D, 4] RPM.
        path: output image file.
        title: figure title.

    Returns:
        ``path`` as a string.
    """
    times, pos, ref_pos, vel, rpm = (np.asarray(x) for x in (times, pos, ref_pos, vel, rpm))
    fig, axes = _figure(5, 1, figsize=(8, 10), sharex=True)
    for d in range(pos.shape[1]):
        for k, name in enumerate("xyz"):
            line = axes[k].plot(times, pos[:, d, k], label=f"drone {d}")[0]
            axes[k].plot(times, ref_pos[:, d, k], ls="--", lw=0.8, color=line.get_color())
            axes[k].set_ylabel(f"{name} (m)")
        axes[3].plot(times, np.linalg.norm(vel[:, d], axis=-1), label=f"drone {d}")
        for m in range(rpm.shape[-1]):
            axes[4].plot(
                times, rpm[:, d, m], lw=0.8, label=f"drone {d} motor {m}" if pos.shape[1] > 1 else f"motor {m}"
            )
    axes[0].legend(fontsize=7, ncol=4, title="dashed: reference", title_fontsize=7)
    axes[3].set_ylabel("speed (m/s)")
    axes[4].set_ylabel("motor speed (RPM)")
    axes[4].set_xlabel("time (s)")
    axes[4].legend(fontsize=6, ncol=4)
    for ax in axes:
        ax.grid(alpha=0.3)
    return _save(fig, path, title)


def plot_velocity_tracking(
    times: ArrayLike,
    vel: ArrayLike,
    vel_cmd: ArrayLike,
    path: str | os.PathLike,
    *,
    settled: ArrayLike | None = None,
    title: str | None = None,
    note: str | None = None,
) -> str:
    """Commanded vs reached velocity: one row per drone, one column per world axis (vx, vy, vz).

    Args:
        times: f[T] s.
        vel: f[T, N, 3] m/s, world frame, the velocity reached (solid line).
        vel_cmd: f[T, N, 3] m/s, world frame, the velocity commanded (dashed black line).
        path: output image file.
        settled: optional bool[T, N]; the samples where it is False (settling after a command change) are shaded
            grey.
        title: figure title.
        note: text printed under the title.

    Returns:
        ``path`` as a string.
    """
    times, vel, vel_cmd = (np.asarray(x) for x in (times, vel, vel_cmd))
    n_drones = vel.shape[1]
    colors = _colors(n_drones)
    fig, axes = _figure(n_drones, 3, figsize=(12, 2.1 * n_drones + 1.2), sharex=True, squeeze=False)
    for d in range(n_drones):
        for axis, label in enumerate(("vx", "vy", "vz")):
            ax = axes[d, axis]
            if settled is not None:
                ax.fill_between(
                    times,
                    0,
                    1,
                    where=~np.asarray(settled)[:, d],
                    color="0.85",
                    step="pre",
                    transform=ax.get_xaxis_transform(),
                    lw=0,
                )
            ax.plot(times, vel[:, d, axis], color=colors[d], lw=1.2, label="reached")
            ax.plot(times, vel_cmd[:, d, axis], color="k", lw=0.9, ls="--", label="commanded")
            ax.set_ylabel(f"drone {d} {label} (m/s)")
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    return _save_with_note(fig, path, title, note)


def plot_takeoff_comparison(
    times: ArrayLike,
    runs: Mapping[str, Mapping],
    target_z: ArrayLike,
    path: str | os.PathLike,
    *,
    title: str | None = None,
    note: str | None = None,
) -> str:
    """Take-off of one drone in several runs: altitude, vertical velocity and the four motor speeds against time.

    Args:
        times: f[T] s.
        runs: label → mapping with ``pos`` f[T, 3] m and ``vel`` f[T, 3] m/s (world frame) and ``rpm`` f[T, 4] RPM.
            The first run is drawn solid, the others dashed, dotted, ...
        target_z: f[T] m, the altitude commanded (thin black line).
        path: output image file.
        title: figure title.
        note: text printed under the title.

    Returns:
        ``path`` as a string.
    """
    times, target_z = np.asarray(times), np.asarray(target_z)
    styles = ("-", "--", ":", "-.")
    fig, axes = _figure(3, 1, figsize=(8, 8.5), sharex=True)
    axes[0].plot(times, target_z, color="k", lw=0.8, label="target")
    for j, (label, run) in enumerate(runs.items()):
        ls = styles[j % len(styles)]
        pos, vel, rpm = (np.asarray(run[k]) for k in ("pos", "vel", "rpm"))
        axes[0].plot(times, pos[:, 2], color=f"C{j}", ls=ls, label=label)
        axes[1].plot(times, vel[:, 2], color=f"C{j}", ls=ls, label=label)
        for k in range(rpm.shape[-1]):
            axes[2].plot(
                times, rpm[:, k], color=f"C{k + 2}", ls=ls, lw=1.0, label=f"motor {k} ({label})" if j < 2 else None
            )
    axes[0].set_ylabel("z (m)")
    axes[1].set_ylabel("vz (m/s)")
    axes[2].set_ylabel("motor speed (RPM)")
    axes[2].set_xlabel("time (s)")
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=8)
    axes[2].legend(fontsize=7, ncol=2)
    for ax in axes:
        ax.grid(alpha=0.3)
    return _save_with_note(fig, path, title, note)


def plot_altitude_comparison(
    times: ArrayLike,
    runs: Mapping[str, np.ndarray],
    target_z: ArrayLike,
    path: str | os.PathLike,
    *,
    drone_labels: Sequence[str] | None = None,
    shade: ArrayLike | None = None,
    title: str | None = None,
    note: str | None = None,
) -> str:
    """Altitude of each drone in several runs (one panel per drone), e.g. with and without downwash.

    Args:
        times: f[T] s.
        runs: label → altitude f[T, N] m. The first run is drawn solid, the others dashed, dotted, ...
        target_z: f[N] or f[T, N] m, the commanded altitude (thin black line).
        path: output image file.
        drone_labels: N panel labels; default "drone i".
        shade: optional bool[T], times shaded grey in every panel (e.g. when the drones pass over each other).
        title: figure title.
        note: text printed under the title.

    Returns:
        ``path`` as a string.
    """
    times = np.asarray(times)
    first = np.asarray(next(iter(runs.values())))
    n_drones = first.shape[1]
    target_z = np.broadcast_to(np.asarray(target_z), first.shape)
    labels = drone_labels or [f"drone {d}" for d in range(n_drones)]
    styles = ("-", "--", ":", "-.")
    fig, axes = _figure(n_drones, 1, figsize=(10, 2.6 * n_drones + 1.0), sharex=True, squeeze=False)
    for d, ax in enumerate(axes[:, 0]):
        if shade is not None:
            ax.fill_between(
                times, 0, 1, where=np.asarray(shade), color="0.88", step="pre", transform=ax.get_xaxis_transform(), lw=0
            )
        ax.plot(times, target_z[:, d], color="k", lw=0.8, label="target")
        for j, (label, z) in enumerate(runs.items()):
            ax.plot(times, np.asarray(z)[:, d], color=f"C{j}", ls=styles[j % len(styles)], lw=1.1, label=label)
        ax.set_ylabel(f"{labels[d]}: z (m)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=8, loc="best")
    return _save_with_note(fig, path, title, note)


def _save_with_note(fig, path: str | os.PathLike, title: str | None, note: str | None) -> str:
    """Save like `_save`, with ``note`` printed under the title."""
    if note:
        fig.text(0.5, 0.955, note, ha="center", va="top", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.93 if note else 0.97))
    path = os.fspath(path)
    fig.savefig(path, dpi=110)
    return path


def render_state(
    pos: ArrayLike,
    quat: ArrayLike,
    *,
    arm: float = 0.0397,
    targets: ArrayLike | None = None,
    width: int = 480,
    height: int = 480,
    title: str | None = None,
) -> np.ndarray:
    """A 3-D view of drones drawn with matplotlib, as an RGB image (what ``render()`` shows on the JAX backend).

    Args:
        pos: f[D, 3] m, world frame.
        quat: f[D, 4] (x, y, z, w), body→world; each drone is drawn as its two arms (body x ± y diagonals).
        arm: arm length to draw, m.
        targets: optional f[K, 3] m, drawn as crosses.
        width, height: image size, pixels.
        title: optional title.

    Returns:
        u8[height, width, 3].
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from jaxdrones.physics.rotations import quat_to_rotmat

    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    rot = np.asarray(quat_to_rotmat(np.asarray(quat, np.float64).reshape(-1, 4)))
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    scale = 3 * arm
    for p, r in zip(pos, rot, strict=True):
        for diag in (np.array([1.0, 1.0, 0.0]), np.array([1.0, -1.0, 0.0])):
            d = r @ diag * scale / np.sqrt(2)
            ax.plot(*np.stack([p - d, p + d]).T, color="tab:blue", lw=2)
        up = r[:, 2] * scale
        ax.plot(*np.stack([p, p + up]).T, color="tab:red", lw=1)
    if targets is not None:
        t = np.asarray(targets, np.float64).reshape(-1, 3)
        ax.scatter(t[:, 0], t[:, 1], t[:, 2], marker="x", color="tab:green")
    finite = pos[np.all(np.isfinite(pos), axis=1)]
    centre = finite.mean(axis=0) if len(finite) else np.zeros(3)
    span = max(1.0, float(np.ptp(finite, axis=0).max()) if len(finite) else 1.0)
    ax.set_xlim(centre[0] - span, centre[0] + span)
    ax.set_ylim(centre[1] - span, centre[1] + span)
    ax.set_zlim(0.0, max(2.0, centre[2] + span))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    if title:
        ax.set_title(title)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
