"""Short-horizon actor-critic (SHAC; Xu et al., "Accelerated Policy Learning with Parallel Differentiable
Simulation", ICLR 2022): analytic policy gradients through short windows of batched rollouts, with a learned value
at the window's end.

Each update rolls ``num_envs`` worlds ``horizon`` control steps under the current policy and differentiates, w.r.t.
the policy's parameters and through the simulator, the discounted return of the window plus the discounted value
of where it ends. The reward is the task's smooth training loss, negated (`jaxdrones.envs.task.Task.loss_terms`
weighted by `Task.loss_weights`), as for `jaxdrones.training.apg`. An episode that ends inside the window adds its
return there, bootstrapped with the value of its last observation when it was cut by the time limit and with 0
when it terminated; the world is reset and no gradient crosses the reset. The critic V(obs) then regresses the
window's TD(λ) returns, computed with a slowly following target critic, for a few epochs of minibatches; the target
follows the critic by Polyak averaging. Each drone of a world is one sample (they share the policy and the critic).

The policy is deterministic, the network of `jaxdrones.training.apg`; the loop is shared with the other trainers
(`jaxdrones.training.common.run_updates`).
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
from jaxdrones.training.apg import APGConfig, make_network
from jaxdrones.training.common import mlp, param_maps, program_description, run_updates

if TYPE_CHECKING:
    from flax import linen


@dataclasses.dataclass(frozen=True)
class SHACConfig(APGConfig):
    """Settings of `train`: those of `APGConfig` (the actor's), and the critic's.

    Attributes:
        discounting: the discount γ per control step.
        td_lambda: λ of the critic's TD(λ) targets.
        critic_learning_rate: Adam's step size for the critic.
        critic_epochs: passes over each window's samples to fit the critic.
        critic_minibatches: minibatches per pass.
        target_alpha: target critic ← α·target + (1 - α)·critic after each update (the paper's 0.2).
        critic_hidden_layer_sizes: of the critic MLP.

    Raises:
        ValueError: those of `APGConfig`, a rate outside its range, or ``num_envs`` · ``horizon`` · drones not
            divisible into ``critic_minibatches`` (checked by `train`).
    """

    horizon: int = 32
    discounting: float = 0.95
    td_lambda: float = 0.95
    critic_learning_rate: float = 2e-3
    critic_epochs: int = 4
    critic_minibatches: int = 4
    target_alpha: float = 0.2
    critic_hidden_layer_sizes: tuple[int, ...] = (64, 64)

    algo: ClassVar[str] = "shac"

    def __post_init__(self):
        super().__post_init__()
        check_fields(
            self,
            integers={"critic_epochs": 1, "critic_minibatches": 1},
            positive=("critic_learning_rate",),
            open_fractions=("discounting", "td_lambda", "target_alpha"),
        )


def make_critic(config: SHACConfig) -> linen.Module:
    """The critic (flax): obs f[..., n_obs] -> value f[..., 1]."""
    return mlp(config.critic_hidden_layer_sizes, 1)


def td_lambda_returns(
    rewards: jax.Array, next_values: jax.Array, ended: jax.Array, discounting: float, td_lambda: float
) -> jax.Array:
    """TD(λ) returns of a window, f[T, ...]: G_t = r_t + γ·((1 - λ)·V_{t+1} + λ·G_{t+1}), cut to r_t + γ·V_{t+1}
    where the episode ended at step t and at the window's last step.

    Args:
        rewards: f[T, ...], the reward of each step.
        next_values: f[T, ...], the value of the state after each step (0 where the episode terminated; of the
            last observation where it was truncated).
        ended: bool[T, ...], the episode ended at that step.
        discounting: the discount γ per step.
        td_lambda: λ, the weight of the longer returns (0: one-step TD targets, 1: Monte-Carlo returns).
    """

    def back(later, inputs):
        reward, value, end = inputs
        ret = reward + discounting * jnp.where(end, value, (1 - td_lambda) * value + td_lambda * later)
        return ret, ret

    last = rewards[-1] + discounting * next_values[-1]
    _, returns = jax.lax.scan(back, last, (rewards[:-1], next_values[:-1], ended[:-1]), reverse=True)
    return jnp.concatenate([returns, last[None]])


def train(
    env: Env,
    config: SHACConfig = SHACConfig(),
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable[..., dict] | None = None,
    runs: Sequence[SHACConfig] | None = None,
) -> tuple[linen.Module, Any]:
    """Train a policy on ``env`` with SHAC (module doc; arguments and return as `jaxdrones.training.apg.train`).

    ``progress`` also reports ``train/critic_loss`` (the critic's mean squared error on the last window's targets,
    before fitting).

    Raises:
        ValueError: ``num_envs`` · ``horizon`` · drones not divisible by ``critic_minibatches``.
    """
    import optax

    from jaxdrones.envs.base import world_axes
    from jaxdrones.wrappers import VmapAutoReset

    samples = config.num_envs * config.horizon * env.n_drones
    if samples % config.critic_minibatches:
        raise ValueError(
            f"SHACConfig: num_envs * horizon * drones = {samples} samples per window must split into "
            f"critic_minibatches={config.critic_minibatches} equal minibatches"
        )
    auto = VmapAutoReset(env)
    batched_loss = jax.vmap(env.loss, in_axes=(world_axes(auto.params_shared),))
    actor, critic = make_network(config, env), make_critic(config)
    obs0 = np.zeros((env.observation_size,), env.dtype)

    def shapes(net):
        return jax.eval_shape(lambda: net.init(jax.random.key(0), obs0))

    def build(config):
        """The trainer's functions (`jaxdrones.training.common.run_updates`)."""
        actor_opt = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.schedule()))
        critic_opt = optax.chain(
            optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.critic_learning_rate)
        )
        gamma = config.discounting

        # The actor's and the critic's parameters, as flat vectors with ``config.flat_params``.
        ravel_actor, unravel_actor = param_maps(shapes(actor), config.flat_params)
        ravel_critic, unravel_critic = param_maps(shapes(critic), config.flat_params)

        def actor_loss(flat, target_flat, state):
            """Minus the mean discounted window return per step, and what the critic learns from."""
            params, target_params = unravel_actor(flat), unravel_critic(target_flat)
            starts = auto.starts(state) if config.starts_per_window else None  # the worlds' next episodes

            def body(carry, last):
                s, discount, acc, total = carry
                ended, s_next = auto.step_ended(s, actor.apply(params, s.obs), starts)
                reward = -batched_loss(ended)  # [W, D]
                term, end = (jnp.broadcast_to(x[:, None], reward.shape) for x in (ended.terminated, ended.done))
                # The value after the step: of the last observation before any reset; 0 where the episode terminated.
                next_value = jnp.where(term, 0.0, critic.apply(target_params, ended.obs)[..., 0])
                acc = acc + discount * reward
                closes = end | last  # an episode's return closes where it ends, and every one at the window's end
                total = total + jnp.sum(jnp.where(closes, acc + discount * gamma * next_value, 0.0))
                discount, acc = jnp.where(end, 1.0, discount * gamma), jnp.where(end, 0.0, acc)
                record = jax.lax.stop_gradient((s.obs, reward, next_value, end))
                return (s_next, discount, acc, total), record

            shape = (config.num_envs, env.n_drones)
            zeros = jnp.zeros(shape, env.dtype)
            last = jnp.arange(config.horizon) == config.horizon - 1
            (state, _, _, total), record = jax.lax.scan(body, (state, jnp.ones(shape, env.dtype), zeros, 0.0), last)
            return -total / (config.horizon * config.num_envs * env.n_drones), (state, record)

        def fit_critic(critic_params, opt_state, obs, targets, key):
            obs, targets = obs.reshape(samples, -1), targets.reshape(samples)
            size = samples // config.critic_minibatches

            def mse(p, o, t):
                return jnp.mean((critic.apply(unravel_critic(p), o)[..., 0] - t) ** 2)

            def minibatch(carry, index):
                p, opt_state = carry
                grad = jax.grad(mse)(p, obs[index], targets[index])
                updates, opt_state = critic_opt.update(grad, opt_state, p)
                return (optax.apply_updates(p, updates), opt_state), None

            order = jax.vmap(lambda k: jax.random.permutation(k, samples))(jax.random.split(key, config.critic_epochs))
            before = mse(critic_params, obs, targets)
            (critic_params, opt_state), _ = jax.lax.scan(minibatch, (critic_params, opt_state), order.reshape(-1, size))
            return critic_params, opt_state, before

        def update(carry, _):
            actor_params, critic_params, target_params, actor_state, critic_state, state, key = carry
            key, key_fit = jax.random.split(key)
            (loss, (state, (obs, rewards, next_values, ended))), grad = jax.value_and_grad(actor_loss, has_aux=True)(
                actor_params, target_params, state
            )
            updates, actor_state = actor_opt.update(grad, actor_state, actor_params)
            actor_params = optax.apply_updates(actor_params, updates)
            targets = td_lambda_returns(rewards, next_values, ended, gamma, config.td_lambda)
            critic_params, critic_state, critic_loss = fit_critic(critic_params, critic_state, obs, targets, key_fit)
            target_params = jax.tree.map(
                lambda t, c: config.target_alpha * t + (1 - config.target_alpha) * c, target_params, critic_params
            )
            carry = (
                actor_params,
                critic_params,
                target_params,
                actor_state,
                critic_state,
                jax.lax.stop_gradient(state),
                key,
            )
            return carry, {
                "train/loss": loss,
                "train/grad_norm": optax.tree.norm(grad),
                "train/critic_loss": critic_loss,
            }

        def init(key):
            key_actor, key_critic, key_reset, key_shuffle = jax.random.split(key, 4)
            actor_params, critic_params = (
                ravel_actor(actor.init(key_actor, obs0)),
                ravel_critic(critic.init(key_critic, obs0)),
            )
            return (
                actor_params,
                critic_params,
                critic_params,
                actor_opt.init(actor_params),
                critic_opt.init(critic_params),
                auto.reset(jax.random.split(key_reset, config.num_envs)),
                key_shuffle,
            )

        def result(carry):
            return actor, unravel_actor(carry[0])

        return init, update, result

    description = program_description(config, env)
    return run_updates(config, build, config.num_envs, progress, evaluate, description, runs)
