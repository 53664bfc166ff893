"""Plots of flights: states and motor speeds against time (matplotlib, Agg backend, written to a file)."""

from __future__ import annotations

import os
from typing import Mapping

import numpy as np

#: Rows of each column: (result key, column title, component labels, unit).
_GROUPS = (
    ("pos", "position (world)", ("x", "y", "z"), "m"),
    ("vel", "velocity (world)", ("vx", "vy", "vz"), "m/s"),
    ("rpy", "attitude", ("roll", "pitch", "yaw"), "rad"),
    ("ang_vel", "angular velocity (body)", ("wx", "wy", "wz"), "rad/s"),
    ("rpm", "motor speed", ("motor 0", "motor 1", "motor 2", "motor 3"), "RPM"),
)


def plot_flight(flight: Mapping, path: str | os.PathLike, *, title: str | None = None,
                note: str | None = None, mark_t: float | None = None) -> str:
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
    plt = _pyplot()

    data = _check(flight)
    times, n_drones = data["times"], data["pos"].shape[1]
    colors = plt.get_cmap("tab10")(np.arange(n_drones) % 10)
    fig, axes = plt.subplots(4, len(_GROUPS), figsize=(4.2 * len(_GROUPS), 10), sharex=True, squeeze=False)
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
    plt.close(fig)
    return path


def _pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (files only, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: str | os.PathLike, title: str | None) -> str:
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = os.fspath(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _check(flight: Mapping) -> dict:
    missing = [k for k in ("times", *(g[0] for g in _GROUPS)) if k not in flight]
    if missing:
        raise ValueError(f"plot_flight: flight lacks {missing}; expected times, pos, vel, rpy, ang_vel, rpm")
    data = {k: np.asarray(v) for k, v in flight.items()
            if k in ("times", "target_pos") or k in {g[0] for g in _GROUPS}}
    t = data["times"]
    if t.ndim != 1:
        raise ValueError(f"plot_flight: times must be f[T], got shape {t.shape}")
    n = data["pos"].shape[1] if data["pos"].ndim == 3 else -1
    for key, _, labels, _ in _GROUPS + (("target_pos", "", "xyz", ""),):
        if key in data and data[key].shape != (t.shape[0], n, len(labels)):
            raise ValueError(f"plot_flight: {key} must have shape [T={t.shape[0]}, N, {len(labels)}] with the same N "
                             f"as pos, got {data[key].shape}")
    return data


def plot_learning_curve(history: list[Mapping], path: str | os.PathLike, *, title: str | None = None) -> str:
    """Plot evaluation return and mean distance to the target against env steps.

    Args:
        history: rows with ``env_steps``, ``episode_reward`` and ``mean_distance_m`` (as `ProgressLog` records).
        path: output image file.
        title: figure title.

    Returns:
        ``path`` as a string.
    """
    plt = _pyplot()

    steps = np.array([row["env_steps"] for row in history], dtype=float)
    fig, (ax_r, ax_d) = plt.subplots(1, 2, figsize=(10, 3.8))
    ax_r.plot(steps, [row["episode_reward"] for row in history], marker="o")
    ax_r.set_ylabel("evaluation episode return")
    ax_d.plot(steps, [row["mean_distance_m"] for row in history], marker="o", color="tab:red")
    ax_d.set_ylabel("mean distance to target over episode (m)")
    ax_d.set_yscale("log")
    for ax in (ax_r, ax_d):
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    return _save(plt, fig, path, title)


def plot_hover_flight(times, pos, vel, rpm, target_z: float, path: str | os.PathLike, *,
                      title: str | None = None) -> str:
    """The paper's hover figure: altitude, vertical velocity and the four motor speeds against time.

    Args:
        times: f[T] s.
        pos: f[T, 3] m, world frame.
        vel: f[T, 3] m/s, world frame.
        rpm: f[T, 4] RPM.
        target_z: target altitude, m (drawn dashed).
        path: output image file.
        title: figure title.

    Returns:
        ``path`` as a string.
    """
    plt = _pyplot()

    times, pos, vel, rpm = (np.asarray(x) for x in (times, pos, vel, rpm))
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    axes[0].plot(times, pos[:, 2], label="z")
    axes[0].axhline(target_z, color="k", ls="--", lw=0.8, label="target")
    axes[0].set_ylabel("z (m)")
    axes[0].legend(fontsize=8)
    axes[1].plot(times, vel[:, 2])
    axes[1].set_ylabel("vz (m/s)")
    for k in range(rpm.shape[-1]):
        axes[2].plot(times, rpm[:, k], lw=1.0, label=f"motor {k}")
    axes[2].set_ylabel("motor speed (RPM)")
    axes[2].set_xlabel("time (s)")
    axes[2].legend(fontsize=8, ncol=4)
    for ax in axes:
        ax.grid(alpha=0.3)
    return _save(plt, fig, path, title)
