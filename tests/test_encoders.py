"""The image encoder's convolution (patches and a matrix product) against flax's ``linen.Conv``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen

from jaxdrones.training.encoders import Conv, same_padding


@pytest.mark.parametrize(
    "shape,features,kernel,stride",
    [
        ((2, 24, 32, 1), 8, 4, 2),  # the default encoder's layers
        ((2, 12, 16, 8), 16, 3, 2),
        ((2, 6, 8, 16), 16, 3, 2),
        ((3, 7, 5, 2), 4, 3, 1),  # odd sizes, stride 1
        ((1, 9, 11, 3), 5, 5, 3),  # kernel wider than the stride, sizes not multiples of it
        ((2, 7, 9, 1), 3, 4, 2),  # an odd total padding (one more pixel at the high end)
        ((2, 4, 3, 24, 32, 1), 8, 4, 2),  # two leading axes (brax's [batch, unroll] minibatches)
    ],
)
def test_conv_computes_flax_conv(shape, features, kernel, stride):
    """Same parameters, same outputs and same gradients as ``linen.Conv(padding="SAME")``."""
    x = jax.random.normal(jax.random.key(0), shape)
    ours = Conv(features, kernel, stride)
    theirs = linen.Conv(features, (kernel, kernel), strides=(stride, stride), padding="SAME")
    params = ours.init(jax.random.key(1), x)
    params["params"]["bias"] = jax.random.normal(jax.random.key(2), (features,))
    assert jax.tree.map(jnp.shape, params) == jax.tree.map(jnp.shape, theirs.init(jax.random.key(1), x))
    out, ref = ours.apply(params, x), theirs.apply(params, x)
    assert out.shape == ref.shape == shape[:-3] + (-(-shape[-3] // stride), -(-shape[-2] // stride), features)
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)

    def loss(module):
        return lambda p, x: jnp.sum(jnp.sin(module.apply(p, x)))

    g_ours, g_theirs = (
        jax.grad(loss(ours), argnums=(0, 1))(params, x),
        jax.grad(loss(theirs), argnums=(0, 1))(params, x),
    )
    for a, b in zip(jax.tree.leaves(g_ours), jax.tree.leaves(g_theirs), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_same_padding_is_xlas():
    """XLA's SAME rule: ceil(n / s) outputs, the odd pixel of padding at the high end."""
    assert same_padding(24, 4, 2) == (1, 1)
    assert same_padding(7, 3, 1) == (1, 1)
    assert same_padding(9, 5, 3) == (1, 1)
    assert same_padding(7, 4, 2) == (1, 2)
    assert same_padding(12, 1, 2) == (0, 0)
