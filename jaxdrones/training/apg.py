"""Analytic policy gradients (APG): a policy trained by backpropagation through batched rollouts of the simulator.

Each update differentiates the task's smooth training loss (`jaxdrones.envs.task.Task.loss_terms`, weighted by
`Task.loss_weights`, averaged over ``horizon`` control steps and ``num_envs`` worlds) w.r.t. the policy's
parameters through the env's dynamics, and takes an Adam step. The worlds' states carry over from one window to
the next with the gradient stopped (truncated backpropagation through time, as in brax's APG and in short-horizon
actor-critic without the critic); a world whose episode ends is reset (`jaxdrones.wrappers.reset_where`, or with
``starts_per_window`` from episodes drawn once per window), and no gradient crosses the reset. brax's APG trainer
optimises ``-mean(reward)``, whose shaped hover reward (clipped at 0) has no gradient far from the target, so the
loop is written here, on flax and optax.

The policy is an MLP (tanh hidden layers, tanh output in the action box), deterministic.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_fields
from jaxdrones.envs.base import Env
from jaxdrones.training.common import (
    Schedule,
    mlp,
    param_maps,
    program_description,
    run_updates,
)

if TYPE_CHECKING:
    from flax import linen


@dataclasses.dataclass(frozen=True)
class APGConfig(Schedule):
    """Settings of `train` (``num_timesteps`` counts env (control) steps).

    Attributes:
        num_timesteps: env steps to train, rounded up to whole evaluation chunks.
        num_envs: worlds stepped in parallel.
        horizon: control steps per gradient window.
        learning_rate: Adam's step size (at the start, with ``cosine_decay``).
        cosine_decay: decay the step size to 0 over the run's updates along a half cosine (optax's
            ``cosine_decay_schedule``), for a more precise policy at the end of a short run.
        max_grad_norm: the gradient's global norm is clipped to this.
        hidden_layer_sizes: of the policy MLP.
        num_evals: evaluations (learning-curve points) over the run, one after each chunk of updates, ≥ 1.
        seed: random seed.
        starts_per_window, flat_params: how an update is built, for the device
            (`jaxdrones.training.common.BUILD_SETTINGS`; on with ``--defaults gpu``).

    Raises:
        ValueError: a count below 1, a non-positive rate or norm, a build setting that is not a bool.
    """

    num_timesteps: int = 1_000_000
    num_envs: int = 16
    horizon: int = 32
    learning_rate: float = 2e-3
    cosine_decay: bool = False
    max_grad_norm: float = 1.0
    hidden_layer_sizes: tuple[int, ...] = (64, 64)
    num_evals: int = 10
    seed: int = 0
    starts_per_window: bool = False
    flat_params: bool = False

    algo: ClassVar[str] = "apg"

    def __post_init__(self):
        check_fields(
            self,
            integers={"num_timesteps": 1, "num_envs": 1, "horizon": 1, "num_evals": 1, "seed": 0},
            positive=("learning_rate", "max_grad_norm"),
            booleans=("cosine_decay", "starts_per_window", "flat_params"),
        )

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.horizon

    def schedule(self) -> float | Callable[[jax.Array], jax.Array]:
        """Adam's step size: ``learning_rate``, or its cosine decay over the run's updates."""
        import optax

        if not self.cosine_decay:
            return self.learning_rate
        return optax.cosine_decay_schedule(self.learning_rate, self.num_evals * self.updates_per_eval)


def make_network(config: APGConfig, env: Env) -> linen.Module:
    """The policy network (flax): obs f[..., n_obs] -> action f[..., env.action_size] in (-1, 1)."""
    import flax.linen as nn

    # A small last layer: the first actions are near 0 (hover RPM for the rpm action).
    return mlp(config.hidden_layer_sizes, env.action_size, nn.initializers.normal(0.01), squash=True)


def make_policy(network: linen.Module, params: Any) -> Callable:
    """``policy(obs, key) -> (action, {})``, deterministic, with the signature of brax's policies: on one drone's
    observation f[..., n_obs] it gives that drone's action f[..., n_act]; on a world's flat observation
    f[..., D·n_obs] (the drones' observations one after another, as brax's policies see a team) the drones' actions
    one after another, f[..., D·n_act], every drone flying the same network."""
    n_obs = params["params"]["Dense_0"]["kernel"].shape[0]

    def policy(obs, key):
        del key
        if obs.shape[-1] == n_obs:
            return network.apply(params, obs), {}
        drones = obs.reshape(*obs.shape[:-1], -1, n_obs)
        action = network.apply(params, drones)
        return action.reshape(*obs.shape[:-1], -1), {}

    return policy


def train(
    env: Env,
    config: APGConfig = APGConfig(),
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable[..., dict] | None = None,
    runs: Sequence[APGConfig] | None = None,
) -> tuple[linen.Module, Any]:
    """Train a policy on ``env`` (one world; D drones share the policy, each seeing its own observation).

    Args:
        env: a jaxdrones env without camera images.
        config: `APGConfig`.
        progress, evaluate, runs: as every trainer takes them (`jaxdrones.training.trainers`); the metrics are
            ``train/loss``, the mean window loss of the last update, ``train/grad_norm``.

    Raises:
        jaxdrones.training.common.Interrupted: on Ctrl-C, with the result of the last completed chunk.

    Returns:
        ``(network, params)``: the flax module and its trained parameters (see `make_policy`); with ``runs``, a list
        of one per run.
    """
    import optax

    from jaxdrones.envs.base import world_axes
    from jaxdrones.wrappers import VmapAutoReset

    auto = VmapAutoReset(env)
    batched_loss = jax.vmap(env.loss, in_axes=(world_axes(auto.params_shared),))
    network = make_network(config, env)
    obs0 = np.zeros((env.observation_size,), env.dtype)

    def build(config):
        """The trainer's functions (`jaxdrones.training.common.run_updates`)."""
        optimizer = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.schedule()))
        ravel, unravel = param_maps(jax.eval_shape(lambda: network.init(jax.random.key(0), obs0)), config.flat_params)

        def window_loss(flat, state):
            params = unravel(flat)
            starts = auto.starts(state) if config.starts_per_window else None  # the worlds' next episodes

            def body(s, _):
                ended, s = auto.step_ended(s, network.apply(params, s.obs), starts)
                return s, jnp.mean(batched_loss(ended))  # the loss of the step, also where it ended an episode

            state, losses = jax.lax.scan(body, state, None, length=config.horizon)
            return jnp.mean(losses), state

        def update(carry, _):
            params, opt_state, state = carry
            (loss, state), grad = jax.value_and_grad(window_loss, has_aux=True)(params, state)
            updates, opt_state = optimizer.update(grad, opt_state, params)
            carry = (optax.apply_updates(params, updates), opt_state, jax.lax.stop_gradient(state))
            return carry, {"train/loss": loss, "train/grad_norm": optax.tree.norm(grad)}

        def init(key):
            key_init, key_reset = jax.random.split(key)
            params = ravel(network.init(key_init, obs0))
            return params, optimizer.init(params), auto.reset(jax.random.split(key_reset, config.num_envs))

        def result(carry):
            return network, unravel(carry[0])

        return init, update, result

    description = program_description(config, env)
    return run_updates(config, build, config.num_envs, progress, evaluate, description, runs)
