"""Command line: ``jaxdrones train TASK``, ``jaxdrones fly``, ``jaxdrones camera``."""

from __future__ import annotations

import argparse
import sys
import time


def build_parser() -> argparse.ArgumentParser:
    from jaxdrones import __version__
    from jaxdrones.examples import camera_scene, circle
    from jaxdrones.training import run

    parser = argparse.ArgumentParser(prog="jaxdrones", description=__doc__)
    parser.add_argument("--version", action="version", version=f"jaxdrones {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    run.register(sub)
    circle.register(sub)
    camera_scene.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    t_start = time.perf_counter()
    args = build_parser().parse_args(argv)
    args.t_start = t_start
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
