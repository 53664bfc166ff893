"""The progress display and log of every trainer: a tqdm bar with the training speed and the task's success metric
as the run is judged (its value at the episode's end, its mean or its maximum, with its unit and threshold), and the
rows the learning curve is drawn from. It reads only what `jaxdrones.training.evaluation.episode_statistics`
returns, nothing of any trainer's internals."""

from __future__ import annotations

import math
import threading
import time

#: How a summary names `Task.success_at`.
AGGREGATES = {"final": "final", "mean": "mean over episode", "max": "max over episode"}
#: What the display says until the first evaluation: the programs are compiled (or, from JAX's compilation cache,
#: loaded) before the first training step.
PREPARING = "compiling the programs (or loading them from the compilation cache)"


class ProgressLog:
    """Rows ``{env_steps, time_s, success_value, terminated_rate, episode_reward}`` and a progress bar.

    The bar's total is the run's env steps; its steps/s counts from the first evaluation (after compilation), so it
    is the training speed. Until that first evaluation the bar says so (`PREPARING`) and its elapsed time counts,
    redrawn every second.

    Args:
        total_steps: env steps of the run.
        task: the `jaxdrones.envs.task.Task` whose ``success_metric``, ``success_at``, ``success_unit`` and
            ``success_threshold`` the display shows.
        enabled: show the bar.
    """

    def __init__(self, total_steps: int, task, enabled: bool = True):
        if enabled:
            from tqdm.auto import tqdm  # a notebook's widget where ipywidgets is installed, else text
        else:  # tqdm.auto's import warns in a notebook without ipywidgets: not for a bar never shown
            from tqdm import tqdm

        self.t0 = time.perf_counter()
        self.task = task
        self.history: list[dict] = []
        self._first: tuple[float, int] | None = None
        self.bar = tqdm(
            total=total_steps,
            unit="step",
            unit_scale=True,
            disable=not enabled,
            bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}",  # tqdm puts ", " before it
        )
        self._prepared = threading.Event()
        if enabled:
            self.bar.set_postfix_str(PREPARING)
            self._ticker = threading.Thread(target=self._tick, daemon=True)
            self._ticker.start()

    def _tick(self) -> None:
        """Redraw the bar every second until the first evaluation, so that its elapsed time counts the compilation."""
        while not self._prepared.wait(1.0):
            self.bar.refresh()

    @property
    def label(self) -> str:
        """The judged quantity with its unit, e.g. ``"final distance (m)"``."""
        task = self.task
        return f"{AGGREGATES[task.success_at]} {task.success_metric} ({task.success_unit})"

    def __call__(self, step: int, stats: dict) -> None:
        """Record an evaluation: ``stats`` as `episode_statistics` returns them, at ``step`` env steps."""
        self._prepared.set()
        now = time.perf_counter()
        row = {
            "env_steps": int(step),
            "time_s": now - self.t0,
            "success_value": float(stats.get("success_value", math.nan)),
            "terminated_rate": float(stats.get("terminated_rate", math.nan)),
            "episode_reward": float(stats.get("episode_reward", math.nan)),
        }
        self.history.append(row)
        if self._first is None:
            self._first = (now, step)
        elapsed, done = now - self._first[0], step - self._first[1]
        rate = f"{done / elapsed:,.0f} steps/s  " if elapsed > 0 and done > 0 else ""
        task = self.task
        self.bar.set_postfix_str(
            f"{rate}{AGGREGATES[task.success_at]} {task.success_metric} "
            f"{row['success_value']:.3g} {task.success_unit} (solved < "
            f"{task.success_threshold:g} {task.success_unit})  terminated {row['terminated_rate']:.0%}"
        )
        self.bar.total = max(self.bar.total, step)
        self.bar.update(step - self.bar.n)

    def close(self) -> None:
        self._prepared.set()
        self.bar.close()

    def save(self, path: str) -> None:
        """Write the rows to ``path`` as strict JSON (`jaxdrones.io.runs.write_json`)."""
        from jaxdrones.io.runs import write_json

        write_json(path, self.history, indent=1)
