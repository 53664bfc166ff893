"""XLA flags for the ``jaxdrones`` command line and the test suite, each set only where the running XLA accepts it.

``import jaxdrones`` sets no XLA flag: a library does not change how the rest of its user's process compiles.
The ``jaxdrones`` command line, which owns its process, adds the flags of the device it compiles for
(`flags_for`: `CLI_FLAGS` for XLA:CPU, `GPU_FLAGS` for XLA:GPU) to ``XLA_FLAGS`` before JAX starts a backend
(`add_flags`), and so does the test suite (``tests/conftest.py``).

XLA reads ``XLA_FLAGS`` when JAX starts a backend and aborts the process on a flag it does not know (``Unknown flag
in XLA_FLAGS``), and flags come and go between jaxlib releases (jaxlib 0.11 removed
``--xla_cpu_use_fusion_emitters``, whose name still stands in its library as a reserved field). So each flag is
first given to XLA itself, in a subprocess that starts JAX's backends with it (`accepted`); the answer is kept in a
file in the user's cache folder (`cache_file`), keyed by the XLA libraries installed (jaxlib's and any PJRT
plugin's, e.g. CUDA), so the check runs once per installation (1.1 s on jax 0.10.2, 2.2 s on jax 0.12 on 2 cores:
``benchmarks/xla_flags.py``). A flag the user already set in ``XLA_FLAGS`` is left alone, whatever its value.
``JAXDRONES_XLA_FLAGS=0`` (set before the ``jaxdrones`` command or the test run) turns every flag off, and the JAX
options and environment variables below.

`CLI_FLAGS` are for XLA:CPU, and are added only where the process compiles for the CPU (`compiles_for_cpu`: the
platform asked for is the CPU, or no GPU or TPU plugin is installed). They were measured on the CPU only; on an
NVIDIA H200 (jax 0.11.2) their check cost the first ``jaxdrones train hover`` 2.5 s (5.0 s from the command to the
training instead of 2.4-2.6 s), and training from a warm cache took 3.28 s with them against 2.66-3.19 s without.
Measured on 2 cores (docs/benchmarks.md):

- ``--xla_backend_optimization_level=1`` and ``--xla_llvm_disable_expensive_passes=true`` halve the compile time
  of the training and simulation programs on CPU with no measured change in their run time;
- ``--xla_cpu_use_fusion_emitters=false`` (XLA:CPU's classic emitters, up to jaxlib 0.10; later releases have only
  the fusion emitters and refuse the flag) compiles faster: ``jaxdrones train hover`` with an empty compilation
  cache took 11.7 s instead of 14.1 s on jax 0.10.2, and trained as fast (``benchmarks/train_algos.py``, 3 runs
  each, medians).

`GPU_FLAGS` are for XLA:GPU, added where the process compiles for a GPU (`compiles_for_gpu`). Measured on an NVIDIA
H200 (jax 0.11.2, CUDA 13; docs/benchmarks.md), one run each:

- ``--xla_gpu_enable_triton_gemm=false`` (the matrix products by cuBLAS instead of Triton kernels generated and
  compiled per product): ``jaxdrones train hover`` from an empty cache took 17.9 s instead of 22.1 s (21.7 s
  against 27.4 s on a second machine), warm 6.9-7.2 s against 5.9-7.0 s with its training phase as fast (3.1 s
  against 2.8-3.1 s). The trainers' products are small (a 64 x 64 MLP over a batch of worlds), where Triton's tuned
  kernels gain nothing worth their compilation.
  ``--xla_gpu_autotune_level=0`` compiled 2 s less than XLA's defaults but trained 1.7 times slower.

Where it compiles for a GPU the command line also sets the JAX options of `GPU_JAX_OPTIONS` (`set_jax_options`; a
JAX option is not an XLA flag: JAX reads it when it traces and lowers a program):

- ``jax_threefry_gpu_kernel_lowering``: each threefry hash of ``jax.random`` (the PRNG of every draw: random starts,
  the policy's noise, resets) lowered to one call of jaxlib's CUDA threefry kernel instead of XLA operations written
  out round by round (in memory, JAX's note says, the kernel takes the keys broadcast to each draw's shape: a few
  MB for the trainers). The numbers drawn are the same (the same Threefry-2x32 hash); XLA's optimisation of the
  three training programs took 0.8-1.5 s each instead of 2.7-3.8 s on an NVIDIA H200 (jax 0.11.2), and the first
  ``jaxdrones train hover`` took 8.3-9.8 s instead of 10.9-11.6 s from the command to its exit, warm 4.8 s against
  4.9-5.0 s (docs/benchmarks.md).

And it sets the environment variables of `GPU_ENV` (`set_environment`), where the user has not:

- ``XLA_PYTHON_CLIENT_PREALLOCATE=false``: JAX's GPU client takes the memory its programs need instead of 75 % of
  the GPU's at its first array. On an NVIDIA H200 (141 GB, jax 0.11.2) that first array, in the run's ``setup``
  phase, took 1.4-2.5 s with the preallocation and 0.02-0.03 s without (runs on different machines of one kind);
  the trainers' programs take a few hundred MB. Other processes can then share the GPU, as the test suite's
  workers do (``tests/conftest.py``).
"""

from __future__ import annotations

import functools
import glob
import importlib.util
import json
import os
import subprocess
import sys
import warnings

#: Environment variable that, set to 0 (or false/no/off), stops jaxdrones from setting any XLA flag.
OPT_OUT_VAR = "JAXDRONES_XLA_FLAGS"
#: Flags added by the ``jaxdrones`` command line (and the test suite), before JAX starts a backend.
CLI_FLAGS = (
    "--xla_backend_optimization_level=1",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
)
#: Flags added by the ``jaxdrones`` command line (and the test suite) where JAX compiles for a GPU.
GPU_FLAGS = ("--xla_gpu_enable_triton_gemm=false",)
#: JAX options (name: value) the command line sets where JAX compiles for a GPU (see the module doc).
GPU_JAX_OPTIONS = {"jax_threefry_gpu_kernel_lowering": True}
#: Environment variables (name: value) the command line sets, unless the user did, where JAX compiles for a GPU,
#: before JAX starts its backend (see the module doc).
GPU_ENV = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
#: Libraries below this size are Python bindings, not XLA.
_MIN_XLA_LIBRARY_BYTES = 10 * 2**20
#: What the probe runs: start every backend JAX finds, which parses ``XLA_FLAGS`` (and aborts on an unknown flag).
_PROBE = "import jax; jax.devices()"
_PROBE_TIMEOUT_S = 120


def opted_out() -> bool:
    """Whether the user turned jaxdrones' XLA flags off (``JAXDRONES_XLA_FLAGS=0``)."""
    return os.environ.get(OPT_OUT_VAR, "1").strip().lower() in ("0", "false", "no", "off")


def _flag_name(flag: str) -> str:
    return flag.lstrip("-").split("=", 1)[0]


@functools.cache
def xla_libraries() -> tuple[str, ...]:
    """Paths of the XLA libraries installed: jaxlib's and those of PJRT plugins (``jax_plugins``, e.g. CUDA)."""
    paths = []
    for package in ("jaxlib", "jax_plugins"):
        spec = importlib.util.find_spec(package)
        for root in (spec.submodule_search_locations or []) if spec else []:
            paths += glob.glob(os.path.join(root, "*.so")) + glob.glob(os.path.join(root, "*", "*.so"))
    return tuple(sorted(p for p in set(paths) if os.path.getsize(p) >= _MIN_XLA_LIBRARY_BYTES))


def _installation() -> str:
    """A key of the XLA installed: each library's path, size and modification time (a reinstall changes it)."""
    parts = []
    for path in xla_libraries():
        stat = os.stat(path)
        parts.append(f"{path}:{stat.st_size}:{stat.st_mtime_ns}")
    return "|".join(parts)


def cache_file() -> str:
    """Where `accepted` keeps XLA's answers: ``xla_flags.json`` in `jaxdrones.runs.user_cache_dir`
    (``~/.cache/jaxdrones/xla_flags.json``)."""
    from jaxdrones.io.runs import user_cache_dir

    return os.path.join(user_cache_dir(), "xla_flags.json")


def _read_cache() -> dict:
    try:
        with open(cache_file()) as f:
            cache = json.load(f)
    except (OSError, ValueError):
        return {}
    return cache if isinstance(cache, dict) else {}


def _write_cache(cache: dict) -> None:
    path = cache_file()
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(tmp, "w") as f:
            json.dump(cache, f, indent=1)
        os.replace(tmp, path)  # atomic: concurrent processes (pytest's workers) never read half a file
    except OSError:  # a read-only home: probe again next time
        pass


def _probe(*flag_sets: tuple[str, ...]) -> list[bool]:
    """Per set of flags, whether JAX starts its backends in a fresh interpreter with ``XLA_FLAGS`` set to those flags
    (and nothing else); the interpreters run at once."""
    runs = []
    for flags in flag_sets:
        env = dict(os.environ, XLA_FLAGS=" ".join(flags), XLA_PYTHON_CLIENT_PREALLOCATE="false")
        try:
            runs.append(
                subprocess.Popen(
                    [sys.executable, "-c", _PROBE],
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        except OSError:
            runs.append(None)
    answers = []
    for run in runs:
        try:
            answers.append(run is not None and run.wait(timeout=_PROBE_TIMEOUT_S) == 0)
        except subprocess.TimeoutExpired:
            run.kill()
            run.wait()
            answers.append(False)
    return answers


def accepted(flags: tuple[str, ...]) -> tuple[str, ...]:
    """The ``flags`` (e.g. ``("--xla_foo=1",)``) that the installed XLA accepts, asked of XLA itself.

    All of them are tried at once in a subprocess; if XLA refuses them together, each alone and none at all, in
    subprocesses running side by side. The answers are cached per installation (`cache_file`), so later calls start
    no process. Where no XLA library is found, or JAX does not start in a subprocess even without flags, no flag is
    accepted and nothing is cached.
    """
    installation = _installation()
    if not installation:
        return ()
    known = _read_cache().get(installation, {})
    unknown = tuple(dict.fromkeys(f for f in flags if f not in known))
    if unknown:
        if _probe(unknown)[0]:
            known.update(dict.fromkeys(unknown, True))
        else:
            alone = _probe((), *[(f,) for f in unknown]) if len(unknown) > 1 else [_probe(())[0], False]
            if not alone[0]:  # the refusal was not the flags': ask again next time
                return tuple(f for f in flags if known.get(f))
            known.update(zip(unknown, alone[1:], strict=True))
        cache = _read_cache()  # another process may have written meanwhile: keep its answers
        cache[installation] = {**cache.get(installation, {}), **known}
        _write_cache(cache)
    return tuple(f for f in flags if known[f])


def _platform(platform: str | None) -> str:
    """The platform asked for: ``platform`` (e.g. the command line's ``--device``), else the first of
    ``JAX_PLATFORMS``, lower-cased; "" where neither is set."""
    return (platform or os.environ.get("JAX_PLATFORMS", "").split(",")[0]).strip().lower()


def _plugins() -> list[str]:
    """The folders of ``jax_plugins`` (accelerators' PJRT plugins, e.g. ``xla_cuda13``) that hold an XLA library."""
    spec = importlib.util.find_spec("jax_plugins")
    roots = (spec.submodule_search_locations or []) if spec else []
    return [
        os.path.relpath(path, root).split(os.sep)[0]
        for path in xla_libraries()
        for root in roots
        if path.startswith(os.path.join(root, ""))
    ]


def compiles_for_cpu(platform: str | None = None) -> bool:
    """Whether JAX will compile for the CPU: ``platform`` (e.g. the command line's ``--device``), else the first of
    ``JAX_PLATFORMS``, is ``cpu``; or, with neither set, no accelerator's PJRT plugin (``jax_plugins``: CUDA, ROCm)
    nor ``libtpu`` is installed. Starts no backend."""
    asked = _platform(platform)
    if asked:
        return asked == "cpu"
    return not _plugins() and importlib.util.find_spec("libtpu") is None


def compiles_for_gpu(platform: str | None = None) -> bool:
    """Whether JAX will compile for a GPU: ``platform`` (or the first of ``JAX_PLATFORMS``) is ``gpu``, ``cuda`` or
    ``rocm``; or, with neither set, a CUDA or ROCm PJRT plugin (``jax_plugins``) is installed. Starts no backend."""
    asked = _platform(platform)
    if asked:
        return asked in ("gpu", "cuda", "rocm")
    return any(name.lower().startswith(("xla_cuda", "xla_rocm", "cuda", "rocm")) for name in _plugins())


def _for_gpu(platform: str | None = None) -> bool:
    """Whether the GPU's settings apply: JAX compiles for a GPU (`compiles_for_gpu`), not for the CPU."""
    return not compiles_for_cpu(platform) and compiles_for_gpu(platform)


def flags_for(platform: str | None = None) -> tuple[str, ...]:
    """The flags for the device JAX will compile for: `CLI_FLAGS` for the CPU (`compiles_for_cpu`), `GPU_FLAGS` for
    a GPU (`compiles_for_gpu`), none otherwise (a TPU)."""
    if compiles_for_cpu(platform):
        return CLI_FLAGS
    return GPU_FLAGS if _for_gpu(platform) else ()


def add_flags(flags: tuple[str, ...]) -> list[str]:
    """Add to ``XLA_FLAGS`` each of ``flags`` that the user did not set and the running XLA accepts (`accepted`),
    unless the user opted out (`opted_out`); returns the flags added.

    XLA reads ``XLA_FLAGS`` when JAX starts a backend: if one is already running (JAX computed something before),
    the flags cannot take effect and a `RuntimeWarning` says so.
    """
    if opted_out():
        return []
    current = os.environ.get("XLA_FLAGS", "")
    set_by_user = {_flag_name(f) for f in current.split()}
    added = list(accepted(tuple(f for f in flags if _flag_name(f) not in set_by_user)))
    if not added:
        return []
    os.environ["XLA_FLAGS"] = " ".join([current, *added]).strip()
    bridge = sys.modules.get("jax._src.xla_bridge")
    started = getattr(bridge, "backends_are_initialized", None)
    if started is not None and started():
        warnings.warn(
            f"JAX started its backends before jaxdrones set the XLA flags {added}, so they cannot take "
            f"effect: set them before running JAX code",
            RuntimeWarning,
            stacklevel=2,
        )
    return added


def jax_options_for(platform: str | None = None) -> dict:
    """The JAX options for the device JAX will compile for: `GPU_JAX_OPTIONS` for a GPU, none otherwise."""
    return dict(GPU_JAX_OPTIONS) if _for_gpu(platform) else {}


def environment_for(platform: str | None = None) -> dict:
    """The environment variables for the device JAX will compile for: `GPU_ENV` for a GPU, none otherwise."""
    return dict(GPU_ENV) if _for_gpu(platform) else {}


def set_environment(variables: dict) -> list[str]:
    """Set each of ``variables`` (names and values, e.g. `environment_for`'s) that the user did not set, unless the
    user opted out (`opted_out`); returns the names set. Call it before JAX starts its backend."""
    if opted_out():
        return []
    done = [name for name in variables if name not in os.environ]
    os.environ.update({name: variables[name] for name in done})
    return done


def set_jax_options(options: dict) -> list[str]:
    """Set each of ``options`` (JAX option names and values, e.g. `jax_options_for`'s) that the user did not set in
    its environment variable (the option's name in upper case, e.g. ``JAX_THREEFRY_GPU_KERNEL_LOWERING``) and the
    running JAX knows, with ``jax.config.update``, unless the user opted out (`opted_out`); returns the names set.
    Call it before JAX traces the programs they are for."""
    if opted_out() or not options:
        return []
    import jax

    done = []
    for name, value in options.items():
        if name.upper() in os.environ:
            continue
        try:
            jax.config.update(name, value)
        except AttributeError:  # an option this JAX does not have
            continue
        done.append(name)
    return done
