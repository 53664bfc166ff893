"""Cost of gradients through rollouts: forward time, gradient time and their ratio, by horizon and worlds.

The work: a rollout of T control steps of W worlds of one Crazyflie (cf2x) at 240 Hz physics and 240 Hz control
(one physics substep per command), drag and ground effect on, starting 5-30 cm above the ground (where ground
effect acts) with RPM commands within 2 % of hover; the loss is the mean over the rollout of the squared distance
to (0, 0, 1) m plus 0.1 × the mean squared velocity. Timed, each as one jitted call:

- ``forward``: the loss;
- ``grad_commands``: the loss and its gradient w.r.t. the RPM commands f[T, W, 1, 4];
- ``grad_initial_state``: the loss and its gradient w.r.t. the initial pos, quat, vel and ang_vel.

``ratio`` is gradient time over forward time: the median over rounds of one call of each (forward and
gradients in turn, so that both see the machine's load of the moment). The same work is run by three callers (the
``caller`` field of each result):

- ``rollout``: ``jaxdrones.rollout``, with ``remat=True`` (its default: the backward pass recomputes each control
  step from its saved input state instead of storing every intermediate) and ``remat=False``;
- ``user_scan``: a user's own ``jax.lax.scan`` over the step that ``jaxdrones.make_step`` returns, stacking the
  positions and velocities;
- ``env_step``: ``jax.lax.scan`` over the ``hover`` env's ``step`` (``jaxdrones.make("hover", ctrl_freq=240,
  drag=True, ground_effect=True)``, the physics above, vmapped over the worlds, started from the same states), the
  action of each step being a linear policy of the observation (fixed small weights) plus a per-step offset, the
  "command" (normalised RPM actions: an offset of 0.4 N(0, 1) is the rollouts' 2 % of hover). What the APG and
  SHAC trainers differentiate; ``grad_policy`` is also timed: the loss and its gradient w.r.t. the policy's
  weights and bias.

Memory is XLA's own count of the temporary buffers of the compiled call (``memory_analysis().temp_size_in_bytes``).

crazyflow 0.4.0 runs the same work in the same run, in its own virtual environment (``benchmarks/.venv-crazyflow``,
created with ``pip install crazyflow==0.4.0`` by `envs.py`'s installer when missing; ``--no-crazyflow`` skips it):
its ``first_principles`` model with ``rotor_vel`` control (RPM commands), its ``Sim`` at 240 Hz stepped by its pure
step function under ``lax.scan``, the same loss, gradients w.r.t. the commands and the initial position and
velocity. Its model has no drag or ground effect.

Usage::

    python benchmarks/gradients/gradients.py                      # writes benchmarks/results/gradients.json
    python benchmarks/gradients/gradients.py --quick              # horizons 10, 100; worlds 1, 1024
    python benchmarks/gradients/gradients.py --horizons 100 --worlds 1024 --no-crazyflow
    python benchmarks/gradients/gradients.py --horizons 100 --worlds 1024 --no-crazyflow --callers default_env
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common.py
from common import RESULTS

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(RESULTS, "gradients.json")
HORIZONS = (10, 100, 1000)
WORLDS = (1, 1024, 16384)
QUICK_HORIZONS, QUICK_WORLDS = (10, 100), (1, 1024)
SIM_FREQ = CTRL_FREQ = 240
TARGET = (0.0, 0.0, 1.0)
CALLERS = ("rollout", "user_scan", "env_step", "default_env", "default_env_crazyflie")
CRAZYFLOW_WORKER = os.path.join(HERE, "_crazyflow_gradients.py")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        allow_abbrev=False, description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--horizons", type=int, nargs="+", help=f"control steps T (default {HORIZONS})")
    parser.add_argument("--worlds", type=int, nargs="+", help=f"worlds W (default {WORLDS})")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds per measurement (median; default 5)")
    parser.add_argument("--quick", action="store_true", help=f"horizons {QUICK_HORIZONS}, worlds {QUICK_WORLDS}")
    parser.add_argument(
        "--crazyflow",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also measure crazyflow 0.4.0 in its own venv (default on)",
    )
    parser.add_argument(
        "--callers", nargs="+", choices=CALLERS, default=list(CALLERS), help="which callers to measure (default: all)"
    )
    parser.add_argument("--out", default=DEFAULT_OUT, help="JSON output path (default: %(default)s)")
    args = parser.parse_args(argv)
    args.horizons = sorted(args.horizons or (QUICK_HORIZONS if args.quick else HORIZONS))
    args.worlds = sorted(args.worlds or (QUICK_WORLDS if args.quick else WORLDS))
    if min(args.horizons + args.worlds) < 1 or args.repeats < 1:
        parser.error("--horizons, --worlds and --repeats must be positive")
    return args


def time_calls(jax, calls: dict, repeats: int) -> dict:
    """Compile ``jax.jit(fn)`` for each ``name: (fn, inputs)`` of ``calls``, then time ``repeats`` rounds of one
    call of each, in turn (to ``block_until_ready``): on a shared machine every call of a round sees the same load,
    so that ratios taken within rounds hold where absolute times drift.

    Returns, per name, seconds (median and all, in round order), compile seconds and XLA's temporary-buffer bytes.
    Needs only the ``jax`` passed in, so crazyflow's worker (another JAX) uses it too.
    """
    compiled, results = {}, {}
    for name, (fn, inputs) in calls.items():
        start = time.perf_counter()
        compiled[name] = jax.jit(fn).lower(*inputs).compile()
        memory = compiled[name].memory_analysis()
        results[name] = {
            "times_s": [],
            "compile_s": time.perf_counter() - start,
            "temp_bytes": getattr(memory, "temp_size_in_bytes", None),
        }
        jax.block_until_ready(compiled[name](*inputs))
    for _ in range(repeats):
        for name, (_, inputs) in calls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(compiled[name](*inputs))
            results[name]["times_s"].append(time.perf_counter() - t0)
    for result in results.values():
        result["s"] = statistics.median(result["times_s"])
    return results


def measure(jax, loss, commands, state, horizon: int, worlds: int, repeats: int, more: dict | None = None) -> dict:
    """Forward, gradient w.r.t. the commands and gradient w.r.t. the initial state of ``loss(commands, state)``,
    and the ``more`` calls (``"grad_<what>": (fn, inputs)``), timed in rounds (`time_calls`). ``ratio_<what>`` is
    the median over rounds of that gradient's time over the forward time of the same round."""
    calls = {
        "forward": (loss, (commands, state)),
        "grad_commands": (jax.value_and_grad(loss, argnums=0), (commands, state)),
        "grad_initial_state": (jax.value_and_grad(loss, argnums=1), (commands, state)),
        **(more or {}),
    }
    results = time_calls(jax, calls, repeats)
    forward = results["forward"]["times_s"]
    ratios = {
        "ratio_" + name.removeprefix("grad_"): statistics.median(
            t / f for t, f in zip(r["times_s"], forward, strict=True)
        )
        for name, r in results.items()
        if name != "forward"
    }
    return {"horizon": horizon, "worlds": worlds, **results, **ratios}


def measure_policy(jax, loss_of, policy, offsets, state, horizon: int, worlds: int, repeats: int) -> dict:
    """`measure` of ``loss_of(policy, offsets, state)`` as a function of the per-step offsets (the commands) and the
    start, with ``grad_policy``: the loss and its gradient w.r.t. the policy's parameters."""
    return measure(
        jax,
        lambda offsets, state: loss_of(policy, offsets, state),
        offsets,
        state,
        horizon,
        worlds,
        repeats,
        more={"grad_policy": (jax.value_and_grad(loss_of), (policy, offsets, state))},
    )


def start_positions(np, worlds: int):
    """f32[W, 1, 3]: x, y in ±1 m, z in 5-30 cm (in ground effect)."""
    rng = np.random.default_rng(0)
    return np.concatenate([rng.uniform(-1, 1, (worlds, 1, 2)), rng.uniform(0.05, 0.3, (worlds, 1, 1))], axis=-1).astype(
        np.float32
    )


def trajectory_loss(jnp, pos, vel):
    """Mean squared distance to `TARGET` plus 0.1 × the mean squared velocity, over steps and worlds."""
    return jnp.mean(jnp.sum((pos - jnp.asarray(TARGET)) ** 2, -1)) + 0.1 * jnp.mean(vel**2)


def jaxdrones_setup(jax, jd, np, horizon: int, worlds: int):
    """The config, params, step, initial state, the differentiated part of it and the RPM commands."""
    jnp = jax.numpy
    config = jd.SimConfig(n_drones=1, sim_freq=SIM_FREQ, ctrl_freq=CTRL_FREQ, drag=True, ground_effect=True)
    params = jd.load_params("cf2x")
    init = jd.init_state(config, pos=jnp.asarray(start_positions(np, worlds)))
    state = {k: getattr(init, k) for k in ("pos", "quat", "vel", "ang_vel")}
    noise = np.random.default_rng(1).standard_normal((horizon, worlds, 1, 4))
    commands = jnp.asarray(float(params.hover_rpm) * (1 + 0.02 * noise), jnp.float32)
    return config, params, jd.make_step(config), init, state, commands, noise


def jaxdrones_case(jax, jd, np, horizon: int, worlds: int, repeats: int, remat: bool) -> dict:
    """``caller: rollout``: `jaxdrones.rollout` with ``remat``."""
    _, params, step, init, state, commands, _ = jaxdrones_setup(jax, jd, np, horizon, worlds)

    def loss(commands, state):
        states = jd.rollout(step, params, init.replace(**state), commands, remat=remat)
        return trajectory_loss(jax.numpy, states.pos, states.vel)

    return {
        "sim": "jaxdrones",
        "caller": "rollout",
        "remat": remat,
        **measure(jax, loss, commands, state, horizon, worlds, repeats),
    }


def user_scan_case(jax, jd, np, horizon: int, worlds: int, repeats: int) -> dict:
    """``caller: user_scan``: a user's own ``lax.scan`` over `jaxdrones.make_step`'s step."""
    _, params, step, init, state, commands, _ = jaxdrones_setup(jax, jd, np, horizon, worlds)

    def loss(commands, state):
        def body(s, rpm):
            s = step(params, s, rpm)
            return s, (s.pos, s.vel)

        _, (pos, vel) = jax.lax.scan(body, init.replace(**state), commands)
        return trajectory_loss(jax.numpy, pos, vel)

    return {
        "sim": "jaxdrones",
        "caller": "user_scan",
        "remat": None,
        **measure(jax, loss, commands, state, horizon, worlds, repeats),
    }


def env_step_case(jax, jd, np, horizon: int, worlds: int, repeats: int) -> dict:
    """``caller: env_step``: ``lax.scan`` over the hover env's vmapped ``step`` with a linear policy (see above)."""
    from jaxdrones.envs.base import world_axes

    jnp = jax.numpy
    _, _, _, init, state, _, noise = jaxdrones_setup(jax, jd, np, horizon, worlds)
    env = jd.make("hover", ctrl_freq=CTRL_FREQ, sim_freq=SIM_FREQ, drag=True, ground_effect=True)
    axes = world_axes(env.shared_params is not None)
    start = jax.vmap(env.reset, out_axes=axes)(jax.random.split(jax.random.key(0), worlds)).replace(sim=init)
    step = jax.vmap(env.step, in_axes=(axes, 0), out_axes=axes)
    offsets = jnp.asarray(0.4 * noise, jnp.float32)  # rpm = hover (1 + 0.05 a): 2 % of hover, as the commands
    weights = np.random.default_rng(2).standard_normal((env.observation_size, env.action_size))
    policy = {"w": jnp.asarray(0.01 * weights, jnp.float32), "b": jnp.zeros(env.action_size, jnp.float32)}

    def loss_of(policy, offsets, state):
        def body(s, offset):
            s = step(s, s.obs @ policy["w"] + policy["b"] + offset)
            return s, (s.sim.pos, s.sim.vel)

        _, (pos, vel) = jax.lax.scan(body, start.replace(sim=init.replace(**state)), offsets)
        return trajectory_loss(jnp, pos, vel)

    result = measure_policy(jax, loss_of, policy, offsets, state, horizon, worlds, repeats)
    return {"sim": "jaxdrones", "caller": "env_step", "remat": None, **result}


def default_env_parts(jax, jd, np, horizon: int, worlds: int, realism: str | None = None) -> dict:
    """What the ``default_env`` callers are built of: ``env`` (``jd.make("hover", realism=realism)``), ``start``
    (its vmapped reset for ``worlds`` worlds), ``step`` and ``env_loss`` (its ``step`` and ``loss`` vmapped over the
    worlds), ``offsets`` f[horizon, W, D, n_act] (0.4 N(0, 1)), ``policy`` (a linear policy's ``w`` f[n_obs, n_act],
    0.01 N(0, 1), and ``b``, zeros) and ``state`` (the start's pos, quat, vel and ang_vel)."""
    from jaxdrones.envs.base import world_axes

    jnp = jax.numpy
    env = jd.make("hover", realism=realism)
    axes = world_axes(env.shared_params is not None)
    start = jax.vmap(env.reset, out_axes=axes)(jax.random.split(jax.random.key(0), worlds))
    rng = np.random.default_rng(2)
    return {
        "env": env,
        "start": start,
        "step": jax.vmap(env.step, in_axes=(axes, 0), out_axes=axes),
        "env_loss": jax.vmap(env.loss, in_axes=(axes,)),
        "offsets": jnp.asarray(0.4 * rng.standard_normal((horizon, worlds, env.n_drones, env.action_size)), env.dtype),
        "policy": {
            "w": jnp.asarray(0.01 * rng.standard_normal((env.observation_size, env.action_size)), env.dtype),
            "b": jnp.zeros(env.action_size, env.dtype),
        },
        "state": {k: getattr(start.sim, k) for k in ("pos", "quat", "vel", "ang_vel")},
    }


def env_scan_loss(jax, parts: dict, action_of):
    """``loss_of(policy, offsets, state)``: the mean over ``lax.scan`` steps of ``parts``' (`default_env_parts`) env
    loss, from its start with ``state`` (pos, quat, vel, ang_vel), each step's action
    ``action_of(policy, obs, offset)``."""
    jnp = jax.numpy
    start, step, env_loss = parts["start"], parts["step"], parts["env_loss"]

    def loss_of(policy, offsets, state):
        def body(s, offset):
            s = step(s, action_of(policy, s.obs, offset))
            return s, jnp.mean(env_loss(s))

        _, losses = jax.lax.scan(body, start.replace(sim=start.sim.replace(**state)), offsets)
        return jnp.mean(losses)

    return loss_of


def linear_tanh_policy(jax, policy, obs, offset):
    """The ``default_env`` callers' action: ``tanh(obs @ w + b + offset)``."""
    return jax.numpy.tanh(obs @ policy["w"] + policy["b"] + offset)


def default_env_setup(jax, jd, np, horizon: int, worlds: int, realism: str | None = None):
    """``(loss_of, policy, offsets, state)`` of the ``default_env`` callers: ``loss_of(policy, offsets, state)`` is
    the env's loss over a ``lax.scan`` of ``horizon`` steps of ``jd.make("hover", realism=realism)``'s vmapped
    ``step`` at its defaults for ``worlds`` worlds, the action a linear tanh policy of the observation plus a
    per-step offset (`linear_tanh_policy`); ``state`` the start's pos, quat, vel and ang_vel (`default_env_parts`)."""
    parts = default_env_parts(jax, jd, np, horizon, worlds, realism)
    loss_of = env_scan_loss(jax, parts, functools.partial(linear_tanh_policy, jax))
    return loss_of, parts["policy"], parts["offsets"], parts["state"]


def default_env_case(jax, jd, np, horizon: int, worlds: int, repeats: int, realism: str | None = None) -> dict:
    """``caller: default_env`` / ``default_env_<realism>``: `default_env_setup`'s loss, timed (see above)."""
    loss_of, policy, offsets, state = default_env_setup(jax, jd, np, horizon, worlds, realism)
    result = measure_policy(jax, loss_of, policy, offsets, state, horizon, worlds, repeats)
    caller = "default_env" if realism is None else f"default_env_{realism}"
    return {"sim": "jaxdrones", "caller": caller, "remat": None, **result}


def run_crazyflow(args) -> tuple[list[dict], dict, str | None]:
    """Run `_crazyflow_gradients.py` in crazyflow's venv (installed by `common.crazyflow_python` when missing)."""
    from common import CRAZYFLOW_VENV, crazyflow_python

    python, setup = crazyflow_python(CRAZYFLOW_VENV)
    if python is None:
        return [], {}, setup
    command = [
        python,
        CRAZYFLOW_WORKER,
        "--horizons",
        *map(str, args.horizons),
        "--worlds",
        *map(str, args.worlds),
        "--repeats",
        str(args.repeats),
    ]
    results, info = [], {"setup": setup}
    with (
        tempfile.TemporaryFile("w+") as err,
        subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err, text=True, cwd=CRAZYFLOW_VENV) as proc,
    ):
        for line in proc.stdout:
            if line.startswith("RESULT "):
                results.append(json.loads(line[7:]))
                print_row(results[-1])
            elif line.startswith("INFO "):
                info.update(json.loads(line[5:]))
        proc.wait()
        err.seek(0)
        stderr = err.read().strip().splitlines()
    error = None if proc.returncode == 0 else f"worker exited {proc.returncode}: " + " | ".join(stderr[-5:])
    return results, info, error


def machine_header(jax, more: str = "") -> tuple[dict, tuple]:
    """Print the run's JAX, backend, CPU, cores, ``XLA_FLAGS`` and load average (then ``more``); return the
    machine's info (`common.machine_info`) and the load average at the start."""
    from common import machine_info

    info = machine_info(jax)
    load_start = os.getloadavg()
    print(
        f"jax {info['jax']} on {info['backend']}, {info['cpu_model']}, {info['cpus_available']} cores, "
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}, load {load_start}{more}",
        flush=True,
    )
    return info, load_start


def print_row(r: dict) -> None:
    mib = (r["grad_commands"]["temp_bytes"] or 0) / 2**20
    caller = r.get("caller", "rollout")
    label = f"{caller} remat={r['remat']}" if caller == "rollout" else caller
    policy = (
        f", grad(policy) {r['grad_policy']['s'] * 1e3:9.2f} ms ({r['ratio_policy']:5.1f}x)"
        if "grad_policy" in r
        else ""
    )
    print(
        f"  {r['sim']:<9} {label:<19} T={r['horizon']:>5} W={r['worlds']:>6}: forward "
        f"{r['forward']['s'] * 1e3:9.2f} ms, grad(commands) {r['grad_commands']['s'] * 1e3:9.2f} ms "
        f"({r['ratio_commands']:5.1f}x, {mib:,.0f} MiB), grad(initial state) "
        f"{r['grad_initial_state']['s'] * 1e3:9.2f} ms ({r['ratio_initial_state']:5.1f}x){policy}",
        flush=True,
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax
    import numpy as np
    from common import write_report

    import jaxdrones as jd

    info, load_start = machine_header(jax)
    results = []
    cases = {
        "rollout": [functools.partial(jaxdrones_case, remat=remat) for remat in (False, True)],
        "user_scan": [user_scan_case],
        "env_step": [env_step_case],
        "default_env": [default_env_case],
        "default_env_crazyflie": [functools.partial(default_env_case, realism="crazyflie")],
    }
    for horizon in args.horizons:
        for worlds in args.worlds:
            for caller in args.callers:
                for case in cases[caller]:
                    results.append(case(jax, jd, np, horizon, worlds, repeats=args.repeats))
                    print_row(results[-1])
    crazyflow = {"requested": args.crazyflow}
    if args.crazyflow:
        cf_results, crazyflow["info"], crazyflow["error"] = run_crazyflow(args)
        results += cf_results
        if crazyflow["error"]:
            print(f"crazyflow: NOT MEASURED: {crazyflow['error']}", flush=True)
    settings = {k: v for k, v in vars(args).items() if k != "out"} | {
        "sim_freq": SIM_FREQ,
        "ctrl_freq": CTRL_FREQ,
        "effects": ["drag", "ground_effect"],
        "model": "cf2x",
    }
    write_report(
        args.out,
        "gradients through rollouts: forward vs gradient time",
        info,
        settings,
        results,
        loadavg_start=load_start,
        crazyflow=crazyflow,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
