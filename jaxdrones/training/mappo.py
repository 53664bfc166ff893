"""Multi-agent PPO on the stacked ``[world, drone]`` envs: MAPPO (per-agent actors, a centralised critic; Yu et al.,
"The Surprising Effectiveness of PPO in Cooperative Multi-Agent Games", NeurIPS 2022 Datasets and Benchmarks) or
independent PPO (each agent's critic sees its own observation only; de Witt et al., 2020).

Each drone of a world is an agent with its own reward ``f[D]``. The actor maps an agent's observation to a Gaussian
over its action (the env clips actions to their box); the critic gives each agent a value. With parameter sharing
(the default) one actor and one critic serve every agent, told apart by a one-hot agent id appended to their input;
without it each agent has its own networks (the same MLPs, their parameters stacked along an agent axis). The
centralised critic adds the positions and velocities of every drone of the world (6·D entries, relative to the
world's centroid) to the agent's observation. The first layer takes the id and the world's features by parts
(`agent_mlp`), so that neither costs D times over in a team of D.

One update collects ``unroll_length`` steps of ``num_envs`` worlds (episodes that end are reset by
`jaxdrones.wrappers.VmapAutoReset`; an episode cut by the time limit is bootstrapped with the value of its last
state), computes per-agent GAE advantages, and takes ``epochs`` passes of ``minibatches`` clipped-surrogate PPO
steps with Adam, the advantages standardised per agent within each minibatch (so that a role that one drone plays,
as the leader of a leader-follower team, weighs as much as one that many play: with advantages standardised over
the whole team, ``leader_follower`` with 5 drones failed on one seed of three, its leader climbing with the team);
everything between two evaluations is one jitted `lax.scan`. With several local devices (GPUs, or CPU devices from
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) the worlds are split over them
(`jaxdrones.training.common.world_shardings`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrones._validate import check_fields
from jaxdrones.envs.base import Env, EnvState
from jaxdrones.training.common import (
    Schedule,
    param_maps,
    program_description,
    run_updates,
)

if TYPE_CHECKING:
    from flax import linen

#: Critic inputs of `MAPPOConfig.critic`.
CRITICS = ("central", "local")


@dataclasses.dataclass(frozen=True)
class MAPPOConfig(Schedule):
    """Settings of `train` (``num_timesteps`` counts env steps: one step of one world, all its drones).

    Attributes:
        num_timesteps: env steps to train, rounded up to whole evaluation chunks.
        num_envs: worlds stepped in parallel.
        unroll_length: steps per world collected for each update.
        epochs: passes over each update's samples.
        minibatches: minibatches per pass (they split the ``num_envs · unroll_length`` world-steps).
        learning_rate: Adam's step size (at the start, with ``anneal_lr``).
        anneal_lr: decay the step size linearly to 0 over the run's gradient steps (PureJaxRL's ``ANNEAL_LR``,
            CleanRL's ``anneal_lr``).
        discounting: discount γ per control step.
        gae_lambda: λ of the GAE advantages.
        clip: PPO's ratio clip ε.
        entropy_cost: weight of the policy's entropy bonus.
        value_cost: weight of the critic's squared error.
        max_grad_norm: the gradient's global norm is clipped to this.
        critic: ``"central"`` (MAPPO: the critic also sees every drone's position and velocity) or ``"local"``
            (independent PPO).
        share_params: one actor and one critic for all agents with an agent-id input (True) or per-agent networks.
        hidden_layer_sizes: of the actor and critic MLPs.
        init_std: the Gaussian policy's initial standard deviation (in action units, or before the tanh with
            ``squash``; it is learned).
        squash: act with tanh of the Gaussian's sample (and tanh of its mean when deterministic), inside the action
            box as brax's PPO does (its ``NormalTanhDistribution``), rather than with the sample itself, which the
            env clips to the box. PPO's ratio is that of the Gaussian densities of the sample before the tanh (the
            tanh's Jacobian cancels in it).
        num_evals: evaluations (learning-curve points) over the run, one after each chunk of updates, ≥ 1.
        seed: random seed.
        starts_per_window, flat_params, noise_per_window: how an update is built, for the device
            (`jaxdrones.training.common.BUILD_SETTINGS`; on with ``--defaults gpu``).

    Raises:
        ValueError: a count below 1, a rate or weight out of range, an unknown critic, a flag that is not a bool, or
            ``num_envs · unroll_length`` not divisible by ``minibatches``.
    """

    num_timesteps: int = 3_000_000
    num_envs: int = 512
    unroll_length: int = 10
    epochs: int = 4
    minibatches: int = 8
    learning_rate: float = 1e-3
    anneal_lr: bool = False
    discounting: float = 0.97
    gae_lambda: float = 0.95
    clip: float = 0.2
    entropy_cost: float = 1e-3
    value_cost: float = 0.5
    max_grad_norm: float = 0.5
    critic: str = "central"
    share_params: bool = True
    hidden_layer_sizes: tuple[int, ...] = (64, 64)
    init_std: float = 0.5
    squash: bool = False
    num_evals: int = 10
    seed: int = 0
    starts_per_window: bool = False
    flat_params: bool = False
    noise_per_window: bool = False

    def __post_init__(self):
        check_fields(
            self,
            integers={
                "num_timesteps": 1,
                "num_envs": 1,
                "unroll_length": 1,
                "epochs": 1,
                "minibatches": 1,
                "num_evals": 1,
                "seed": 0,
            },
            positive=("learning_rate", "clip", "max_grad_norm", "init_std"),
            nonnegative=("entropy_cost", "value_cost"),
            fractions=("discounting", "gae_lambda"),
            booleans=("anneal_lr", "share_params", "squash", "starts_per_window", "flat_params", "noise_per_window"),
        )
        if self.critic not in CRITICS:
            raise ValueError(f"MAPPOConfig: critic must be one of {CRITICS}, got {self.critic!r}")
        if (self.num_envs * self.unroll_length) % self.minibatches:
            raise ValueError(
                f"MAPPOConfig: num_envs * unroll_length = {self.num_envs * self.unroll_length} must "
                f"split into minibatches={self.minibatches} equal parts"
            )

    @property
    def algo(self) -> str:
        return "mappo" if self.critic == "central" else "ippo"

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.unroll_length


#: The observation's standardisation (`Networks.normalize`): the variance's floor and the clip of the result.
NORM_EPS = 1e-6
NORM_CLIP = 10.0


def agent_mlp(
    hidden_layer_sizes: tuple[int, ...], out: int, n_ids: int, fan_in: int, last_init: Callable | None = None
) -> linen.Module:
    """An MLP on an agent's observation f[..., D, n], its agent id (0 .. D - 1, when ``n_ids``) and its world's
    features f[..., m] (or None), with tanh hidden layers and a linear output f[..., D, out].

    The first layer is a Dense layer on the concatenation [obs, one-hot id, world], computed by parts: the id's
    columns as an embedding, the world's once per world and broadcast to its agents. That is the same function,
    in O(hidden) per agent for the id instead of O(D·hidden), and O(m·hidden) per world for the world instead of per
    agent: the team size does not multiply their cost. ``fan_in`` (the concatenation's size) scales the first
    layer's initial weights as LeCun's initialiser would the concatenated layer's.
    """
    import flax.linen as nn

    first = nn.initializers.normal(1.0 / np.sqrt(fan_in))

    class AgentMLP(nn.Module):
        @nn.compact
        def __call__(self, obs, world=None):
            width = hidden_layer_sizes[0]
            x = nn.Dense(width, kernel_init=first)(obs)
            if n_ids:
                x = x + jnp.broadcast_to(nn.Embed(n_ids, width, embedding_init=first)(jnp.arange(n_ids)), x.shape)
            if world is not None:
                x = x + nn.Dense(width, use_bias=False, kernel_init=first)(world)[..., None, :]
            x = nn.tanh(x)
            for size in hidden_layer_sizes[1:]:
                x = nn.tanh(nn.Dense(size)(x))
            return nn.Dense(out, **({} if last_init is None else {"kernel_init": last_init}))(x)

    return AgentMLP()


class Networks:
    """The actor and critic of ``n_agents`` agents (see the module doc), as pure functions of their parameters.

    ``actor(params, obs) -> mean`` and ``critic(params, obs, world) -> value`` take an observation f[..., D, n_obs]
    (and, for the central critic, the world features f[..., 6·D]) and return f[..., D, n_act] and f[..., D].
    """

    def __init__(self, config: MAPPOConfig, n_agents: int, obs_size: int, action_size: int):
        import flax.linen as nn

        self.config, self.n_agents, self.obs_size, self.action_size = config, n_agents, obs_size, action_size
        small = nn.initializers.variance_scaling(0.01, "fan_in", "truncated_normal")  # first actions near 0
        ids = n_agents if config.share_params else 0
        self.world_size = 6 * n_agents if config.critic == "central" else 0
        hidden = config.hidden_layer_sizes
        self.actor_mlp = agent_mlp(hidden, action_size, ids, obs_size + ids, small)
        self.critic_mlp = agent_mlp(hidden, 1, ids, obs_size + ids + self.world_size)

    def init(self, key: jax.Array) -> dict:
        keys = jax.random.split(key, 2)
        obs = jnp.zeros((self.n_agents if self.config.share_params else 1, self.obs_size))
        world = jnp.zeros(self.world_size) if self.world_size else None

        def one(key_actor, key_critic):
            return {
                "actor": self.actor_mlp.init(key_actor, obs),
                "critic": self.critic_mlp.init(key_critic, obs, world),
            }

        if self.config.share_params:
            params = one(*keys)
        else:
            params = jax.vmap(one)(*(jax.random.split(k, self.n_agents) for k in keys))
        log_std = jnp.full((self.action_size,), jnp.log(self.config.init_std), jnp.float32)
        norm = {"mean": jnp.zeros(self.obs_size), "var": jnp.ones(self.obs_size), "count": jnp.zeros(())}
        return {**params, "log_std": log_std, "norm": norm}

    @staticmethod
    def normalize(params: dict, x: jax.Array) -> jax.Array:
        """X standardised by the running statistics ``params["norm"]`` (`update_norm`), (x − mean) / sqrt(var +
        `NORM_EPS`), clipped to ±`NORM_CLIP`."""
        norm = params["norm"]
        mean, var = (jnp.broadcast_to(norm[k], x.shape) for k in ("mean", "var"))
        return jnp.clip((x - mean) / jnp.sqrt(var + NORM_EPS), -NORM_CLIP, NORM_CLIP)

    def _apply(self, mlp, params, x, world=None):
        """``mlp`` on x f[..., D, n] (and the world's features f[..., m]): shared or one parameter set per agent."""
        if self.config.share_params:
            return mlp.apply(params, x, world)
        # Per-agent networks: agent k's parameters on its own observation (a team of one, without an id).
        per_agent = jax.vmap(
            lambda p, xk: mlp.apply(p, xk[..., None, :], world)[..., 0, :], in_axes=(0, -2), out_axes=-2
        )
        return per_agent(params, x)

    def actor(self, params: dict, obs: jax.Array) -> jax.Array:
        return self._apply(self.actor_mlp, params["actor"], self.normalize(params, obs))

    def critic(self, params: dict, obs: jax.Array, world: jax.Array | None) -> jax.Array:
        return self._apply(self.critic_mlp, params["critic"], self.normalize(params, obs), world)[..., 0]


def update_norm(norm: dict, obs: jax.Array) -> dict:
    """Running mean and variance of the observation entries (Chan et al.'s parallel update), over every agent and
    sample of ``obs`` f[..., n_obs] (as brax's ``running_statistics``)."""
    batch = obs.reshape(-1, obs.shape[-1])
    n = batch.shape[0]
    mean, var = jnp.mean(batch, 0), jnp.var(batch, 0)
    total = norm["count"] + n
    delta = mean - norm["mean"]
    new_mean = norm["mean"] + delta * n / total
    m2 = norm["var"] * norm["count"] + var * n + delta**2 * norm["count"] * n / total
    return {"mean": new_mean, "var": m2 / total, "count": total}


def world_features(state: EnvState) -> jax.Array:
    """The central critic's view of a world: every drone's position relative to the drones' centroid (m) and
    velocity (m/s), flattened: f[..., 6·D]."""
    pos, vel = state.sim.pos, state.sim.vel
    pos = pos - jnp.mean(pos, axis=-2, keepdims=True)
    return jnp.concatenate([pos, vel], axis=-1).reshape(pos.shape[:-2] + (-1,))


def make_network(config: MAPPOConfig, env: Env) -> Networks:
    """The `Networks` of ``config`` for ``env``'s team, observation and action."""
    return Networks(config, env.n_drones, env.observation_size, env.action_size)


def make_policy(networks: Networks, params: dict) -> Callable:
    """``policy(obs, key) -> (action, {})``, deterministic (the Gaussian's mean, through a tanh with
    ``config.squash``), on a world's flat observation f[D·n_obs] (as brax's policies; see
    `jaxdrones.training.evaluation.act`)."""

    def policy(obs, key):
        del key
        mean = networks.actor(params, obs.reshape(networks.n_agents, networks.obs_size))
        return (jnp.tanh(mean) if networks.config.squash else mean).reshape(-1), {}

    return policy


def _log_prob(mean, log_std, action):
    log_std = jnp.broadcast_to(log_std, mean.shape)
    return jnp.sum(-0.5 * ((action - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi), axis=-1)


def gae(
    rewards: jax.Array,
    values: jax.Array,
    bootstrap: jax.Array,
    terminated: jax.Array,
    ended: jax.Array,
    discounting: float,
    gae_lambda: float,
) -> jax.Array:
    """Generalised advantage estimates f[T, ...] (Schulman et al., 2016): δ_t = r_t + γ (1 - terminated_t) V'_t - V_t,
    where V'_t is the value of the state the step reached (before any reset), and A_t = δ_t + γλ (1 - ended_t)
    A_{t+1}."""
    deltas = rewards + discounting * (1.0 - terminated) * bootstrap - values

    def back(later, inputs):
        delta, end = inputs
        advantage = delta + discounting * gae_lambda * (1.0 - end) * later
        return advantage, advantage

    _, advantages = jax.lax.scan(back, jnp.zeros_like(deltas[0]), (deltas, ended), reverse=True)
    return advantages


def train(
    env: Env,
    config: MAPPOConfig = MAPPOConfig(),
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable[..., dict] | None = None,
    runs: Sequence[MAPPOConfig] | None = None,
) -> tuple[Networks, dict]:
    """Train the agents of ``env`` (D drones per world) with MAPPO or independent PPO (module doc).

    Args:
        env: a jaxdrones env without camera images (any D ≥ 1).
        config: `MAPPOConfig`.
        progress, evaluate, runs: as every trainer takes them (`jaxdrones.training.trainers`); the metrics are
            ``train/policy_loss``, ``train/value_loss``, ``train/entropy``, ``train/std`` of the last update.

    Raises:
        jaxdrones.training.common.Interrupted: on Ctrl-C, with the result of the last completed chunk.

    Returns:
        ``(networks, params)`` (see `make_policy`); with ``runs``, a list of one per run.
    """
    import optax

    from jaxdrones.envs.base import world_axes
    from jaxdrones.wrappers import VmapAutoReset

    auto = VmapAutoReset(env)
    axes = world_axes(auto.params_shared)
    central = config.critic == "central"
    features = jax.vmap(world_features, in_axes=(axes,)) if central else (lambda s: None)

    def build(config):
        """The trainer's functions (`jaxdrones.training.common.run_updates`)."""
        nets = make_network(config, env)
        steps = config.num_evals * config.updates_per_eval * config.epochs * config.minibatches
        rate = optax.linear_schedule(config.learning_rate, 0.0, steps) if config.anneal_lr else config.learning_rate
        optimizer = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(rate))
        gamma = config.discounting

        def collect(params, state, key):  # params with "norm"
            starts = auto.starts(state) if config.starts_per_window else None  # the worlds' next episodes
            # The actions' standard normal noise: drawn for the whole unroll before it, or in each step from its key.
            if config.noise_per_window:
                action_shape = jax.eval_shape(nets.actor, params, state.obs)
                noises = jax.random.normal(key, (config.unroll_length, *action_shape.shape), action_shape.dtype)
            else:
                noises = jax.random.split(key, config.unroll_length)

            def body(state, noise):
                world = features(state)
                mean = nets.actor(params, state.obs)
                std = jnp.broadcast_to(jnp.exp(params["log_std"]), mean.shape)
                if not config.noise_per_window:  # a key
                    noise = jax.random.normal(noise, mean.shape, mean.dtype)
                action = mean + std * noise
                ended, nxt = auto.step_ended(state, jnp.tanh(action) if config.squash else action, starts)
                sample = {
                    "obs": state.obs,
                    "world": world,
                    "action": action,
                    "log_prob": _log_prob(mean, params["log_std"], action),
                    "value": nets.critic(params, state.obs, world),
                    "reward": ended.reward,
                    "bootstrap": nets.critic(params, ended.obs, features(ended)),
                    "terminated": jnp.broadcast_to(ended.terminated[:, None], ended.reward.shape),
                    "ended": jnp.broadcast_to(ended.done[:, None], ended.reward.shape),
                }
                return nxt, sample

            return jax.lax.scan(body, state, noises)

        def trainable_init(key):
            params = nets.init(key)
            params.pop("norm")  # the observation statistics: updated from the data, not by the optimiser
            return params

        ravel, unravel = param_maps(jax.eval_shape(lambda: trainable_init(jax.random.key(0))), config.flat_params)

        def ppo_loss(trainable, norm, batch):
            params = {**unravel(trainable), "norm": norm}
            mean = nets.actor(params, batch["obs"])
            ratio = jnp.exp(_log_prob(mean, params["log_std"], batch["action"]) - batch["log_prob"])
            adv = batch["advantage"]  # [B, D], standardised per agent: each drone's role weighs the same
            adv = (adv - adv.mean(axis=0, keepdims=True)) / (adv.std(axis=0, keepdims=True) + 1e-8)
            clipped = jnp.clip(ratio, 1 - config.clip, 1 + config.clip)
            policy_loss = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
            value_loss = jnp.mean((nets.critic(params, batch["obs"], batch["world"]) - batch["return"]) ** 2)
            entropy = jnp.sum(params["log_std"] + 0.5 * np.log(2 * np.pi * np.e))
            total = policy_loss + config.value_cost * value_loss - config.entropy_cost * entropy
            return total, {"train/policy_loss": policy_loss, "train/value_loss": value_loss, "train/entropy": entropy}

        def update(carry, _):
            params, norm, opt_state, state, key = carry
            key, key_collect, key_shuffle = jax.random.split(key, 3)
            state, data = collect({**unravel(params), "norm": norm}, state, key_collect)
            advantage = gae(
                data["reward"],
                data["value"],
                data["bootstrap"],
                data["terminated"],
                data["ended"],
                gamma,
                config.gae_lambda,
            )
            data = {**data, "advantage": advantage, "return": advantage + data["value"]}
            data.pop("bootstrap")
            samples = jax.tree.map(
                lambda x: x.reshape((config.steps_per_update,) + x.shape[2:]),
                {k: v for k, v in data.items() if v is not None},
            )

            def minibatch(carry, index):
                params, opt_state = carry
                batch = jax.tree.map(lambda x: x[index], samples)
                if not central:
                    batch["world"] = None
                (_, metrics), grad = jax.value_and_grad(ppo_loss, has_aux=True)(params, norm, batch)
                updates, opt_state = optimizer.update(grad, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), metrics

            orders = jax.vmap(lambda k: jax.random.permutation(k, config.steps_per_update))(
                jax.random.split(key_shuffle, config.epochs)
            )
            (params, opt_state), metrics = jax.lax.scan(
                minibatch, (params, opt_state), orders.reshape(config.epochs * config.minibatches, -1)
            )
            metrics = {k: v[-1] for k, v in metrics.items()}
            metrics["train/std"] = jnp.mean(jnp.exp(unravel(params)["log_std"]))
            norm = update_norm(norm, data["obs"])  # after the update, which used the statistics the data was taken with
            return (params, norm, opt_state, state, key), metrics

        def init(key):
            key_init, key_reset, key_run = jax.random.split(key, 3)
            params = nets.init(key_init)
            norm = params.pop("norm")
            params = ravel(params)
            state = auto.reset(jax.random.split(key_reset, config.num_envs))
            return params, norm, optimizer.init(params), state, key_run

        def result(carry):
            return nets, {**unravel(carry[0]), "norm": carry[1]}

        return init, update, result

    description = program_description(config, env)
    return run_updates(config, build, config.num_envs, progress, evaluate, description, runs)
