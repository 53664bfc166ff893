"""The plan of a training run's seeds and sweep (`plan_runs`): every setting checked once, before anything
compiles (types, ranges, finite values, the trainer config's own rules), the runs grouped into the programs that
train them, their memory estimated against the device's, the aggregate of their results (`aggregate`), and how a
run ends other than complete (`Stopped`, `TrainingFailed`)."""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxdrones._validate import is_integer
from jaxdrones.training.common import mappable

if TYPE_CHECKING:
    from jaxdrones.envs.base import Env
    from jaxdrones.training.trainers import Trainer

#: What the summary of several runs keeps of each run's own summary (in ``seed_<k>/summary.json``).
PER_SEED = ("success_value", "success", "failed_criteria", "diverged", "env_steps", "out_dir")


class TrainingFailed(RuntimeError):
    """A run stopped by an error (its parameters went non-finite, or a later program failed) after something was
    trained: ``summary`` is what was saved (its ``out_dir``), and the error its cause."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


class Stopped(KeyboardInterrupt):
    """Ctrl-C, after what was trained was saved: ``summary`` is the run's (its ``out_dir``, ``interrupted``)."""

    def __init__(self, summary: dict):
        super().__init__(f"interrupted: saved in {summary['out_dir']}")
        self.summary = summary


@dataclasses.dataclass(frozen=True)
class Run:
    """One run of a plan: its trainer config, its sweep setting (``{}`` without a sweep) and its seed."""

    config: Any
    setting: Mapping[str, Any]
    seed: int

    def folder(self, sweep: bool) -> str:
        """Its folder inside a run of several: ``seed_<k>``, under its setting's (`setting_label`) in a sweep."""
        return f"{setting_label(self.setting)}/seed_{self.seed}" if sweep else f"seed_{self.seed}"


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """The runs of `train_task` (`plan_runs`).

    Attributes:
        runs: every run, settings in the sweep's order (the last name's values changing fastest), seeds within.
        programs: the indices of ``runs`` each compiled program trains, in order.
        mapped: the runs of a program are mapped over in it (our trainers), else one program per run.
        seeds: the seeds of every setting.
        sweep: ``{name: values}`` as checked (values cast to the field's type), or None.
        several: more than one run folder (``seeds`` or ``sweep`` given): ``seed_<k>/`` folders and an aggregate.
    """

    runs: tuple[Run, ...]
    programs: tuple[tuple[int, ...], ...]
    mapped: bool
    seeds: tuple[int, ...]
    sweep: Mapping[str, tuple] | None
    several: bool


def plan_runs(
    config: Any,
    trainer: Trainer,
    seeds: int | Sequence[int] | None = None,
    sweep: Mapping[str, Sequence] | None = None,
    per_run: int | None = None,
    free: tuple[int, str] | None = None,
) -> RunPlan:
    """The plan of ``config``'s runs over ``seeds`` and ``sweep``.

    Args:
        config: the trainer's config (its ``seed`` is the first seed of ``seeds=N``).
        trainer: the trainer of `jaxdrones.training.trainers` (`Trainer.maps_runs`: one program mapped over the runs
            that differ only in float fields and seeds).
        seeds: None (one run of ``config.seed``), ``N`` (seeds ``config.seed`` to ``config.seed + N - 1``) or
            distinct non-negative integer seeds.
        sweep: ``{name: values}`` over fields of ``config`` (`sweep_settings`; values may be the command line's
            strings), or None.
        per_run, free: one run's memory (`run_bytes`) and the memory free (`available_bytes`), to refuse a plan
            whose largest program would not fit (`check_memory`), before its runs are built; no check where None.

    Raises:
        ValueError: seeds of the wrong type or range, a sweep `sweep_settings` refuses, a setting the config
            refuses (a non-finite or out-of-range value; named with its setting), or runs that would not fit.
    """
    seed_list = check_seeds(seeds, config.seed)
    settings = sweep_settings(config, sweep)
    configs = []  # one per setting, each checked by its config
    for setting in settings or [{}]:
        try:
            configs.append(dataclasses.replace(config, **setting))
        except ValueError as err:
            raise ValueError(f"sweep {setting_label(setting)}: {err}" if setting else str(err)) from None
    several = seed_list is not None or settings is not None
    mapped = several and trainer.maps_runs
    all_seeds = seed_list or (config.seed,)
    n = len(all_seeds)
    # A program maps a group of settings with every seed (our trainers), else trains one run.
    groups = program_groups(configs, config) if mapped else []
    if per_run is not None:
        check_memory(max(map(len, groups)) * n if mapped else 1, per_run, free)
    runs = [
        Run(dataclasses.replace(one, seed=seed), setting, seed)
        for one, setting in zip(configs, settings or [{}], strict=True)
        for seed in all_seeds
    ]
    if mapped:
        programs = [tuple(k * n + j for k in group for j in range(n)) for group in groups]
    else:
        programs = [(k,) for k in range(len(runs))]
    checked = None if settings is None else {name: tuple(dict.fromkeys(s[name] for s in settings)) for name in sweep}
    return RunPlan(tuple(runs), tuple(programs), mapped, all_seeds, checked, several)


def check_seeds(seeds: Any, seed: int) -> tuple[int, ...] | None:
    """``seeds`` as a tuple of ints (None for a single run): ``N`` >= 1 gives ``seed`` to ``seed + N - 1``.

    Raises:
        ValueError: not an integer or a sequence of distinct non-negative integers (a string, a float, a bool).
    """
    if seeds is None:
        return None
    if is_integer(seeds):
        if seeds < 1:
            raise ValueError(f"seeds must be a count >= 1 or a list of seeds, got {seeds}")
        return tuple(range(seed, seed + int(seeds)))
    if isinstance(seeds, str | bytes) or not isinstance(seeds, Sequence | np.ndarray):
        raise ValueError(f"seeds must be an integer count or a list of integer seeds, got {seeds!r}")
    out = tuple(seeds)
    if not out or not all(is_integer(s) and s >= 0 for s in out) or len(set(out)) != len(out):
        raise ValueError(f"seeds must be distinct non-negative integers, got {seeds!r}")
    return tuple(int(s) for s in out)


def parse_sweep(settings: Sequence[str]) -> dict[str, list[str]] | None:
    """The command line's ``--sweep NAME=V1,V2,...`` settings as ``{name: [text, ...]}`` (None without any);
    `sweep_settings` casts and checks them.

    Raises:
        ValueError: a setting that is not NAME=V1,V2,..., or a name given twice.
    """
    if not settings:
        return None
    sweep: dict[str, list[str]] = {}
    for setting in settings:
        name, sep, text = (part.strip() for part in setting.partition("="))
        if not sep or not name or not text:
            raise ValueError(f"--sweep takes NAME=V1,V2,..., got {setting!r}")
        if name in sweep:
            raise ValueError(f"--sweep {name} is given twice")
        sweep[name] = [word.strip() for word in text.split(",")]
    return sweep


def sweep_settings(config: Any, sweep: Mapping[str, Sequence] | None) -> list[dict] | None:
    """The settings of a sweep ``{name: values}`` over fields of ``config``: every combination of the values (the
    product, the last name's values changing fastest), as dicts of field values; None without a sweep. Each value
    is cast to the field's type (an int, a float or a bool; text as the command line gives it: ``1e-3``,
    ``true``); the config's own checks (ranges, finite values) run on each run in `plan_runs`.

    Raises:
        ValueError: an empty sweep, ``seed`` (set with ``seeds``), a name that is not a field of ``config`` (with the
            closest one), a field that takes no single number or switch, a value of another type, no values or a
            value twice.
    """
    from jaxdrones._hints import unknown_option

    if sweep is None:
        return None
    if not isinstance(sweep, Mapping) or not sweep:
        raise ValueError(f"sweep must be a dict of at least one setting name to its values, got {sweep!r}")
    fields = {field.name: getattr(config, field.name) for field in dataclasses.fields(config)}
    cast = {}
    for name, values in sweep.items():
        if name == "seed":
            raise ValueError("sweep: seeds are set with seeds (--seeds), not swept")
        if name not in fields:
            raise ValueError(unknown_option(f"sweep ({type(config).__name__})", name, fields))
        kind = type(fields[name])
        if kind not in (int, float, bool):
            raise ValueError(f"sweep takes settings that are numbers or true/false; {name} is {fields[name]!r}")
        if isinstance(values, str | bytes) or not isinstance(values, Sequence | np.ndarray):
            raise ValueError(f"sweep: {name} takes a list of values, got {values!r}")
        try:
            cast[name] = [_cast(kind, value) for value in values]
        except ValueError:
            raise ValueError(f"sweep: {name} takes {kind.__name__} values, got {list(values)!r}") from None
        if not cast[name] or len({repr(v) for v in cast[name]}) != len(cast[name]):
            raise ValueError(f"sweep: {name} takes distinct values, got {list(values)!r}")
    return [dict(zip(cast, combination, strict=True)) for combination in itertools.product(*cast.values())]


def _cast(kind: type, value: Any) -> Any:
    """A sweep's value as the field's type ``kind``: text read as the command line writes it; a float field takes
    any finite or non-finite real (its config checks the range), an int field only whole numbers."""
    if isinstance(value, str):
        word = value.strip().lower()
        if kind is bool:
            if word not in ("true", "false"):
                raise ValueError(value)
            return word == "true"
        return kind(word)
    if kind is bool:
        if not isinstance(value, bool | np.bool_):
            raise ValueError(value)
        return bool(value)
    if isinstance(value, bool | np.bool_):
        raise ValueError(value)
    if kind is int:
        if not is_integer(value):
            raise ValueError(value)
        return int(value)
    if not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(value)
    return float(value)


def program_groups(configs: Sequence[Any], config: Any) -> list[tuple[int, ...]]:
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


def describe(plan: RunPlan, trainer: Trainer) -> str:
    """The line that says how the runs are trained, where they take several programs."""
    n_runs, n_programs = len(plan.runs), len(plan.programs)
    if not trainer.maps_runs:
        return f"{n_runs} runs one after another: {trainer.name} runs its own training loop, which cannot be mapped"
    config = plan.runs[0].config
    separate = [name for name in plan.sweep or {} if not mappable(getattr(config, name))]
    mapped = ["the seeds", *(name for name in plan.sweep or {} if name not in separate)]
    return (
        f"{n_runs} runs as {n_programs} programs, one after another: {', '.join(separate)} "
        f"change{'s' * (len(separate) == 1)} the program (its shapes or its steps); {' and '.join(mapped)} are mapped "
        f"within each"
    )


#: The factor over the arrays a run's program is known to hold (`run_bytes`) that its memory takes (the gradient's
#: saved activations, the optimiser's moments, XLA's buffers): above the largest ratio measured, over hover, velocity,
#: crossing and leader_follower at their recipes (0.8 to 2.3; `benchmarks/speed/run_memory.py`, docs/benchmarks.md,
#: "Memory of mapped runs").
MEMORY_FACTOR = 2.5


def run_bytes(config: Any, env: Env, train_env: Env, n_eval_episodes: int) -> int:
    """An estimate of one run's memory in a program, from shapes alone (nothing compiled): its evaluation's
    ``n_eval_episodes`` episodes (an env state each, and over the episode's steps the reward, step count, termination
    and metrics that the statistics read) and one update's ``config.steps_per_update`` training env states, times
    `MEMORY_FACTOR`."""
    import jax

    def size(tree):
        return sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree))

    def reset_shapes(e):  # traced only: no eager operation, which would compile a program of its own
        return jax.eval_shape(lambda: e.reset(jax.random.key(0)))

    state = reset_shapes(env)
    per_step = size((state.reward, state.steps, state.terminated, state.metrics))
    evaluation = n_eval_episodes * ((env.episode_length + 1) * per_step + size(state))
    steps = getattr(config, "steps_per_update", config.num_envs)
    training = steps * size(reset_shapes(train_env))
    return int(MEMORY_FACTOR * (evaluation + training))


def available_bytes() -> tuple[int, str] | None:
    """``(bytes, where)``: the memory free for a program on JAX's default device: a GPU's or TPU's limit
    (``memory_stats``), or the host's available memory (``MemAvailable`` of /proc/meminfo); None where unknown."""
    import jax

    device = jax.devices()[0]
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        limit = stats.get("bytes_limit")
        return None if limit is None else (int(limit), f"the memory of {device.device_kind}")
    try:
        with open("/proc/meminfo") as f:
            fields = dict(line.split(":", 1) for line in f)
        return int(fields["MemAvailable"].split()[0]) * 1024, "the host's available memory"
    except (OSError, KeyError, ValueError):
        return None


#: The share of the free memory that `check_memory` lets a program take (the rest: the process, its compiler).
HEADROOM = 0.9


def check_memory(largest: int, per_run: int, free: tuple[int, str] | None) -> None:
    """Refuse a plan whose largest program, ``largest`` runs mapped, would not fit: ``per_run`` bytes (`run_bytes`)
    each against `HEADROOM` of ``free`` (`available_bytes`; no check where None).

    Raises:
        ValueError: naming the largest program, its estimate, the memory free and how many runs fit in one program.
    """
    if free is None:
        return
    need, usable = per_run * largest, int(HEADROOM * free[0])
    if need <= usable:
        return
    fits = usable // max(per_run, 1)
    raise ValueError(
        f"the largest program maps {largest} runs and needs about {need / 2**30:.1f} GiB (an estimate: "
        f"{per_run / 2**20:.1f} MiB a run), more than {free[1]} allows ({free[0] / 2**30:.1f} GiB free): at most "
        f"{fits} runs fit in one program; train fewer seeds or settings at a time"
    )


def diverged_message(plan: RunPlan, diverged: Sequence[int | None], out: str) -> str:
    """The error of runs whose loss or parameters went non-finite: the update (from 1; ``diverged``, per run of
    ``plan``, None for a run that did not) and the setting of each, and where their last finite parameters are."""
    parts = []
    for run, update in zip(plan.runs, diverged, strict=True):
        if update is not None:
            fields = {
                name: getattr(run.config, name)
                for name in ("learning_rate", "max_grad_norm")
                if hasattr(run.config, name)
            }
            setting = setting_label({**fields, **run.setting}) + f", seed {run.seed}"
            parts.append(f"update {update} ({setting})")
    return (
        f"training diverged: the loss or the parameters went non-finite at {'; '.join(parts)}; the last finite "
        f"parameters are saved in {out}: try a smaller learning_rate or max_grad_norm"
    )


def aggregate(values: Sequence[float], solved: Sequence[bool]) -> dict:
    """The seeds' results as reported over runs (Agarwal et al., "Deep Reinforcement Learning at the Edge of the
    Statistical Precipice", NeurIPS 2021): ``median``, ``iqm`` (the interquartile mean, `scipy.stats.trim_mean` at
    25 %), ``iqm_ci95`` (its 95 % percentile bootstrap interval over the seeds, `scipy.stats.bootstrap`, 10,000
    resamples, fixed seed; None for fewer than 3 seeds or a non-finite value), ``solved_share`` and ``n_seeds``."""
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
