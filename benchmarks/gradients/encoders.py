"""The image encoder's gradient inside and outside a ``lax.scan``: flax's ``linen.Conv`` (XLA's convolution) against
`jaxdrones.training.encoders.Conv` (patches and a matrix product), in one run.

The work: the gradient of Σ features² of the default vision encoder (`BraxPPOConfig`: 8-16-16 filters, 4×4/2,
3×3/2, 3×3/2, ReLU) over ``--minibatches`` minibatches of ``--batch`` 24×32×1 images, a parameter step after
each, as brax's PPO runs its minibatch updates: once as a ``lax.scan`` over the minibatches and once as a Python
loop unrolled into the program. Each of the four programs is timed in turn within each repeat
(`common.timed_together`); µs per sample of the median.

Usage::

    python benchmarks/gradients/encoders.py                # writes benchmarks/results/encoders.json
    python benchmarks/gradients/encoders.py --batch 1024 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS, timed_together

DEFAULT_OUT = os.path.join(RESULTS, "encoders.json")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=4096, help="samples per minibatch (brax's PPO for avoid: 4096)")
    parser.add_argument("--minibatches", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=DEFAULT_OUT)
    return parser.parse_args(argv)


def encoders():
    """name → flax module of the default encoder's convolutions (without the flattening)."""
    from flax import linen

    from jaxdrones.training.brax_ppo import BraxPPOConfig
    from jaxdrones.training.encoders import Conv

    config = BraxPPOConfig()
    layers = list(zip(config.cnn_output_channels, config.cnn_kernel_size, config.cnn_stride, strict=True))

    class Convolutions(linen.Module):  # the layers, each made by ``conv(features, kernel, stride)``, with ReLU
        conv: object

        @linen.compact
        def __call__(self, x):
            for f, k, s in layers:
                x = linen.relu(self.conv(f, k, s)(x))
            return x

    return {
        "linen.Conv": Convolutions(lambda f, k, s: linen.Conv(f, (k, k), strides=(s, s), padding="SAME")),
        "encoders.Conv": Convolutions(Conv),
    }


def programs(module, images):
    """The scanned and the unrolled program of minibatch gradient steps, each a no-argument callable."""
    import jax
    import jax.numpy as jnp

    params = module.init(jax.random.key(0), images[0, :1])
    grad = jax.grad(lambda p, x: jnp.sum(module.apply(p, x) ** 2))

    def step(p, x):
        return jax.tree.map(lambda a, g: a - 1e-6 * g, p, grad(p, x))

    scanned = jax.jit(lambda p, xs: jax.lax.scan(lambda p, x: (step(p, x), None), p, xs)[0])

    def loop(p, xs):
        for i in range(xs.shape[0]):
            p = step(p, xs[i])
        return p

    unrolled = jax.jit(loop)
    return {
        "scan": lambda: jax.block_until_ready(scanned(params, images)),
        "unrolled": lambda: jax.block_until_ready(unrolled(params, images)),
    }


def main(argv=None):
    args = parse_args(argv)
    import jax
    import numpy as np

    images = jax.numpy.asarray(
        np.random.default_rng(0).random((args.minibatches, args.batch, 24, 32, 1)), jax.numpy.float32
    )
    runs = {
        f"{name} {kind}": run for name, module in encoders().items() for kind, run in programs(module, images).items()
    }
    times = timed_together(runs, args.repeats)
    samples = args.minibatches * args.batch
    rows = [
        {
            "encoder": name.split()[0],
            "program": name.split()[1],
            "us_per_sample": 1e6 * median / samples,
            "best_us_per_sample": 1e6 * best / samples,
        }
        for name, (best, median) in times.items()
    ]
    for row in rows:
        print(
            f"{row['encoder']:>14} {row['program']:>9}: {row['us_per_sample']:7.1f} µs per sample "
            f"(best {row['best_us_per_sample']:.1f})"
        )
    result = {
        "batch": args.batch,
        "minibatches": args.minibatches,
        "repeats": args.repeats,
        "device": str(jax.devices()[0]),
        "rows": rows,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
