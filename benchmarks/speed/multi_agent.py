"""Multi-agent throughput against the team size D, with downwash on and off, with every drone coupled to every other
or through neighbour lists: the physics step, the multi-agent env and a full MAPPO update, in agent-steps per second
(one agent-step: one control step of one drone).

For each D (default 2, 8, 64, 256, 1024), coupling (every drone; or neighbour lists: ``downwash_radius=1`` m, the
downwash's cut-off with a cell list, and ``max_neighbors=8``, a ``neighbors`` observation of the 8 nearest drones)
and downwash off/on, in one process:

* physics: `jaxdrones.make_step` on ``worlds`` worlds of D hovering drones (240 Hz physics, 30 Hz control, 8
  substeps per step), ``steps`` control steps in one jitted `lax.scan`; also given per drone and physics substep;
* env: the ``multi_hover`` env (D drones, the ``neighbors`` observation), `jaxdrones.wrappers.VmapAutoReset` over
  the worlds under `jit`, random actions, ``steps`` steps in one `lax.scan`;
* MAPPO update: `jaxdrones.training.mappo.train`'s update (collecting ``unroll_length`` steps of every world, GAE,
  ``epochs`` × ``minibatches`` PPO steps) timed as training chunks of a few updates, compilation excluded.

``worlds`` is chosen so that every size simulates about ``--agents`` drones at once (at least one world). Each
timing is the best of ``--repeats`` calls after a warm-up call. Every drone coupled to every other, the downwash and
the ``neighbors`` observation cost D² per world; with the cell list the downwash costs O(D) pairs (and a sort of the
drones once per control step); the 8 nearest drones of the observation are chosen from the D² distances once per
control step. The other effects are off. The drones fly in a grid 0.5 m apart (jittered by ±5 cm), 0.5-2.5 m high;
with the cell list, the table also gives the largest difference of the downwash force from the original's (every
pair within 10 m) over the physics benchmark's drones, relative to the weight plus the force.

    python benchmarks/speed/multi_agent.py         # D = 2, 8, 64, 256; writes benchmarks/results/multi_agent.json
    python benchmarks/speed/multi_agent.py --drones 2 8 --no-mappo
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS


def best_time(fn, *args, repeats: int) -> float:
    import jax

    jax.block_until_ready(fn(*args))  # compile and warm up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return min(times)


#: The neighbour lists' settings: the downwash's cut-off (m) and the observation's nearest drones.
LISTS = {"downwash_radius": 1.0, "max_neighbors": 8}


def swarm(n_drones: int, worlds: int):
    """Positions f[worlds, D, 3] m: a square grid 0.5 m apart, jittered by ±5 cm, 0.5-2.5 m high."""
    import numpy as np

    rng = np.random.default_rng(0)
    side = int(np.ceil(np.sqrt(n_drones)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n_drones] * 0.5
    xy = grid + rng.uniform(-0.05, 0.05, (worlds, n_drones, 2))
    return np.concatenate([xy, rng.uniform(0.5, 2.5, (worlds, n_drones, 1))], -1)


def downwash_error(n_drones: int, worlds: int) -> float:
    """max |F_cells - F_all| / (weight + |F_all|) over the drones of `swarm`: the cell list with `LISTS`' cut-off
    against every pair within 10 m (relative to the force where it exceeds the weight: drones at nearly the same
    height push each other with up to hundreds of newtons, whose float32 rounding alone is 1e-7 of them)."""
    import jax.numpy as jnp

    import jaxdrones as jd
    from jaxdrones import aerodynamics
    from jaxdrones.neighbors import cell_candidates

    params = jd.load_params("cf2x")
    pos = jnp.asarray(swarm(n_drones, worlds), jnp.float32)
    cutoff = LISTS["downwash_radius"]
    near = cell_candidates(pos[..., 0], pos[..., 1], cutoff, jd.SimConfig().cell_capacity)
    full = aerodynamics.downwash_force(params, pos)
    listed = aerodynamics.downwash_force(params, pos, neighbors=near, cutoff=cutoff)
    return float(jnp.max(jnp.abs(listed - full) / (params.weight + jnp.abs(full))))


def physics_rate(n_drones: int, worlds: int, downwash: bool, steps: int, repeats: int, lists: dict) -> float:
    """Agent-steps/s (control steps × drones × worlds per second) of the JAX core."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxdrones as jd

    config = jd.SimConfig(
        n_drones=n_drones, sim_freq=240, ctrl_freq=30, downwash=downwash, downwash_radius=lists.get("downwash_radius")
    )
    step = jd.make_step(config)
    params = jd.load_params("cf2x")
    pos = swarm(n_drones, worlds)
    state = jd.init_state(config, pos=pos, rpm=float(params.hover_rpm) * np.ones((worlds, n_drones, 4)))
    rpm = jnp.full((worlds, n_drones, 4), params.hover_rpm)

    @jax.jit
    def run(state):
        return jax.lax.scan(lambda s, _: (step(params, s, rpm), None), state, None, length=steps)[0].pos

    return steps * worlds * n_drones / best_time(run, state, repeats=repeats)


def env_rate(n_drones: int, worlds: int, downwash: bool, steps: int, repeats: int, lists: dict) -> float:
    """Agent-steps/s of the multi_hover env with auto-reset."""
    import jax

    import jaxdrones as jd
    from jaxdrones.wrappers import VmapAutoReset

    env = VmapAutoReset(jd.make("multi_hover", n_drones=n_drones, obs_type="neighbors", downwash=downwash, **lists))
    state = env.reset(jax.random.split(jax.random.key(0), worlds))
    shape = (steps, worlds, n_drones, env.action_size)

    @jax.jit
    def run(state, key):
        actions = jax.random.uniform(key, shape, minval=-1.0, maxval=1.0)
        return jax.lax.scan(lambda s, a: (env.step(s, a), None), state, actions)[0].obs

    return steps * worlds * n_drones / best_time(run, state, jax.random.key(1), repeats=repeats)


def mappo_rate(n_drones: int, worlds: int, downwash: bool, repeats: int, lists: dict) -> float:
    """Agent-steps/s of MAPPO training (collection and update), from the wall time between its progress reports
    after the first (which includes compilation)."""
    import jaxdrones as jd
    from jaxdrones.training import mappo

    env = jd.make("multi_hover", n_drones=n_drones, obs_type="neighbors", downwash=downwash, **lists)
    config = mappo.MAPPOConfig(
        num_envs=worlds,
        unroll_length=10,
        minibatches=min(8, worlds * 10),
        num_timesteps=worlds * 10 * 2 * (repeats + 1),
        num_evals=repeats + 2,
    )
    stamps = []
    mappo.train(env, config, progress=lambda steps, metrics: stamps.append((steps, time.perf_counter())))
    rates = [(s1 - s0) * n_drones / (t1 - t0) for (s0, t0), (s1, t1) in zip(stamps[1:], stamps[2:], strict=False)]
    return max(rates)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--drones", type=int, nargs="+", default=[2, 8, 64, 256, 1024])
    parser.add_argument("--agents", type=int, default=4096, help="drones simulated at once (default 4096)")
    parser.add_argument("--steps", type=int, default=30, help="control steps per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-mappo", action="store_true", help="skip the MAPPO update timing")
    parser.add_argument("--out", default=os.path.join(RESULTS, "multi_agent.json"))
    args = parser.parse_args(argv)

    import jax

    import jaxdrones  # noqa: F401  (first: it sets XLA's flags before JAX starts)

    rows = []
    print(
        f"jax {jax.__version__} on {jax.default_backend()}, {os.cpu_count()} cores; agent-steps/s "
        f"(about {args.agents} drones at once)"
    )
    print("  D worlds coupling downwash    physics (ns per drone-substep)        env      MAPPO  force error/weight")
    for n in args.drones:
        worlds = max(1, args.agents // n)
        for lists in ({}, LISTS):
            error = downwash_error(n, worlds) if lists else None
            for downwash in (False, True):
                row = {
                    "n_drones": n,
                    "worlds": worlds,
                    "lists": lists,
                    "downwash": downwash,
                    "physics": physics_rate(n, worlds, downwash, args.steps, args.repeats, lists),
                    "env": env_rate(n, worlds, downwash, args.steps, args.repeats, lists),
                    "mappo": None if args.no_mappo else mappo_rate(n, worlds, downwash, args.repeats, lists),
                    "downwash_error_over_weight": error if downwash else None,
                }
                row["physics_ns_per_drone_substep"] = 1e9 / (row["physics"] * 8)
                rows.append(row)
                mappo_text = "-" if row["mappo"] is None else f"{row['mappo']:10.3g}"
                coupling = "lists" if lists else "all"
                error_text = f"{error:.2g}" if downwash and error is not None else "-"
                print(
                    f"{n:3d} {worlds:6d} {coupling:8s} {'on ' if downwash else 'off'}      {row['physics']:10.3g} "
                    f"({row['physics_ns_per_drone_substep']:6.1f})                 {row['env']:10.3g} {mappo_text}"
                    f"  {error_text}",
                    flush=True,
                )
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(
            {
                "rows": rows,
                "machine": platform.platform(),
                "cpus": os.cpu_count(),
                "load_avg": os.getloadavg(),
                "agents": args.agents,
                "steps": args.steps,
            },
            f,
            indent=2,
        )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
