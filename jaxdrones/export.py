"""A trained policy as one dependency-free C file, for a microcontroller (a Crazyflie's STM32F405: 1 MB flash,
192 KB RAM) or any C program.

`export` writes the MLP of a policy saved by ``jaxdrones train`` (``policy.pkl``) as float32 weight arrays and one
function ``void NAME(const float obs[N_OBS], float action[N_ACT])``. The header comment states the observation's
layout (entry by entry, with units and frames), the clip the env applies to it, and how the action becomes motor
commands. The function clips the observation to the env's box, as the env does, then runs the network: tanh hidden
layers and a tanh output (the policies of ``apg`` and ``shac``, `jaxdrones.training.common.mlp`). It needs only
``<math.h>`` (``tanhf``); ``tests/test_export.py`` compiles it with the system's C compiler and compares it with the
JAX policy. The same network is also written as an ONNX model (`onnx_model`, with the ``onnx`` package: the
``export`` extra), for ONNX runtimes and converters to microcontroller toolchains (e.g. STM32Cube.AI).

Policies of the other trainers (brax's PPO with its observation normaliser, MAPPO, camera policies) are refused with
a `ValueError` naming the ones supported.
"""

from __future__ import annotations

import os
import re
import textwrap
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import onnx

    from jaxdrones.envs.env import TaskEnv

#: The trainers whose saved policy `export` writes: an MLP with tanh hidden layers and a tanh output.
SUPPORTED = ("apg", "shac")

#: Entry labels of the state observation types (`jaxdrones.envs.observations`), one per entry.
_KIN = [
    "x (m, world)",
    "y (m, world)",
    "z (m, world)",
    "roll (rad, PyBullet Euler)",
    "pitch (rad)",
    "yaw (rad)",
    "vx (m/s, world)",
    "vy (m/s, world)",
    "vz (m/s, world)",
    "wx (rad/s, body)",
    "wy (rad/s, body)",
    "wz (rad/s, body)",
]
_ROTMAT = [f"R{i}{j} (rotation body->world, row-major)" for i in range(3) for j in range(3)]
_KIN_NORM = [
    "x / 15 m",
    "y / 15 m",
    "z / 5 m",
    "roll / pi",
    "pitch / pi",
    "yaw / pi",
    "vx / 3 m/s",
    "vy / 3 m/s",
    "vz / 1 m/s",
    "body rate unit vector x",
    "body rate unit vector y",
    "body rate unit vector z",
]
_BASE_LABELS = {"kin": _KIN, "kin_rotmat": _KIN + _ROTMAT, "kin_norm": _KIN_NORM}


def load_payload(run: str | os.PathLike) -> dict:
    """The saved policy of a run folder (or a ``policy.pkl``): `jaxdrones.training.checkpoint.read_payload`'s.

    Raises:
        ValueError: no policy file there, or not one of jaxdrones.
    """
    from jaxdrones.training.checkpoint import read_payload

    return read_payload(run)[1]


def mlp_layers(payload: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (kernel f32[in, out], bias f32[out]) of each layer of a saved MLP policy, input first.

    Raises:
        ValueError: a policy of a trainer not in `SUPPORTED`, or parameters that are not flax ``Dense_0 ...``.
    """
    if payload["algo"] not in SUPPORTED:
        raise ValueError(
            f"export: policies of {payload['algo']!r} are not supported yet; it writes those of "
            f"{SUPPORTED} (an MLP with tanh layers)"
        )
    params = payload["params"].get("params", payload["params"])
    names = sorted((k for k in params if re.fullmatch(r"Dense_\d+", k)), key=lambda k: int(k.split("_")[1]))
    if not names or len(names) != len(params):
        raise ValueError(f"export: expected flax Dense_0 ... Dense_n parameters, got {sorted(params)}")
    layers = [(np.asarray(params[k]["kernel"], np.float32), np.asarray(params[k]["bias"], np.float32)) for k in names]
    for (w, b), (w_next, _) in zip(layers, layers[1:] + [(None, None)], strict=True):
        if w.ndim != 2 or b.shape != (w.shape[1],) or (w_next is not None and w_next.shape[0] != w.shape[1]):
            raise ValueError("export: the layers' shapes do not chain")
    return layers


def _layout(env) -> dict[str, int]:
    """Entries per drone of each part of the observation, in its order: the observation type's own (``base``), the
    action buffer (``buffer``), the task's (``task``), the error integral (``integral``)."""
    obs_type = env.obs_type
    buffer = obs_type.buffer_len * obs_type.action_size
    return {"base": obs_type.size - buffer, "buffer": buffer, "task": env.task.obs_size, "integral": env.integral_size}


#: What `jaxdrones.envs.task.Task.tracking_error` is, per task (default: the reference position's error).
_ERRORS = {"velocity": "commanded velocity - measured velocity (m/s, world)"}
_POSITION_ERROR = "reference position - measured position (m, world; hover: the target - x, y, z)"


def _obs_labels(env) -> list[str]:
    obs_type, parts = env.obs_type, _layout(env)
    base = _BASE_LABELS.get(obs_type.name)
    if base is None or len(base) != parts["base"]:
        base = [f"{obs_type.name} entry {i} (jaxdrones.envs.observations)" for i in range(parts["base"])]
    buffer = [
        f"action buffer: action {-(obs_type.buffer_len - k)} step(s) ago, entry {j}"
        for k in range(obs_type.buffer_len)
        for j in range(obs_type.action_size)
    ]
    task = [f"task observation {i} ({env.task.name}: jaxdrones.envs.tasks)" for i in range(env.task.obs_size)]
    error = _ERRORS.get(env.task.name, _POSITION_ERROR)
    integral = [f"error integral {axis}: sum of ({error}) / ctrl_freq, clipped" for axis in "xyz"][: parts["integral"]]
    return base + buffer + task + integral


def _action_text(env) -> str:
    from jaxdrones.envs import actions

    name = env.action_type.name
    rows = [line for line in actions.__doc__.splitlines() if line.startswith(f"``{name}``")]
    mapping = " ".join(rows[0].split()[2:]) if rows else f"see jaxdrones.envs.actions ({name})"
    hover = float(np.asarray(env.params.hover_rpm).reshape(-1)[0])
    return (
        f"action_type {name!r}, each entry in [-1, 1]: {mapping}. Model {env.config.model!r}: hover_rpm = "
        f"{hover:.2f} RPM, motor order as in its URDF (docs/physics.md)."
    )


def _array(name: str, values: np.ndarray) -> str:
    flat = np.asarray(values, np.float32).reshape(-1)
    body = ",\n".join(
        "  "
        + ", ".join(
            f"{v!r}f" if np.isfinite(v) else ("3.4e38f" if v > 0 else "-3.4e38f") for v in map(float, flat[i : i + 8])
        )
        for i in range(0, flat.size, 8)
    )
    return f"static const float {name}[{flat.size}] = {{\n{body}\n}};\n"


def _policy_env(payload: dict):
    """(layers, env) of a saved policy, checked: a single-drone state env whose sizes the network maps."""
    from jaxdrones.envs import make

    layers = mlp_layers(payload)
    env = make(payload["env_name"], **payload["env_overrides"])
    if env.n_drones != 1 or env.config.vision:
        raise ValueError(
            "export: single-drone state policies only (this one flies "
            f"{env.n_drones} drones{' with cameras' if env.config.vision else ''})"
        )
    n_obs, n_act = layers[0][0].shape[0], layers[-1][0].shape[1]
    if (n_obs, n_act) != (env.observation_size, env.action_size):
        raise ValueError(
            f"export: the network maps {n_obs} -> {n_act}, the env {env.observation_size} -> {env.action_size}"
        )
    return layers, env


def sizes_of(layers: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict:
    """``{"n_obs", "n_act", "weight_bytes", "multiply_adds"}`` of an exported network (the bytes count the weights,
    the biases and the observation box's two bounds, float32)."""
    n_obs, n_act = layers[0][0].shape[0], layers[-1][0].shape[1]
    return {
        "n_obs": n_obs,
        "n_act": n_act,
        "weight_bytes": 4 * (sum(w.size + b.size for w, b in layers) + 2 * n_obs),
        "multiply_adds": sum(w.size for w, _ in layers),
    }


def describe(payload: dict, env: TaskEnv, layers: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[str]:
    """What an exported policy computes and expects, as lines of text: its origin, its layers and sizes, the
    observation entry by entry (units, frames, the clip) and the action's mapping to motor commands."""
    sizes = sizes_of(layers)
    return [
        f"A policy trained by jaxdrones ({payload['algo']}) on the task {payload['env_name']!r} with options "
        f"{payload['env_overrides'] or '(defaults)'}, exported by `jaxdrones export`.",
        f"{len(layers)} dense layers {' -> '.join(str(w.shape[0]) for w, _ in layers)} -> {sizes['n_act']}, tanh "
        f"after each; {sizes['multiply_adds']} multiply-adds per call; {sizes['weight_bytes']} bytes of float32 "
        "constants.",
        f"Observation (one drone, float32, control rate {env.config.ctrl_freq} Hz; clipped to the env's box, as the "
        "env does):",
        *[f"  [{i:2d}] {label}" for i, label in enumerate(_obs_labels(env))],
        *textwrap.wrap(f"Action: {_action_text(env)}", 110, subsequent_indent="  "),
    ]


def c_source(payload: dict, name: str = "jaxdrones_policy") -> tuple[str, dict]:
    """The C file of a saved policy and its sizes (`sizes_of`): ``(source, sizes)``.

    Raises:
        ValueError: an unsupported policy (see `mlp_layers`), a multi-drone or camera env, or a ``name`` that is not
            a C identifier.
    """
    if not re.fullmatch(r"[A-Za-z_]\w*", name):
        raise ValueError(f"export: the function name must be a C identifier, got {name!r}")
    layers, env = _policy_env(payload)
    sizes = sizes_of(layers)
    n_obs, n_act = sizes["n_obs"], sizes["n_act"]
    from jaxdrones.envs.env import ERROR_INTEGRAL_BOUND

    low, high = (b[0] for b in env.observation_bounds())
    width = max(w.shape[1] for w, _ in layers)
    upper = name.upper()
    parts = _layout(env)
    lines = [
        f"/* {name}: void {name}(const float obs[{n_obs}], float action[{n_act}]); needs <math.h> (tanhf) only.",
        f" * The observation is clipped to {name}_obs_low/high before the network.",
        " *",
        f" * With its memory, at every control step ({env.config.ctrl_freq} Hz; {name}_reset at an episode's start):",
        f" *   void {name}_step({name}_memory *m, const float state[{upper}_N_STATE], const float error[3],",
        f" *                    float action[{n_act}]);",
        f" * state: the observation without its memory: entries 0-{parts['base'] - 1} below"
        + (f", then the task's {parts['task']}" if parts["task"] else "")
        + ". It assembles the observation below:",
        f" * the last {env.obs_type.buffer_len} actions it returned (oldest first; zeros after {name}_reset)"
        + (
            f", and the error integral, m->integral += error / {env.config.ctrl_freq} clipped to "
            f"+-{ERROR_INTEGRAL_BOUND:g},"
            if parts["integral"]
            else ","
        ),
        " * error: "
        + (
            _ERRORS.get(env.task.name, _POSITION_ERROR) + ", from the same measurements as state."
            if parts["integral"]
            else "unused (no error integral in this observation; may be NULL)."
        ),
        " *",
        *[f" * {line}".rstrip() for line in describe(payload, env, layers)],
        " */",
        "#include <math.h>",
        "",
        f"#define {upper}_N_OBS {n_obs}",
        f"#define {upper}_N_ACT {n_act}",
        "",
        _array(f"{name}_obs_low", low),
        _array(f"{name}_obs_high", high),
    ]
    for k, (w, b) in enumerate(layers):
        lines += [_array(f"{name}_w{k}", w.T), _array(f"{name}_b{k}", b)]  # row per output: a contiguous dot
    lines += [
        f"static void {name}_dense(const float *w, const float *b, const float *x, int n_in, int n_out, float *y)",
        "{",
        "  for (int o = 0; o < n_out; ++o) {",
        "    float s = b[o];",
        "    for (int i = 0; i < n_in; ++i) s += w[o * n_in + i] * x[i];",
        "    y[o] = tanhf(s);",
        "  }",
        "}",
        "",
        f"void {name}(const float obs[{n_obs}], float action[{n_act}])",
        "{",
        f"  float a[{max(width, n_obs)}], h[{width}];",
        f"  for (int i = 0; i < {n_obs}; ++i) {{",
        "    float v = obs[i];",
        f"    a[i] = v < {name}_obs_low[i] ? {name}_obs_low[i] : (v > {name}_obs_high[i] ? {name}_obs_high[i] : v);",
        "  }",
    ]
    src = "a"
    for k, (w, _) in enumerate(layers):
        dst = "action" if k == len(layers) - 1 else ("h" if src == "a" else "a")
        lines.append(f"  {name}_dense({name}_w{k}, {name}_b{k}, {src}, {w.shape[0]}, {w.shape[1]}, {dst});")
        src = dst
    lines += ["}", "", *_memory_source(env, name, n_act)]
    return "\n".join(lines), sizes


def _memory_source(env, name: str, n_act: int) -> list[str]:
    """C of ``NAME_step``: the policy with the memory the observation holds (action buffer, error integral)."""
    from jaxdrones.envs.env import ERROR_INTEGRAL_BOUND

    parts, upper = _layout(env), name.upper()
    n_state, n_hist = parts["base"] + parts["task"], parts["buffer"]
    lines = [
        f"#define {upper}_N_STATE {n_state}",
        f"#define {upper}_N_HISTORY {env.obs_type.buffer_len}",
        f"#define {upper}_CTRL_FREQ {env.config.ctrl_freq}",
        "",
        f"typedef struct {{ float actions[{max(n_hist, 1)}]; float integral[3]; }} {name}_memory;",
        "",
        f"void {name}_reset({name}_memory *m)",
        "{",
        f"  for (int i = 0; i < {max(n_hist, 1)}; ++i) m->actions[i] = 0.0f;",
        "  for (int i = 0; i < 3; ++i) m->integral[i] = 0.0f;",
        "}",
        "",
        f"void {name}_step({name}_memory *m, const float state[{max(n_state, 1)}], const float error[3], "
        f"float action[{n_act}])",
        "{",
        f"  float obs[{upper}_N_OBS];",
        "  int j = 0;",
        f"  for (int i = 0; i < {parts['base']}; ++i) obs[j++] = state[i];",
        f"  for (int i = 0; i < {n_hist}; ++i) obs[j++] = m->actions[i];",
        f"  for (int i = 0; i < {parts['task']}; ++i) obs[j++] = state[{parts['base']} + i];",
    ]
    if parts["integral"]:
        bound = f"{float(ERROR_INTEGRAL_BOUND)!r}f"
        lines += [
            "  for (int i = 0; i < 3; ++i) {",
            f"    float v = m->integral[i] + error[i] / {float(env.config.ctrl_freq)!r}f;",
            f"    v = v < -{bound} ? -{bound} : (v > {bound} ? {bound} : v);",
            "    m->integral[i] = v;",
            "    obs[j++] = v;",
            "  }",
        ]
    else:
        lines.append("  (void)error;")
    lines.append(f"  {name}(obs, action);")
    if n_hist:
        lines += [
            f"  for (int i = 0; i < {n_hist - n_act}; ++i) m->actions[i] = m->actions[i + {n_act}];",
            f"  for (int i = 0; i < {n_act}; ++i) m->actions[{n_hist - n_act} + i] = action[i];",
        ]
    return [*lines, "}", ""]


def onnx_model(payload: dict) -> onnx.ModelProto:
    """The ONNX model (``onnx.ModelProto``, opset 17) of a saved policy: input ``obs`` f32[N, n_obs], output
    ``action`` f32[N, n_act]; Max/Min with the env's box, then Gemm and Tanh per layer. `describe`'s text is its
    ``doc_string``. Needs the ``onnx`` package (the ``export`` extra).

    Raises:
        ValueError: as `c_source`; ModuleNotFoundError: no ``onnx``, naming the extra.
    """
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError(
            "export --format onnx needs the onnx package: pip install onnx, or the export "
            'extra (pip install "jaxdrones[export]")'
        ) from e
    layers, env = _policy_env(payload)
    sizes = sizes_of(layers)
    low, high = (np.asarray(b[0], np.float32) for b in env.observation_bounds())
    inits = [numpy_helper.from_array(low[None], "obs_low"), numpy_helper.from_array(high[None], "obs_high")]
    nodes = [
        helper.make_node("Max", ["obs", "obs_low"], ["obs_above"]),
        helper.make_node("Min", ["obs_above", "obs_high"], ["x0"]),
    ]
    for k, (w, b) in enumerate(layers):
        inits += [numpy_helper.from_array(w, f"w{k}"), numpy_helper.from_array(b, f"b{k}")]
        out = "action" if k == len(layers) - 1 else f"x{k + 1}"
        nodes += [
            helper.make_node("Gemm", [f"x{k}", f"w{k}", f"b{k}"], [f"z{k}"]),
            helper.make_node("Tanh", [f"z{k}"], [out]),
        ]
    graph = helper.make_graph(
        nodes,
        "jaxdrones_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["N", sizes["n_obs"]])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["N", sizes["n_act"]])],
        initializer=inits,
    )
    model = helper.make_model(
        graph,
        producer_name="jaxdrones",
        opset_imports=[helper.make_opsetid("", 17)],
        doc_string="\n".join(describe(payload, env, layers)),
    )
    onnx.checker.check_model(model)
    return model, sizes


FORMATS = ("c", "onnx")


def export(
    run: str | os.PathLike,
    fmt: str = "c",
    out: str | os.PathLike | None = None,
    name: str = "jaxdrones_policy",
    overwrite: bool = False,
) -> tuple[str, dict]:
    """Write the policy of ``run`` (a run folder or its ``policy.pkl``) as a C file (`c_source`) or an ONNX model
    (`onnx_model`); returns ``(path, sizes)``. ``out`` defaults to ``<run>/<name>.c`` or ``.onnx``.

    Raises:
        ValueError: an unknown format, or see `c_source`; FileExistsError: ``out`` exists and not ``overwrite``;
        ModuleNotFoundError: ``onnx`` without the onnx package.
    """
    if fmt not in FORMATS:
        raise ValueError(f"export: format must be one of {FORMATS}, got {fmt!r}")
    payload = load_payload(run)
    if fmt == "c":
        data, sizes = c_source(payload, name)
        data = data.encode()
    else:
        model, sizes = onnx_model(payload)
        data = model.SerializeToString()
    if out is None:
        folder = run if os.path.isdir(run) else os.path.dirname(os.fspath(run))
        out = os.path.join(folder, f"{name}.{fmt}")
    out = os.fspath(out)
    with open(out, "wb" if overwrite else "xb") as f:
        f.write(data)
    return out, sizes
