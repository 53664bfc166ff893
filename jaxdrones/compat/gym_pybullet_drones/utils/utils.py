"""gym-pybullet-drones' helpers ``sync`` and ``str2bool``."""

from __future__ import annotations

import argparse
import time


def sync(i: int, start_time: float, timestep: float) -> None:
    """Sleep so that step ``i`` of a loop started at ``start_time`` (``time.time()``) is not shown before
    ``i · timestep`` s of wall-clock time; like the original, only every ``1 / (24 timestep)``-th step syncs when
    ``timestep`` ≤ 0.04 s."""
    if timestep > 0.04 or i % max(1, int(1 / (24 * timestep))) == 0:
        ahead = i * timestep - (time.time() - start_time)
        if ahead > 0:
            time.sleep(ahead)


def str2bool(val) -> bool:
    """``val`` as a bool: a bool, or one of yes/true/t/y/1 and no/false/f/n/0 (any case).

    Raises:
        argparse.ArgumentTypeError: any other value (so that argparse reports it).
    """
    if isinstance(val, bool):
        return val
    text = str(val).lower()
    if text in ("yes", "true", "t", "y", "1"):
        return True
    if text in ("no", "false", "f", "n", "0"):
        return False
    raise argparse.ArgumentTypeError(f"a boolean value is expected (true/false, yes/no, 1/0), got {val!r}")
