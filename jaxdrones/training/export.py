"""A trained policy as one dependency-free C file, for a microcontroller (a Crazyflie's STM32F405: 1 MB flash,
192 KB RAM) or any C program.

`export` writes the MLP of a policy saved by ``jaxdrones train`` (``policy.pkl``) as float32 weight arrays, the
function ``void NAME(const float obs[N_OBS], float action[N_ACT])``, and ``NAME_step``, which keeps the memory the
observation holds (the last actions, `jaxdrones.envs.config.TaskConfig.action_buffer`; the error integral,
``error_integral``) in a ``NAME_memory`` struct, cleared by ``NAME_reset``: called at every control step with the
observation's other entries and the tracking error, it assembles the observation as the env does. The header
comment states the observation's layout (entry by entry, with units and frames), the clip the env applies to it, the
control rate, and how the action becomes motor commands. The function clips the observation to the env's box, as
the env does, then runs the network (`Network`): tanh hidden layers and a tanh output (the policies of ``apg`` and
``shac``, `jaxdrones.training.common.mlp`), or for our PPO (``ppo``, one drone) the observation standardised by its
running statistics first and its mean action clipped to the box last. It needs only ``<math.h>`` (``tanhf``);
``tests/test_export.py`` compiles it with the system's C compiler, compares it with the JAX policy, and flies it in
closed loop through ``ctypes``. The same network is also written as an ONNX model (`onnx_model`, with the ``onnx``
package: the ``export`` extra), for ONNX runtimes and converters to microcontroller toolchains (e.g. STM32Cube.AI).

Policies of the other trainers (brax's PPO, MAPPO's teams, camera policies) are refused with a `ValueError` naming
the ones supported.
"""

from __future__ import annotations

import itertools
import os
import re
import textwrap
from typing import TYPE_CHECKING, NamedTuple

import jax
import numpy as np

from jaxdrones.io.runs import check_replace, write_file
from jaxdrones.training.mappo import NORM_CLIP, NORM_EPS

if TYPE_CHECKING:
    import onnx

    from jaxdrones.envs.env import TaskEnv

#: The trainers whose saved policy `export` writes (`network_of`): MLPs with tanh hidden layers.
SUPPORTED = ("apg", "shac", "ppo")

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


class Network(NamedTuple):
    """A saved policy's network as the exported code computes it, on an observation x clipped to the env's box:
    x ← clip((x − ``norm[0]``) / ``norm[1]``, ±`NORM_CLIP`) when ``norm`` is set (our PPO's running statistics,
    ``(x − mean) / sqrt(var + 1e-6)``), then each layer y = W x + b, tanh after the hidden ones, and after the last
    a tanh (``output="tanh"``) or a clip to the action box [−1, 1] (``output="clip"``: a Gaussian policy's mean,
    which the env clips)."""

    layers: list[tuple[np.ndarray, np.ndarray]]  # (kernel f32[in, out], bias f32[out]), input first
    norm: tuple[np.ndarray, np.ndarray] | None  # (mean f32[n_obs], scale f32[n_obs])
    output: str


def _dense_layers(params: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    names = sorted((k for k in params if re.fullmatch(r"Dense_\d+", k)), key=lambda k: int(k.split("_")[1]))
    if not names:
        raise ValueError(f"export: expected flax Dense_0 ... Dense_n parameters, got {sorted(params)}")
    layers = [(np.asarray(params[k]["kernel"], np.float32), np.asarray(params[k]["bias"], np.float32)) for k in names]
    for (w, b), (w_next, _) in zip(layers, layers[1:] + [(None, None)], strict=True):
        if w.ndim != 2 or b.shape != (w.shape[1],) or (w_next is not None and w_next.shape[0] != w.shape[1]):
            raise ValueError("export: the layers' shapes do not chain")
    return layers


def network_of(payload: dict) -> Network:
    """The `Network` of a saved policy: ``apg`` and ``shac`` (`jaxdrones.training.common.mlp`: tanh layers and a
    tanh output), ``ppo`` (one drone: `jaxdrones.training.mappo`'s actor, its observation standardisation, its agent
    embedding folded into the first bias, the deterministic action: its mean, through a tanh with ``squash``).

    Raises:
        ValueError: a policy of a trainer not in `SUPPORTED`, or parameters that are not flax ``Dense_0 ...``.
    """
    algo = payload["algo"]
    if algo not in SUPPORTED:
        raise ValueError(
            f"export: policies of {algo!r} are not supported yet; it writes those of {SUPPORTED} (MLPs with tanh "
            "layers)"
        )
    params = payload["params"]
    if algo != "ppo":
        params = params.get("params", params)
        extra = sorted(k for k in params if not re.fullmatch(r"Dense_\d+", k))
        if extra:
            raise ValueError(f"export: expected flax Dense_0 ... Dense_n parameters, got {sorted(params)}")
        return Network(_dense_layers(params), None, "tanh")
    squeeze = payload["config"].get("share_params", True) is False  # per-agent networks: a leading axis of 1
    actor = jax.tree.map(lambda x: np.asarray(x)[0] if squeeze else np.asarray(x), params["actor"]["params"])
    layers = _dense_layers(actor)
    if "Embed_0" in actor:  # the one agent's id embedding, added to the first layer's output
        w, b = layers[0]
        layers[0] = (w, b + np.asarray(actor["Embed_0"]["embedding"], np.float32)[0])
    norm = params["norm"]
    scale = np.sqrt(np.asarray(norm["var"], np.float32) + np.float32(NORM_EPS))
    output = "tanh" if payload["config"].get("squash", False) else "clip"
    return Network(layers, (np.asarray(norm["mean"], np.float32), scale), output)


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
    lines = actions.__doc__.splitlines()
    start = next((k for k, line in enumerate(lines) if line.startswith(f"``{name}``")), None)
    if start is None:
        mapping = f"see jaxdrones.envs.actions ({name})"
    else:  # the table's row and its continuation lines, each constant it names with its value
        row = [lines[start], *itertools.takewhile(lambda line: line.startswith(" "), lines[start + 1 :])]
        mapping = " ".join(" ".join(row).split()[2:])
        mapping = re.sub(r"`([A-Z][A-Z_]+)`", lambda m: f"{m[1]} = {getattr(actions, m[1]):.6g}", mapping)
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
    """(network, env) of a saved policy, checked: a single-drone state env whose sizes the network maps."""
    from jaxdrones.envs import make

    net = network_of(payload)
    layers = net.layers
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
    return net, env


def sizes_of(net: Network) -> dict:
    """``{"n_obs", "n_act", "weight_bytes", "multiply_adds"}`` of an exported network (the bytes count the weights,
    the biases, the observation box's two bounds and the standardisation's two vectors, float32)."""
    layers = net.layers
    n_obs, n_act = layers[0][0].shape[0], layers[-1][0].shape[1]
    vectors = 2 + (2 if net.norm is not None else 0)
    return {
        "n_obs": n_obs,
        "n_act": n_act,
        "weight_bytes": 4 * (sum(w.size + b.size for w, b in layers) + vectors * n_obs),
        "multiply_adds": sum(w.size for w, _ in layers),
    }


def describe(payload: dict, env: TaskEnv, net: Network) -> list[str]:
    """What an exported policy computes and expects, as lines of text: its origin, its layers and sizes, the
    observation entry by entry (units, frames, the clip) and the action's mapping to motor commands."""
    sizes, layers = sizes_of(net), net.layers
    norm = (
        f"standardised by the running mean and deviation of training, clipped to +-{NORM_CLIP:g}, then "
        if net.norm is not None
        else ""
    )
    last = (
        "a tanh after each" if net.output == "tanh" else "a tanh after each hidden one, the output clipped to [-1, 1]"
    )
    return [
        f"A policy trained by jaxdrones ({payload['algo']}) on the task {payload['env_name']!r} with options "
        f"{payload['env_overrides'] or '(defaults)'}, exported by `jaxdrones export`.",
        f"The observation {norm}{len(layers)} dense layers {' -> '.join(str(w.shape[0]) for w, _ in layers)} -> "
        f"{sizes['n_act']}, {last}; {sizes['multiply_adds']} multiply-adds per call; {sizes['weight_bytes']} bytes "
        "of float32 constants.",
        f"Observation (one drone, float32, control rate {env.config.sim.ctrl_freq} Hz; clipped to the env's box, as "
        "the env does):",
        *[f"  [{i:2d}] {label}" for i, label in enumerate(_obs_labels(env))],
        *textwrap.wrap(f"Action: {_action_text(env)}", 110, subsequent_indent="  "),
    ]


def c_source(payload: dict, name: str = "jaxdrones_policy") -> tuple[str, dict]:
    """The C file of a saved policy and its sizes (`sizes_of`): ``(source, sizes)``.

    Raises:
        ValueError: an unsupported policy (see `network_of`), a multi-drone or camera env, or a ``name`` that is not
            a C identifier.
    """
    if not re.fullmatch(r"[A-Za-z_]\w*", name):
        raise ValueError(f"export: the function name must be a C identifier, got {name!r}")
    net, env = _policy_env(payload)
    layers, sizes = net.layers, sizes_of(net)
    n_obs, n_act = sizes["n_obs"], sizes["n_act"]
    low, high = (b[0] for b in env.observation_bounds())
    width = max(w.shape[1] for w, _ in layers)
    upper = name.upper()
    lines = [
        f"/* {name}: void {name}(const float obs[{n_obs}], float action[{n_act}]); needs <math.h> (tanhf) only.",
        f" * The observation is clipped to {name}_obs_low/high before the network.",
        " *",
        *[f" * {line}" for line in _memory_text(env, name, n_act)],
        " *",
        *[f" * {line}".rstrip() for line in describe(payload, env, net)],
        " */",
        "#include <math.h>",
        "",
        f"#define {upper}_N_OBS {n_obs}",
        f"#define {upper}_N_ACT {n_act}",
        "",
        _array(f"{name}_obs_low", low),
        _array(f"{name}_obs_high", high),
    ]
    if net.norm is not None:
        lines += [_array(f"{name}_obs_mean", net.norm[0]), _array(f"{name}_obs_scale", net.norm[1])]
    for k, (w, b) in enumerate(layers):
        lines += [_array(f"{name}_w{k}", w.T), _array(f"{name}_b{k}", b)]  # row per output: a contiguous dot
    lines += [
        "/* y = tanh(W x + b), or with clip != 0 y = W x + b clipped to [-1, 1] */",
        f"static void {name}_dense(const float *w, const float *b, const float *x, int n_in, int n_out, float *y,",
        "                          int clip)",
        "{",
        "  for (int o = 0; o < n_out; ++o) {",
        "    float s = b[o];",
        "    for (int i = 0; i < n_in; ++i) s += w[o * n_in + i] * x[i];",
        "    y[o] = clip ? (s < -1.0f ? -1.0f : (s > 1.0f ? 1.0f : s)) : tanhf(s);",
        "  }",
        "}",
        "",
        f"void {name}(const float obs[{n_obs}], float action[{n_act}])",
        "{",
        f"  float a[{max(width, n_obs)}], h[{width}];",
        f"  for (int i = 0; i < {n_obs}; ++i) {{",
        "    float v = obs[i];",
        f"    v = v < {name}_obs_low[i] ? {name}_obs_low[i] : (v > {name}_obs_high[i] ? {name}_obs_high[i] : v);",
        *(
            [
                f"    v = (v - {name}_obs_mean[i]) / {name}_obs_scale[i];",
                f"    v = v < -{NORM_CLIP!r}f ? -{NORM_CLIP!r}f : (v > {NORM_CLIP!r}f ? {NORM_CLIP!r}f : v);",
            ]
            if net.norm is not None
            else []
        ),
        "    a[i] = v;",
        "  }",
    ]
    src = "a"
    for k, (w, _) in enumerate(layers):
        last = k == len(layers) - 1
        dst = "action" if last else ("h" if src == "a" else "a")
        clip = int(last and net.output == "clip")
        lines.append(f"  {name}_dense({name}_w{k}, {name}_b{k}, {src}, {w.shape[0]}, {w.shape[1]}, {dst}, {clip});")
        src = dst
    lines += ["}", "", *_memory_source(env, name, n_act)]
    return "\n".join(lines), sizes


def _memory_text(env, name: str, n_act: int) -> list[str]:
    """The header's lines on ``NAME_step``: when to call it, what it takes, the memory it keeps."""
    from jaxdrones.envs.env import ERROR_INTEGRAL_BOUND

    parts, upper = _layout(env), name.upper()
    task = f", then the task's {parts['task']}" if parts["task"] else ""
    memory = []
    if parts["buffer"]:
        memory.append(f"the last {env.obs_type.buffer_len} actions it returned (oldest first)")
    if parts["integral"]:
        memory.append(
            f"the error integral (m->integral += error / {env.config.sim.ctrl_freq}, clipped to "
            f"+-{ERROR_INTEGRAL_BOUND:g}; error: {_ERRORS.get(env.task.name, _POSITION_ERROR)}, from the same "
            "measurements as state)"
        )
    kept = " and ".join(memory) if memory else "nothing (this observation has no memory; error may be NULL)"
    text = (
        f"At every control step ({env.config.sim.ctrl_freq} Hz), after {name}_reset(&m) at the start: "
        f"void {name}_step({name}_memory *m, const float state[{upper}_N_STATE], const float error[3], "
        f"float action[{n_act}]). state: the observation below without its memory, entries 0-{parts['base'] - 1}"
        f"{task}. It keeps {kept}, and assembles the observation below."
    )
    return textwrap.wrap(text, 110, subsequent_indent="  ")


def _memory_source(env, name: str, n_act: int) -> list[str]:
    """C of ``NAME_step``: the policy with the memory the observation holds (action buffer, error integral)."""
    from jaxdrones.envs.env import ERROR_INTEGRAL_BOUND

    parts, upper = _layout(env), name.upper()
    n_state, n_hist = parts["base"] + parts["task"], parts["buffer"]
    lines = [
        f"#define {upper}_N_STATE {n_state}",
        f"#define {upper}_N_HISTORY {env.obs_type.buffer_len}",
        f"#define {upper}_CTRL_FREQ {env.config.sim.ctrl_freq}",
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
            f"    float v = m->integral[i] + error[i] / {float(env.config.sim.ctrl_freq)!r}f;",
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
    net, env = _policy_env(payload)
    layers, sizes = net.layers, sizes_of(net)
    low, high = (np.asarray(b[0], np.float32) for b in env.observation_bounds())
    inits = [numpy_helper.from_array(low[None], "obs_low"), numpy_helper.from_array(high[None], "obs_high")]
    clipped = "x0" if net.norm is None else "obs_clipped"
    nodes = [
        helper.make_node("Max", ["obs", "obs_low"], ["obs_above"]),
        helper.make_node("Min", ["obs_above", "obs_high"], [clipped]),
    ]
    one = np.ones((), np.float32)
    if net.norm is not None:
        inits += [
            numpy_helper.from_array(net.norm[0][None], "obs_mean"),
            numpy_helper.from_array(net.norm[1][None], "obs_scale"),
            numpy_helper.from_array(-NORM_CLIP * one, "norm_low"),
            numpy_helper.from_array(NORM_CLIP * one, "norm_high"),
        ]
        nodes += [
            helper.make_node("Sub", [clipped, "obs_mean"], ["obs_centred"]),
            helper.make_node("Div", ["obs_centred", "obs_scale"], ["obs_scaled"]),
            helper.make_node("Clip", ["obs_scaled", "norm_low", "norm_high"], ["x0"]),
        ]
    if net.output == "clip":
        inits += [numpy_helper.from_array(-one, "action_low"), numpy_helper.from_array(one, "action_high")]
    for k, (w, b) in enumerate(layers):
        inits += [numpy_helper.from_array(w, f"w{k}"), numpy_helper.from_array(b, f"b{k}")]
        last = k == len(layers) - 1
        out = "action" if last else f"x{k + 1}"
        nodes.append(helper.make_node("Gemm", [f"x{k}", f"w{k}", f"b{k}"], [f"z{k}"]))
        if last and net.output == "clip":
            nodes.append(helper.make_node("Clip", [f"z{k}", "action_low", "action_high"], [out]))
        else:
            nodes.append(helper.make_node("Tanh", [f"z{k}"], [out]))
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
        doc_string="\n".join(describe(payload, env, net)),
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
        ValueError: an unknown format, a policy with non-finite weights, ``overwrite`` of a file `export` did not
            write, or see `c_source`; FileExistsError: ``out`` exists and not ``overwrite``; ModuleNotFoundError:
            ``onnx`` without the onnx package.
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
    check_replace(out, overwrite, SIGNATURE)
    write_file(out, data)
    return out, sizes


#: What every file `export` writes says of itself (the C file's header comment, the ONNX model's doc string):
#: ``overwrite`` replaces only a file that holds it (`jaxdrones.io.runs.check_replace`).
SIGNATURE = b"exported by `jaxdrones export`"
