"""Command line: ``jaxdrones train TASK``, ``jaxdrones fly``, ``jaxdrones camera``, ``jaxdrones export RUN``,
``jaxdrones ros2 TASK``, ``jaxdrones view RUN``."""

from __future__ import annotations

import argparse
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


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (default: the process's arguments); returns the exit status. Sets the XLA
    flags of the device it compiles for first (`jaxdrones.cli.xla.configure`)."""
    t_start = time.perf_counter()
    from jaxdrones.cli import xla

    args = build_parser().parse_args(argv)
    xla.configure(getattr(args, "device", None))  # before JAX starts a backend
    args.t_start = t_start
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
