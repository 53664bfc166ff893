"""The files of a training run (`jaxdrones.training.run.train_task`): each run's folder (`write_run`: the policy,
its progress, plots, flight viewer and summary) and the summary of several (`write_runs`). Every JSON file is
strict (`jaxdrones.io.runs.write_json`)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from typing import TYPE_CHECKING, Any

from jaxdrones.io.runs import write_json
from jaxdrones.training.runs import PER_SEED, aggregate, setting_label

if TYPE_CHECKING:
    from jaxdrones.envs.base import Env
    from jaxdrones.training.progress import ProgressLog
    from jaxdrones.training.recipes import Recipe
    from jaxdrones.training.runs import RunPlan


def write_run(
    folder: str,
    final: str,
    params: Any,
    log: ProgressLog,
    last: dict,
    env: Env,
    run: Recipe,
    config: Any,
    *,
    interrupted: bool,
    diverged: int | None,
    phases: dict,
    t_start: float,
    source: dict,
    plots: bool = True,
) -> dict:
    """Write one run's files into ``folder`` (the run's folder as written; ``final``: where it is moved into place,
    the summary's ``out_dir``) and return its summary (`jaxdrones.training.run.train_task`'s; ``source``: its
    ``provenance``; without ``plots``, no learning curve, flight plot or viewer page)."""
    from jaxdrones.training import checkpoint
    from jaxdrones.training.evaluation import episode_statistics, judged

    os.makedirs(folder, exist_ok=True)
    t_phase = time.perf_counter()
    checkpoint.save(os.path.join(folder, "policy.pkl"), run.algo, params, run.task, dict(run.env), config)
    log.save(os.path.join(folder, "progress.json"))
    stats = episode_statistics(env, last["eval"]["outcomes"]) if last else {}
    phases["save"] = time.perf_counter() - t_phase
    if plots:
        t_phase = time.perf_counter()
        _plot(env, run, log, last.get("eval"), folder)
        phases["plots"] = time.perf_counter() - t_phase
        t_phase = time.perf_counter()
        _write_viewer(env, last.get("eval"), folder)
        phases["viewer"] = time.perf_counter() - t_phase
    verdict = judged(env.task, stats)
    if diverged is not None:
        verdict["failed_criteria"].insert(
            0, f"the loss or the parameters went non-finite at update {diverged} (the last finite kept)"
        )
        verdict["success"] = False
    summary = {
        "task": run.task,
        "algo": run.algo,
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": phases.get("train"),
        "phases_s": phases,
        "interrupted": interrupted,
        "diverged": diverged,
        "env_steps": int(log.history[-1]["env_steps"] if log.history else 0),
        **verdict,
        "out_dir": final,
        "env": json.loads(json.dumps(dataclasses.asdict(env.config), default=str)),
        "train_env_overrides": dict(run.train_env),
        "defaults": run.defaults,
        "config": dataclasses.asdict(config),
        "provenance": source,
    }
    if "final_pos_error_m" in stats:
        summary["eval_final_pos_error_m"] = stats["final_pos_error_m"]
    write_json(os.path.join(folder, "summary.json"), summary)
    return summary


def write_runs(
    folder: str,
    plan: RunPlan,
    summaries: dict[int, dict],
    logs: list[ProgressLog],
    env: Env,
    status: dict,
    t_start: float,
    phases: dict,
    source: dict | None,
    out_dir: str,
    evaluations: dict[int, dict | None] | None = None,
) -> dict:
    """Write the summary of several runs (`jaxdrones.training.run.train_task`'s ``seeds`` and ``sweep``) into
    ``folder``: ``summary.json`` (each setting's runs and aggregate), ``progress.json``, ``learning_curve.png`` and,
    for seeds without a sweep, ``flight.png``, the evaluation flight of the median seed (``evaluations``: each run's
    last evaluation, by index of ``plan.runs``), from ``summaries`` (the runs saved, by index of ``plan.runs``;
    `write_run`) and ``status`` (``interrupted``, ``error``), with ``out_dir`` where the folder goes; returns the
    summary."""
    from jaxdrones.io.plotting import plot_learning_curves

    sweep = plan.sweep is not None
    order = sorted(summaries)

    def results_of(setting):
        ks = [k for k in order if plan.runs[k].setting == setting]
        return {
            "aggregate": aggregate([summaries[k]["success_value"] for k in ks], [summaries[k]["success"] for k in ks]),
            "runs": [{"seed": plan.runs[k].seed, **{name: summaries[k][name] for name in PER_SEED}} for k in ks],
        }

    summary = {
        "task": summaries[order[0]]["task"],
        "algo": summaries[order[0]]["algo"],
        "seeds": list(plan.seeds),
        "mapped": plan.mapped,
        "programs": len(plan.programs),
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": phases.get("train"),
        **status,
        "env_steps": [summaries[k]["env_steps"] for k in order],
        "success_metric": summaries[order[0]]["success_metric"],
        "success_unit": env.task.success_unit,
        "success_threshold": env.task.success_threshold,
        "out_dir": out_dir,
        "provenance": source,
    }
    if sweep:
        settings: dict[str, dict] = {}  # the settings with a run saved, in order
        for k in order:
            settings.setdefault(setting_label(plan.runs[k].setting), plan.runs[k].setting)
        summary["sweep"] = {name: list(values) for name, values in plan.sweep.items()}
        summary["settings"] = [{"setting": s, **results_of(s)} for s in settings.values()]
    else:
        summary.update(results_of({}))
    names = [f"{setting_label(plan.runs[k].setting) + ',' if sweep else ''}seed_{plan.runs[k].seed}" for k in order]
    write_json(
        os.path.join(folder, "progress.json"), {n: logs[k].history for n, k in zip(names, order, strict=True)}, indent=1
    )
    plot_learning_curves(
        [logs[k].history for k in order],
        os.path.join(folder, "learning_curve.png"),
        groups=[setting_label(plan.runs[k].setting) for k in order] if sweep else None,
        metric_label=f"evaluation {logs[order[0]].label}",
        threshold=env.task.success_threshold,
        title=f"{summary['algo'].upper()} on {summary['task']}, seeds {', '.join(map(str, plan.seeds))}",
    )
    median = None if sweep else median_run(order, summaries)
    if median is not None and (evaluations or {}).get(median) is not None:
        summary["median_seed"] = plan.runs[median].seed
        title = f"{summary['task']}: evaluation flight of seed {summary['median_seed']}, the median of {len(order)}"
        _plot_flight(env, evaluations[median], folder, title)
    write_json(os.path.join(folder, "summary.json"), summary)
    return summary


def median_run(order: list[int], summaries: dict[int, dict]) -> int | None:
    """The run (an index of ``order``'s) whose ``success_value`` is the median of the runs' (the lower of the two
    middle ones for an even count; a non-finite value ranks last), or None without runs."""
    if not order:
        return None
    ranked = sorted(
        order, key=lambda k: (not math.isfinite(summaries[k]["success_value"]), summaries[k]["success_value"], k)
    )
    return ranked[(len(ranked) - 1) // 2]


def _write_viewer(env: Env, evaluation: dict | None, out: str) -> None:
    """``flight.html``, the first evaluation episodes in the flight viewer (`jaxdrones.viz.write_html`), where viser
    is installed; without it, one printed line says how to get it."""
    from jaxdrones import viz

    if evaluation is None:
        return
    if not viz.viewer_available():
        print(f"flight.html not written: the flight viewer needs viser ({viz.VIEWER_INSTALL})")
        return
    flight = viz.Flight.from_data(env, evaluation["viewer"], time_axis=1)
    viz.write_html(os.path.join(out, "flight.html"), flight, overwrite=True)


def _plot(env: Env, run: Recipe, log: ProgressLog, evaluation: dict | None, out: str) -> None:
    """``learning_curve.png`` (the judged metric against env steps, with its threshold) and, when an evaluation ran,
    ``flight.png`` (its first episode)."""
    from jaxdrones.io.plotting import plot_learning_curve

    title = f"{run.algo.upper()} on {run.task} ({env.config.model}, {env.config.action_type})"
    if log.history:
        plot_learning_curve(
            log.history,
            os.path.join(out, "learning_curve.png"),
            metric="success_value",
            metric_label=f"evaluation {log.label}",
            threshold=env.task.success_threshold,
            title=title,
        )
    if evaluation is not None:
        _plot_flight(env, evaluation, out, f"{run.task}: evaluation flight")


def _plot_flight(env: Env, evaluation: dict, out: str, title: str) -> None:
    """``flight.png`` in ``out``: the first episode of ``evaluation``."""
    import numpy as np

    from jaxdrones.io.plotting import plot_task_flight

    flight = evaluation["flight"]
    times = np.arange(env.episode_length + 1) / env.config.sim.ctrl_freq
    plot_task_flight(
        times, flight["pos"], flight["ref"], flight["vel"], flight["rpm"], os.path.join(out, "flight.png"), title=title
    )
