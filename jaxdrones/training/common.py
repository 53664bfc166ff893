"""Pieces shared by our own trainers (`jaxdrones.training.apg`, ``shac``, ``mappo``): checking a config, the
schedule of updates between evaluations, the MLP, spreading the worlds over devices, and the jitted training
loop."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np


def check_config(config, *, integers: dict[str, int] | None = None, positive=(), nonnegative=(), fractions=(),
                 open_fractions=()) -> None:
    """Raise ``ValueError`` naming the config class and field for a value out of range: ``integers`` maps fields to
    their least value; ``positive`` fields must be > 0, ``nonnegative`` ≥ 0, ``fractions`` in [0, 1] and
    ``open_fractions`` in [0, 1)."""
    name = type(config).__name__
    for field, low in (integers or {}).items():
        value = getattr(config, field)
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name}: {field} must be an integer >= {low}, got {value!r}")
    checks = ((positive, lambda v: v > 0, "> 0"), (nonnegative, lambda v: v >= 0, ">= 0"),
              (fractions, lambda v: 0 <= v <= 1, "in [0, 1]"), (open_fractions, lambda v: 0 <= v < 1, "in [0, 1)"))
    for fields, ok, text in checks:
        for field in fields:
            value = getattr(config, field)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not ok(value):
                raise ValueError(f"{name}: {field} must be {text}, got {value!r}")


class Schedule:
    """The schedule of a trainer's config: ``num_timesteps`` env steps in ``num_evals - 1`` jitted chunks of updates
    of `steps_per_update` env steps (a config mixin; the config defines ``steps_per_update``)."""

    num_timesteps: int
    num_evals: int

    @property
    def updates_per_eval(self) -> int:
        """Updates between two evaluations (one jitted call)."""
        return max(1, -(-self.num_timesteps // (self.steps_per_update * (self.num_evals - 1))))

    @property
    def total_steps(self) -> int:
        """The env steps `run_updates` runs (``num_timesteps`` rounded up to whole chunks)."""
        return (self.num_evals - 1) * self.updates_per_eval * self.steps_per_update


def mlp(hidden_layer_sizes: tuple[int, ...], out: int, last_init=None, squash: bool = False):
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


def spread_worlds(shared, worlds, n_worlds: int):
    """Place a trainer's carry on the local devices: ``worlds`` (the env states, world axis first) split along the
    world axis (`jaxdrones.sim.shard_worlds`), ``shared`` (parameters, optimiser state, keys) replicated. The jitted
    update then steps each device's worlds on that device, and XLA sums the gradients across devices. Uses the
    largest number of local devices that divides ``n_worlds``; with one, both are returned as they are.

    Returns:
        ``(shared, worlds)`` placed.
    """
    from jaxdrones.sim import shard_worlds

    devices = jax.local_devices()
    count = max(n for n in range(1, len(devices) + 1) if n_worlds % n == 0)
    if count == 1:
        return shared, worlds
    mesh = jax.sharding.Mesh(np.array(devices[:count]), ("worlds",))
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    return jax.device_put(shared, replicated), shard_worlds(worlds, devices=devices[:count])


def run_updates(config: Schedule, update: Callable, carry, policy_params: Callable, network,
                progress: Callable[[int, dict], None] | None, evaluate: Callable[..., dict] | None):
    """The training loop: ``config.num_evals - 1`` jitted chunks of ``config.updates_per_eval`` calls of
    ``update(carry, None) -> (carry, metrics)`` (a `jax.lax.scan` body), with ``progress(env_steps, metrics)``
    before the first chunk and after each: the last update's metrics and what
    ``evaluate(network, policy_params(carry))`` returns. Returns the final carry."""

    @jax.jit
    def chunk(carry):
        return jax.lax.scan(update, carry, None, length=config.updates_per_eval)

    def report(steps, carry, metrics):
        if progress is not None:
            extra = evaluate(network, policy_params(carry)) if evaluate is not None else {}
            progress(steps, {**metrics, **extra})

    report(0, carry, {"train/loss": float("nan"), "train/grad_norm": float("nan")})
    for k in range(1, config.num_evals):
        carry, metrics = chunk(carry)
        report(k * config.updates_per_eval * config.steps_per_update, carry,
               {name: float(value[-1]) for name, value in metrics.items()})
    return carry
