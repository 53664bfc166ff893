"""Command line: ``jaxdrones train hover``, ``jaxdrones fly``, ``jaxdrones camera``."""

from __future__ import annotations

import argparse
import sys
import time


def build_parser() -> argparse.ArgumentParser:
    from jaxdrones.examples import camera_scene, circle
    from jaxdrones.training import hover

    parser = argparse.ArgumentParser(prog="jaxdrones", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    hover.register(sub)
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
