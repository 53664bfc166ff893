"""Command line: ``jaxdrones train TASK``, ``jaxdrones fly``, ``jaxdrones camera``, ``jaxdrones export RUN``,
``jaxdrones ros2 TASK``, ``jaxdrones view RUN``."""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxdrones`` command line: its ``--version`` and one subcommand per job."""
    from jaxdrones import __version__
    from jaxdrones.cli import camera, export, fly, ros2, train, view

    parser = argparse.ArgumentParser(prog="jaxdrones", description=__doc__)
    parser.add_argument("--version", action="version", version=f"jaxdrones {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    train.register(sub)
    fly.register(sub)
    camera.register(sub)
    export.register(sub)
    ros2.register(sub)
    view.register(sub)
    return parser


def process_start() -> float:
    """The `time.perf_counter` reading at which this process started (Linux: from ``/proc``), so that a run's wall
    time includes Python's start and the imports before `main`; elsewhere, now."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime, in clock ticks
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        age = uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        age = 0.0
    return time.perf_counter() - max(age, 0.0)


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (default: the process's arguments, and the wall time of a run then counts
    from the process's start); returns the exit status.

    As the process's command (``argv`` None), it moves the objects that live as long as the process out of the
    cyclic garbage collector's sight (`gc.freeze`): after the imports (JAX's and jaxdrones' modules, which every
    full collection while a program is traced would otherwise walk again), and once the command is done (Python's
    collections at exit would otherwise walk everything the run made: 0.3-0.4 s of a ``jaxdrones train hover`` on 2
    CPU cores). Nothing is lost: the run's files are written and closed by then, and the process's memory goes
    back to the system at its exit as always. Called with ``argv`` (from Python), it leaves the collector alone."""
    t_start = process_start() if argv is None else time.perf_counter()
    from jaxdrones import _xla

    args = build_parser().parse_args(argv)
    device = getattr(args, "device", None)
    _xla.add_flags(_xla.flags_for(device))  # before JAX starts a backend
    _xla.set_environment(_xla.environment_for(device))
    _xla.set_jax_options(_xla.jax_options_for(device))  # before JAX traces a program
    args.t_start = t_start
    if argv is not None:
        return int(args.func(args) or 0)
    gc.freeze()
    try:
        return int(args.func(args) or 0)
    finally:
        gc.freeze()


if __name__ == "__main__":
    sys.exit(main())
