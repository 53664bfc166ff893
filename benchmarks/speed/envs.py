"""Env-steps per second of the jaxdrones gymnasium vector env, the JAX-native env, and crazyflow's vector env.

One env-step is one control step of one world: the hover task at 30 Hz control and 240 Hz physics (8 substeps),
one drone, random actions in [-1, 1]. Three ways of stepping N worlds, side by side in one run:

- ``vector``: ``gymnasium.make_vec("jaxdrones/Hover-v0", num_envs=N, vectorization_mode="vector_entry_point")``,
  one ``step(actions)`` per control step from a Python loop, NumPy actions in (drawn with NumPy before the timed
  loop) and NumPy observations, rewards, flags and infos out; next-step autoreset.
- ``native``: the JAX-native env, ``VmapAutoReset(jd.make("hover", ctrl_freq=30))`` (all worlds stepped in one
  vmapped call, only the finished ones reset) under ``jit``: one jitted call runs ``lax.scan`` over K control
  steps, the random actions drawn with NumPy and put on the device before the timed loop. Compile time is measured
  separately (``compile_s``) and is not in the rate.
- ``crazyflow``: crazyflow 0.4.0's ``gymnasium.make_vec("DroneReachPos-v0", num_envs=N, freq=30)`` (attitude
  control, its ``so_rpy`` model, physics fixed at 500 Hz by its env class, so 16 substeps per 30 Hz step), wrapped
  in its ``NormalizeActions`` (actions in [-1, 1]) and gymnasium's ``JaxToNumpy`` (NumPy in and out), stepped by
  the same timing loop as ``vector``. It runs in its own virtual environment (``benchmarks/.venv-crazyflow``),
  which this script creates with ``pip install crazyflow==0.4.0`` when it is missing (``--no-crazyflow`` skips
  it); if that fails, the output and the JSON say why and the jaxdrones figures are still reported.

Every measurement is warmed up (its first call, which compiles, is timed on its own), then timed ``--repeats``
times over ``--steps`` control steps; the table gives the median rate (the JSON also the best, the CPU time over
wall time, and the 1-minute load average, since the timings are wall-clock on a possibly shared machine).

``--devices 2`` shards the JAX-native env's worlds over two CPU devices, one per core (the vector envs use one).

Usage::

    python benchmarks/speed/envs.py                 # writes benchmarks/results/envs.json
    python benchmarks/speed/envs.py --quick         # sizes 1 and 1024, fewer steps and repeats
    python benchmarks/speed/envs.py --sizes 4096 --no-crazyflow
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import CRAZYFLOW, CRAZYFLOW_VENV, RESULTS, configure_devices, crazyflow_python, machine_info, write_report

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(RESULTS, "envs.json")
SIZES = (1, 64, 1024, 4096)
#: The JAX-native env also runs at these sizes by default.
NATIVE_EXTRA = (16384,)
QUICK_SIZES = (1, 1024)
CTRL_FREQ = 30
CRAZYFLOW_WORKER = os.path.join(HERE, "_crazyflow_worker.py")
#: Aim for timed runs of about this many env-steps (fewer when --quick), within [MIN_STEPS, MAX_STEPS] steps.
TARGET_ENV_STEPS = 400_000
MIN_STEPS, MAX_STEPS = 20, 1000


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        help=f"numbers of worlds (default {SIZES}; the JAX-native env also {NATIVE_EXTRA})",
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help=f"control steps per timed run (default: about {TARGET_ENV_STEPS:.0e} env-steps, "
        f"{MIN_STEPS} to {MAX_STEPS} steps)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per measurement (default 5; 3 quick)")
    parser.add_argument("--quick", action="store_true", help=f"sizes {QUICK_SIZES}, shorter runs, 3 repeats")
    parser.add_argument(
        "--crazyflow",
        action=argparse.BooleanOptionalAction,
        default=True,
        help=f"also measure {CRAZYFLOW} (installed into {os.path.relpath(CRAZYFLOW_VENV)} when missing; default on)",
    )
    parser.add_argument("--crazyflow-venv", default=CRAZYFLOW_VENV, help="its virtual environment (%(default)s)")
    parser.add_argument(
        "--devices",
        type=int,
        default=1,
        help="CPU devices for the JAX-native env, its worlds sharded over them when their number "
        "divides evenly (more than 1 sets XLA_FLAGS before jax is imported; the vector envs "
        "use one device); default 1",
    )
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output path (default: %(default)s)")
    args = parser.parse_args(argv)
    explicit_sizes = args.sizes is not None
    args.sizes = sorted(set(args.sizes or (QUICK_SIZES if args.quick else SIZES)))
    args.native_sizes = args.sizes if explicit_sizes or args.quick else sorted(set(args.sizes) | set(NATIVE_EXTRA))
    args.repeats = args.repeats or (3 if args.quick else 5)
    args.target = TARGET_ENV_STEPS // (8 if args.quick else 1)
    if min(args.sizes) < 1 or (args.steps is not None and args.steps < 1) or args.repeats < 1 or args.devices < 1:
        parser.error("--sizes, --steps, --repeats and --devices must be positive")
    return args


def steps_for(n: int, steps: int | None, target: int) -> int:
    """Control steps per timed run at ``n`` worlds: ``steps`` if given, else about ``target`` env-steps."""
    return steps or int(np.clip(target // n, MIN_STEPS, MAX_STEPS))


def time_vector_env(env, n: int, steps: int, repeats: int, seed: int = 0) -> dict:
    """Env-steps/s of a gymnasium ``VectorEnv`` of ``n`` worlds with actions in [-1, 1].

    The actions are drawn with NumPy before the clock starts, ``steps`` arrays f32[n, ...]; each timed run is a
    Python loop of ``steps`` ``env.step`` calls. The first ``reset`` + ``step`` (which compile) are timed on their
    own as ``first_call_s``, then one untimed run warms up. Used for crazyflow too (`_crazyflow_worker.py`), so
    this function needs only NumPy.
    """
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (steps, n) + env.single_action_space.shape).astype(np.float32)
    start = time.perf_counter()
    env.reset(seed=seed)
    out = env.step(actions[0])
    first_call_s = time.perf_counter() - start

    def run():
        for action in actions:
            result = env.step(action)
        return result

    run()
    times, cpu = [], []
    for _ in range(repeats):
        wall, proc = time.perf_counter(), time.process_time()
        out = run()
        times.append(time.perf_counter() - wall)
        cpu.append((time.process_time() - proc) / times[-1])
    obs = out[0]
    return {
        "worlds": n,
        "steps": steps,
        "first_call_s": first_call_s,
        **rates(n * steps, times),
        "cpu_util": statistics.median(cpu),
        "loadavg_1min": os.getloadavg()[0],
        "obs_types": sorted({type(v).__name__ for v in (obs.values() if isinstance(obs, dict) else [obs])}),
        "reward_type": type(out[1]).__name__,
    }


def rates(env_steps: int, times: list[float]) -> dict:
    return {
        "env_steps_per_run": env_steps,
        "times_s": times,
        "median_env_steps_per_s": env_steps / statistics.median(times),
        "best_env_steps_per_s": env_steps / min(times),
    }


def bench_vector(gymnasium, n: int, args) -> dict:
    env = gymnasium.make_vec(
        "jaxdrones/Hover-v0", num_envs=n, vectorization_mode="vector_entry_point", ctrl_freq=CTRL_FREQ
    )
    try:
        cfg = env.unwrapped.env.config
        result = time_vector_env(env, n, steps_for(n, args.steps, args.target), args.repeats)
    finally:
        env.close()
    return {
        "env": "vector",
        **result,
        "sim_freq": cfg.sim.sim_freq,
        "ctrl_freq": cfg.sim.ctrl_freq,
        "substeps": cfg.sim.sim_freq // cfg.sim.ctrl_freq,
        "obs_type": cfg.obs_type,
        "action_type": cfg.action_type,
    }


def bench_native(jax, jd, n: int, args) -> dict:
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrones.wrappers import VmapAutoReset

    env = jd.make("hover", ctrl_freq=CTRL_FREQ)
    auto = VmapAutoReset(env)
    steps = steps_for(n, args.steps, args.target)
    # Random actions drawn before the clock starts, as for the vector envs.
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, (steps, n, env.n_drones, env.action_size)).astype(np.float32)

    def rollout(state, actions):
        return jax.lax.scan(lambda s, a: (auto.step(s, a), None), state, actions)[0]

    state = jax.jit(auto.reset)(jax.random.split(jax.random.key(0), n))
    devices = jax.devices()[: max(k for k in range(1, args.devices + 1) if n % k == 0)]
    if len(devices) > 1:  # each device steps (and resets) its own slice of the worlds
        mesh = Mesh(np.array(devices), ("worlds",))
        state = jd.sim.shard_worlds(state, devices=devices)
        actions = jax.device_put(actions, NamedSharding(mesh, P(None, "worlds")))
        rollout = jax.shard_map(rollout, mesh=mesh, in_specs=(P("worlds"), P(None, "worlds")), out_specs=P("worlds"))
    else:
        actions = jax.device_put(actions)  # on the device before the clock starts: no host copy in the timed call
    start = time.perf_counter()
    compiled = jax.jit(rollout, donate_argnums=0).lower(state, actions).compile()
    compile_s = time.perf_counter() - start
    state = jax.block_until_ready(compiled(state, actions))  # warm-up
    times, cpu = [], []
    for _ in range(args.repeats):
        wall, proc = time.perf_counter(), time.process_time()
        state = jax.block_until_ready(compiled(state, actions))
        times.append(time.perf_counter() - wall)
        cpu.append((time.process_time() - proc) / times[-1])
    return {
        "env": "native",
        "worlds": n,
        "devices": len(devices),
        "steps": steps,
        "compile_s": compile_s,
        **rates(n * steps, times),
        "cpu_util": statistics.median(cpu),
        "loadavg_1min": os.getloadavg()[0],
        "sim_freq": env.config.sim.sim_freq,
        "ctrl_freq": env.config.sim.ctrl_freq,
        "substeps": env.config.sim.n_substeps,
        "obs_type": env.config.obs_type,
        "action_type": env.config.action_type,
        "obs_size": env.observation_size,
        "state_bytes_per_world": sum(x.nbytes for x in jax.tree.leaves(state) if hasattr(x, "nbytes")) / n,
    }


# -- crazyflow -----------------------------------------------------------------------------------------------------


def bench_crazyflow(python: str, n: int, args) -> tuple[dict | None, dict, str | None]:
    """Run `_crazyflow_worker.py` at ``n`` worlds in crazyflow's venv; returns (result, its setup, error or None)."""
    command = [
        python,
        CRAZYFLOW_WORKER,
        "--sizes",
        str(n),
        "--repeats",
        str(args.repeats),
        "--target",
        str(args.target),
        "--ctrl-freq",
        str(CTRL_FREQ),
    ]
    if args.steps:
        command += ["--steps", str(args.steps)]
    result, info = None, {}
    # stderr to a file (a full pipe would block the worker); run in the venv's folder, since MuJoCo writes
    # MUJOCO_LOG.TXT into the working directory.
    with (
        tempfile.TemporaryFile("w+") as err,
        subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err, text=True, cwd=args.crazyflow_venv) as proc,
    ):
        for line in proc.stdout:
            if line.startswith("RESULT "):
                result = json.loads(line[7:])
            elif line.startswith("INFO "):
                info = json.loads(line[5:])
        proc.wait()
        err.seek(0)
        stderr = err.read().strip().splitlines()
    if proc.returncode != 0 or result is None:
        return result, info, f"crazyflow worker exited {proc.returncode}: " + " | ".join(stderr[-5:])
    return result, info, None


# -- report --------------------------------------------------------------------------------------------------------

LABELS = {"vector": "jaxdrones vector env", "native": "jaxdrones JAX-native", "crazyflow": "crazyflow vector env"}


def print_row(r: dict) -> None:
    first = f"compile {r['compile_s']:.1f} s" if "compile_s" in r else f"first call {r['first_call_s']:.1f} s"
    print(
        f"  {LABELS[r['env']]:<22} {r['worlds']:>6} worlds: {r['median_env_steps_per_s']:>13,.0f} env-steps/s "
        f"median (best {r['best_env_steps_per_s']:,.0f}), {r['steps']} steps x {len(r['times_s'])}, {first}, "
        f"cpu {r['cpu_util']:.2f}, load {r['loadavg_1min']:.2f}",
        flush=True,
    )


def print_table(results: list[dict], crazyflow_note: str) -> None:
    by = {(r["env"], r["worlds"]): r for r in results}
    sizes = sorted({r["worlds"] for r in results})
    ours = next((r for r in results if "obs_type" in r), {})
    print(
        f"\nmedian env-steps/s (hover, {CTRL_FREQ} Hz control, {ours.get('action_type')} actions drawn at random, "
        f"{ours.get('obs_type')} observations)"
    )
    print(f"{'worlds':>7} " + " ".join(f"{LABELS[e]:>22}" for e in LABELS))
    for n in sizes:
        cells = [f"{by[(e, n)]['median_env_steps_per_s']:>22,.0f}" if (e, n) in by else f"{'-':>22}" for e in LABELS]
        print(f"{n:>7} " + " ".join(cells))
    print("best of the timed runs:")
    for n in sizes:
        cells = [f"{by[(e, n)]['best_env_steps_per_s']:>22,.0f}" if (e, n) in by else f"{'-':>22}" for e in LABELS]
        print(f"{n:>7} " + " ".join(cells))
    print(f"crazyflow: {crazyflow_note}")


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.devices > 1:
        configure_devices(args.devices)
    import gymnasium
    import jax

    import jaxdrones as jd

    info = machine_info(jax)
    load_start = os.getloadavg()
    print(
        f"jax {info['jax']} on {info['backend']} (devices: {len(jax.devices())}), {info['cpu_model']}, "
        f"{info['cpus_available']} cores, load {load_start}"
    )
    crazyflow = {
        "requested": args.crazyflow,
        "requirement": CRAZYFLOW,
        "venv": args.crazyflow_venv,
        "measured": False,
        "error": None,
    }
    python = None
    if args.crazyflow:
        python, crazyflow["setup"] = crazyflow_python(args.crazyflow_venv)
        print(f"crazyflow: {crazyflow['setup']}", flush=True)
        if python is None:
            crazyflow["error"] = crazyflow["setup"]
    # Size by size, the three side by side, so that each comparison sees about the same machine load.
    results = []
    for n in sorted(set(args.sizes) | set(args.native_sizes)):
        if n in args.sizes:
            results.append(bench_vector(gymnasium, n, args))
            print_row(results[-1])
        if n in args.native_sizes:
            results.append(bench_native(jax, jd, n, args))
            print_row(results[-1])
        if python is not None and n in args.sizes and crazyflow["error"] is None:
            result, crazyflow["setup_in_worker"], crazyflow["error"] = bench_crazyflow(python, n, args)
            if result is not None:
                results.append(result)
                print_row(result)
            if crazyflow["error"]:
                print(f"crazyflow: {crazyflow['error']}", flush=True)
    crazyflow["measured"] = any(r["env"] == "crazyflow" for r in results)
    setup = crazyflow.get("setup_in_worker", {})
    if not args.crazyflow:
        note = "skipped (--no-crazyflow)"
    elif crazyflow["error"]:
        note = f"NOT MEASURED{' at every size' if crazyflow['measured'] else ''}: {crazyflow['error']}"
    else:
        note = (
            f"{setup.get('env_id')} (crazyflow {setup.get('crazyflow')}, jax {setup.get('jax')}), "
            f"{setup.get('control')} control, {setup.get('dynamics')} model, {setup.get('sim_freq')} Hz physics: "
            f"{setup.get('substeps')} substeps per step"
        )

    print_table(results, note)
    settings = {k: v for k, v in vars(args).items() if k != "out"} | {"ctrl_freq": CTRL_FREQ, "task": "hover"}
    write_report(
        args.out,
        "jaxdrones env-steps per second: vector env, JAX-native env, crazyflow",
        info,
        settings,
        results,
        loadavg_start=load_start,
        crazyflow=crazyflow,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
