"""gym-pybullet-drones' ``Logger``: per-drone flight logs at the control rate, saved as NumPy and CSV, plotted."""

from __future__ import annotations

import os
from datetime import datetime

import numpy as np

from jaxdrones.control.pid import PWM2RPM_CONST, PWM2RPM_SCALE

#: The 16 logged state entries, in the Logger's order (the state vector reordered by `Logger.log`).
STATE_LABELS = (
    "x (m)",
    "y (m)",
    "z (m)",
    "vx (m/s)",
    "vy (m/s)",
    "vz (m/s)",
    "roll (rad)",
    "pitch (rad)",
    "yaw (rad)",
    "wx (rad/s)",
    "wy (rad/s)",
    "wz (rad/s)",
    "RPM0",
    "RPM1",
    "RPM2",
    "RPM3",
)
#: The 12 logged control targets.
CONTROL_LABELS = ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw", "wx", "wy", "wz")


class Logger:
    """Logs, per drone, a timestamp, the 20-entry state of the aviaries (`BaseAviary._getDroneStateVector`) and a
    12-entry control target, as the original's ``Logger`` (same arguments and array layout).

    Attributes (NumPy, built from the log):
        timestamps: f64[num_drones, T] s.
        states: f64[num_drones, 16, T]: pos (m), vel (m/s), roll/pitch/yaw (rad), angular velocity (rad/s, the
            aviary's frame), the four RPMs — the state vector's entries 0:3, 10:13, 7:10, 13:20.
        controls: f64[num_drones, 12, T], as logged.

    Unlike the original, nothing is overwritten: `save` and `save_as_csv` add a suffix when a file of the same
    name exists, and `plot` saves the figure (and returns its path) when matplotlib cannot show a window.

    Raises:
        ValueError: (``log``) a drone index out of range, a negative timestamp, a state of another length than 20
            or a control of another length than 12.
    """

    def __init__(
        self,
        logging_freq_hz: int,
        output_folder: str = "results",
        num_drones: int = 1,
        duration_sec: int = 0,
        colab: bool = False,
    ):
        if not (isinstance(num_drones, (int, np.integer)) and num_drones >= 1):
            raise ValueError(f"num_drones must be a positive integer, got {num_drones!r}")
        if not logging_freq_hz > 0:
            raise ValueError(f"logging_freq_hz must be > 0 Hz, got {logging_freq_hz!r}")
        self.COLAB = colab
        self.OUTPUT_FOLDER = output_folder
        self.LOGGING_FREQ_HZ = logging_freq_hz
        self.NUM_DRONES = int(num_drones)
        self._rows: list[list[tuple]] = [[] for _ in range(self.NUM_DRONES)]
        os.makedirs(output_folder, exist_ok=True)

    def log(self, drone: int, timestamp, state, control=None) -> None:
        """Log one entry of drone ``drone``: ``timestamp`` s, ``state`` f[20], ``control`` f[12] (default 0)."""
        state = np.asarray(state, np.float64).reshape(-1)
        control = np.zeros(12) if control is None else np.asarray(control, np.float64).reshape(-1)
        if not 0 <= drone < self.NUM_DRONES or timestamp < 0 or state.size != 20 or control.size != 12:
            raise ValueError(
                f"Logger.log: expected drone in [0, {self.NUM_DRONES}), timestamp >= 0, a state of 20 "
                f"and a control of 12 entries; got drone {drone}, timestamp {timestamp}, "
                f"{state.size} and {control.size}"
            )
        ordered = np.concatenate([state[0:3], state[10:13], state[7:10], state[13:20]])
        self._rows[drone].append((float(timestamp), ordered, control))

    def _stack(self, index: int, width: int) -> np.ndarray:
        n = max((len(rows) for rows in self._rows), default=0)
        out = np.zeros((self.NUM_DRONES, width, n)) if width else np.zeros((self.NUM_DRONES, n))
        for d, rows in enumerate(self._rows):
            if rows:
                values = np.asarray([r[index] for r in rows])
                out[d, ..., : len(rows)] = values.T
        return out

    @property
    def timestamps(self) -> np.ndarray:
        return self._stack(0, 0)

    @property
    def states(self) -> np.ndarray:
        return self._stack(1, 16)

    @property
    def controls(self) -> np.ndarray:
        return self._stack(2, 12)

    def _new_path(self, stem: str, suffix: str = "") -> str:
        base = os.path.join(self.OUTPUT_FOLDER, f"{stem}-{datetime.now().strftime('%m.%d.%Y_%H.%M.%S')}")
        path, n = base + suffix, 1
        while os.path.exists(path):
            path, n = f"{base}-{n}{suffix}", n + 1
        return path

    def save(self) -> str:
        """Write ``timestamps``, ``states`` and ``controls`` with ``numpy.savez`` to ``save-flight-<time>.npy`` in the
        output folder (the original's name; load it with ``numpy.load``); returns the path."""
        path = self._new_path("save-flight", ".npy")
        with open(path, "xb") as f:
            np.savez(f, timestamps=self.timestamps, states=self.states, controls=self.controls)
        return path

    def save_as_csv(self, comment: str = "") -> str:
        """Write one CSV per drone, ``drone<i>.csv`` with a header (time, then the 16 states), to a new folder
        ``save-flight-<comment>-<time>`` in the output folder; returns the folder."""
        folder = self._new_path(f"save-flight-{comment}" if comment else "save-flight")
        os.makedirs(folder)
        t, states = self.timestamps, self.states
        header = ",".join(("time (s)",) + STATE_LABELS)
        for d in range(self.NUM_DRONES):
            np.savetxt(
                os.path.join(folder, f"drone{d}.csv"),
                np.column_stack([t[d], states[d].T]),
                delimiter=",",
                header=header,
                comments="",
            )
        return folder

    def plot(self, pwm: bool = False) -> str | None:
        """Plot each logged state against time, one curve per drone (RPMs as PWM with ``pwm``, for Crazyflies).

        Shown in a window with an interactive matplotlib backend; otherwise (e.g. headless) saved as
        ``flight-<time>.png`` in the output folder, whose path is returned.
        """
        import matplotlib
        import matplotlib.pyplot as plt

        states = self.states.copy()
        if pwm:
            states[:, 12:16] = (states[:, 12:16] - PWM2RPM_CONST) / PWM2RPM_SCALE
        t = np.arange(states.shape[-1]) / self.LOGGING_FREQ_HZ
        fig, axs = plt.subplots(8, 2, figsize=(12, 14), sharex=True)
        for k, label in enumerate(STATE_LABELS):
            ax = axs[k % 8, k // 8]
            for d in range(self.NUM_DRONES):
                ax.plot(t, states[d, k], label=f"drone_{d}")
            ax.set_ylabel(label.replace("RPM", "PWM") if pwm and label.startswith("RPM") else label)
            ax.grid(True)
        axs[0, 0].legend(loc="upper right")
        for ax in axs[-1]:
            ax.set_xlabel("time (s)")
        fig.tight_layout()
        if matplotlib.get_backend().lower() in ("agg", "pdf", "svg", "ps", "cairo", "template") or self.COLAB:
            path = self._new_path("flight", ".png")
            fig.savefig(path, dpi=80)
            plt.close(fig)
            return path
        plt.show()
        return None
