"""gym-pybullet-drones' own example scripts, ``pid.py`` and ``learn.py``, run on
`jaxdrones.compat.gym_pybullet_drones` with their imports changed and nothing else, beside the original.

The ports are made here from the original's files: every ``gym_pybullet_drones.`` in an import line becomes
``jaxdrones.compat.gym_pybullet_drones.``, and pid.py's unused ``import pybullet as p`` is dropped where pybullet is
not installed (Python >= 3.12); the number of changed lines is printed. Each run is a fresh process calling the
script's ``run()`` with ``gui=False, plot=False`` (the scripts' own command-line flags), its prints discarded.

    python benchmarks/experiments/gpd_examples.py --original /path/to/gym-pybullet-drones                 # pid.py, both
    python benchmarks/experiments/gpd_examples.py --original DIR --original-python /venv-with-pybullet/bin/python
    python benchmarks/experiments/gpd_examples.py --original DIR --learn                                  # + learn.py

pid.py (3 drones, 12 s at 48 Hz: 576 control steps, each a step of the aviary, three DSL PID calls, three log
entries and a text render): control steps per second over ``run()``, the first call (what a user waits for) and a
second call in the same process; medians over ``--repeats`` processes. The compat package turns on JAX's
persistent compilation cache: ``jaxdrones`` runs with a cache that a previous run filled (a script run again),
``jaxdrones_new_cache`` with an empty one (the first run ever, compiling everything).
learn.py (SB3 PPO on ``HoverAviary``, ONE_D_RPM, stop at a mean evaluation return of 474 or 1e7 steps): the steps
at which training stopped, the final evaluation return and the wall time of ``run()`` (which after training also
evaluates and replays the policy for 10 s of wall-clock time), for both; ``OMP_NUM_THREADS=1``. The original's
interpreter then needs stable-baselines3 and torch too.

The original's interpreter needs pybullet, gymnasium, scipy, pillow, transforms3d and setuptools<81; see
benchmarks/speed/original.py. ``--out FILE`` writes the figures as JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile

_DRIVER = """
import contextlib, io, json, runpy, sys, time
path, calls, folder, kwargs = sys.argv[1], int(sys.argv[2]), sys.argv[3], json.loads(sys.argv[4])
times = []
sink = io.StringIO()
with contextlib.redirect_stdout(sink):
    run = runpy.run_path(path, run_name="example")["run"]
    for _ in range(calls):
        t = time.perf_counter()
        run(gui=False, plot=False, output_folder=folder, **kwargs)
        times.append(time.perf_counter() - t)
out = sink.getvalue()
evals = [float(x) for x in __import__("re").findall(r"Eval num_timesteps=\\d+, episode_reward=([-\\d.]+)", out)]
stop = __import__("re").findall(r"Eval num_timesteps=(\\d+)", out)
print(json.dumps({"times": times, "last_eval_step": int(stop[-1]) if stop else None,
                  "last_eval_return": evals[-1] if evals else None,
                  "stopped": "Stopping training because" in out}))
"""


def port(source: str, dest: str) -> int:
    """Write ``source`` with its imports moved to the compat package; returns the number of lines changed."""
    lines, changed = open(source).read().splitlines(keepends=True), 0
    has_pybullet = importlib.util.find_spec("pybullet") is not None
    out = []
    for line in lines:
        new = line
        if re.match(r"\s*(from|import)\s+gym_pybullet_drones", line):
            new = line.replace("gym_pybullet_drones.", "jaxdrones.compat.gym_pybullet_drones.")
        elif not has_pybullet and re.match(r"\s*import pybullet as p\s*$", line):
            new = ""
        changed += new != line
        out.append(new)
    with open(dest, "w") as f:
        f.write("".join(out))
    return changed


def run_script(
    python: str,
    path: str,
    calls: int,
    extra_path: str | None = None,
    kwargs: dict | None = None,
    env: dict | None = None,
) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        environ = {**os.environ, **(env or {})}
        if extra_path:
            environ["PYTHONPATH"] = os.pathsep.join([extra_path, environ.get("PYTHONPATH", "")])
        done = subprocess.run(
            [python, "-c", _DRIVER, path, str(calls), folder, json.dumps(kwargs or {})],
            capture_output=True,
            text=True,
            env=environ,
            cwd=folder,
        )
    if done.returncode:
        raise SystemExit(f"{path} failed under {python}:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--original", required=True, metavar="DIR", help="a checkout of gym-pybullet-drones")
    parser.add_argument(
        "--original-python", default=sys.executable, help="the interpreter that runs the original (default: this one)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="processes per pid.py measurement (default 3)")
    parser.add_argument("--learn", action="store_true", help="also run the port of learn.py to its stop")
    parser.add_argument("--out", default=None, help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    examples = os.path.join(args.original, "gym_pybullet_drones", "examples")
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        ported = {name: os.path.join(tmp, f"{name}.py") for name in ("pid", "learn")}
        for name, dest in ported.items():
            results[f"{name}_lines_changed"] = port(os.path.join(examples, f"{name}.py"), dest)
            print(f"{name}.py: {results[f'{name}_lines_changed']} lines changed (imports)")
        steps = 12 * 48  # pid.py's defaults: 12 s at 48 Hz
        runs = {"original": [], "jaxdrones": [], "jaxdrones_new_cache": []}
        shared = os.path.join(tmp, "cache")
        run_script(sys.executable, ported["pid"], 1, env={"JAXDRONES_CACHE_DIR": shared})  # fills the cache
        for k in range(args.repeats):  # interleaved, so that all see the same machine load
            runs["original"].append(
                run_script(
                    args.original_python, os.path.join(examples, "pid.py"), 2, extra_path=os.path.abspath(args.original)
                )
            )
            runs["jaxdrones"].append(run_script(sys.executable, ported["pid"], 2, env={"JAXDRONES_CACHE_DIR": shared}))
            runs["jaxdrones_new_cache"].append(
                run_script(
                    sys.executable, ported["pid"], 2, env={"JAXDRONES_CACHE_DIR": os.path.join(tmp, f"empty{k}")}
                )
            )
        for impl, rs in runs.items():
            first = statistics.median(steps / r["times"][0] for r in rs)
            warm = statistics.median(steps / r["times"][1] for r in rs)
            results[f"pid_{impl}"] = {"first_call_steps_per_s": first, "warm_steps_per_s": warm}
            print(
                f"pid.py {impl:>19}: {first:7.0f} control steps/s (first call), {warm:7.0f} (second call); "
                f"median of {len(rs)} processes"
            )
        if args.learn:
            scripts = {
                "jaxdrones": (sys.executable, ported["learn"], None),
                "original": (args.original_python, os.path.join(examples, "learn.py"), os.path.abspath(args.original)),
            }
            for impl, (python, path, extra) in scripts.items():
                r = run_script(python, path, 1, extra_path=extra, kwargs={"local": True}, env={"OMP_NUM_THREADS": "1"})
                results[f"learn_{impl}"] = r
                print(
                    f"learn.py {impl:>9}: stopped={r['stopped']} at {r['last_eval_step']} steps, last evaluation "
                    f"return {r['last_eval_return']}, run() {r['times'][0]:.0f} s"
                )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
    return results


if __name__ == "__main__":
    main()
