"""``jaxdrones export RUN --format c|onnx``: a trained policy as one dependency-free C file, or an ONNX model
(`jaxdrones.training.export`)."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "export",
        help="write a trained policy as one dependency-free C file (or an ONNX model)",
        description="Write the policy of a run of `jaxdrones train` (an MLP of apg or shac) as one C file: float32 "
        "weights and `void NAME(const float obs[N_OBS], float action[N_ACT])`, with the observation's "
        "layout, units, frames and clip and the action's mapping to motor commands in its header "
        "comment. Prints its path, its bytes of constants and its multiply-adds per call.",
    )
    parser.add_argument("run", help="a run folder of `jaxdrones train` (or its policy.pkl)")
    parser.add_argument(
        "--format",
        choices=("c", "onnx"),
        default="c",
        help="c (default), or onnx (an ONNX model of the same network; needs the onnx package)",
    )
    parser.add_argument("--out", default=None, help="output file (default RUN/NAME.c or .onnx)")
    parser.add_argument("--name", default="jaxdrones_policy", help="the C function's name (default jaxdrones_policy)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run ``jaxdrones export`` with its parsed arguments; returns the exit status."""
    from jaxdrones.training.export import export

    try:
        path, sizes = export(args.run, args.format, args.out, name=args.name, overwrite=args.overwrite)
    except FileExistsError as e:
        print(f"jaxdrones export: {e.filename} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    except (ValueError, ModuleNotFoundError) as e:
        print(f"jaxdrones export: {e}", file=sys.stderr)
        return 2
    print(
        f"wrote {path}: {sizes['n_obs']} observations -> {sizes['n_act']} actions, {sizes['weight_bytes']} bytes "
        f"of float32 constants, {sizes['multiply_adds']} multiply-adds per call"
    )
    return 0
