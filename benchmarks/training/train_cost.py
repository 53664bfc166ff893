"""What a trained hover policy costs in sequential XLA operations, per trainer and defaults profile.

On a GPU every operation of a compiled program (a fusion, a copy, a library call, a loop's step) is at least one
kernel launch of a few microseconds, run one after the other; a training run whose updates are small is bound by
their number, not by its arithmetic. This script counts them, without a GPU:

1. **Operations per iteration, by phase.** A short run of the trainer (``--count-updates`` updates in one chunk and
   one evaluation, the profile's settings otherwise) is traced with ``jax.profiler``; the operations XLA ran are
   grouped by compiled program (the trace's ``hlo_module``) and divided by the runs of that program. On the CPU the
   operations are XLA:CPU's thunks; on a GPU, the kernels and copies on the device's streams. ``update`` is the
   chunk's operations per update (rollout, gradient or PPO epochs, optimiser); ``rollout`` is a ``lax.scan`` of the
   trainer's rollout length (APG's ``horizon``, PPO's ``unroll_length``) of the same env's auto-resetting step with a
   policy MLP of the trainer's size over its worlds (the resets drawn per window where the config's
   ``starts_per_window`` says so), traced apart (forward only: APG's gradient is in ``update``);
   ``evaluation`` is one evaluation (`jaxdrones.training.run`'s: 256 episodes of the task from random starts).
2. **The run itself.** ``jaxdrones train hover --algo ALGO --defaults PROFILE`` in a subprocess, as a user runs it
   (JAX's compilation cache in its default folder: the first run is cold, a second one warm), from which come the
   iterations (the run's updates), its wall time and phases (``summary.json``), and its verdict.
3. **Sequential operations**: to the end of the run, its iterations × operations per update + its evaluations ×
   operations per evaluation; and to a solved policy, the same up to the run's first evaluation from which on every
   evaluation was solved (< 5 cm with no start crashed; "never" if the run ended unsolved). This is the number to
   drive down; on a GPU each of them costs at least a launch.

The figures of docs/benchmarks.md are from jax 0.10.2, where XLA:CPU's trace shows the operations inside loops; on
jax >= 0.11 it runs an inner loop (the substeps) as one ``call``, so there the looped step counts far fewer
operations than it runs (64 worlds: 157 forward operations per control step, against 600 at 4096 on jax 0.10.2).
Every program is counted with the env's defaults (the physics substeps as a loop: `jaxdrones.SimConfig.
unroll_substeps`); the CPU's count of a program is an upper bound of a GPU's kernels (XLA:GPU fuses more).

Usage::

    python benchmarks/training/train_cost.py                                  # apg, ppo, brax_ppo x cpu, gpu
    python benchmarks/training/train_cost.py --algos apg --profiles gpu --runs 2
    python benchmarks/training/train_cost.py --no-train                       # the counts only
    python benchmarks/training/train_cost.py --algos ppo --profiles gpu --no-train --by-loop   # and by loop (CPU)
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import gzip
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

#: The solved hover of the issue's goal: < 5 cm final distance with no crashed start.
TASK = "hover"


def trace_operations(run, by_name: dict | None = None) -> dict[str, tuple[int, int | None]]:
    """Run ``run()`` under ``jax.profiler`` and return, per compiled program (``hlo_module``), the operations it
    executed in all and in its longest run: ``{module: (operations, operations of the longest run)}``. On the CPU
    the operations are XLA:CPU's thunks, told apart by run (``run_id``; programs of the same name, e.g. brax's
    ``jit__fun``, are then apart too); on a GPU they are the kernels and copies on the device's streams (in CUDA
    graphs or not), and the longest run is None (the trace does not tell the runs apart). ``by_name``, if given, is
    filled with the operations per program and operation name (the HLO instruction's): ``{module: Counter}``."""
    import jax

    options = jax.profiler.ProfileOptions()
    options.python_tracer_level = 0  # Python's calls would fill the trace's buffer before XLA's operations
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir, profiler_options=options)
        try:
            jax.block_until_ready(run())
        finally:
            jax.profiler.stop_trace()
        path = sorted(glob.glob(f"{trace_dir}/**/*.trace.json.gz", recursive=True))[-1]
        events = json.load(gzip.open(path))["traceEvents"]
    names = {
        e["pid"]: e["args"].get("name", "") for e in events if e.get("ph") == "M" and e.get("name") == "process_name"
    }
    devices = {pid for pid, name in names.items() if "/device:GPU" in name or "/device:TPU" in name}
    ops, runs = collections.Counter(), collections.defaultdict(collections.Counter)
    for event in events:
        args = event.get("args") or {}
        module = args.get("hlo_module")
        if event.get("ph") != "X" or not module or "hlo_op" not in args:
            continue
        if devices and event.get("pid") not in devices:
            continue
        ops[module] += 1
        runs[module][args.get("run_id")] += 1
        if by_name is not None:
            by_name.setdefault(module, collections.Counter())[event["name"]] += 1
    return {module: (count, None if devices else max(runs[module].values())) for module, count in ops.items()}


def per_run(counted: tuple[int, int | None], expected: int) -> float:
    """Operations of one run of a program: its longest run on the CPU; where the trace does not tell the runs apart
    (GPU), its operations divided by the ``expected`` runs."""
    ops, longest = counted
    return longest if longest is not None else ops / expected


def profile_config(algo: str, profile: str):
    """The trainer's config and the env's settings of ``jaxdrones train hover --algo ALGO --defaults PROFILE``."""
    from jaxdrones.training import trainers
    from jaxdrones.training.recipes import recipe

    plan = recipe(TASK, profile, algo=algo)
    return trainers.get(algo), plan.config, dict(plan.env)


def iterations(config) -> int:
    """The updates of a run with ``config`` (brax's PPO: its training steps)."""
    if hasattr(config, "updates_per_eval"):
        return config.num_evals * config.updates_per_eval
    return config.total_steps // (config.batch_size * config.unroll_length * config.num_minibatches)


def rollout_length(config) -> int:
    return getattr(config, "horizon", None) or config.unroll_length


def control_step_cost(
    env, n_worlds: int, length: int, hidden=(64, 64), grad: bool = False, timed: int = 5, predrawn: bool = True
) -> dict:
    """Operations and milliseconds per control step of ``n_worlds`` worlds of ``env`` with auto-reset
    (`jaxdrones.wrappers.VmapAutoReset`) and an MLP policy, in a ``lax.scan`` of ``length`` steps: forward, or with
    ``grad`` the value and gradient of APG's loss (`jaxdrones.training.apg`) w.r.t. the policy's parameters.
    ``timed`` calls are timed (median); the operations come from one traced call."""
    import jax
    import jax.numpy as jnp

    from jaxdrones.envs.base import world_axes
    from jaxdrones.training.common import mlp
    from jaxdrones.wrappers import VmapAutoReset

    auto = VmapAutoReset(env)
    loss = jax.vmap(env.loss, in_axes=(world_axes(auto.params_shared),))
    network = mlp(tuple(hidden), env.action_size)

    def window(params, state):
        starts = auto.starts(state) if predrawn else None

        def body(s, _):
            ended, s = auto.step_ended(s, jnp.tanh(network.apply(params, s.obs)), starts)
            return s, jnp.mean(loss(ended))

        state, losses = jax.lax.scan(body, state, None, length=length)
        return jnp.mean(losses), state.obs

    key = jax.random.key(0)
    params = network.init(key, jnp.zeros((env.observation_size,), env.dtype))
    state = jax.jit(auto.reset)(jax.random.split(key, n_worlds))
    fn = jax.jit(jax.value_and_grad(window, has_aux=True) if grad else window)
    jax.block_until_ready(fn(params, state))
    times = []
    for _ in range(timed):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(params, state))
        times.append(time.perf_counter() - t0)
    ops = max(per_run(counted, 1) for counted in trace_operations(lambda: fn(params, state)).values())
    return {"ops": ops / length, "ms": 1e3 * statistics.median(times) / length if times else math.nan}


def count(algo: str, profile: str, updates: int, by_name: dict | None = None) -> dict:
    """Operations per update, per rollout and per evaluation of ``algo`` at ``profile`` (the module doc);
    ``by_name`` as in `trace_operations`."""

    from jaxdrones.envs import make
    from jaxdrones.training.evaluation import eval_program
    from jaxdrones.training.recipes import recipe

    trainer, config, env_options = profile_config(algo, profile)
    env = make(TASK, **env_options)
    train_env = make(TASK, **env_options, **recipe(TASK, profile, algo=algo).train_env)
    if algo == "brax_ppo":
        per_step = config.batch_size * config.unroll_length * config.num_minibatches
        short = dataclasses.replace(config, num_timesteps=updates * per_step, num_evals=2)
    else:
        short = dataclasses.replace(config, num_timesteps=updates * config.steps_per_update, num_evals=1)
    evaluate = eval_program(env, trainer, 256)
    modules = trace_operations(lambda: trainer.train(train_env, short, lambda *_: None, evaluate)[1], by_name)
    # Runs where the trace does not count them (GPU): the evaluation runs once, after the one chunk
    # (`jaxdrones.training.common.run_updates`; brax's PPO: after its one training epoch), and so does the chunk.
    eval_runs = 1
    eval_ops = max((per_run(v, eval_runs) for name, v in modules.items() if "evaluate" in name), default=0.0)
    # The chunk of updates: the program with the most operations other than the evaluation.
    chunk_name, chunk = max(((n, v) for n, v in modules.items() if "evaluate" not in n), key=lambda item: item[1][0])
    per_update = per_run(chunk, 1) / updates

    hidden = getattr(config, "hidden_layer_sizes", None) or config.policy_hidden_layer_sizes
    length = rollout_length(config)
    # brax's PPO resets in the step (the brax adapter's auto-reset); ours as their config says.
    predrawn = getattr(config, "starts_per_window", False)
    rollout_ops = (
        control_step_cost(train_env, config.num_envs, length, hidden, timed=0, predrawn=predrawn)["ops"] * length
    )
    return {
        "algo": algo,
        "profile": profile,
        "worlds": config.num_envs,
        "rollout_length": length,
        "iterations": iterations(config),
        "num_evals": config.num_evals - (algo == "brax_ppo"),
        "ops_rollout": rollout_ops,
        "ops_update": per_update,
        "ops_evaluation": eval_ops,
        "programs": {name: ops for name, (ops, _) in modules.items() if ops > 10},
        "chunk": chunk_name,
        "evaluation_runs": eval_runs,
    }


def train(algo: str, profile: str, out: str, extra: list[str], env: dict | None = None) -> dict:
    """``jaxdrones train hover --algo ALGO --defaults PROFILE`` in a subprocess (its environment ``env``, by default
    this process's); its summary."""
    cmd = [
        sys.executable,
        "-m",
        "jaxdrones.cli",
        "train",
        TASK,
        "--algo",
        algo,
        "--defaults",
        profile,
        "--out",
        out,
        "--overwrite",
        "--no-progress",
        *extra,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    with open(os.path.join(out, "progress.json")) as f:
        history = json.load(f)
    from jaxdrones.envs.registry import get_task

    solved_from = solved_from_eval(history, get_task(summary["task"]))
    chunks = [b["time_s"] - a["time_s"] for a, b in zip(history, history[1:], strict=False)]
    return {
        **summary,
        "solved_from_eval": solved_from,
        "solved_from_share": history[solved_from - 1]["env_steps"] / history[-1]["env_steps"] if solved_from else None,
        "first_chunk_s": history[0]["time_s"],
        "chunk_s": statistics.median(chunks) if chunks else math.nan,
        "verdict": proc.stdout.strip().splitlines()[0],
    }


def solved_from_eval(history: list[dict], task) -> int | None:
    """The first evaluation of ``history`` (a run's ``progress.json``) from which on every evaluation solved ``task``
    (the run's verdict, `jaxdrones.training.evaluation.failed_criteria`: for hover, the distance below its threshold
    with no episode ended early), counted from 1; None if the last did not."""
    from jaxdrones.training.evaluation import failed_criteria

    solved = [not failed_criteria(task, h) for h in history]
    return next((i + 1 for i in range(len(solved)) if all(solved[i:])), None)


def ops_to_solved(row: dict, run: dict) -> float | None:
    """The sequential operations of ``run`` (`train`'s result) up to its first evaluation from which on every
    evaluation was solved: the updates done by then (the run's share of env steps) × operations per update + the
    evaluations up to it × operations per evaluation; None if the run ended unsolved."""
    if run["solved_from_eval"] is None:
        return None
    updates = round(row["iterations"] * run["solved_from_share"])
    return updates * row["ops_update"] + run["solved_from_eval"] * row["ops_evaluation"]


def operations_by_loop(dump_dir: str, module: str, names: collections.Counter) -> list[tuple[int, str]]:
    """The operations of a program's trace (``names``: per HLO instruction, `trace_operations`' ``by_name``) summed
    by the loop that ran them: ``[(operations, loop)]``, most first. A loop is named by the JAX name path of its
    ``while`` and its trip count, inside those of the loops around it (``outer (xN) > inner (xM)``, each inner one
    by what its name adds), read from XLA's optimised HLO of ``module`` in ``dump_dir`` (``XLA_FLAGS=--xla_dump_to=DIR
    --xla_dump_hlo_as_text``); ``"(no loop)"`` outside every loop. The CPU's thunks only: a GPU's kernels are named
    otherwise."""
    import re

    texts = {}
    for path in glob.glob(os.path.join(dump_dir, f"*.{module}.cpu_after_optimizations.txt")):
        with open(path) as f:
            texts[path] = f.read()
    if not texts:
        return []
    # The dump of the compilation that ran: the one holding the most of the traced operations.
    best = max(texts, key=lambda path: sum(n for name, n in names.items() if f"%{name} = " in texts[path]))
    # instruction -> its computation; computation -> (the computation that calls it, its loop's name and trip
    # count if it is a loop's body or condition, else None)
    computation_of, parent = {}, {}
    computation = None
    for line in texts[best].splitlines():
        if head := re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line):
            computation = head[1]
        elif (instruction := re.match(r"^\s+(?:ROOT )?%([\w.\-]+) = ", line)) and computation:
            computation_of[instruction[1]] = computation
            loop = None
            if " while(" in line:
                name = re.search(r'op_name="([^"]*)"', line)
                trips = re.search(r'"known_trip_count":\{"n":"(\d+)"', line)
                loop = (name[1] if name else instruction[1], trips[1] if trips else "?")
            for _, called in re.findall(r"(body|condition|calls|to_apply|\w+_computations?)=\{?%([\w.\-]+)", line):
                parent[called] = (computation, loop)
            for branches in re.findall(r"branch_computations=\{([^}]*)\}", line):
                for called in re.findall(r"%([\w.\-]+)", branches):
                    parent[called] = (computation, None)
    by_loop = collections.Counter()
    for name, n in names.items():
        where, loops = computation_of.get(name), []
        while where in parent:
            where, loop = parent[where]
            if loop:
                loops.insert(0, loop)
        labels = [
            f"{loop[len(outer[0]) :] if outer and loop.startswith(outer[0]) else loop} (x{trips})"
            for outer, (loop, trips) in zip([None, *loops], loops, strict=False)
        ]
        by_loop[" > ".join(labels) or "(no loop)"] += n
    return [(n, loop) for loop, n in by_loop.most_common()]


def print_by_loop(dump_dir: str, by_name: dict, row: dict, updates: int) -> None:
    """Print `operations_by_loop` for ``row``'s chunk (per update) and evaluation (per evaluation)."""
    programs = [(row["chunk"], updates, "update")]
    programs += [(m, row["evaluation_runs"], "evaluation") for m in by_name if "evaluate" in m][:1]
    for module, runs, what in programs:
        print(f"\n{row['algo']} {row['profile']}: operations per {what} ({module}) by the loop that runs them")
        for n, loop in operations_by_loop(dump_dir, module, by_name[module]):
            if n / runs >= 1:
                print(f"{n / runs:10,.0f}  {loop}")


def per_step_table(worlds: list[int]) -> int:
    """Print operations and milliseconds per control step of the default hover env (`control_step_cost`): as the
    trainers stepped it before (the substeps in a loop, the resets computed in each step) and now (the worlds' next
    episodes drawn once per window, the substeps looped or unrolled)."""
    from jaxdrones.envs import make

    print("| worlds | substeps | resets | forward ops | forward ms | gradient ops | gradient ms | gradient ÷ forward |")
    print("|---:|---|---|---:|---:|---:|---:|---:|")
    for w in worlds:
        for substeps, predrawn in (("loop", False), ("loop", True), ("unrolled", True)):
            env = make(TASK, unroll_substeps=substeps == "unrolled")
            fwd, grad = (control_step_cost(env, w, 32, grad=g, predrawn=predrawn) for g in (False, True))
            print(
                f"| {w} | {substeps} | {'drawn per window' if predrawn else 'in each step'} "
                f"| {fwd['ops']:.0f} | {fwd['ms']:.3f} | {grad['ops']:.0f} | {grad['ms']:.3f} | "
                f"{grad['ms'] / fwd['ms']:.2f}x |",
                flush=True,
            )
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--algos", nargs="+", default=["apg", "ppo", "brax_ppo"])
    parser.add_argument("--profiles", nargs="+", default=["cpu", "gpu"])
    parser.add_argument("--count-updates", type=int, default=2, help="updates of the traced short run")
    parser.add_argument("--runs", type=int, default=1, help="training runs per setting (medians of their times)")
    parser.add_argument("--no-train", action="store_true", help="count the operations only")
    parser.add_argument(
        "--per-step",
        type=int,
        nargs="*",
        default=None,
        metavar="W",
        help="only the table of operations and time per control step of the default hover env (32-step windows "
        "with auto-reset and a 64x64 MLP), forward and gradient, substeps looped or unrolled, "
        "resets in each step or drawn per window, at these worlds (default 4096)",
    )
    parser.add_argument(
        "--by-loop",
        action="store_true",
        help="also the operations per update and per evaluation by the loop that runs them (CPU; XLA's optimised "
        "HLO dumped to a temporary folder)",
    )
    parser.add_argument("--json", default=None, help="also write the rows to this file")
    parser.add_argument("--train-args", nargs=argparse.REMAINDER, default=[], help="passed to jaxdrones train")
    args = parser.parse_args(argv)
    environ = dict(os.environ)  # the training runs' environment: without the dump of --by-loop
    dump_dir = tempfile.mkdtemp(prefix="train_cost_hlo_") if args.by_loop else None
    if dump_dir:  # before JAX starts its backend
        dump = f"--xla_dump_to={dump_dir} --xla_dump_hlo_as_text --xla_dump_hlo_module_re=chunk|evaluate|fun"
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {dump}".strip()

    import jax

    from jaxdrones.io.runs import provenance

    info = provenance()
    print(
        f"jax {jax.__version__}, {jax.default_backend()} ({jax.devices()[0].device_kind}), "
        f"{os.cpu_count()} CPUs; {info.get('cpu', '')}"
    )
    if args.per_step is not None:
        return per_step_table(args.per_step or [4096])
    rows = []
    for algo in args.algos:
        for profile in args.profiles:
            by_name = {} if dump_dir else None
            row = count(algo, profile, args.count_updates, by_name)
            row["ops_to_end"] = row["iterations"] * row["ops_update"] + row["num_evals"] * row["ops_evaluation"]
            if dump_dir:
                print_by_loop(dump_dir, by_name, row, args.count_updates)
            if not args.no_train:
                with tempfile.TemporaryDirectory() as tmp:
                    runs = [
                        train(algo, profile, os.path.join(tmp, f"r{i}"), args.train_args, environ)
                        for i in range(args.runs)
                    ]
                row["wall_s"] = [r["wall_time_s"] for r in runs]
                row["train_s"] = statistics.median(r["phases_s"]["train"] for r in runs)
                row["phases_s"] = runs[-1]["phases_s"]
                row["success"] = [r["success"] for r in runs]
                row["final_m"] = [r["success_value"] for r in runs]
                row["terminated"] = [r["eval"]["terminated_rate"] for r in runs]
                row["env_steps"] = runs[-1]["env_steps"]
                row["solved_from_eval"] = [r["solved_from_eval"] for r in runs]
                row["ops_to_solved"] = [ops_to_solved(row, r) for r in runs]
                row["first_chunk_s"] = statistics.median(r["first_chunk_s"] for r in runs)
                row["chunk_s"] = statistics.median(r["chunk_s"] for r in runs)
                row["verdict"] = runs[-1]["verdict"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(
        "\n| trainer | defaults | worlds | iterations | ops/rollout | ops/update | ops/evaluation | evaluations "
        "| sequential ops to the end | wall s (runs) | train s | final m | crashed | solved from evaluation "
        "| sequential ops to a solved policy |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---|---|---|---|")
    for r in rows:
        trained = (
            f"{', '.join(f'{w:.1f}' for w in r['wall_s'])} | {r['train_s']:.1f} | "
            f"{', '.join(f'{v:.4f}' for v in r['final_m'])} | {', '.join(f'{t:.1%}' for t in r['terminated'])} | "
            f"{', '.join('never' if e is None else str(e) for e in r['solved_from_eval'])} | "
            f"{', '.join('never' if n is None else f'{n:,.0f}' for n in r['ops_to_solved'])}"
            if "wall_s" in r
            else "| | | | |"
        )
        print(
            f"| {r['algo']} | {r['profile']} | {r['worlds']} | {r['iterations']} | {r['ops_rollout']:,.0f} | "
            f"{r['ops_update']:,.0f} | {r['ops_evaluation']:,.0f} | {r['num_evals']} | {r['ops_to_end']:,.0f} | "
            f"{trained} |"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    if dump_dir:
        shutil.rmtree(dump_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
