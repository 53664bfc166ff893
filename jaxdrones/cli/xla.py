"""The command line's settings of XLA and JAX, made before JAX starts a backend (``import jaxdrones`` makes none).

On the CPU, LLVM's cheaper passes (the training programs compile in about half the time and run as fast), and up to
jaxlib 0.10 XLA:CPU's classic emitters (jaxlib 0.11 removed them and their flag, and XLA aborts on a flag it does
not know). On a GPU, no Triton GEMMs, jax.random's hash lowered to jaxlib's CUDA kernel (the same bits) and the
device's memory taken as programs need it rather than 75 % at start. Why each: docs/devices.md, "XLA flags".
``JAXDRONES_XLA_FLAGS=0`` turns them all off; a flag, variable or option the user set is never replaced.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os

#: Environment variable that, set to 0 (or false/no/off), stops the command line from setting anything here.
OPT_OUT_VAR = "JAXDRONES_XLA_FLAGS"
#: The XLA:GPU flags; `cpu_flags` gives the XLA:CPU ones.
GPU_FLAGS = ("--xla_gpu_enable_triton_gemm=false",)
#: JAX options (name: value) and environment variables set where JAX compiles for a GPU.
GPU_JAX_OPTIONS = {"jax_threefry_gpu_kernel_lowering": True}
GPU_ENV = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}


def cpu_flags(optimization_level: int = 1) -> tuple[str, ...]:
    """The XLA:CPU flags for the installed jaxlib, with LLVM at ``optimization_level``."""
    flags = (f"--xla_backend_optimization_level={optimization_level}", "--xla_llvm_disable_expensive_passes=true")
    major, minor = (int(part) for part in importlib.metadata.version("jaxlib").split(".")[:2])
    return flags + (("--xla_cpu_use_fusion_emitters=false",) if (major, minor) < (0, 11) else ())


def platform(asked: str | None = None) -> str:
    """What JAX will compile for: ``"cpu"``, ``"gpu"`` or another platform's name. ``asked`` (the command line's
    ``--device``), else the first of ``JAX_PLATFORMS``; with neither, ``"gpu"`` where a CUDA or ROCm plugin of JAX
    (``jax_plugins``) is installed, ``"tpu"`` where libtpu is, else ``"cpu"``. Starts no backend."""
    asked = (asked or os.environ.get("JAX_PLATFORMS", "").split(",")[0]).strip().lower()
    if asked:
        return "gpu" if asked in ("cuda", "rocm") else asked
    spec = importlib.util.find_spec("jax_plugins")
    roots = (spec.submodule_search_locations or []) if spec else []
    plugins = [name.lower() for root in roots for name in os.listdir(root)]
    if any(name.startswith(("xla_cuda", "xla_rocm", "cuda", "rocm")) for name in plugins):
        return "gpu"
    return "tpu" if importlib.util.find_spec("libtpu") else "cpu"


def configure(device: str | None = None, cpu: tuple[str, ...] | None = None) -> list[str]:
    """Add the flags of ``device``'s platform (`platform`; on the CPU ``cpu``, default `cpu_flags`) to ``XLA_FLAGS``,
    and on a GPU set `GPU_ENV` and `GPU_JAX_OPTIONS`, each unless the user set it or opted out (`OPT_OUT_VAR`).
    Returns the flags added. Call it before JAX starts a backend."""
    if os.environ.get(OPT_OUT_VAR, "1").strip().lower() in ("0", "false", "no", "off"):
        return []
    kind = platform(device)
    flags = (cpu_flags() if cpu is None else cpu) if kind == "cpu" else GPU_FLAGS if kind == "gpu" else ()
    current = os.environ.get("XLA_FLAGS", "")
    users = {flag.lstrip("-").split("=")[0] for flag in current.split()}
    added = [flag for flag in flags if flag.lstrip("-").split("=")[0] not in users]
    if added:
        os.environ["XLA_FLAGS"] = " ".join([current, *added]).strip()
    if kind == "gpu":
        for name, value in GPU_ENV.items():
            os.environ.setdefault(name, value)
        import jax

        for name, value in GPU_JAX_OPTIONS.items():
            if name.upper() not in os.environ:
                jax.config.update(name, value)
    return added
