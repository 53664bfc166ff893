"""Pieces shared by our own trainers (`jaxdrones.training.apg`, ``shac``, ``mappo``): the schedule of updates
between evaluations, the MLP, spreading the worlds over devices, and the jitted training
loop."""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

if TYPE_CHECKING:
    from flax import linen

    from jaxdrones.envs.base import Env


class Schedule:
    """The schedule of a trainer's config: ``num_timesteps`` env steps in ``num_evals`` jitted chunks of updates
    of `steps_per_update` env steps (a config mixin; the config defines ``steps_per_update``)."""

    num_timesteps: int
    num_evals: int

    @property
    def updates_per_eval(self) -> int:
        """Updates between two evaluations (one jitted call)."""
        return max(1, -(-self.num_timesteps // (self.steps_per_update * self.num_evals)))

    @property
    def total_steps(self) -> int:
        """The env steps `run_updates` runs (``num_timesteps`` rounded up to whole chunks)."""
        return self.num_evals * self.updates_per_eval * self.steps_per_update


def mlp(
    hidden_layer_sizes: tuple[int, ...], out: int, last_init: Callable | None = None, squash: bool = False
) -> linen.Module:
    """A flax MLP x f[..., n] -> f[..., out]: tanh hidden layers, a linear last layer with kernel initialiser
    ``last_init`` (default flax's LeCun normal; a small one makes the first outputs near 0), and a tanh on the
    output if ``squash``."""
    import flax.linen as nn

    class MLP(nn.Module):
        @nn.compact
        def __call__(self, x):
            for size in hidden_layer_sizes:
                x = nn.tanh(nn.Dense(size)(x))
            x = nn.Dense(out, **({} if last_init is None else {"kernel_init": last_init}))(x)
            return nn.tanh(x) if squash else x

    return MLP()


#: The settings of our trainers' configs that choose how an update is built for a device, not what it computes
#: (`jaxdrones.training.trainers.DEFAULTS` sets them per profile; both off is the CPU's choice):
#:
#: - ``starts_per_window``: every world's next episode is drawn once per window or unroll
#:   (`jaxdrones.wrappers.VmapAutoReset.starts`) rather than reset in the step (random numbers, and a ``lax.cond``
#:   whose predicate a GPU hands to the host, in every step); a world whose episode ends twice within one window
#:   starts the same episode again.
#: - ``flat_params``: the optimised parameters, and so Adam's moments, are one flat vector (`param_maps`), so that an
#:   optimiser step is a few fused operations on one vector rather than a few per leaf (PPO's actor and critic have
#:   13 leaves). The same arithmetic, element by element.
#: - ``noise_per_window`` (our PPO's): the Gaussian actions' noise of a whole unroll is drawn in one call before it
#:   rather than from a key in each step: one Threefry hash per update instead of one per step (XLA:CPU runs each
#:   as a loop of about 90 operations; a GPU as one kernel and the normal's transform). The same distribution,
#:   other draws.
#:
#: On a GPU every operation of an update is a kernel run after the previous one, and each cuts them; on the CPU the
#: first two slow APG's updates and the third gains nothing (`benchmarks/training/train_cost.py`, docs/benchmarks.md,
#: "Training at a GPU's speed").
BUILD_SETTINGS = ("starts_per_window", "flat_params", "noise_per_window")

#: The profiles of default settings (``jaxdrones train --defaults``): ``"cpu"``, tuned for the fewest seconds to a
#: solved policy on a CPU (few worlds, many small updates), and ``"gpu"``, for the fewest sequential
#: operations (many worlds, few large updates: a GPU steps thousands of worlds in the time of one, while every
#: operation of an update runs after the previous one, each at least one kernel launch;
#: `benchmarks/training/train_cost.py`). The results do not depend on the device that runs them: ``--defaults gpu
#: --device cpu`` trains the same policy.
DEFAULTS = ("cpu", "gpu")


def check_defaults(defaults: str) -> None:
    """Raise ``ValueError`` unless ``defaults`` is one of `DEFAULTS`."""
    if defaults not in DEFAULTS:
        raise ValueError(f"defaults must be one of {DEFAULTS}, got {defaults!r}")


def param_maps(shapes: Any, flat: bool = True) -> tuple[Callable[[Any], Any], Callable[[Any], Any]]:
    """``(ravel, unravel)`` for parameter pytrees shaped like ``shapes`` (arrays or ``jax.ShapeDtypeStruct``, e.g.
    ``jax.eval_shape`` of a network's ``init``): with ``flat``, ``ravel(params)`` is one flat vector (the leaves
    in `jax.tree.leaves` order, as `jax.flatten_util.ravel_pytree` orders them) and ``unravel(flat)`` the pytree
    again; without, both are the identity (see `BUILD_SETTINGS`' ``flat_params``). Outside a trace ``unravel``
    splits the vector on the host, so that a trainer's result compiles no program of its own."""
    if not flat:
        return (lambda params: params), (lambda params: params)
    leaves, treedef = jax.tree.flatten(shapes)
    dtype = jnp.result_type(*(leaf.dtype for leaf in leaves))
    bounds = np.cumsum([0, *(math.prod(leaf.shape) for leaf in leaves)])

    def ravel(params):
        return jnp.concatenate([jnp.ravel(x).astype(dtype) for x in jax.tree.leaves(params)])

    def unravel(vector):
        on_host = not isinstance(vector, jax.core.Tracer)
        vector = host_array(vector) if on_host else vector
        parts = [
            vector[a:b].reshape(leaf.shape).astype(leaf.dtype)
            for a, b, leaf in zip(bounds[:-1], bounds[1:], leaves, strict=True)
        ]
        tree = jax.tree.unflatten(treedef, parts)
        return jax.device_put(tree) if on_host else tree

    return ravel, unravel


class Interrupted(Exception):
    """Training stopped by Ctrl-C (``KeyboardInterrupt``) between two evaluations.

    Attributes:
        result: what the trainer returns, from the last completed chunk of updates (the initial parameters if none
            completed).
        env_steps: the env steps trained before the stop.
    """

    def __init__(self, result, env_steps: int):
        super().__init__(f"training interrupted after {env_steps} env steps")
        self.result, self.env_steps = result, env_steps


def nonfinite_leaves(tree: Any) -> list[str]:
    """The key paths (`jax.tree_util.keystr`) of the float leaves of ``tree`` holding a NaN or an infinity, read on
    the host; empty where every one is finite."""
    return [
        jax.tree_util.keystr(path)
        for path, x in jax.tree_util.tree_leaves_with_path(tree)
        if np.issubdtype(np.asarray(x).dtype, np.inexact) and not np.all(np.isfinite(host_array(x)))
    ]


def host_array(x: ArrayLike) -> np.ndarray:
    """A NumPy copy of a JAX array, also of one replicated over the devices of several processes (where
    ``np.asarray`` cannot gather it: each process holds a full copy)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return np.asarray(x.addressable_shards[0].data)
    return np.asarray(x)


def world_shardings(tree: Any, n_worlds: int) -> Any | None:
    """Shardings that spread a trainer's carry over the devices of every process (`jax.devices()`): each leaf whose
    leading axis has ``n_worlds`` entries (the worlds' states, observations, keys) split along it, every other leaf
    (parameters, optimiser state, shared env params) replicated. Uses the largest number of devices that divides
    ``n_worlds``; None with one device (no sharding needed).

    Sharding never changes what a jitted program computes, only where: worlds do not interact, so each device steps
    its own, and XLA sums gradients across devices where a loss averages over worlds.
    """
    devices = jax.devices()
    count = max(n for n in range(1, len(devices) + 1) if n_worlds % n == 0)
    if count == 1:
        return None
    mesh = jax.sharding.Mesh(np.array(devices[:count]), ("worlds",))
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("worlds"))
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    return jax.tree.map(lambda x: split if x.ndim and x.shape[0] == n_worlds else replicated, tree)


def program_description(config: object, env: Env) -> str:
    """What a trainer's chunk is built from, as text for `jaxdrones.training.programs`: the trainer's config and the
    env's task and config (its params follow from them)."""
    return f"{type(config).__module__}.{config!r}\n{type(env).__name__} {env.task.name} {env.config!r}"


def mappable(value: Any) -> bool:
    """Whether a config field's value can be an input of the compiled programs, mapped over runs (`run_updates`): a
    float (a step size, a discount, a weight). Any other value (a count, a shape, a switch) shapes the program."""
    return type(value) is float


def mapped_fields(config: Schedule, runs: Sequence[Schedule]) -> tuple[str, ...]:
    """The fields other than ``seed`` whose values differ between ``runs`` and ``config``: `run_updates` maps each
    over the runs as an input of the compiled programs, so each must be a float (a step size, a discount, a weight).

    Raises:
        ValueError: no runs, a run of another config class, or one that differs in a field that is not a float (a
            count, a shape, a switch: it changes the program, so it is trained as a program of its own).
    """
    if not runs:
        raise ValueError("runs must hold at least one config")
    for run in runs:
        if type(run) is not type(config):
            raise ValueError(f"runs must be {type(config).__name__}s, got {type(run).__name__}")
    names = []
    for field in dataclasses.fields(config):
        values = [getattr(run, field.name) for run in runs]
        if field.name == "seed" or all(value == getattr(config, field.name) for value in values):
            continue
        if not all(mappable(value) for value in [*values, getattr(config, field.name)]):
            raise ValueError(
                f"runs mapped in one program differ only in their seed and float fields; {field.name!r} takes "
                f"{sorted({repr(v) for v in values})} (train each value as its own program)"
            )
        names.append(field.name)
    return tuple(names)


def traced_config(config: Schedule, values: Mapping[str, Any]) -> Schedule:
    """``config`` with the fields of ``values`` set to them (inside a trace: arrays, a mapped run's own values;
    `mapped_fields`), without the config's checks, which every run's config passed."""
    if not values:
        return config
    traced = copy.copy(config)
    for name, value in values.items():
        object.__setattr__(traced, name, value)
    return traced


def _programs(init, chunk, evaluate, inputs, n_batch: int, description: str | None, eval_description: str | None):
    """`run_updates`' three programs, jitted: ``(init, chunk, evaluate)``. Over several devices, the carry
    spread over them along its leading axis of ``n_batch`` entries (`world_shardings`: the worlds, or the runs of a
    mapped run); on one, kept in the program cache (`jaxdrones.training.programs`) where ``description`` and the
    evaluation's own ``description`` name them and the cache is on."""
    from jaxdrones.training.programs import cache_folder, cached_jit

    shardings = world_shardings(jax.eval_shape(init, inputs), n_batch) if jax.device_count() > 1 else None
    if shardings is not None:
        replicated = jax.sharding.NamedSharding(jax.tree.leaves(shardings)[0].mesh, jax.sharding.PartitionSpec())
        return (
            jax.jit(init, out_shardings=shardings),
            jax.jit(chunk, in_shardings=(shardings,), out_shardings=(shardings, replicated)),
            jax.jit(evaluate, in_shardings=(shardings,), out_shardings=replicated),
        )
    if description is None or eval_description is None or cache_folder() is None:
        return jax.jit(init), jax.jit(chunk), jax.jit(evaluate)
    return (
        cached_jit(init, f"{description}\ninit"),
        cached_jit(chunk, f"{description}\nchunk"),
        cached_jit(evaluate, f"{description}\n{eval_description}"),
    )


def _run_functions(config: Schedule, build: Callable, evaluate: Callable | None, runs: Sequence | None):
    """`run_updates`' programs before compilation, ``(inputs, (init, chunk, evaluate, replay), result)``: the inputs
    of a run (its seed, from which the compiled init makes the key, and the values of `mapped_fields`), ``init(inputs)
    -> carry``, ``chunk(carry) -> (carry, metrics)``, ``evaluate(carry) -> {FINITE: the parameters all finite,
    "eval": the trainer's evaluation, where given}`` and ``replay(carry) -> bool[updates_per_eval]`` (the chunk from
    ``carry`` again, whether each update's metrics and parameters are finite) on a carry ``(inputs, the trainer's
    carry)``, and the trainer's ``result``; with ``runs``, each input with a runs axis and the programs mapped over
    it."""
    group = [config] if runs is None else runs
    seeds = np.asarray([run.seed for run in group]).astype(jax.dtypes.canonicalize_dtype(np.int64))
    if runs is None:
        inputs = (seeds[0], {})
    else:
        inputs = (
            seeds,
            {name: np.asarray([getattr(r, name) for r in runs], np.float32) for name in mapped_fields(config, runs)},
        )
    result = build(config)[2]  # the network and the parameters' layout: the same for every run

    def init_run(inputs):
        init = build(traced_config(config, inputs[1]))[0]
        return inputs, init(jax.random.key(inputs[0]))

    def chunk(carry):
        inputs, state = carry
        update = build(traced_config(config, inputs[1]))[1]
        state, metrics = jax.lax.scan(update, state, None, length=config.updates_per_eval)
        return (inputs, state), {name: value[-1] for name, value in metrics.items()}

    def replay(carry):  # each update of a chunk from ``carry`` all finite (its metrics and the parameters after it)
        update = build(traced_config(config, carry[0][1]))[1]

        def step(state, _):
            state, metrics = update(state, None)
            return state, _all_finite(metrics) & _all_finite(result(state)[1])

        return jax.lax.scan(step, carry[1], None, length=config.updates_per_eval)[1]

    def evaluate_run(carry):  # named: benchmarks/training/train_cost.py finds the evaluation by its name
        network, params = result(carry[1])
        checked = {FINITE: _all_finite(params)}  # here, not in the chunk: the chunk's program stays as it was
        return checked if evaluate is None else {**checked, "eval": evaluate(network, params, carry[0][0])}

    programs = (init_run, chunk, evaluate_run, replay)
    return inputs, tuple(fn and (fn if runs is None else jax.vmap(fn)) for fn in programs), result


#: The metric `run_updates` adds for a run whose metrics or parameters went non-finite: the first such update
#: (from 1), or -1.
NONFINITE = "nonfinite_update"

#: What the evaluation program of `run_updates` returns beside the evaluation: its parameters all finite.
FINITE = "finite"


def _all_finite(tree: Any) -> jax.Array:
    """Whether every float of ``tree`` is finite (one bool)."""
    checks = [jnp.isfinite(x).all() for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.stack(checks).all() if checks else jnp.bool_(True)


def run_updates(
    config: Schedule,
    build: Callable[[Schedule], tuple[Callable, Callable, Callable]],
    n_worlds: int,
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable | None = None,
    description: str | None = None,
    runs: Sequence[Schedule] | None = None,
) -> Any:
    """Our trainers' loop. ``build(config) -> (init, update, result)`` gives the trainer's ``init(key) -> carry``,
    ``update(carry, None) -> (carry, metrics)`` and ``result(carry) -> (network, params)``; then
    ``config.num_evals`` chunks, each a `jax.lax.scan` of ``config.updates_per_eval`` updates and the trainer's
    ``evaluate(network, params, seed)``: three compiled programs (`_programs`), each chunk dispatched before the
    previous one's metrics go to ``progress(env_steps, metrics)`` (the evaluation under ``"eval"``). With ``runs``
    (configs that differ from ``config`` in their seed and float fields, `mapped_fields`), one run per config in the
    three programs mapped over them (`jax.vmap`; over several devices, spread along the runs), ``build`` seeing those
    fields as arrays (`traced_config`), each metric with a runs axis. A run whose metrics or parameters go
    non-finite (checked after each chunk, in a program of its own) keeps the result of its last finite chunk and
    reports, under `NONFINITE` in the metrics, the first update that was not (found by replaying the chunk; counted
    from 1; -1 while finite); the loop stops once every run has. Returns ``result`` of the final carry (a list over
    ``runs``); on Ctrl-C raises `Interrupted` with that of the last completed chunk."""
    inputs, programs, result = _run_functions(config, build, evaluate, runs)
    eval_description = "" if evaluate is None else getattr(evaluate, "description", None)
    n_runs, n_updates = 1 if runs is None else len(runs), config.updates_per_eval
    n_batch = n_worlds if runs is None else n_runs
    init_c, chunk_c, eval_c = _programs(*programs[:3], inputs, n_batch, description, eval_description)
    replay_c = jax.jit(programs[3])
    diverged, kept = np.full(n_runs, -1), {}  # each run's first non-finite update; its result before it

    def results(carry):
        if runs is None:
            return kept[0] if 0 in kept else result(carry[1])
        return [kept[k] if k in kept else result(jax.tree.map(lambda x, k=k: x[k], carry[1])) for k in range(n_runs)]

    def check(previous, finite, metrics, k):
        """Record the runs whose metrics or ``finite`` parameters went non-finite in chunk ``k`` (from
        ``previous``)."""
        ok = np.reshape(host_array(finite), n_runs).copy()
        for name, value in metrics.items():
            if name != "eval":
                ok &= np.isfinite(np.reshape(value, (n_runs, -1))).all(axis=1)
        new = np.flatnonzero(~ok & (diverged < 0))
        if new.size:  # the chunk again from its start, update by update, to name the first non-finite one
            flags = np.reshape(host_array(replay_c(previous)), (n_runs, n_updates))
            before = results(previous)
            for j in new:
                diverged[j] = (k - 1) * n_updates + (int(np.argmin(flags[j])) if not flags[j].all() else n_updates) + 1
                kept[j] = before if runs is None else before[j]

    carry, done = None, 0
    try:
        carry = init_c(inputs)
        pending = chunk_c(carry)
        for k in range(1, config.num_evals + 1):
            finished, metrics = pending
            metrics = {**metrics, **eval_c(finished)}
            if k < config.num_evals:
                pending = chunk_c(finished)  # runs while this chunk's metrics are read and shown
            metrics = jax.tree.map(host_array, metrics)
            check(carry, metrics.pop(FINITE), metrics, k)
            carry, done = finished, k * n_updates * config.steps_per_update
            metrics[NONFINITE] = diverged.copy() if runs else int(diverged[0])
            if progress is not None:
                progress(done, metrics if runs else {k: v if k == "eval" else float(v) for k, v in metrics.items()})
            if np.all(diverged >= 0):  # every run stopped at its last finite parameters: nothing more to train
                break
    except KeyboardInterrupt:
        raise Interrupted(results(init_c(inputs) if carry is None else carry), done) from None
    return results(carry)
