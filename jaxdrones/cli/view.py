"""``jaxdrones view RUN``: a training run's evaluation flights as one self-contained HTML file (`view_run`, drawn
by `jaxdrones.viz.write_html`)."""

from __future__ import annotations

import argparse
import os
import sys

from jaxdrones._validate import check_int
from jaxdrones.viz import VIEW_EPISODES


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``view`` subcommand to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "view",
        help="write a training run's evaluation flights as one HTML file that plays offline",
        description="Fly the policy of a run of `jaxdrones train` for a few evaluation episodes on the JAX backend "
        "and write them as one self-contained HTML file (RUN/flight.html by default) that plays in a browser from "
        "file://, with play/pause, a time slider and trails. Needs viser: "
        'pip install ".[viewer]" from a clone of jaxdrones.',
    )
    parser.add_argument("run", help="a run folder of `jaxdrones train` (or its policy.pkl)")
    parser.add_argument(
        "--out", default=None, help="output file (default RUN/flight.html, the run's own, which it replaces)"
    )
    parser.add_argument(
        "--episodes",
        type=int,
        default=VIEW_EPISODES,
        help=f"evaluation episodes to fly and show (default {VIEW_EPISODES})",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes' random starts (default 0)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file given by --out")
    parser.set_defaults(func=run_cli)


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``view`` subcommand; returns the exit status."""
    try:
        path = view_run(args.run, args.out, n_episodes=args.episodes, seed=args.seed, overwrite=args.overwrite)
    except FileExistsError as e:
        print(f"jaxdrones view: {e.filename} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    except (ValueError, ModuleNotFoundError) as e:
        print(f"jaxdrones view: {e}", file=sys.stderr)
        return 2
    size = os.path.getsize(path) / 1e6
    print(f"wrote {path} ({size:.2f} MB): {args.episodes} evaluation episodes; open it in a browser")
    return 0


def view_run(
    run: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    n_episodes: int = VIEW_EPISODES,
    seed: int = 0,
    overwrite: bool = False,
    **options: object,
) -> str:
    """Fly a training run's policy for a few evaluation episodes on the JAX backend and write them with
    `jaxdrones.viz.write_html` (what ``jaxdrones view RUN`` runs).

    The policy is loaded with `jaxdrones.training.load_policy` and flown deterministically from ``n_episodes``
    random starts (keys split from ``seed``) in the env it was trained on, or, for a run of the PyBullet backend, in
    the same task on the JAX backend. Episodes are the worlds of one `jaxdrones.viz.Flight`: overlaid, or side by
    side where each has its own scene (a gate or obstacles drawn per episode).

    Args:
        run: a run folder of ``jaxdrones train`` (or its ``policy.pkl``).
        out: the HTML file (default ``RUN/flight.html``, the run's own viewer file, which ``jaxdrones train``
            wrote: replaced by the new flights).
        n_episodes: episodes to fly (>= 1).
        seed: the seed of their random starts.
        overwrite: replace an existing ``out`` given by the caller.
        **options: `jaxdrones.viz.write_html`'s options (``trail_s``, ``spacing``, ``camera``, ...).

    Returns:
        The path written.

    Raises:
        ModuleNotFoundError: viser is not installed (`jaxdrones.viz.VIEWER_INSTALL`).
        FileExistsError: an ``out`` given by the caller exists and not ``overwrite`` (checked before flying).
        ValueError: no policy at ``run``, or a bad option.
    """
    import jax

    from jaxdrones import viz
    from jaxdrones.envs import make
    from jaxdrones.io.runs import written_by_jaxdrones
    from jaxdrones.training import load_policy, rollout_policy
    from jaxdrones.training.checkpoint import read_payload

    check_int("n_episodes", n_episodes)
    path, payload = read_payload(run)
    own = out is None  # the run folder's own viewer file, written by `jaxdrones train`: made again from the policy
    overwrite = overwrite or own
    out = os.path.join(os.path.dirname(path), "flight.html") if own else os.fspath(out)
    if os.path.exists(out) and not overwrite:
        raise FileExistsError(17, "exists; pass overwrite=True to replace it", out)
    if not viz.viewer_available():
        raise ModuleNotFoundError(f"the flight viewer needs viser: {viz.VIEWER_INSTALL}", name="viser")
    env = None
    if payload["env_overrides"].get("backend", "jax") != "jax":
        env = make(payload["env_name"], **{**payload["env_overrides"], "backend": "jax"})
    env, policy = load_policy(path, env=env)
    keys = jax.random.split(jax.random.key(seed), n_episodes)
    states = jax.jit(jax.vmap(lambda k: rollout_policy(env, policy, k)))(keys)
    flight = viz.Flight.from_states(env, states, time_axis=1)
    if own and os.path.isfile(out) and written_by_jaxdrones(os.path.dirname(path)):
        os.remove(out)  # the run's own page, also one written before pages carried their mark
    return viz.write_html(out, flight, overwrite=overwrite, **options)
