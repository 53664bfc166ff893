"""brax's PPO (``brax.training.agents.ppo``) on jaxdrones envs, through the brax adapter (`jaxdrones.adapters.brax`),
as a trainer of the table (`jaxdrones.training.trainers`: ``jaxdrones train --algo brax_ppo``)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from jaxdrones._validate import check_fields, check_real
from jaxdrones.envs.base import Env
from jaxdrones.training.common import NONFINITE, Interrupted, nonfinite_leaves

if TYPE_CHECKING:
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import networks_vision

    #: brax's PPO networks: on flat observations, or with cameras on `jaxdrones.training.encoders`' CNN.
    PPONetworks = ppo_networks.PPONetworks | networks_vision.PPONetworks


def _import_brax():
    """Import brax's PPO and the adapter (whose import silences what brax's MuJoCo dependency prints)."""
    from jaxdrones.adapters import brax as adapter

    return adapter


@dataclasses.dataclass(frozen=True)
class BraxPPOConfig:
    """Hyperparameters of brax's PPO (``brax.training.agents.ppo.train``) and of the networks.

    Field names and meanings are brax's; see its documentation. ``num_timesteps`` counts env (control) steps.

    Raises:
        ValueError: a count below 1, a negative seed, a step size, clip, norm or reward scale that is not finite and
            positive, a negative entropy cost, a discount or GAE lambda outside [0, 1], an unknown schedule, or a
            batch brax's PPO cannot split (checked here: brax itself takes a negative step size and seed -1).
    """

    num_timesteps: int = 2_500_000
    num_envs: int = 512
    batch_size: int = 512
    num_minibatches: int = 8
    unroll_length: int = 10
    num_updates_per_batch: int = 4
    learning_rate: float = 1e-3
    entropy_cost: float = 1e-3
    discounting: float = 0.98
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    max_grad_norm: float = 1.0
    #: None: a constant ``learning_rate``; ``"ADAPTIVE_KL"``: brax's adaptive schedule (the learning rate divided by
    #: 1.5 after an update whose KL divergence exceeds 2·``desired_kl``, multiplied by 1.5 below ``desired_kl``/2, as
    #: in RSL-RL's PPO, Rudin et al., "Learning to Walk in Minutes Using Massively Parallel Deep RL", CoRL 2021).
    learning_rate_schedule: str | None = None
    desired_kl: float = 0.01
    reward_scaling: float = 1.0
    normalize_observations: bool = True
    num_evals: int = 10
    num_eval_envs: int = 128
    policy_hidden_layer_sizes: tuple[int, ...] = (32, 32)
    value_hidden_layer_sizes: tuple[int, ...] = (64, 64)
    seed: int = 0
    #: The image encoder of envs with cameras (`jaxdrones.training.encoders`: convolutions with ReLU, the last feature
    #: map flattened, which keeps where in the image a feature is, then the state appended and the MLP): filters,
    #: square kernel sizes and strides per layer. The default is the Nature-DQN encoder (Mnih et al., "Human-level
    #: control through deep reinforcement learning", Nature 2015: three convolutions with ReLU, 32-64-64 filters,
    #: 8×8/4, 4×4/2, 3×3/1) scaled to small depth images and to the CPU: 8-16-16 filters, 4×4/2, 3×3/2, 3×3/2 (a
    #: 6×8×16 feature map of the gate's 48×64 images; ``avoid``'s recipe strides the first by 4, a 1×4×16 map of its
    #: 16×64 strip).
    cnn_output_channels: tuple[int, ...] = (8, 16, 16)
    cnn_kernel_size: tuple[int, ...] = (4, 3, 3)
    cnn_stride: tuple[int, ...] = (2, 2, 2)
    #: With cameras: an asymmetric critic (Pinto et al., "Asymmetric Actor Critic for Image-Based Robot Learning", RSS
    #: 2018), the value network an MLP on the state and the task's privileged observation (`jaxdrones.envs.task.Task.
    #: privileged`: for ``avoid`` and the gate, the obstacles around the drone) instead of a CNN on the images. The
    #: policy still reads only the state and the images; only the policy is needed to fly. Envs without a
    #: privileged observation (`jaxdrones.envs.base.Env.privileged` None) or without cameras keep the usual critic.
    privileged_critic: bool = False

    @property
    def total_steps(self) -> int:
        """The env steps brax's PPO runs: ``num_timesteps`` rounded up to whole training epochs."""
        per_step = self.batch_size * self.unroll_length * self.num_minibatches
        epochs = max(self.num_evals - 1, 1)
        return int(epochs * math.ceil(self.num_timesteps / (epochs * per_step)) * per_step)

    def __post_init__(self):
        counts = ("num_timesteps", "num_envs", "batch_size", "num_minibatches", "unroll_length", "num_evals")
        check_fields(
            self,
            integers={**dict.fromkeys((*counts, "num_updates_per_batch", "num_eval_envs"), 1), "seed": 0},
            positive=("learning_rate", "clipping_epsilon", "max_grad_norm", "reward_scaling"),
            nonnegative=("entropy_cost",),
            fractions=("discounting", "gae_lambda"),
            booleans=("privileged_critic", "normalize_observations"),
        )
        if self.learning_rate_schedule not in (None, "NONE", "ADAPTIVE_KL"):
            raise ValueError(
                f"BraxPPOConfig: learning_rate_schedule must be None, 'NONE' or 'ADAPTIVE_KL' (brax's "
                f"LRSchedule), got {self.learning_rate_schedule!r}"
            )
        check_real("BraxPPOConfig: desired_kl", self.desired_kl, 0, low_open=True, what="a finite number")
        if (self.batch_size * self.num_minibatches) % self.num_envs:
            raise ValueError(
                f"BraxPPOConfig: batch_size·num_minibatches ({self.batch_size}·{self.num_minibatches}) "
                f"must be a multiple of num_envs ({self.num_envs}), as brax's PPO requires"
            )


#: The config fields that shape the networks (`_network_factory`), not arguments of brax's ``ppo.train``.
NETWORK_FIELDS = (
    "policy_hidden_layer_sizes",
    "value_hidden_layer_sizes",
    "cnn_output_channels",
    "cnn_kernel_size",
    "cnn_stride",
    "privileged_critic",
)


def _network_factory(config: BraxPPOConfig, vision: bool = False, privileged: bool = False):
    from brax.training.agents.ppo import networks as ppo_networks

    layers = dict(
        policy_hidden_layer_sizes=tuple(config.policy_hidden_layer_sizes),
        value_hidden_layer_sizes=tuple(config.value_hidden_layer_sizes),
    )
    if not vision:
        return functools.partial(ppo_networks.make_ppo_networks, **layers)
    from jaxdrones.training.encoders import make_ppo_networks_vision

    return functools.partial(
        make_ppo_networks_vision,
        **layers,
        cnn_output_channels=tuple(config.cnn_output_channels),
        cnn_kernel_size=tuple(config.cnn_kernel_size),
        cnn_stride=tuple(config.cnn_stride),
        value_obs_key="privileged_state" if privileged else None,
    )


def _rank_promotion_allowed(fn: Callable) -> Callable:
    """``fn`` run with JAX's implicit rank promotion allowed: brax's PPO and its observation normaliser
    (``running_statistics``) subtract f[n_obs] statistics from f[..., n_obs] observations without expanding them,
    which raises where the user set ``jax_numpy_rank_promotion="raise"``."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.numpy_rank_promotion("allow"):
            return fn(*args, **kwargs)

    return wrapped


def make_network(config: BraxPPOConfig, env: Env) -> PPONetworks:
    """Brax's PPO networks for ``env`` (on the world's flat observation and action, normalised observations when
    ``config.normalize_observations``; with cameras, brax's vision PPO networks on our encoder
    (`jaxdrones.training.encoders.make_ppo_networks_vision`) reading `jaxdrones.envs.observations.policy_input`, the
    images not normalised)."""
    adapter = _import_brax()
    from brax.training.acme import running_statistics

    preprocess = (
        _rank_promotion_allowed(running_statistics.normalize) if config.normalize_observations else (lambda x, _: x)
    )
    return _network_factory(config, bool(env.config.vision), _privileged(config, env))(
        _brax_env(adapter, config, env).observation_size,
        env.n_drones * env.action_size,
        preprocess_observations_fn=preprocess,
    )


def _privileged(config: BraxPPOConfig, env: Env) -> bool:
    """Whether the critic reads ``env``'s privileged observation: ``config.privileged_critic`` and an env with
    cameras and a privileged observation."""
    if not (config.privileged_critic and env.config.vision):
        return False
    from jaxdrones.adapters.brax import privileged_shape

    return privileged_shape(env) is not None


def _brax_env(adapter, config: BraxPPOConfig, env: Env):
    """``env`` as brax sees it, with the privileged observation when the critic reads it (`_privileged`)."""
    return adapter.BraxEnv(env, privileged=_privileged(config, env))


def make_policy(networks: PPONetworks, params: Any, deterministic: bool = True) -> Callable:
    """``policy(obs, key) -> (action, extras)`` of brax's PPO networks and (normaliser, policy, value) params."""
    from brax.training.agents.ppo import networks as ppo_networks

    return ppo_networks.make_inference_fn(networks)(params, deterministic=deterministic)


def train(
    env: Env,
    config: BraxPPOConfig = BraxPPOConfig(),
    progress: Callable[[int, dict], None] | None = None,
    evaluate: Callable | None = None,
    eval_env: Env | None = None,
) -> tuple[PPONetworks, Any]:
    """Train a policy on ``env`` with brax's PPO.

    Args:
        env: a jaxdrones `Env` (the brax adapter flattens its f[D, n] observation and action; with cameras, brax's
            vision PPO on `jaxdrones.envs.observations.policy_input` with the CNN of ``config``,
            `jaxdrones.training.encoders`).
        config: PPO hyperparameters.
        progress: called as ``progress(env_steps, metrics)`` at each of brax's evaluations after the first, with
            brax's training metrics and, under ``"eval"``, what ``evaluate`` returns (NumPy arrays).
        evaluate: ``evaluate(networks, params, seed) -> pytree of arrays`` (jitted here, compiled once), as in the
            other trainers (`jaxdrones.training.trainers`).
        eval_env: the env of brax's own evaluations (``eval/...`` metrics); without one brax evaluates nothing
            itself.

    Returns:
        ``(networks, params)``: brax's PPO networks (`make_network`) and the trained (normaliser, policy, value)
        parameters; `make_policy` makes the policy.

    A run whose parameters go non-finite (checked at brax's evaluations) reports the update under
    `jaxdrones.training.common.NONFINITE` and returns its last finite parameters.

    Raises:
        jaxdrones.training.common.Interrupted: on Ctrl-C, with the parameters of brax's last evaluation.
    """
    adapter = _import_brax()
    from brax.training.agents.ppo import train as ppo

    networks = make_network(config, env)
    kwargs = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.name not in NETWORK_FIELDS}
    latest = {"params": None, "steps": 0}

    def evaluate_params(params):
        return evaluate(networks, params, np.int64(config.seed))

    run_eval = None if evaluate is None else jax.jit(evaluate_params)

    per_update = config.batch_size * config.unroll_length * config.num_minibatches  # env steps of one update
    finite = {"params": None, "update": -1}  # the last finite parameters; the update after which they were not

    def keep(steps, make_policy, params):
        latest.update(params=params, steps=int(steps))
        if finite["update"] < 0 and not nonfinite_leaves(params):
            finite["params"] = params
        elif finite["update"] < 0:
            finite["update"] = max(int(steps) // per_update, 1)

    def report(steps, metrics):
        if progress is not None and steps > 0:
            extra = {} if run_eval is None else {"eval": jax.tree.map(np.asarray, run_eval(latest["params"]))}
            scalars = {k: float(v) for k, v in metrics.items() if np.ndim(v) == 0}
            progress(int(steps), {**scalars, **extra, NONFINITE: finite["update"]})

    try:
        vision = bool(env.config.vision)
        _, params, _ = _rank_promotion_allowed(ppo.train)(
            _brax_env(adapter, config, env),
            episode_length=env.episode_length,
            wrap_env_fn=adapter.wrap_for_brax_training,
            vision=vision,
            network_factory=_network_factory(config, vision, _privileged(config, env)),
            deterministic_eval=True,
            progress_fn=report,
            policy_params_fn=keep,
            eval_env=None if eval_env is None else _brax_env(adapter, config, eval_env),
            run_evals=eval_env is not None,
            **kwargs,
        )
    except KeyboardInterrupt:
        if latest["params"] is None:
            raise
        raise Interrupted((networks, latest["params"]), latest["steps"]) from None
    if finite["update"] >= 0 and finite["params"] is not None:
        return networks, finite["params"]
    return networks, params
