"""docs/adapters.md's Stable-Baselines3 ``VecEnv`` block, as written there, with and without its
``torch.set_num_threads(1)`` line: env steps per second of SB3's PPO beside JAX on the CPU.

The block is read from docs/adapters.md (the Python block that builds ``VecEnv("hover", num_envs=256, ...)``) and
run in a fresh process as it stands, ``learn(300_000)`` and all, with a clock around ``learn``; then again without
its ``torch.set_num_threads(1)`` line, for ``--steps-without`` env steps (default 16,384: two of PPO's rollouts,
since torch's default threads may take minutes per update). Each run prints its env steps per second and whether
the adapters' `jaxdrones.adapters.TorchThreadsWarning` was given. Needs the ``sb3`` extra.

    python benchmarks/experiments/torch_threads.py
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TIMED = """
import time as _time
_learn = PPO.learn
def _timed(self, total_timesteps, *args, **kwargs):
    start = _time.perf_counter()
    out = _learn(self, {steps}, *args, **kwargs)
    seconds = _time.perf_counter() - start
    rate = self.num_timesteps / seconds
    print(f"RESULT {{self.num_timesteps}} env steps in {{seconds:.1f}} s: {{rate:.0f}} env steps/s")
    return out
PPO.learn = _timed
"""


def docs_block() -> str:
    """The SB3 ``VecEnv`` block of docs/adapters.md."""
    with open(os.path.join(ROOT, "docs", "adapters.md")) as f:
        blocks = re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)
    return next(block for block in blocks if 'VecEnv("hover", num_envs=256' in block)


def run(block: str, steps: int | None) -> str:
    """Run ``block`` in a fresh process (``learn`` timed; with ``steps``, that many env steps instead)."""
    lines = block.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("env = "))
    hook = TIMED.format(steps="total_timesteps" if steps is None else steps)
    source = "\n".join([*lines[:at], hook, *lines[at:]])
    done = subprocess.run([sys.executable, "-c", source], capture_output=True, text=True, cwd=ROOT)
    result = next((line for line in done.stdout.splitlines() if line.startswith("RESULT")), done.stderr[-2000:])
    warned = "TorchThreadsWarning" in done.stderr
    return f"{result.removeprefix('RESULT ')} (TorchThreadsWarning {'given' if warned else 'not given'})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps-without", type=int, default=16_384, help="env steps without the threads line")
    args = parser.parse_args(argv)
    block = docs_block()
    if "torch.set_num_threads(1)" not in block:
        raise SystemExit("docs/adapters.md's SB3 VecEnv block has no torch.set_num_threads(1) line")
    print(f"as written: {run(block, None)}")
    without = "\n".join(line for line in block.splitlines() if "torch.set_num_threads(1)" not in line)
    print(f"without torch.set_num_threads(1): {run(without, args.steps_without)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
