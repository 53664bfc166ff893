"""Choosing the devices a run uses and joining several processes into one run (`jax.distributed`).

The trainers spread their worlds over `jax.devices()`: every local device (GPUs, or CPU devices from
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) and, after `start` with several processes, the devices of
every process. Each process then holds its share of the worlds; parameters are replicated and stay identical, since
every process runs the same program on the same global arrays (JAX's multi-controller model). `shard_worlds` spreads
a state's world axis over the devices, for a step or rollout to run on all of them.
"""

from __future__ import annotations

import socket
from collections.abc import Sequence
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import jax

#: A pytree type, kept through `shard_worlds`.
Tree = TypeVar("Tree")

#: Platforms `start` accepts for ``platform`` (JAX's names; ``gpu`` is CUDA or ROCm).
PLATFORMS = ("cpu", "gpu", "cuda", "rocm", "tpu")


class DeviceError(RuntimeError):
    """A device or process setting that cannot work: an unknown or absent platform, a process index out of range,
    a coordinator that cannot be reached in time."""


def start(
    platform: str | None = None,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    auto: bool = False,
    timeout_s: int = 60,
) -> None:
    """Select the platform and, for a run over several processes, join them with `jax.distributed.initialize`.
    Call before JAX computes anything.

    Args:
        platform: one of `PLATFORMS`, or None for JAX's choice.
        coordinator: ``HOST:PORT`` of process 0's coordinator (process 0 listens there); with ``num_processes`` and
            ``process_id``.
        num_processes: processes in the run, ≥ 1.
        process_id: this process's index in ``[0, num_processes)``.
        auto: call ``jax.distributed.initialize()`` without arguments, which reads them from the cluster (SLURM,
            Open MPI, Cloud TPU; see JAX's documentation) or from ``JAX_COORDINATOR_ADDRESS``,
            ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``.
        timeout_s: seconds to wait for every process to join before failing.

    Raises:
        DeviceError: an unknown platform or one with no device here (naming those there are); ``coordinator``
            without ``num_processes`` and ``process_id`` (or the reverse), a count below 1 or an index out of range,
            a malformed address; a coordinator that did not gather every process within ``timeout_s``.
    """
    import jax

    if platform is not None:
        if platform not in PLATFORMS:
            raise DeviceError(f"unknown device {platform!r}: expected one of {PLATFORMS}")
        jax.config.update("jax_platforms", platform)
    given = [v is not None for v in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise DeviceError("--coordinator, --num-processes and --process-id go together: give all three")
    if any(given) or auto:
        _join(jax, coordinator, num_processes, process_id, auto, timeout_s)
    if platform is not None:
        try:
            jax.devices()
        except RuntimeError as err:
            jax.config.update("jax_platforms", None)
            raise DeviceError(
                f"no {platform} device here ({str(err).splitlines()[0]}); available: "
                f"{sorted({d.platform for d in jax.devices()})}"
            ) from None


def _join(jax, coordinator, num_processes, process_id, auto: bool, timeout_s: int) -> None:
    """Check the process settings and call `jax.distributed.initialize` (see `start`)."""
    if not auto:
        if num_processes < 1:
            raise DeviceError(f"--num-processes must be >= 1, got {num_processes}")
        if not 0 <= process_id < num_processes:
            raise DeviceError(
                f"--process-id must be in [0, {num_processes - 1}] for --num-processes "
                f"{num_processes}, got {process_id}"
            )
        host, _, port = coordinator.rpartition(":")
        if not host or not port.isdigit():
            raise DeviceError(f"--coordinator must be HOST:PORT, got {coordinator!r}")
        if process_id != 0:
            _wait_for(host, int(port), timeout_s)
    # Collectives between the CPU devices of several processes (the CPU backend's; GPUs use NCCL).
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    kwargs = {} if auto else dict(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
    try:
        jax.distributed.initialize(**kwargs, initialization_timeout=timeout_s)
    except (RuntimeError, ValueError) as err:
        raise DeviceError(f"jax.distributed.initialize failed: {str(err).splitlines()[0]}") from None


def _wait_for(host: str, port: int, timeout_s: int) -> None:
    """Wait until ``host:port`` accepts connections (process 0's coordinator is up), at most ``timeout_s``."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=1.0):
                return
        except OSError as err:
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"the coordinator {host}:{port} could not be reached within {timeout_s} s "
                    f"({err.strerror or err}): start process 0 first, check the address and the "
                    f"firewall, or raise --distributed-timeout"
                ) from None
            time.sleep(0.2)


def shard_worlds(tree: Tree, axis: int = 0, devices: Sequence[jax.Device] | None = None) -> Tree:
    """Spread the world axis of every array in ``tree`` over devices, for a step or rollout to run on all of them.

    Each leaf is placed with a `jax.sharding.NamedSharding` over a 1-D mesh ``("worlds",)``: device k holds a
    contiguous slice of the worlds. A jitted `make_step` step or `rollout` on such arrays runs on every device at
    once, each on its own slice (worlds do not interact, so no data moves between devices), and returns arrays
    sharded the same way. Shared, unbatched params need no sharding; per-world params are sharded like the state.
    On a CPU host, start Python with ``XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`` (set before
    ``jax`` is imported) to get one device per core; on GPUs the devices are the GPUs.

    Args:
        tree: a pytree of arrays whose axis ``axis`` is the world axis, e.g. a DroneState f[W, D, ...], an RPM
            command f[W, D, 4] (``axis=0``) or a rollout's commands f[T, W, D, 4] (``axis=1``).
        axis: the world axis of every leaf.
        devices: the devices to use, default ``jax.devices()``.

    Returns:
        The same pytree with its leaves sharded over ``devices``.

    Raises:
        ValueError: if a leaf lacks ``axis`` or its size there is not a multiple of the number of devices.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    devices = list(jax.devices() if devices is None else devices)
    mesh = jax.sharding.Mesh(np.array(devices), ("worlds",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(*[None] * axis, "worlds"))

    def put(x):
        x = jnp.asarray(x)
        if x.ndim <= axis or x.shape[axis] % len(devices):
            raise ValueError(
                f"shard_worlds: a leaf of shape {x.shape} has no world axis {axis} whose size is a "
                f"multiple of the {len(devices)} devices"
            )
        return jax.device_put(x, sharding)

    return jax.tree.map(put, tree)
