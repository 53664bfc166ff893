"""The JAX core's control step as one Pallas kernel, and its reverse-mode derivative as a second: `make_step`.

Experimental: checked against the XLA path on the CPU (tests/test_pallas.py), never yet timed on a GPU, where it is
meant to pay. On a GPU every XLA operation is at least one kernel launch, and a control step of the default hover env
(physics, observation, reward) runs dozens of them forward and hundreds with its gradient (docs/benchmarks.md): a
training run of many small updates is bound by those launches, not by the arithmetic. Here
the whole control step's physics (the RPM clip, the quaternion's normalisation, the motors and every physics substep
with its ground contact) is one `jax.experimental.pallas` kernel, lowered through Triton on an NVIDIA GPU, and its
vector-Jacobian product a second: the backward kernel recomputes the substeps from the control step's input, then
transposes them one by one with the hand-written adjoint of `jaxdrones.physics.adjoint` (`substep_vjp`) and the few
element-wise operations around them with JAX's derivative, all inside the kernel. On the CPU both run in Pallas's
interpret mode (as the XLA operations the kernel's body traces to): what the suite checks against the XLA path
(tests/test_pallas.py), not a way to run fast.

The kernel's body is the physics of `jaxdrones.physics.dynamics` itself, traced on blocks of drones, one value per
drone: each drone is independent within a control step, so the kernel takes configs without coupling between drones (no
downwash with more than one drone per world) and the hand-written adjoint's (the Euler integrator, exact kinks):
`unsupported`. The params are read in the kernel entry by entry (`_Entries`): one scalar each when every drone has the
same, else one value per drone. A step given a `Disturbance` runs on the XLA path; a gradient with respect to the params
(system identification) takes JAX's derivative of the XLA path.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import CustomVJPPrimal, SymbolicZero

from jaxdrones.physics import adjoint, dynamics
from jaxdrones.physics.config import SimConfig
from jaxdrones.physics.params import CORE_NDIM, DroneParams, params_batch_shape
from jaxdrones.physics.rotations import normalize_c
from jaxdrones.physics.state import CONTACT_GROUND, DroneState
from jaxdrones.physics.step import JaxStep, compiled_step_c

__all__ = ["BLOCK", "control_step_c", "make_step", "unsupported"]

#: Drones per kernel program (one Triton program of 4 warps, one drone per thread).
BLOCK = 128
#: The state's vectors and their sizes, in the kernels' order of values.
_VECTORS = (("pos", 3), ("quat", 4), ("vel", 3), ("ang_vel", 3), ("rpm", 4))
#: Values of a state (`_VECTORS`) and of a command (one RPM per motor) in the kernels' inputs and outputs.
STATE_SIZE = sum(size for _, size in _VECTORS)
COMMAND_SIZE = dict(_VECTORS)["rpm"]


def unsupported(config: SimConfig) -> str | None:
    """None when ``config``'s control step can run as the Pallas kernels, else what they take: the hand-written
    adjoint's settings (`SimConfig.hand_written_adjoint`) and drones that do not act on each other (no downwash
    between several drones of a world: the kernel steps each drone on its own)."""
    if not config.hand_written_adjoint:
        return "the hand-written adjoint's settings: adjoint=True, integrator='euler', kinks='exact'"
    if config.downwash and config.n_drones > 1:
        return "drones that do not act on each other: downwash=False with several drones per world"
    return None


def make_step(config: SimConfig) -> JaxStep:
    """The control step of ``config`` as `jaxdrones.make_step` gives it, ``step(params, state, rpm, disturbance=None)
    -> state``, with its physics run as one Pallas kernel forward and one backward (`control_step_c`); the values
    are the XLA path's to float rounding. On the CPU the kernels run in Pallas's interpret mode, slowly.

    Raises:
        ValueError: a config the kernels do not take (`unsupported`).
    """
    if (why := unsupported(config)) is not None:
        raise ValueError(f"the Pallas control step takes {why}; got {config}")
    return JaxStep(config, control_step_c(config, compiled_step_c(config)))


class _Entries(np.ndarray):
    """A params field (e.g. ``inertia``, 3 x 3) as a NumPy object array of its entries, each a JAX value (a scalar,
    or one value per drone of the kernel's block): indexed as the physics indexes the field (``m[..., i, j]``,
    ``m[..., i, :]``, `jaxdrones.physics.rotations.split`), it gives the entry itself rather than a 0-d array."""

    def __getitem__(self, index):
        out = super().__getitem__(index)
        return out.item() if isinstance(out, np.ndarray) and out.ndim == 0 else out


def _substeps(config, params, state: DroneState, command: tuple, keep: list | None = None) -> DroneState:
    """The physics substeps of the control step on values (in the kernel): ``state``'s vectors as tuples of per-drone
    values, its quaternion normalised, ``command`` the clipped RPM command as 4 values (`_prepare`). As
    `jaxdrones.sim`'s control step, the substeps written out; each substep's input kinematics and RPM state are
    appended to ``keep`` when given (for the backward pass)."""
    kin = dynamics.Kinematics(state.pos, state.quat, state.vel, state.ang_vel)
    rpm, touched = state.rpm, False
    for k in range(config.n_substeps):
        motors, rpm_prev, rpm_next = _motors(config, params, k, command, rpm)
        if keep is not None:
            keep.append((kin, rpm))
        kin = dynamics.euler_step_c(params, config.effects, kin, motors, rpm_prev, config.dt, True, None, None, None)
        kin, touching = dynamics.ground_contact_c(params, kin, config.effects.kinks)
        rpm, touched = rpm_next, touched | touching
    contact = jnp.where(touched, CONTACT_GROUND, 0).astype(jnp.int32)
    return DroneState(*kin, rpm=rpm, contact=contact)


def _control_step(config, params, state: DroneState, command: tuple) -> DroneState:
    """The control step on values (in the kernel), from the raw command and quaternion: `_prepare`, `_substeps`."""
    command, quat = _prepare(config, params, command, state.quat)
    return _substeps(config, params, state.replace(quat=quat), command)


def _prepare(config, params, command: tuple, quat: tuple) -> tuple[tuple, tuple]:
    """The clipped command and the normalised quaternion, as the XLA path's control step starts."""
    clipped = tuple(config.kinks.clip(r, 0.0, params.max_rpm, config.kinks.rpm) for r in command)
    return clipped, normalize_c(quat)


def _motors(config, params, k: int, command: tuple, rpm: tuple) -> tuple[dynamics.Motors, tuple, tuple]:
    """Substep ``k``'s motors, the RPM its drag reads (the previous substep's) and the RPM state after it, from the
    clipped ``command`` and the RPM state ``rpm`` before it: lagged motors move towards the command first
    (`dynamics.motor_response_c`); instant ones apply it."""
    if config.motor_dynamics:
        speeds = dynamics.motor_response_c(params, rpm, command, config.dt)
        return dynamics.motors_c(params, speeds), rpm, speeds
    return dynamics.motors_c(params, command), rpm if k == 0 else command, command


def _backward(config, params, state: DroneState, command: tuple, ct: DroneState) -> tuple[DroneState, tuple]:
    """The cotangents of the control step's ``state`` (its vectors; the contact has none) and ``command`` for the
    cotangent ``ct`` of its output (in the kernel, on values): the substeps recomputed, then transposed in reverse
    with `adjoint.substep_vjp`; the motors, the clip and the normalisation with JAX's derivative."""
    (clipped, quat), prepare_vjp = jax.vjp(lambda c, q: _prepare(config, params, c, q), command, state.quat)
    keep: list = []
    _substeps(config, params, state.replace(quat=quat), clipped, keep)
    kin_b = dynamics.Kinematics(ct.pos, ct.quat, ct.vel, ct.ang_vel)
    rpm_b = ct.rpm
    clipped_b = tuple(jnp.zeros_like(c) for c in clipped)
    for k in reversed(range(config.n_substeps)):
        kin, rpm = keep[k]
        (motors, rpm_prev, _), motors_vjp = jax.vjp(lambda c, r, k=k: _motors(config, params, k, c, r), clipped, rpm)
        kin_b, motors_b, rpm_prev_b, _, _ = adjoint.substep_vjp(
            params, config.effects, kin, motors, rpm_prev, None, config.dt, kin_b
        )
        command_b, rpm_b = motors_vjp((motors_b, rpm_prev_b, rpm_b))
        clipped_b = tuple(a + b for a, b in zip(clipped_b, command_b, strict=True))
    command_b, quat_b = prepare_vjp((clipped_b, kin_b.quat))
    state_b = DroneState(kin_b.pos, quat_b, kin_b.vel, kin_b.ang_vel, rpm=rpm_b, contact=None)
    return state_b, command_b


def _flat_params(params: DroneParams, shape: tuple[int, ...]) -> tuple[list, list, jax.Array | None]:
    """The params as kernel inputs: ``(names, per_drone, shared)``, ``names`` ``(field, entry shape)`` in order;
    ``per_drone`` (when the params differ between drones) one array per entry, of ``shape``
    (the state's ``[..., D]``), else ``shared`` one vector of every entry, padded to a power of two (a Triton block)."""
    names = [
        (f.name, jnp.shape(getattr(params, f.name))[jnp.ndim(getattr(params, f.name)) - CORE_NDIM.get(f.name, 0) :])
        for f in dataclasses.fields(params)
    ]
    if math.prod(params_batch_shape(params)) == 1:
        flat = jnp.concatenate([jnp.reshape(getattr(params, name), (-1,)) for name, _ in names])
        size = 1 << (flat.shape[0] - 1).bit_length()
        return names, [], jnp.pad(flat, (0, size - flat.shape[0]))
    per_drone = []
    for name, core in names:
        leaf = jnp.broadcast_to(getattr(params, name), shape + core)
        per_drone += [leaf[(..., *index)] for index in np.ndindex(core)]
    return names, per_drone, None


def _kernel_params(names: list, entries: list) -> DroneParams:
    """`DroneParams` in the kernel from its entries in `_flat_params`'s order (values, scalars or per drone)."""
    fields, entries = {}, iter(entries)
    for name, core in names:
        if not core:
            fields[name] = next(entries)
            continue
        grid = np.empty(math.prod(core), dtype=object)
        for i in range(grid.size):
            grid[i] = next(entries)
        fields[name] = grid.reshape(core).view(_Entries)
    return DroneParams(**fields)


def _components(state: DroneState) -> list:
    return [c for name, _ in _VECTORS for c in getattr(state, name)]


def _state_of(values, contact=None) -> DroneState:
    values = iter(values)
    return DroneState(**{name: tuple(next(values) for _ in range(k)) for name, k in _VECTORS}, contact=contact)


def _kernel(body, n_out: int, int_out: bool):
    """``launch(params, arrays) -> outputs``: ``body(params, values) -> (outputs, contact)`` run as one Pallas kernel
    over the drones (`_call`), batched under ``jax.vmap`` by taking the mapped axis as one more axis of drones
    (``jax.custom_batching.custom_vmap``) rather than as a grid of one block per mapped element."""

    @jax.custom_batching.custom_vmap
    def launch(params, arrays):
        return _call(body, params, arrays, n_out, int_out)

    @launch.def_vmap
    def launch_vmap(axis_size, in_batched, params, arrays):
        params_batched, arrays_batched = in_batched
        # Mapped at axis 0; an unmapped array or params field broadcasts against the mapped ones, right-aligned.
        # Params mapped in part (one field randomised, say) are mapped whole, so that they share one batch shape.
        partly = any(jax.tree.leaves(params_batched))
        params = jax.tree.map(
            lambda x, b: x if b else jnp.broadcast_to(x[None], (axis_size if partly else 1, *jnp.shape(x))),
            params,
            params_batched,
        )
        arrays = [x if b else x[None] for x, b in zip(arrays, arrays_batched, strict=True)]
        shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in arrays))
        arrays = [jnp.broadcast_to(x, (axis_size, *shape[1:])) for x in arrays]
        outputs = launch(params, arrays)
        return outputs, [True] * len(outputs)

    return launch


def _call(body, params: DroneParams, arrays: list, n_out: int, int_out: bool) -> list:
    """``body(params, values) -> (outputs, contact)`` run as one Pallas kernel over the drones: ``arrays`` broadcast
    to their common shape ``[..., D]``, flattened and stacked into one f[len(arrays), N] input (one XLA fusion before
    the kernel rather than one per array), N padded to whole blocks of `BLOCK` drones (with the last drone's values:
    Triton's loads of a block are not masked), one block per program; returns the ``n_out`` float outputs (and the
    i32 contact when ``int_out``), each of that shape."""
    from jax.experimental import pallas as pl

    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in arrays))
    n = math.prod(shape)
    padded = pl.cdiv(n, BLOCK) * BLOCK
    dtype = jnp.result_type(*arrays)
    names, per_drone, shared = _flat_params(params, shape)

    def stack(xs):
        rows = jnp.stack([jnp.reshape(jnp.broadcast_to(x, shape), (n,)) for x in xs]).astype(dtype)
        return jnp.pad(rows, ((0, 0), (0, padded - n)), mode="edge")

    def rows(count):  # one row of a stacked input, the block of drones of program i
        return [pl.BlockSpec((None, BLOCK), lambda i, j=j: (j, i)) for j in range(count)]

    inputs, in_specs = [stack(arrays)] * len(arrays), rows(len(arrays))
    if per_drone:
        inputs, in_specs = [stack(per_drone)] * len(per_drone) + inputs, rows(len(per_drone)) + in_specs
    if shared is not None:
        inputs, in_specs = [shared.astype(dtype), *inputs], [pl.BlockSpec(shared.shape, lambda i: (0,)), *in_specs]

    def kernel(*refs):
        if shared is not None:
            shared_ref, refs = refs[0], refs[1:]
            entries = [shared_ref[i] for i in range(sum(math.prod(core) for _, core in names))]
        values = [ref[...] for ref in refs[: len(inputs) - (shared is not None)]]
        outs = refs[len(values) :]
        if per_drone:
            entries, values = values[: len(per_drone)], values[len(per_drone) :]
        floats, contact = body(_kernel_params(names, entries), values)
        for ref, value in zip(outs, floats, strict=False):
            ref[...] = jnp.broadcast_to(value, ref.shape).astype(ref.dtype)
        if int_out:
            outs[-1][...] = contact

    out_shape = [jax.ShapeDtypeStruct((padded,), dtype)] * n_out
    out_shape += [jax.ShapeDtypeStruct((padded,), jnp.int32)] if int_out else []
    interpret = _interpret()
    compiler_params = None
    if not interpret:
        from jax.experimental.pallas import triton

        compiler_params = triton.CompilerParams(num_warps=BLOCK // 32, num_stages=1)
    outputs = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(padded // BLOCK,),
        in_specs=in_specs,
        out_specs=[pl.BlockSpec((BLOCK,), lambda i: (i,))] * len(out_shape),
        interpret=interpret,
        compiler_params=compiler_params,
        name="jaxdrones_control_step",
    )(*inputs)
    return [jnp.reshape(x[:n], shape) for x in outputs]


def control_step_c(config: SimConfig, xla_step: Callable[..., DroneState]) -> Callable[..., DroneState]:
    """The control step of ``config`` (one that `unsupported` accepts) in component form, as
    `jaxdrones.sim`'s ``core_c(params, state_c, rpm_c, disturbance_c=None) -> state_c`` and with its values (to float
    rounding), run as one Pallas kernel forward and one backward; ``xla_step``, the XLA path's ``core_c``, steps a
    call with a disturbance and gives the derivative with respect to the params."""

    def forward_body(params, values):
        out = _control_step(config, params, _state_of(values[:STATE_SIZE]), tuple(values[STATE_SIZE:]))
        return _components(out), out.contact

    def backward_body(params, values):
        state_b, command_b = _backward(
            config,
            params,
            _state_of(values[:STATE_SIZE]),
            tuple(values[STATE_SIZE : STATE_SIZE + COMMAND_SIZE]),
            _state_of(values[STATE_SIZE + COMMAND_SIZE :]),
        )
        return [*_components(state_b), *command_b], None

    forward, backward = (
        _kernel(forward_body, STATE_SIZE, True),
        _kernel(backward_body, STATE_SIZE + COMMAND_SIZE, False),
    )

    @jax.custom_vjp
    def step(params, state, command):
        outputs = forward(params, [*_components(state), *command])
        return _state_of(outputs[:STATE_SIZE], outputs[STATE_SIZE])

    def step_fwd(params, state, command):
        is_primal = lambda x: isinstance(x, CustomVJPPrimal)  # noqa: E731
        params_perturbed = any(x.perturbed for x in jax.tree.leaves(params, is_leaf=is_primal))
        params, state, command = jax.tree.map(lambda x: x.value, (params, state, command), is_leaf=is_primal)
        # The residuals' structure tells the backward pass whether the params need a cotangent (as in `adjoint`).
        return step(params, state, command), (params, state, command, (None,) if params_perturbed else ())

    def step_bwd(residuals, ct):
        params, state, command, params_perturbed = residuals
        ct = _state_of([_instantiate(c) for c in _components(ct)])
        if params_perturbed:  # JAX's derivative of the XLA path, params included (system identification)
            contact = jnp.zeros(jnp.shape(state.pos[0]), jnp.int32)
            _, vjp = jax.vjp(lambda p, s, c: _xla(p, s, c, contact), params, state, command)
            params_b, state_b, command_b = vjp(ct)
            return params_b, state_b.replace(contact=None), command_b
        grads = backward(params, [*_components(state), *command, *_components(ct)])
        return None, _state_of(grads[:STATE_SIZE]), tuple(grads[STATE_SIZE:])

    def _xla(params, state, command, contact):
        out = xla_step(params, state.replace(contact=contact), command)
        return out.replace(contact=None)

    step.defvjp(step_fwd, step_bwd, symbolic_zeros=True)

    def core_c(params, state: DroneState, rpm: tuple, disturbance=None) -> DroneState:
        if disturbance is not None:
            return xla_step(params, state, rpm, disturbance)
        return step(params, state.replace(contact=None), tuple(rpm))

    return core_c


def _interpret() -> bool:
    """Whether the kernels run in Pallas's interpret mode (as XLA operations): on the CPU, where Pallas compiles
    no kernel; decided when the step is traced."""
    return jax.default_backend() == "cpu"


def _instantiate(x):
    return jnp.zeros(x.aval.shape, x.aval.dtype) if isinstance(x, SymbolicZero) else x
