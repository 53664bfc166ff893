"""``jaxdrones view RUN``: a training run's evaluation flights as one self-contained HTML file
(`jaxdrones.viz.view_run`)."""

from __future__ import annotations

import argparse
import os
import sys


def register(subparsers) -> None:
    """Add the ``view`` subcommand to an argparse subparsers object."""
    from jaxdrones.viz import VIEW_EPISODES

    parser = subparsers.add_parser(
        "view", help="write a training run's evaluation flights as one HTML file that plays offline",
        description="Fly the policy of a run of `jaxdrones train` for a few evaluation episodes on the JAX backend "
                    "and write them as one self-contained HTML file (RUN/flight.html by default) that plays in a "
                    "browser from file://, with play/pause, a time slider and trails. Needs viser: "
                    'pip install "jaxdrones[viewer]".')
    parser.add_argument("run", help="a run folder of `jaxdrones train` (or its policy.pkl)")
    parser.add_argument("--out", default=None, help="output file (default RUN/flight.html)")
    parser.add_argument("--episodes", type=int, default=VIEW_EPISODES,
                        help=f"evaluation episodes to fly and show (default {VIEW_EPISODES})")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes' random starts (default 0)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``view`` subcommand; returns the exit status."""
    from jaxdrones.viz import view_run

    try:
        path = view_run(args.run, args.out, n_episodes=args.episodes, seed=args.seed, overwrite=args.overwrite)
    except FileExistsError as e:
        print(f"jaxdrones view: {e.filename} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    except (ValueError, ModuleNotFoundError) as e:
        print(f"jaxdrones view: {e}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.2f} MB): {args.episodes} evaluation episodes; open it in a "
          f"browser")
    return 0
