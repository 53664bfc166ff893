"""Pieces shared by our own trainers (`jaxdrones.training.apg`, ``shac``, ``mappo``): the schedule of updates
between evaluations, the MLP, spreading the worlds over devices, and the jitted training
loop."""

from __future__ import annotations

import concurrent.futures
import math
import threading
from collections.abc import Callable
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
#: On a GPU every operation of an update is a kernel run after the previous one, and each cuts them
#: (`benchmarks/train_cost.py`); on 2 CPU cores the first two each made APG's default hover run 20-40 % slower per
#: update, and the third left our PPO's `cpu` settings as fast (each chunk 1.21 s against 1.20 s).
BUILD_SETTINGS = ("starts_per_window", "flat_params", "noise_per_window")

#: The profiles of default settings (``jaxdrones train --defaults``): ``"cpu"``, tuned for the fewest seconds to a
#: solved policy on a few CPU cores (few worlds, many small updates), and ``"gpu"``, for the fewest sequential
#: operations (many worlds, few large updates: a GPU steps thousands of worlds in the time of one, while every
#: operation of an update runs after the previous one, each at least one kernel launch; `benchmarks/train_cost.py`).
#: The results do not depend on the device that runs them: ``--defaults gpu --device cpu`` trains the same policy.
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


def described(fn: Callable, evaluate: Callable) -> Callable:
    """``fn`` with the ``description`` of the ``evaluate`` it calls (None if that has none), named ``evaluate`` (the
    name of its compiled program)."""
    fn.description = getattr(evaluate, "description", None)
    fn.__name__ = fn.__qualname__ = "evaluate"
    return fn


def run_updates(
    config: Schedule,
    init: Callable,
    update: Callable,
    result: Callable,
    n_worlds: int,
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable | None = None,
    description: str | None = None,
) -> Any:
    """The training loop of our trainers: three compiled programs, ``init``, a chunk of updates and the evaluation.

    ``init(key) -> carry`` builds the parameters, optimiser state and the worlds' states (jitted, with the carry
    spread over every device: `world_shardings`). Then ``config.num_evals`` calls of one jitted chunk, a
    `jax.lax.scan` of ``config.updates_per_eval`` calls of ``update(carry, None) -> (carry, metrics)``, each followed
    by a call of the jitted ``evaluate(carry)`` (a pytree of arrays, e.g. per-episode outcomes of the current
    policy). Each chunk is dispatched before the previous chunk's metrics are read, so that the host's work (the
    progress display) overlaps the next chunk; nothing else leaves the device during training. On one device, with
    the program cache (``description``, below), the chunk and then the evaluation are traced or loaded and compiled
    in two threads while ``init`` is (the chunk first: tracing holds Python's lock, XLA's compilation does not);
    without it, the evaluation is traced and compiled in a second thread, on its first run on the initial carry,
    while the chunk is compiled and the first chunk trains (on 2 CPU cores this hides its 2 s of tracing and
    compiling).

    ``progress(env_steps, metrics)`` is called after each chunk, with the last update's metrics (floats) and the
    evaluation under ``"eval"`` (NumPy arrays).

    ``description`` (the trainer, its config and its env's config, as text) lets a later process load the traced
    init, chunk and evaluation, and the shapes of init's result, from disk instead of tracing them
    (`jaxdrones.training.programs`), when ``evaluate`` has a ``description`` too (or is None); otherwise they are
    traced as usual.

    Returns:
        ``result(carry)`` of the final carry.

    Raises:
        Interrupted: on Ctrl-C, with ``result`` of the last completed chunk's carry.
    """
    # The key is made inside the compiled init from the seed: a key made here would compile programs of its own.
    seed = np.asarray(config.seed).astype(jax.dtypes.canonicalize_dtype(np.int64))

    def init_seeded(seed):
        return init(jax.random.key(seed))

    def chunk(carry):
        carry, metrics = jax.lax.scan(update, carry, None, length=config.updates_per_eval)
        return carry, {name: value[-1] for name, value in metrics.items()}

    steps_per_chunk = config.updates_per_eval * config.steps_per_update
    init_c, carry, done = jax.jit(init_seeded), None, 0
    chunk_what = f"updates {config.updates_per_eval}"
    # Programs traced and compiled beside the training thread; `Future.result` raises their errors there.
    background = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="jaxdrones-compile")
    building = compiling = eval_fn = None
    try:
        from jaxdrones.training.programs import cache_folder, cached_eval_shape, cached_jit

        # Read from the program cache where it is on: init is not traced in a warm run.
        shapes = cached_eval_shape(init_seeded, seed, None if description is None else f"{description}\ninit")
        shardings = world_shardings(shapes, n_worlds)
        eval_description = "" if evaluate is None else getattr(evaluate, "description", None)
        if shardings is None:
            replicated = None
            cached = description is not None and eval_description is not None and cache_folder() is not None

            def jit(fn, what, out_shardings, example=shapes):  # what: the program's key beyond ``description``
                return cached_jit(fn, example, f"{description}\n{what}") if cached else jax.jit(fn)

            def build(fn, what, after=None, traced=None):
                # Traced (or loaded) once ``after`` is set, then compiled; sets ``traced`` when its tracing is done.
                try:
                    if after is not None:
                        after.wait()
                    program = jit(fn, what, None)
                finally:
                    if traced is not None:
                        traced.set()
                program.precompile()
                return program

            if cached:
                # The chunk's and the evaluation's programs (their inputs' shapes known) traced or loaded and
                # compiled beside the init's: the chunk, the longest to compile, traced first and alone (tracing
                # holds Python's lock; XLA's compilation does not), the evaluation once it is.
                chunk_traced = threading.Event()
                building = background.submit(build, chunk, chunk_what, None, chunk_traced)
                if evaluate is not None:
                    compiling = background.submit(build, evaluate, eval_description, chunk_traced)
            init_c = jit(init_seeded, "init", None, seed)
        else:
            replicated = jax.sharding.NamedSharding(jax.tree.leaves(shardings)[0].mesh, jax.sharding.PartitionSpec())
            init_c = jax.jit(init_seeded, out_shardings=shardings)

            def jit(fn, what, out_shardings):
                return jax.jit(fn, in_shardings=(shardings,), out_shardings=out_shardings)

        carry = init_c(seed)
        if evaluate is not None and shardings is None and compiling is None:
            # One device, no program cache: trace and compile the evaluation (on its first call) beside the chunk
            # (several devices, or processes, run their programs in the same order everywhere, so there it is
            # compiled in turn).
            def compile_eval(first=carry):
                fn = jit(evaluate, eval_description, replicated)
                jax.block_until_ready(fn(first))
                return fn

            compiling = background.submit(compile_eval)
        elif evaluate is not None and shardings is not None:
            eval_fn = jit(evaluate, eval_description, replicated)
        chunk_c = jit(chunk, chunk_what, (shardings, replicated)) if building is None else building.result()
        pending = chunk_c(carry)
        for k in range(1, config.num_evals + 1):
            finished, metrics = pending
            if compiling is not None:
                eval_fn, compiling = compiling.result(), None
            if evaluate is not None:
                metrics = {**metrics, "eval": eval_fn(finished)}
            if k < config.num_evals:
                pending = chunk_c(finished)  # runs while this chunk's metrics are read and shown
            metrics = jax.tree.map(host_array, metrics)
            carry, done = finished, k * steps_per_chunk
            if progress is not None:
                progress(done, {name: (value if name == "eval" else float(value)) for name, value in metrics.items()})
    except KeyboardInterrupt:
        raise Interrupted(result(init_c(seed) if carry is None else carry), done) from None
    finally:
        background.shutdown(wait=True)  # never leave XLA compiling in a thread while Python shuts down
    return result(carry)
