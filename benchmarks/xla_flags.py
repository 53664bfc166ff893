"""What the command line's XLA flag check costs on its first run: `jaxdrones._xla.accepted` of `CLI_FLAGS` with an
empty cache (a new ``XDG_CACHE_HOME`` per run), in a fresh process, and again with the answers cached.

    python benchmarks/xla_flags.py            # 3 runs, medians
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

CODE = """
import time
t0 = time.perf_counter()
from jaxdrones import _xla
flags = _xla.accepted(_xla.CLI_FLAGS)
t1 = time.perf_counter()
_xla.accepted(_xla.CLI_FLAGS)
print(t1 - t0, time.perf_counter() - t1, " ".join(flags))
"""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args(argv)
    first, cached = [], []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as cache:
            out = subprocess.run(
                [sys.executable, "-c", CODE],
                env={**os.environ, "XDG_CACHE_HOME": cache},
                capture_output=True,
                text=True,
                check=True,
            ).stdout.split()
        first.append(float(out[0]))
        cached.append(float(out[1]))
        accepted = out[2:]
    import jax

    print(
        f"jax {jax.__version__}: accepted {accepted}; first check {statistics.median(first):.2f} s, "
        f"cached {1e3 * statistics.median(cached):.1f} ms (medians of {args.runs})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
