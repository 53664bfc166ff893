"""Train a policy on a task with any trainer of the table (`jaxdrones.training.trainers`), evaluate it and save the
run: what ``jaxdrones train TASK`` runs (`train_task`)."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import math
import os
import time
from typing import TYPE_CHECKING

import numpy as np

from jaxdrones.training.common import mappable
from jaxdrones.training.recipes import Recipe, recipe

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from jaxdrones.envs.base import Env
    from jaxdrones.envs.task import Task
    from jaxdrones.training.brax_ppo import BraxPPOConfig
    from jaxdrones.training.common import Schedule
    from jaxdrones.training.trainers import Trainer


def eval_program(env: Env, trainer: Trainer, n_episodes: int) -> Callable:
    """The evaluation compiled beside the trainer's chunks: ``n_episodes`` episodes from random starts (for a run of
    seed ``s``, the same keys at every evaluation: ``jax.random.split(key(s + 1))[0]`` split ``n_episodes`` ways;
    `outcomes_of`) and the flight of the first one for the plot (positions, the task's reference, velocities, RPMs),
    as ``evaluate(networks, params, seed) -> pytree of arrays`` for a trainer's ``evaluate`` argument
    (`jaxdrones.training.trainers`)."""
    import jax

    from jaxdrones.training.evaluation import outcomes_of, rollout_policy
    from jaxdrones.viz import VIEW_EPISODES, flight_data

    def evaluate(network, params, seed):
        keys = jax.random.split(jax.random.split(jax.random.key(seed + 1))[0], n_episodes)
        policy = trainer.make_policy(network, params)
        # The episodes' starts, as rollout_policy draws them; the task of the first episode from its start, not from
        # the flown states, so that the compiled evaluation keeps no per-step copy of every episode's task data.
        starts = jax.vmap(lambda k: env.reset(jax.random.split(k)[0]))(keys)
        states = jax.vmap(lambda k, start: rollout_policy(env, policy, k, start))(keys, starts)
        flight = jax.tree.map(lambda x: x[0], states)  # the first episode, for the flight plot
        steps = jax.numpy.arange(env.episode_length + 1)
        task = jax.tree.map(lambda x: x[0], starts.task)
        ref = jax.vmap(lambda s: env.task.reference(env.config, task, s))(steps)
        return {
            "outcomes": outcomes_of(states),
            "flight": {"pos": flight.sim.pos, "ref": ref.pos, "vel": flight.sim.vel, "rpm": flight.sim.rpm},
            "viewer": jax.tree.map(lambda x: x[:VIEW_EPISODES], flight_data(states)),
        }  # for flight.html

    evaluate.description = f"evaluation {n_episodes} {trainer.name} {env.task.name} {env.config!r}"
    return evaluate


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

    Outputs in a new run folder (see `jaxdrones.io.runs.new_run_dir`; an existing run is never overwritten unless
    ``overwrite``): ``policy.pkl`` (`jaxdrones.training.checkpoint`; load with `jaxdrones.training.load_policy`),
    ``learning_curve.png`` (the task's success metric as the run is judged, with its threshold), ``progress.json``,
    ``flight.png`` (position against the task's reference, speed and RPMs of one evaluation episode),
    ``flight.html`` (the first `jaxdrones.viz.VIEW_EPISODES` evaluation episodes in the flight viewer, which plays
    offline in a browser; where viser, the ``viewer`` extra, is installed) and ``summary.json``. With several
    processes (`jax.distributed`) every process trains its share of the worlds and process 0 writes the run.

    An evaluation on ``n_eval_episodes`` random starts runs after each of the trainer's chunks of updates (compiled
    beside them, for our trainers); the last one is the run's result. On Ctrl-C the run stops after the chunk
    running, and the policy so far, its learning curve and a summary marked ``"interrupted": true`` are saved
    (with several programs, those of the runs trained before; the later programs are not trained).

    Args:
        task: a registered task's name (`jaxdrones.envs.registered`: `TRAINABLE` and those added by
            `jaxdrones.envs.register`), trained at its recipe (`jaxdrones.training.recipes.recipe` of ``task``,
            ``defaults``, ``env_overrides`` and ``algo``) with ``config`` and ``train_env_overrides`` in place of
            the recipe's where given; or a `jaxdrones.training.recipes.Recipe`, trained as it is (then give none of
            ``algo``, ``config``, ``env_overrides``, ``train_env_overrides``, ``defaults``).
        out: output folder (default ``runs/<task>``).
        overwrite: replace an existing ``out``.
        algo: one of `jaxdrones.training.trainers.ALGOS` (default: the recipe's).
        config: the trainer's config (default: the recipe's).
        env_overrides: task config fields for ``jd.make(task, ...)``, over the recipe's: the env the policy is
            trained in, evaluated in and saved with.
        train_env_overrides: task config fields of the training env only, for the fields the env does not set
            (default: the recipe's; ``{}`` trains in the evaluation env).
        n_eval_episodes: evaluation episodes from random starts (≥ 64).
        progress: show the progress bar.
        t_start: ``time.perf_counter()`` at which the wall-clock measurement starts (default: now).
        defaults: the recipe's profile (`jaxdrones.training.common.DEFAULTS`: ``"cpu"`` or ``"gpu"``; default: the
            device's, `jaxdrones.training.trainers.default_profile`).
        seeds: train several independent runs: ``N`` (seeds ``config.seed`` to ``config.seed + N - 1``) or the
            seeds. Our trainers run them as one program mapped over the seeds (`jaxdrones.training.common.
            run_updates`: seed ``k`` trains the policy of the single run of seed ``k``, within float rounding);
            brax's PPO runs them one after another (`jaxdrones.training.trainers.Trainer.maps_runs`). Each seed's
            ``policy.pkl``, ``progress.json`` and ``summary.json`` are written to ``seed_<k>/`` of ``out`` (it loads
            alone; ``jaxdrones view`` draws its flights), and ``out`` holds ``summary.json`` with every seed's result
            and their aggregate (`aggregate`), ``progress.json`` (each seed's rows) and ``learning_curve.png`` (the
            seeds, their median and range).
        sweep: ``{name: values}`` over fields of the trainer's config: a run for every combination of the values
            (`sweep_settings`) and every seed, each in ``<name>=<value>,.../seed_<k>/`` of ``out``. Our trainers map
            the runs that differ only in float settings (step sizes, discounts, weights) and their seeds in one
            program; a setting that changes shapes or steps (``num_envs``, ``horizon``, layer sizes, ...) takes a
            program of its own, trained after the previous one (`program_groups`). ``summary.json`` then holds each
            setting's runs and aggregate under ``"settings"``, and ``learning_curve.png`` each setting's median.

    Returns:
        The summary dict (also written to ``summary.json``): ``wall_time_s`` (everything from ``t_start``: imports,
        compilation, training, evaluation, plots), ``phases_s`` (the seconds of each phase: ``startup`` before this
        call, ``setup`` (envs, run folder), ``train`` (tracing, compilation, training and the evaluations),
        ``save``, ``plots``, ``viewer``), ``env_steps``,
        ``success_metric``, ``success_value`` (the task's success metric over ``n_eval_episodes`` random starts),
        ``success`` (that value below the task's threshold with no episode terminated early), ``failed_criteria``
        (what kept the run from success, as sentences: `failed_criteria`), ``defaults``, ``eval`` (all
        evaluation statistics), ``interrupted``, ``provenance`` (versions, commit, devices, processes, CPU), the
        output folder and the settings.

        With ``seeds``: ``task``, ``algo``, ``seeds``, ``runs`` (each seed's summary as above), ``aggregate``,
        ``wall_time_s``, ``env_steps`` (per run), ``programs`` (how many were compiled), ``out_dir``,
        ``interrupted``; with ``sweep``, ``sweep`` and ``settings`` (each setting's ``runs`` and ``aggregate``) in
        place of ``runs`` and ``aggregate``.

    Raises:
        ValueError: bad settings (unknown task, algorithm or env option, fewer than 64 evaluation episodes, a config
            of another trainer, seeds not distinct non-negative integers, a sweep `sweep_settings` refuses, ...).
    """
    t_phase = time.perf_counter()
    t_start = t_phase if t_start is None else t_start
    phases = {"startup": t_phase - t_start}  # from t_start: Python, imports, the command line's parsing and devices
    import jax

    from jaxdrones.envs import make
    from jaxdrones.io.runs import new_run_dir, provenance
    from jaxdrones.training import trainers
    from jaxdrones.training.common import Interrupted
    from jaxdrones.training.evaluation import episode_statistics
    from jaxdrones.training.progress import ProgressLog

    run = _run_recipe(task, algo, config, env_overrides, train_env_overrides, defaults)
    task, algo, config, env_overrides = run.task, run.algo, run.config, dict(run.env)
    trainer = trainers.get(algo)
    if n_eval_episodes < 64:
        raise ValueError(f"n_eval_episodes must be >= 64, got {n_eval_episodes}")
    if type(config) is not trainer.config_cls:
        raise ValueError(f"train: algo {algo!r} takes a {trainer.config_cls.__name__}, got {config!r}")
    env = make(task, **env_overrides)
    train_env = make(task, **env_overrides, **run.train_env) if run.train_env else env
    if env.config.vision and not trainer.images:
        takes = [name for name in trainers.ALGOS if trainers.get(name).images]
        raise ValueError(f"train: camera images are taken by --algo {' or '.join(takes)}, not {algo!r}")
    if trainer.differentiable and env.config.backend != "jax":
        raise ValueError(f"train: --algo {algo} differentiates the simulator and needs backend='jax'")
    seed_list = _seeds(seeds, config.seed)
    settings = sweep_settings(config, sweep)
    multi = seed_list is not None or settings is not None
    grid = [(setting, seed) for setting in settings or [{}] for seed in seed_list or [config.seed]]
    configs = [dataclasses.replace(config, **setting, seed=seed) for setting, seed in grid]
    mapped = multi and trainer.maps_runs
    groups = program_groups(configs, config) if mapped else [(k,) for k in range(len(configs))]
    writer = jax.process_index() == 0
    out = new_run_dir(out or os.path.join("runs", task), overwrite=overwrite) if writer else out
    phases["setup"] = time.perf_counter() - t_phase
    if writer and len(groups) > 1:
        print(_plan(trainer, sweep, config, len(configs), len(groups)))
    offsets = np.cumsum([0, *(configs[group[0]].total_steps for group in groups)])  # of each program's env steps
    bar = ProgressLog(int(offsets[-1]), env.task, enabled=progress and writer)
    logs = [ProgressLog(c.total_steps, env.task, False) for c in configs] if multi else [bar]
    last = [{} for _ in configs]
    evaluate = eval_program(env, trainer, n_eval_episodes)

    def report(steps, metrics, group=(0,), offset=0):
        """Record an evaluation of the runs ``group`` (those of the program training), ``offset`` env steps of the
        progress display after the start."""
        for j, k in enumerate(group):
            evaluation = jax.tree.map(lambda x, j=j: x[j], metrics["eval"]) if mapped else metrics["eval"]
            last[k].update(eval=evaluation)
            logs[k](steps, episode_statistics(env, evaluation["outcomes"]))
        if multi:  # the display: the runs' median at their latest evaluation
            rows = [log.history[-1] for log in logs if log.history]
            median = {name: float(np.median([row[name] for row in rows])) for name in MEDIAN_OF}
            bar(offset + steps, median)

    t_train = time.perf_counter()
    interrupted, results = False, {}
    try:
        for g, group in enumerate(groups):  # compiled programs after the first are read back from the cache
            calls = dict(progress=functools.partial(report, group=group, offset=int(offsets[g])), evaluate=evaluate)
            if mapped:
                trained = trainer.train(train_env, configs[group[0]], **calls, runs=[configs[k] for k in group])
                results.update(zip(group, trained, strict=True))
            else:
                results[group[0]] = trainer.train(train_env, configs[group[0]], **calls)
    except Interrupted as stop:  # the programs after the one stopped are not trained
        interrupted = True
        results.update(zip(group, stop.result, strict=True) if mapped else {group[0]: stop.result})
    except KeyboardInterrupt:  # while a later program was built or compiled: the runs trained so far are saved
        if not results:
            raise
        interrupted = True
    finally:
        bar.close()
    phases["train"] = train_time = time.perf_counter() - t_train
    if not writer:
        steps = logs[0].history[-1]["env_steps"] if logs[0].history else 0
        return {"process_index": jax.process_index(), "env_steps": steps, "interrupted": interrupted}
    source = provenance()  # the same for every run
    settings_of = dict(run=run, algo=algo, config=config, env=env, phases=phases, train_time=train_time, source=source)
    if not multi:
        return _write_run(out, results[0][1], logs[0], last[0], interrupted, t_start, **settings_of)
    head = dict(task=task, algo=algo, seeds=list(seed_list or [config.seed]), mapped=mapped, programs=len(groups))
    return _write_runs(out, grid, configs, results, logs, last, interrupted, t_start, head, bar.label, **settings_of)


#: What the summary of several seeds keeps of each seed's own summary (in ``seed_<k>/summary.json``).
PER_SEED = ("success_value", "success", "failed_criteria", "env_steps", "out_dir")

#: The evaluation statistics whose median over the seeds the progress display shows.
MEDIAN_OF = ("success_value", "terminated_rate", "episode_reward")


def _seeds(seeds, seed: int) -> tuple[int, ...] | None:
    """`train_task`'s ``seeds`` as a tuple of ints (None for a single run)."""
    if seeds is None:
        return None
    if isinstance(seeds, int | np.integer) and not isinstance(seeds, bool):
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        return tuple(range(seed, seed + int(seeds)))
    out = tuple(int(s) for s in seeds)
    if not out or len(set(out)) != len(out) or min(out) < 0:
        raise ValueError(f"seeds must be distinct non-negative integers, got {seeds!r}")
    return out


def sweep_settings(config: Schedule | BraxPPOConfig, sweep: Mapping[str, Sequence] | None) -> list[dict] | None:
    """The settings of a sweep ``{name: values}`` over fields of ``config``: every combination of the values (the
    product, the last name's values changing fastest), as dicts of field values; None without a sweep. Numbers for a
    float field become floats.

    Raises:
        ValueError: an empty sweep, ``seed`` (set with ``seeds``), a name that is not a field of ``config`` (with the
            closest one), no values or a value twice.
    """
    from jaxdrones._hints import unknown_option

    if sweep is None:
        return None
    fields = [field.name for field in dataclasses.fields(config)]
    if not sweep:
        raise ValueError("sweep must name at least one setting")
    cast = {}
    for name, values in sweep.items():
        if name == "seed":
            raise ValueError("sweep: seeds are set with seeds (--seeds), not swept")
        if name not in fields:
            raise ValueError(unknown_option(f"sweep ({type(config).__name__})", name, fields))
        is_float = mappable(getattr(config, name))
        cast[name] = [
            float(v) if is_float and isinstance(v, int | float) and not isinstance(v, bool) else v for v in values
        ]
        if not cast[name] or len({repr(v) for v in cast[name]}) != len(cast[name]):
            raise ValueError(f"sweep: {name} takes distinct values, got {list(values)!r}")
    return [dict(zip(cast, combination, strict=True)) for combination in itertools.product(*cast.values())]


def program_groups(configs: Sequence[Schedule], config: Schedule) -> list[tuple[int, ...]]:
    """The indices of ``configs`` (``config`` with other seeds and settings) grouped into the programs that train
    them: runs that differ only in their seed and float fields share one program mapped over them
    (`jaxdrones.training.common.mapped_fields`); any other field (a count, a shape, a switch) changes the program."""
    programs: dict[str, list[int]] = {}
    for k, run in enumerate(configs):
        shape = [
            repr(getattr(run, field.name))
            for field in dataclasses.fields(config)
            if field.name != "seed" and not mappable(getattr(run, field.name))
        ]
        programs.setdefault("\n".join(shape), []).append(k)
    return [tuple(group) for group in programs.values()]


def setting_label(setting: Mapping) -> str:
    """A sweep's setting as its folder's name: ``name=value`` joined by commas (empty without a sweep)."""
    return ",".join(f"{name}={value}" for name, value in setting.items())


def _plan(trainer: Trainer, sweep: Mapping | None, config, n_runs: int, n_programs: int) -> str:
    """The line that says how the runs are trained, where they take several programs."""
    if not trainer.maps_runs:
        return f"{n_runs} runs one after another: {trainer.name} runs its own training loop, which cannot be mapped"
    separate = [name for name in sweep or {} if not mappable(getattr(config, name))]
    mapped = ["the seeds", *(name for name in sweep or {} if name not in separate)]
    return (
        f"{n_runs} runs as {n_programs} programs, one after another: {', '.join(separate)} "
        f"change{'s' * (len(separate) == 1)} the program (its shapes or its steps); {' and '.join(mapped)} are mapped "
        f"within each"
    )


def aggregate(values: Sequence[float], solved: Sequence[bool]) -> dict:
    """The seeds' results as reported over runs (Agarwal et al., "Deep Reinforcement Learning at the Edge of the
    Statistical Precipice", NeurIPS 2021): ``median``, ``iqm`` (the interquartile mean, `scipy.stats.trim_mean` at
    25 %), ``iqm_ci95`` (its 95 % percentile bootstrap interval over the seeds, `scipy.stats.bootstrap`, 10,000
    resamples, fixed seed; None for fewer than 3 seeds), ``solved_share`` and ``n_seeds``."""
    from scipy import stats

    x = np.asarray(values, dtype=float)
    iqm = functools.partial(stats.trim_mean, proportiontocut=0.25)
    interval = None
    if len(x) >= 3 and np.all(np.isfinite(x)):
        boot = stats.bootstrap((x,), iqm, n_resamples=10_000, method="percentile", random_state=0)
        interval = [float(boot.confidence_interval.low), float(boot.confidence_interval.high)]
    return {
        "median": float(np.median(x)),
        "iqm": float(iqm(x)),
        "iqm_ci95": interval,
        "solved_share": float(np.mean(solved)),
        "n_seeds": len(x),
    }


def _write_run(
    out, params, log, last, interrupted, t_start, *, run, algo, config, env, phases, train_time, source, plots=True
) -> dict:
    """Write one run's folder (`train_task`'s outputs; without ``plots``, no learning curve, flight plot or viewer
    page) and return its summary (``source``: its ``provenance``)."""
    from jaxdrones.training import checkpoint
    from jaxdrones.training.evaluation import episode_statistics
    from jaxdrones.training.progress import AGGREGATES

    os.makedirs(out, exist_ok=True)
    task, env_overrides = run.task, dict(run.env)
    env_steps = log.history[-1]["env_steps"] if log.history else 0
    t_phase = time.perf_counter()
    checkpoint.save(os.path.join(out, "policy.pkl"), algo, params, task, env_overrides, config)
    log.save(os.path.join(out, "progress.json"))
    stats = episode_statistics(env, last["eval"]["outcomes"]) if last else {}
    phases["save"] = time.perf_counter() - t_phase
    if plots:
        t_phase = time.perf_counter()
        _plot(env, task, algo, log, last.get("eval"), out)
        phases["plots"] = time.perf_counter() - t_phase
        t_phase = time.perf_counter()
        _write_viewer(env, last.get("eval"), out)
        phases["viewer"] = time.perf_counter() - t_phase
    value = stats.get("success_value", math.nan)
    failed = failed_criteria(env.task, stats)
    summary = {
        "task": task,
        "algo": algo,
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": train_time,
        "phases_s": phases,
        "interrupted": interrupted,
        "env_steps": int(env_steps),
        "success_metric": f"{env.task.success_metric} ({AGGREGATES[env.task.success_at]})",
        "success_unit": env.task.success_unit,
        "success_value": value,
        "success_threshold": env.task.success_threshold,
        "success": not failed,
        "failed_criteria": failed,
        "eval": stats,
        "out_dir": out,
        "env": json.loads(json.dumps(dataclasses.asdict(env.config), default=str)),
        "train_env_overrides": dict(run.train_env),
        "defaults": run.defaults,
        "config": dataclasses.asdict(config),
        "provenance": source,
    }
    if "final_pos_error_m" in stats:
        summary["eval_final_pos_error_m"] = stats["final_pos_error_m"]
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def _write_runs(out, grid, configs, results, logs, last, interrupted, t_start, head, label, **settings_of) -> dict:
    """Write the runs of several seeds or settings (`train_task`'s ``seeds`` and ``sweep``): each run's folder (its
    setting's, then ``seed_<k>/``; `_write_run` with ``settings_of`` and the run's config), and in ``out`` their
    ``summary.json`` (``head``'s fields, each setting's runs and aggregate), ``progress.json`` and
    ``learning_curve.png``; returns the summary."""
    from jaxdrones.io.plotting import plot_learning_curves

    env, train_time = settings_of["env"], settings_of["train_time"]
    sweep = any(setting for setting, _ in grid)
    summaries = {}
    for k in sorted(results):  # the runs trained
        setting, seed = grid[k]
        folder = os.path.join(out, *([setting_label(setting)] if sweep else []), f"seed_{seed}")
        one = dict(settings_of, config=configs[k], phases={})
        summaries[k] = _write_run(folder, results[k][1], logs[k], last[k], interrupted, t_start, **one, plots=False)

    def results_of(setting):
        ks = [k for k in summaries if grid[k][0] == setting]
        return {
            "aggregate": aggregate([summaries[k]["success_value"] for k in ks], [summaries[k]["success"] for k in ks]),
            "runs": [{"seed": grid[k][1], **{name: summaries[k][name] for name in PER_SEED}} for k in ks],
        }

    summary = {
        **head,
        "wall_time_s": time.perf_counter() - t_start,
        "train_time_s": train_time,
        "interrupted": interrupted,
        "env_steps": [summaries[k]["env_steps"] for k in summaries],
        "success_metric": next(iter(summaries.values()))["success_metric"],
        "success_threshold": env.task.success_threshold,
        "out_dir": out,
        "provenance": settings_of["source"],
    }
    trained = []  # the settings with a run trained, in order
    for k in summaries:
        if grid[k][0] not in trained:
            trained.append(grid[k][0])
    if sweep:
        summary["sweep"] = {name: list(dict.fromkeys(setting[name] for setting, _ in grid)) for name in grid[0][0]}
        summary["settings"] = [{"setting": setting, **results_of(setting)} for setting in trained]
    else:
        summary.update(results_of({}))
    names = [f"{setting_label(grid[k][0]) + ',' if sweep else ''}seed_{grid[k][1]}" for k in summaries]
    with open(os.path.join(out, "progress.json"), "w") as f:
        json.dump({name: logs[k].history for name, k in zip(names, summaries, strict=True)}, f, indent=1)
    plot_learning_curves(
        [logs[k].history for k in summaries],
        os.path.join(out, "learning_curve.png"),
        groups=[setting_label(grid[k][0]) for k in summaries] if sweep else None,
        metric_label=f"evaluation {label}",
        threshold=env.task.success_threshold,
        title=f"{head['algo'].upper()} on {head['task']}, seeds {', '.join(map(str, head['seeds']))}",
    )
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def _run_recipe(task, algo, config, env_overrides, train_env_overrides, defaults) -> Recipe:
    """`train_task`'s recipe: ``task`` if it is one (and nothing else is given), else the task's
    (`jaxdrones.training.recipes.recipe`) with ``config`` and ``train_env_overrides`` in its place where given."""
    given = {
        "algo": algo,
        "config": config,
        "env_overrides": env_overrides,
        "train_env_overrides": train_env_overrides,
        "defaults": defaults,
    }
    if isinstance(task, Recipe):
        if any(value is not None for value in given.values()):
            named = ", ".join(name for name, value in given.items() if value is not None)
            raise ValueError(f"train: a Recipe holds the run's settings; set them in it, not as {named}")
        return task
    run = recipe(task, defaults, env_overrides, algo)
    if config is not None:
        run = dataclasses.replace(run, config=config)
    if train_env_overrides is not None:
        run = dataclasses.replace(run, train_env={k: v for k, v in train_env_overrides.items() if k not in run.env})
    return run


def failed_criteria(task: Task, stats: dict) -> list[str]:
    """The criteria of a solved run that the evaluation ``stats`` (`jaxdrones.training.evaluation.
    episode_statistics`) miss, as sentences (empty: solved): the task's success metric at or above its threshold,
    and, unless the task's metric counts them itself (``success_counts_terminations``), any episode that ended early
    (a crash, or leaving the arena)."""
    from jaxdrones.training.progress import AGGREGATES

    failed = []
    value = stats.get("success_value", math.nan)
    if not value < task.success_threshold:
        failed.append(
            f"{task.success_metric} ({AGGREGATES[task.success_at]}) {value:.4g} {task.success_unit} is not below "
            f"the threshold {task.success_threshold:g}"
        )
    rate, n = stats.get("terminated_rate", math.nan), stats.get("n_episodes", 0)
    if not task.success_counts_terminations and not rate == 0.0:
        failed.append(
            f"{round(rate * n)} of {n} episodes ended early (crashed or left the arena; a solved run has none)"
        )
    return failed


def _write_viewer(env, evaluation: dict | None, out: str) -> None:
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


def _plot(env, task: str, algo: str, log, evaluation: dict | None, out: str) -> None:
    """``learning_curve.png`` (the judged metric against env steps, with its threshold) and, when an evaluation ran,
    ``flight.png`` (its first episode)."""
    import numpy as np

    from jaxdrones.io.plotting import plot_learning_curve, plot_task_flight

    title = f"{algo.upper()} on {task} ({env.config.model}, {env.config.action_type})"
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
        flight = evaluation["flight"]
        times = np.arange(env.episode_length + 1) / env.config.sim.ctrl_freq
        plot_task_flight(
            times,
            flight["pos"],
            flight["ref"],
            flight["vel"],
            flight["rpm"],
            os.path.join(out, "flight.png"),
            title=f"{task}: evaluation flight",
        )
