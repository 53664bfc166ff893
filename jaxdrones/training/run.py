"""Train a policy on a task with any trainer of the table (`jaxdrones.training.trainers`), evaluate it and save the
run: what ``jaxdrones train TASK`` runs (`train_task`). The runs of its seeds and sweep are planned and checked in
`jaxdrones.training.runs`; the run folder is written beside its target and moved into place when complete
(`jaxdrones.io.runs.open_output`)."""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxdrones.training.recipes import Recipe, resolve_recipe
from jaxdrones.training.runs import Stopped, TrainingFailed, diverged_message

if TYPE_CHECKING:
    from jaxdrones.training.brax_ppo import BraxPPOConfig
    from jaxdrones.training.common import Schedule


def train_task(
    task: str | Recipe = "hover",
    out: str | None = None,
    *,
    overwrite: bool = False,
    algo: str | None = None,
    config: Schedule | BraxPPOConfig | None = None,
    env_overrides: dict | None = None,
    train_env_overrides: dict | None = None,
    n_eval_episodes: int = 256,
    progress: bool = True,
    t_start: float | None = None,
    defaults: str | None = None,
    seeds: int | Sequence[int] | None = None,
    sweep: Mapping[str, Sequence] | None = None,
) -> dict:
    """Train a policy on a task with a trainer of `jaxdrones.training.trainers` and save it with a learning curve,
    a flight plot and a summary.

    The run folder is written beside ``out`` and moved into place when complete (`jaxdrones.io.runs.open_output`:
    an existing folder is replaced only with ``overwrite``, only where jaxdrones wrote it, and only by a complete
    run): ``policy.pkl`` (`jaxdrones.training.load_policy` loads it), ``learning_curve.png`` (the task's success
    metric as the run is judged, with its threshold), ``progress.json``, ``flight.png`` (one evaluation episode
    against the task's reference), ``flight.html`` (the flight viewer, where viser, the ``viewer`` extra, is
    installed) and ``summary.json`` (strict JSON). With several processes (`jax.distributed`) each trains its share
    of the worlds and process 0 writes the run.

    An evaluation on ``n_eval_episodes`` random starts follows each of the trainer's chunks of updates; the last is
    the run's result. On Ctrl-C the run stops after the chunk running, what it trained is saved with its summary
    marked ``"interrupted"`` (an interrupted run replaces nothing: where ``out`` holds a run, it goes to a numbered
    sibling) and `Stopped` is raised. With several programs, each program's runs are saved as it ends. A run whose
    loss or parameters go non-finite keeps its last finite parameters and is marked ``"diverged"`` (the update).

    Args:
        task: a registered task's name (`jaxdrones.envs.registered`), trained at its recipe
            (`jaxdrones.training.recipes.recipe` of ``task``, ``defaults``, ``env_overrides`` and ``algo``) with
            ``config`` and ``train_env_overrides`` in place of the recipe's where given; or a
            `jaxdrones.training.recipes.Recipe`, trained as it is (then give none of the five).
        out: output folder (default ``runs/<task>``).
        overwrite: replace an existing ``out`` that jaxdrones wrote, once the new run is complete.
        algo: one of `jaxdrones.training.trainers.ALGOS` (default: the recipe's).
        config: the trainer's config (default: the recipe's).
        env_overrides: task config fields for ``jd.make(task, ...)`` over the recipe's: the env the policy is
            trained in, evaluated in and saved with.
        train_env_overrides: task config fields of the training env only, for the fields the env does not set
            (default: the recipe's; ``{}`` trains in the evaluation env).
        n_eval_episodes: evaluation episodes from random starts (an integer ≥ 64).
        progress: show the progress bar.
        t_start: ``time.perf_counter()`` at which the wall-clock measurement starts (default: now).
        defaults: the recipe's profile, ``"cpu"`` or ``"gpu"`` (default: the device's).
        seeds: several independent runs: ``N`` (seeds ``config.seed`` to ``config.seed + N - 1``) or distinct
            non-negative seeds (`jaxdrones.training.runs.plan_runs`). Our trainers map them in one program (seed
            ``k`` trains the policy of the single run of seed ``k``, within float rounding); brax's PPO trains them
            one after another. Each run goes to ``seed_<k>/`` of ``out``, and ``out`` holds their ``summary.json``
            with the aggregate (`jaxdrones.training.runs.aggregate`), ``progress.json`` and ``learning_curve.png``.
        sweep: ``{name: values}`` over fields of the trainer's config: a run for every combination and every seed,
            each in ``<name>=<value>,.../seed_<k>/`` (`jaxdrones.training.runs.sweep_settings`). Float settings are
            mapped with the seeds; one that changes shapes or steps takes a program of its own, trained after the
            previous one. ``summary.json`` holds each setting's runs and aggregate under ``"settings"``.

    Returns:
        The summary (also ``summary.json``): ``wall_time_s``, ``phases_s`` (``startup`` before this call,
        ``setup``, ``train``, ``save``, ``plots``, ``viewer``), ``env_steps``, ``success_metric``, ``success_value``
        (over ``n_eval_episodes`` random starts), ``success``, ``failed_criteria`` (sentences), ``diverged`` (the
        update, or None), ``defaults``, ``eval``, ``interrupted``, ``provenance``, ``out_dir`` and the settings.
        With ``seeds`` or ``sweep``: ``task``, ``algo``, ``seeds``, ``runs`` and ``aggregate`` (or ``settings``,
        each with its ``runs`` and ``aggregate``), ``wall_time_s``, ``env_steps`` (per run), ``programs``,
        ``out_dir``, ``interrupted``, ``error``.

    Raises:
        ValueError: bad settings, before anything compiles (an unknown task, algorithm or env option, fewer than 64
            evaluation episodes, a config of another trainer, seeds or a sweep that `jaxdrones.training.runs.
            plan_runs` refuses, a non-finite or out-of-range setting, runs that would not fit in memory,
            ``overwrite`` of a folder jaxdrones did not write).
        TrainingFailed: every run's parameters went non-finite (the last finite ones saved), or an error in a later
            program after earlier runs were trained (those saved).
        Stopped: Ctrl-C after something was trained (saved); a plain ``KeyboardInterrupt`` before (nothing saved).
    """
    t_phase = time.perf_counter()
    phases = {"startup": t_phase - (t_start if t_start is not None else t_phase)}
    run = resolve_recipe(task, algo, config, env_overrides, train_env_overrides, defaults)
    training = _Training(run, out, overwrite, n_eval_episodes, progress, seeds, sweep)
    training.t_start, training.phases = t_phase if t_start is None else t_start, phases
    phases["setup"] = time.perf_counter() - t_phase
    t_train, stop, error = time.perf_counter(), None, None
    try:
        for group in training.plan.programs:  # compiled programs after the first are read back from the cache
            training.train(group)
            training.save_runs(group)
    except KeyboardInterrupt as interrupt:
        stop = interrupt
    except Exception as err:  # noqa: BLE001  (whatever failed, the runs trained before it are saved)
        if not training.results:
            training.abandon()
            raise
        error = err
    finally:
        training.bar.close()
    phases["train"] = time.perf_counter() - t_train
    return training.finish(stop, error)


@dataclasses.dataclass
class _Training:
    """The state of one `train_task`: its recipe, trainer, envs, plan, output folder and what each run gave."""

    run: Recipe
    out: str | None
    overwrite: bool
    n_eval_episodes: int
    progress: bool
    seeds: Any
    sweep: Any

    def __post_init__(self):
        import jax

        from jaxdrones._validate import check_bool, check_int
        from jaxdrones.envs import make
        from jaxdrones.io.runs import open_output
        from jaxdrones.training import runs, trainers
        from jaxdrones.training.evaluation import eval_program
        from jaxdrones.training.progress import ProgressLog

        run, self.trainer = self.run, trainers.get(self.run.algo)
        check_int("n_eval_episodes", self.n_eval_episodes, 64)
        check_bool("overwrite", self.overwrite), check_bool("progress", self.progress)
        if self.out is not None and not isinstance(self.out, str | os.PathLike):
            raise ValueError(f"train: out must be a folder's path (a str or os.PathLike), got {self.out!r}")
        if type(run.config) is not self.trainer.config_cls:
            raise ValueError(f"train: algo {run.algo!r} takes a {self.trainer.config_cls.__name__}, got {run.config!r}")
        self.env = make(run.task, **run.env)
        self.train_env = make(run.task, **run.env, **run.train_env) if run.train_env else self.env
        if self.env.config.vision and not self.trainer.images:
            takes = [name for name in trainers.ALGOS if trainers.get(name).images]
            raise ValueError(f"train: camera images are taken by --algo {' or '.join(takes)}, not {run.algo!r}")
        if self.trainer.differentiable and self.env.config.backend != "jax":
            raise ValueError(f"train: --algo {run.algo} differentiates the simulator and needs backend='jax'")
        per_run = runs.run_bytes(run.config, self.env, self.train_env, self.n_eval_episodes)
        self.plan = plan = runs.plan_runs(
            run.config, self.trainer, self.seeds, self.sweep, per_run, runs.available_bytes()
        )
        self.writer = jax.process_index() == 0
        folder = self.out or os.path.join("runs", run.task)
        self.folder = open_output(folder, self.overwrite) if self.writer else None
        if self.writer and len(plan.programs) > 1:
            print(runs.describe(plan, self.trainer))
        starts = np.cumsum([0, *(plan.runs[group[0]].config.total_steps for group in plan.programs)])
        self.offsets = dict(zip(plan.programs, starts.tolist(), strict=False))
        self.bar = ProgressLog(int(starts[-1]), self.env.task, enabled=self.progress and self.writer)
        several = plan.several
        self.logs = (
            [ProgressLog(r.config.total_steps, self.env.task, False) for r in plan.runs] if several else [self.bar]
        )
        self.last: list[dict] = [{} for _ in plan.runs]
        self.diverged: list[int | None] = [None for _ in plan.runs]
        self.results: dict[int, Any] = {}
        self.saved: dict[int, dict] = {}
        self.evaluate = eval_program(self.env, self.trainer, self.n_eval_episodes)
        self.source, self.dest = None, self.folder.target if self.folder else None

    def report(self, steps: int, metrics: dict, group: tuple[int, ...]) -> None:
        """Record an evaluation of the runs ``group`` (those of the program training)."""
        import jax

        from jaxdrones.training.common import NONFINITE
        from jaxdrones.training.evaluation import episode_statistics

        for j, k in enumerate(group):
            one = jax.tree.map(lambda x, j=j: x[j], metrics) if self.plan.mapped else metrics
            if self.diverged[k] is None and one.get(NONFINITE, -1) >= 0:
                self.diverged[k] = int(one[NONFINITE])
            if self.diverged[k] is None:  # a run that diverged keeps its last finite evaluation
                self.last[k].update(eval=one["eval"])
                self.logs[k](steps, episode_statistics(self.env, one["eval"]["outcomes"]))
        rows = [log.history[-1] for log in self.logs if log.history]
        if self.plan.several and rows:  # the display: the runs' median at their latest evaluation
            names = ("success_value", "terminated_rate", "episode_reward")
            self.bar(
                self.offsets[group] + steps, {name: float(np.median([row[name] for row in rows])) for name in names}
            )

    def train(self, group: tuple[int, ...]) -> None:
        """Train the runs ``group`` as one program; on Ctrl-C, keep what they trained, raise ``KeyboardInterrupt``."""
        from jaxdrones.training.common import Interrupted

        configs = [self.plan.runs[k].config for k in group]
        calls = dict(progress=functools.partial(self.report, group=group), evaluate=self.evaluate)
        try:
            if self.plan.mapped:
                trained = self.trainer.train(self.train_env, configs[0], **calls, runs=configs)
            else:
                trained = [self.trainer.train(self.train_env, configs[0], **calls)]
        except Interrupted as stop:
            if stop.env_steps:
                self.results.update(zip(group, stop.result if self.plan.mapped else [stop.result], strict=True))
            raise KeyboardInterrupt from None
        self.results.update(zip(group, trained, strict=True))

    def save_runs(self, group: tuple[int, ...]) -> None:
        """Write the folders of a finished program's runs (several runs only: a single run is written at the end)."""
        if self.writer and self.plan.several:
            for k in group:
                if k in self.results:
                    self.saved[k] = self.write_run(k, plots=False)

    def write_run(self, k: int, plots: bool = True, interrupted: bool = False) -> dict:
        """Write run ``k``'s folder (`jaxdrones.training.writing.write_run`) and return its summary."""
        from jaxdrones.io.runs import provenance
        from jaxdrones.training.writing import write_run

        self.source = self.source or provenance()  # the same for every run
        inside = self.plan.runs[k].folder(self.plan.sweep is not None) if self.plan.several else ""
        return write_run(
            os.path.join(self.folder.path, inside), os.path.join(self.dest, inside).rstrip(os.sep),
            self.results[k][1], self.logs[k], self.last[k], self.env, self.run, self.plan.runs[k].config,
            interrupted=interrupted, diverged=self.diverged[k], phases={} if inside else self.phases,
            t_start=self.t_start, source=self.source, plots=plots,
        )  # fmt: skip

    def abandon(self) -> None:
        """Delete the folder being written (nothing was trained)."""
        if self.folder is not None:
            self.folder.discard()

    def finish(self, stop: KeyboardInterrupt | None, error: Exception | None) -> dict:
        """Save what was trained, move the folder into place and return the summary; or, after saving, raise
        `Stopped` (Ctrl-C, also one while saving) or `TrainingFailed` (plain ``KeyboardInterrupt`` where nothing
        was trained)."""
        from jaxdrones.io.runs import deferred_interrupt, write_json
        from jaxdrones.training.writing import write_runs

        if not self.writer:
            steps = self.logs[0].history[-1]["env_steps"] if self.logs[0].history else 0
            return {"env_steps": steps, "interrupted": stop is not None}
        if not self.results:
            self.abandon()
            raise stop or KeyboardInterrupt
        diverged = all(self.diverged[k] is not None for k in self.results)
        complete, held = stop is None and error is None and not diverged, None
        try:
            with deferred_interrupt():  # a Ctrl-C now waits until the run is saved and in place
                moved, self.dest = self.dest, self.folder.destination(complete)
                if not self.plan.several:
                    summary = self.write_run(0, interrupted=stop is not None)
                else:
                    for k, saved in self.saved.items():  # written as they finished: where they now go
                        if moved != self.dest:
                            saved["out_dir"] = saved["out_dir"].replace(moved, self.dest, 1)
                            folder = self.plan.runs[k].folder(self.plan.sweep is not None)
                            write_json(os.path.join(self.folder.path, folder, "summary.json"), saved)
                    self.save_runs(tuple(k for k in self.results if k not in self.saved))
                    status = {"interrupted": stop is not None, "error": None if error is None else str(error)}
                    evaluations = {k: self.last[k].get("eval") for k in self.saved}
                    summary = write_runs(self.folder.path, self.plan, self.saved, self.logs, self.env, status,
                                         self.t_start, self.phases, self.source, self.dest, evaluations)  # fmt: skip
                summary["out_dir"] = self.folder.commit(complete)
        except KeyboardInterrupt as late:
            held = late
        if error is not None:
            message = f"{error}; the runs trained before it are saved in {summary['out_dir']}"
            raise TrainingFailed(message, summary) from error
        if diverged:
            raise TrainingFailed(diverged_message(self.plan, self.diverged, summary["out_dir"]), summary)
        if stop is not None or held is not None:
            raise Stopped(summary)
        return summary
