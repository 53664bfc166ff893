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

    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the subcommand's usage, and the closest of its options to each unknown one
        _unknown_options(parser, args.command, unknown)
    xla.configure(getattr(args, "device", None))  # before JAX starts a backend
    args.t_start = t_start
    return int(args.func(args) or 0)


def run(argv: list[str] | None = None) -> None:
    """The ``jaxdrones`` command's process: `main`, then exit with its status. A run stopped by Ctrl-C (status 130)
    has saved what it keeps when `main` returns; its process then ends at once (``os._exit``), without Python's
    finalisation, during which XLA's compiler or a computation still running in its threads can end the process
    with a segmentation fault instead."""
    import signal

    signal.signal(signal.SIGINT, _interrupt)
    try:
        status = main(argv)
    except KeyboardInterrupt:  # before a command took over (its imports, the arguments): nothing was written
        print("interrupted", file=sys.stderr)
        status = 130
    if status == 130:
        import os

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


def _interrupt(signum: int, frame) -> None:
    """Ctrl-C as ``KeyboardInterrupt``, as Python's own handler raises it; but where it lands in a garbage
    collector's callback (JAX's ``_xla_gc_callback`` runs at every collection, often while a program is traced),
    whose exceptions Python prints and ignores, the signal is sent again 50 ms later instead of being lost."""
    import gc
    import os
    import signal
    import threading

    callbacks = {getattr(callback, "__code__", None) for callback in gc.callbacks}
    while frame is not None:
        if frame.f_code in callbacks:
            threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
            return
        frame = frame.f_back
    raise KeyboardInterrupt


def _unknown_options(parser: argparse.ArgumentParser, command: str, unknown: list[str]) -> None:
    """Exit (status 2) with ``command``'s usage and its unknown options, each with the closest option it has."""
    from jaxdrones._hints import did_you_mean

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    options = [flag for action in sub._actions for flag in action.option_strings]
    hints = [f"; {word}{hint}" for word in unknown if word.startswith("-") and (hint := did_you_mean(word, options))]
    sub.error(f"unrecognized arguments: {' '.join(unknown)}{''.join(hints)}")


if __name__ == "__main__":
    run()
