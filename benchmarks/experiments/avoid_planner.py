"""How often ``avoid`` can be solved with its own actions, by a planner that knows every obstacle.

An upper reference for policies that see the field only through their camera. For each of ``--episodes`` episodes
(drawn as ``jaxdrones train avoid`` evaluates them, 32 × 24 camera unused), the planner:

1. samples the clearance of the episode's obstacles (`jaxdrones.cameras.distance` less the drone's collision radius)
   on a 5 cm grid at the flight altitude, over the field and 0.5 m beyond its sides;
2. marks free the cells with at least ``--margin`` m of clearance and takes the shortest path from every free cell
   to the goal (Dijkstra on the 8-connected grid, ``scipy.sparse.csgraph``; each step's length weighted by up to 4×
   within 0.3 m of an obstacle, so that paths keep their distance where they can);
3. flies the env's own ``pid`` actions (relative targets, 0.3 m per axis) at full step towards the lowest
   path-to-goal among 32 points 0.3 m around the drone, holding the flight altitude.

It also reports the share of episodes whose grid has a free path from the start to the goal at all, and what a
flight straight at the goal does. Usage::

    python benchmarks/experiments/avoid_planner.py                # 256 episodes, margin 0.08 m
    python benchmarks/experiments/avoid_planner.py --margin 0.15
"""

from __future__ import annotations

import argparse
import json
import pathlib

DEFAULT_OUT = pathlib.Path(__file__).resolve().parents[1] / "results" / "avoid_planner.json"
GRID_M = 0.05
LOOK_M = 0.3


def parse_args(argv=None):
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--margin", type=float, default=0.08, help="clearance a free cell keeps, m (default 0.08)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=DEFAULT_OUT)
    return parser.parse_args(argv)


def path_lengths(clear, goal_cell, margin):
    """f[nx, ny]: the weighted shortest path from each cell to ``goal_cell`` over cells with clearance ≥ margin
    (1e3 where there is none)."""
    import numpy as np
    from scipy.sparse import coo_matrix, csgraph

    nx, ny = clear.shape
    idx = np.arange(nx * ny).reshape(nx, ny)
    free = (clear >= margin).ravel()
    weight = (1.0 + 3.0 * np.clip((0.3 - clear) / 0.3, 0, 1)).ravel()
    rows, cols, lengths = [], [], []
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a = idx[max(0, -di) : nx - max(0, di), max(0, -dj) : ny - max(0, dj)].ravel()
        b = idx[max(0, di) : nx + min(0, di), max(0, dj) : ny + min(0, dj)].ravel()
        ok = free[a] & free[b]
        rows.append(a[ok])
        cols.append(b[ok])
        lengths.append(GRID_M * np.hypot(di, dj) * 0.5 * (weight[a] + weight[b])[ok])
    graph = coo_matrix(
        (np.concatenate(lengths), (np.concatenate(rows), np.concatenate(cols))), shape=(nx * ny, nx * ny)
    ).tocsr()
    d = csgraph.dijkstra(graph, directed=False, indices=idx[goal_cell])
    return np.where(np.isfinite(d), d, 1e3).reshape(nx, ny)


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxdrones as jd  # before JAX starts: its XLA flags
    from jaxdrones import cameras

    env = jd.make("avoid", image_size=(32, 24))
    cfg = env.config
    radius = float(env.task.data(cfg)["collision_radius"][0])
    xs = np.arange(-0.5, cfg.goal_x + 1.0, GRID_M)
    ys = np.arange(-(cfg.field_y + 0.5), cfg.field_y + 0.5 + 1e-9, GRID_M)
    grid_x, grid_y = np.meshgrid(xs, ys, indexing="ij")
    points = jnp.asarray(np.stack([grid_x, grid_y, np.full_like(grid_x, cfg.flight_z)], -1).reshape(-1, 3))
    keys = jax.random.split(jax.random.key(args.seed), args.episodes)
    starts = jax.jit(jax.vmap(env.reset))(keys)
    clear = np.asarray(jax.jit(jax.vmap(lambda task: cameras.distance(task.scene, points)))(starts.task))
    clear = clear.reshape((args.episodes,) + grid_x.shape) - radius

    def cell(p):
        return int(round((p[0] - xs[0]) / GRID_M)), int(round((p[1] - ys[0]) / GRID_M))

    goals, begins = np.asarray(starts.task.target[:, 0]), np.asarray(starts.sim.pos[:, 0])
    fields = np.stack([path_lengths(clear[e], cell(goals[e]), args.margin) for e in range(args.episodes)])
    connected = float(np.mean([fields[e][cell(begins[e])] < 1e3 for e in range(args.episodes)]))
    fields = jnp.asarray(fields, jnp.float32)
    angles = jnp.linspace(0, 2 * jnp.pi, 32, endpoint=False)
    ring = LOOK_M * jnp.stack([jnp.cos(angles), jnp.sin(angles)], -1)

    def episode(start, field, planned: bool):
        def body(state, _):
            pos, goal = state.sim.pos[0], state.task.target[0]
            if planned:
                cand = pos[:2] + ring
                i = jnp.clip(jnp.round((cand[:, 0] - xs[0]) / GRID_M).astype(int), 0, len(xs) - 1)
                j = jnp.clip(jnp.round((cand[:, 1] - ys[0]) / GRID_M).astype(int), 0, len(ys) - 1)
                heading = ring[jnp.argmin(field[i, j])]
            else:
                heading = goal[:2] - pos[:2]
            action = jnp.concatenate([heading, jnp.clip((goal[2:] - pos[2:]) / LOOK_M, -1, 1) * LOOK_M])
            action = action / jnp.max(jnp.abs(action))
            done = state.terminated | state.truncated
            return jax.tree.map(lambda a, b: jnp.where(done, a, b), state, env.step(state, action[None])), None

        return jax.lax.scan(body, start, None, length=env.episode_length)[0].metrics

    out = {"episodes": args.episodes, "margin_m": args.margin, "free_path": connected}
    for name, planned in (("planner", True), ("straight", False)):
        metrics = jax.jit(jax.vmap(lambda s, f, planned=planned: episode(s, f, planned)))(starts, fields)
        out[name] = {
            "success": 1 - float(jnp.mean(metrics["failure"])),
            "collision": float(jnp.mean(metrics["collision"])),
        }
    print(
        f"avoid, {args.episodes} episodes: a free path with {args.margin} m of clearance in "
        f"{100 * connected:.0f} %; the planner reached the goal in {100 * out['planner']['success']:.1f} % "
        f"(collisions {100 * out['planner']['collision']:.1f} %); straight at the goal "
        f"{100 * out['straight']['success']:.1f} % (collisions {100 * out['straight']['collision']:.1f} %)"
    )
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
