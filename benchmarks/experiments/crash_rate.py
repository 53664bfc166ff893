"""The share of crashed episodes of saved policies over many random starts, and the crashes themselves.

A run's own evaluation flies 256 starts; a policy that loses one start in a thousand passes it more often than not.
This flies each run's policy (``policy.pkl`` of a ``jaxdrones train`` folder, in the env it was trained in) from
``--episodes`` starts drawn from one key (``--key``; the same starts for every run) and prints per run the episodes
that ended early (crashed, left the arena, tipped over) and, for each, the start's distance to the target and tilt,
the step it ended at and the height there. docs/experiments.md ("Crash-free seeds under the preset") cites it.

Usage::

    python benchmarks/experiments/crash_rate.py runs/hover-0 runs/hover-1 runs/hover-2
    python benchmarks/experiments/crash_rate.py RUN --episodes 8192 --key 7
"""

from __future__ import annotations

import argparse


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders of jaxdrones train (single-drone tasks)")
    parser.add_argument("--episodes", type=int, default=2048, help="random starts per run (default 2048)")
    parser.add_argument("--key", type=int, default=123, help="the key the starts are drawn from (default 123)")
    return parser.parse_args(argv)


def crashes(run: str, episodes: int, key: int) -> dict:
    """The episodes of ``run``'s policy that ended early, from ``episodes`` starts drawn from ``key``."""
    import jax
    import numpy as np

    from jaxdrones.physics.rotations import quat_to_rotmat
    from jaxdrones.training.checkpoint import load_policy
    from jaxdrones.training.evaluation import rollout_policy

    env, policy = load_policy(run)
    keys = jax.random.split(jax.random.key(key), episodes)
    states = jax.jit(jax.vmap(lambda k: rollout_policy(env, policy, k)))(keys)
    ended = np.flatnonzero(np.asarray(states.metrics["crash"][:, -1]) > 0)
    target = np.asarray(states.task.target[:, 0, 0]) if hasattr(states.task, "target") else 0.0
    start = np.asarray(states.sim.pos[:, 0, 0])
    tilt = np.degrees(np.arccos(np.clip(np.asarray(quat_to_rotmat(states.sim.quat[:, 0, 0]))[..., 2, 2], -1, 1)))
    return {
        "episodes": episodes,
        "crashed": len(ended),
        "crashes": [
            {
                "episode": int(i),
                "start_distance_m": float(np.linalg.norm(start[i] - (target[i] if np.ndim(target) else target))),
                "start_tilt_deg": float(tilt[i]),
                "ended_at_step": int(states.steps[i, -1]),
                "height_at_end_m": float(states.sim.pos[i, -1, 0, 2]),
            }
            for i in ended
        ],
    }


def main(argv=None) -> dict:
    args = parse_args(argv)
    out = {}
    for run in args.runs:
        out[run] = result = crashes(run, args.episodes, args.key)
        print(f"{run}: {result['crashed']} of {result['episodes']} episodes ended early")
        for c in result["crashes"]:
            print(
                f"  episode {c['episode']}: start {c['start_distance_m']:.2f} m from the target, tilted "
                f"{c['start_tilt_deg']:.0f}°; ended at step {c['ended_at_step']}, {c['height_at_end_m']:.2f} m up"
            )
    print(f"all: {sum(r['crashed'] for r in out.values())} of {sum(r['episodes'] for r in out.values())}")
    return out


if __name__ == "__main__":
    main()
