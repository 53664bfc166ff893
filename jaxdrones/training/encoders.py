"""Image encoders for policies on camera observations, and brax's PPO networks built on them.

`Conv` is a 2-D convolution written as patches and one matrix product. It computes what ``flax.linen.Conv`` computes
(same parameters, ``kernel`` f[k, k, C_in, C_out] and ``bias``, same ``SAME`` padding; tests check the two agree),
but stays fast where XLA's CPU convolution is not: inside a loop. brax's PPO runs its minibatch updates in a
``lax.scan``, and there the gradient of XLA's convolution was an order of magnitude slower than outside one; as
patches and a matrix product it is as fast in and out of the loop (`benchmarks/gradients/encoders.py`,
docs/benchmarks.md), and on a GPU the product is one GEMM.

`make_ppo_networks_vision` is brax's ``networks_vision.make_ppo_networks_vision`` (a CNN per image, its features
flattened and joined with the normalised state vector, then an MLP; tanh-normal actions) on this encoder.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import linen

if TYPE_CHECKING:
    from brax.training.agents.ppo import networks_vision


def same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """The (low, high) zero padding of one spatial axis under ``SAME`` (XLA's and flax's rule: ceil(size / stride)
    outputs, the padding split with the extra pixel at the high end)."""
    out = -(-size // stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def patches(x: jax.Array, kernel: int, stride: int) -> jax.Array:
    """The ``SAME``-padded k×k patches of images x f[..., H, W, C] at ``stride``: f[..., H', W', k·k·C], H' =
    ceil(H / stride), the patch's entries in the order of a kernel f[k, k, C, ·] flattened."""
    *lead, h, w, c = x.shape
    (top, bottom), (left, right) = same_padding(h, kernel, stride), same_padding(w, kernel, stride)
    x = jnp.pad(x, [(0, 0)] * len(lead) + [(top, bottom), (left, right), (0, 0)])
    out_h, out_w = -(-h // stride), -(-w // stride)
    cols = [
        x[..., i : i + (out_h - 1) * stride + 1 : stride, j : j + (out_w - 1) * stride + 1 : stride, :]
        for i in range(kernel)
        for j in range(kernel)
    ]
    return jnp.concatenate(cols, axis=-1)


class Conv(linen.Module):
    """A square 2-D convolution with ``SAME`` padding, as patches (`patches`) and one matrix product: f[..., H, W,
    C_in] → f[..., ceil(H / stride), ceil(W / stride), features]. Parameters as ``flax.linen.Conv``'s."""

    features: int
    kernel_size: int
    stride: int = 1
    kernel_init: Callable = jax.nn.initializers.lecun_normal()

    @linen.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, c = self.kernel_size, x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (k, k, c, self.features))
        bias = self.param("bias", jax.nn.initializers.zeros, (self.features,))
        y = patches(x, k, self.stride) @ kernel.reshape(k * k * c, self.features)
        return y + jnp.reshape(bias, (1,) * (y.ndim - 1) + (-1,))


class CNN(linen.Module):
    """Convolutions with ReLU (`Conv`), the last feature map flattened: f[..., H, W, C] → f[..., H'·W'·C']
    (brax's ``networks.CNN`` followed by ``cnn_global_pool="none"``)."""

    features: Sequence[int]
    kernel_sizes: Sequence[int]
    strides: Sequence[int]

    @linen.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for features, kernel, stride in zip(self.features, self.kernel_sizes, self.strides, strict=True):
            x = linen.relu(Conv(features, kernel, stride)(x))
        return x.reshape(x.shape[:-3] + (-1,))


class VisionMLP(linen.Module):
    """A `CNN` per ``pixels/...`` entry of the observation dict, the features joined with ``obs[state_key]``, then
    brax's MLP (swish, LeCun-uniform kernels: brax's ``VisionMLP``)."""

    layer_sizes: Sequence[int]
    state_key: str
    cnn_features: Sequence[int]
    cnn_kernel_sizes: Sequence[int]
    cnn_strides: Sequence[int]

    @linen.compact
    def __call__(self, obs: Mapping[str, jax.Array]) -> jax.Array:
        from brax.training import networks

        feats = [
            CNN(self.cnn_features, self.cnn_kernel_sizes, self.cnn_strides)(obs[key])
            for key in sorted(obs)
            if key.startswith("pixels/")
        ]
        hidden = jnp.concatenate(feats + [obs[self.state_key]], axis=-1)
        return networks.MLP(
            layer_sizes=self.layer_sizes, activation=linen.swish, kernel_init=jax.nn.initializers.lecun_uniform()
        )(hidden)


class StateMLP(linen.Module):
    """brax's MLP (swish, LeCun-uniform kernels) on the vectors ``obs[k]`` of ``keys`` joined, no images."""

    layer_sizes: Sequence[int]
    keys: Sequence[str]

    @linen.compact
    def __call__(self, obs: Mapping[str, jax.Array]) -> jax.Array:
        from brax.training import networks

        hidden = jnp.concatenate([obs[k] for k in self.keys], axis=-1)
        return networks.MLP(
            layer_sizes=self.layer_sizes, activation=linen.swish, kernel_init=jax.nn.initializers.lecun_uniform()
        )(hidden)


def make_ppo_networks_vision(
    observation_size: Mapping[str, tuple[int, ...]],
    action_size: int,
    preprocess_observations_fn: Callable = lambda x, _: x,
    policy_hidden_layer_sizes: Sequence[int] = (64, 64),
    value_hidden_layer_sizes: Sequence[int] = (64, 64),
    state_key: str = "state",
    cnn_output_channels: Sequence[int] = (8, 16, 16),
    cnn_kernel_size: Sequence[int] = (4, 3, 3),
    cnn_stride: Sequence[int] = (2, 2, 2),
    value_obs_key: str | None = None,
) -> networks_vision.PPONetworks:
    """Brax's PPO networks (``networks_vision.PPONetworks``: policy, value, tanh-normal action distribution) on
    `VisionMLP`: what brax's ``make_ppo_networks_vision`` builds with ``cnn_global_pool="none"`` and
    ``policy_obs_key = value_obs_key = state_key``, on `Conv`.

    Args:
        observation_size: ``{key: shape}`` of one observation: ``state_key`` f[n] and images ``pixels/...``
            f[H, W, C].
        action_size: entries of the action.
        preprocess_observations_fn: brax's observation normaliser, applied to ``obs[state_key]`` only.
        policy_hidden_layer_sizes, value_hidden_layer_sizes: the MLPs' hidden units.
        state_key: the state vector's key.
        cnn_output_channels, cnn_kernel_size, cnn_stride: per convolution, its filters, square kernel and stride.
        value_obs_key: None: the value network is the policy's architecture (a CNN per image, the state, an MLP);
            a key of the observation (e.g. ``"privileged_state"``, `jaxdrones.adapters.brax.BraxEnv`): an
            asymmetric critic (Pinto et al., "Asymmetric Actor Critic for Image-Based Robot Learning", RSS 2018), an
            MLP on the normalised state and that entry, normalised, without images.

    Raises:
        ValueError: a ``value_obs_key`` that is not a key of ``observation_size``.
    """
    from brax.training import distribution, networks
    from brax.training.agents.ppo import networks_vision

    action_dist = distribution.NormalTanhDistribution(event_size=action_size)
    dummy = {key: jnp.zeros((1,) + tuple(shape)) for key, shape in observation_size.items()}
    cnn = dict(
        state_key=state_key,
        cnn_features=tuple(cnn_output_channels),
        cnn_kernel_sizes=tuple(cnn_kernel_size),
        cnn_strides=tuple(cnn_stride),
    )

    def network(module, squeeze, keys=(state_key,)):
        def apply(processor_params, params, obs):
            normed = {
                k: preprocess_observations_fn(obs[k], networks.normalizer_select(processor_params, k)) for k in keys
            }
            out = module.apply(params, {**obs, **normed})
            return jnp.squeeze(out, -1) if squeeze else out

        return networks.FeedForwardNetwork(init=lambda key: module.init(key, dummy), apply=apply)

    policy = VisionMLP(layer_sizes=tuple(policy_hidden_layer_sizes) + (action_dist.param_size,), **cnn)
    value_layers = tuple(value_hidden_layer_sizes) + (1,)
    if value_obs_key is None:
        value_keys, value = (state_key,), VisionMLP(layer_sizes=value_layers, **cnn)
    elif value_obs_key not in observation_size:
        raise ValueError(
            f"value_obs_key {value_obs_key!r} is not a key of the observation ({sorted(observation_size)})"
        )
    else:
        value_keys = (state_key, value_obs_key)
        value = StateMLP(layer_sizes=value_layers, keys=value_keys)
    return networks_vision.PPONetworks(
        policy_network=network(policy, False),
        value_network=network(value, True, value_keys),
        parametric_action_distribution=action_dist,
    )
