"""XLA settings that jaxdrones applies before JAX starts a backend, each only where the running XLA knows it.

XLA reads ``XLA_FLAGS`` when JAX starts a backend and aborts the process on a flag it does not know (``Unknown flag
in XLA_FLAGS``): flags come and go between jaxlib releases (jax 0.11 removed ``--xla_cpu_use_fusion_emitters``).
So every flag jaxdrones adds is first looked up in the XLA libraries installed (jaxlib's ``libjax_common.so`` and
any PJRT plugin's, e.g. the CUDA plugin), where XLA keeps the names of the flags it parses, and is added only if
each of them names it. A flag the user already set in ``XLA_FLAGS`` is left alone, whatever its value.

Opt out of every flag jaxdrones sets with the environment variable ``JAXDRONES_XLA_FLAGS=0`` (set before
``import jaxdrones`` or the ``jaxdrones`` command).

The flags, by who sets them:

- `IMPORT_FLAGS`, on ``import jaxdrones``: ``--xla_cpu_use_fusion_emitters=false``. XLA:CPU's MLIR fusion
  emitters (the default since jaxlib 0.9) compiled the backward pass of a control step with ground effect into a
  fused loop that recomputes shared cotangents per element: the gradient of a 100-step rollout over 1024 worlds
  with drag and ground effect cost 180 times its forward pass on 2 cores, against 6 times with the classic emitters,
  which run the forward pass, the envs and training as fast or faster. jax 0.11 has no classic emitters and no flag:
  there it is not set.
- `CLI_FLAGS`, by the ``jaxdrones`` command line (`jaxdrones.cli`): they halve the compile time of the training and
  simulation programs on CPU with no measured change in their run time.
"""

from __future__ import annotations

import functools
import glob
import importlib.util
import mmap
import os
import warnings

#: Environment variable that, set to 0 (or false/no/off), stops jaxdrones from setting any XLA flag.
OPT_OUT_VAR = "JAXDRONES_XLA_FLAGS"
#: Flags added on ``import jaxdrones``.
IMPORT_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
#: Flags added by the ``jaxdrones`` command line, before it imports JAX.
CLI_FLAGS = ("--xla_backend_optimization_level=1", "--xla_llvm_disable_expensive_passes=true")
#: Libraries below this size are Python bindings, not XLA: they hold no flag names.
_MIN_XLA_LIBRARY_BYTES = 10 * 2**20


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


def known(flag: str) -> bool:
    """Whether every installed XLA library (`xla_libraries`) names ``flag`` (e.g. ``"--xla_foo=1"``), i.e. XLA
    will parse it rather than abort. False if no library is found."""
    libraries = xla_libraries()
    return bool(libraries) and all(_names(path, _flag_name(flag)) for path in libraries)


@functools.cache
def _names(path: str, name: str) -> bool:
    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            return data.find(name.encode()) >= 0
    except (OSError, ValueError):
        return False


def add_flags(flags: tuple[str, ...]) -> list[str]:
    """Add to ``XLA_FLAGS`` each of ``flags`` that the user did not set and the running XLA knows, unless the user
    opted out (`opted_out`); returns the flags added.

    XLA reads ``XLA_FLAGS`` when JAX starts a backend: if one is already running (JAX computed something before),
    the flags cannot take effect and a `RuntimeWarning` says so.
    """
    current = os.environ.get("XLA_FLAGS", "")
    if opted_out():
        return []
    added = [f for f in flags if _flag_name(f) not in current and known(f)]
    if not added:
        return []
    os.environ["XLA_FLAGS"] = " ".join([current, *added]).strip()
    try:
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # a JAX without this check: nothing to warn about
        started = False
    if started:
        warnings.warn(f"jaxdrones was imported after JAX started its backends, so the XLA flags {added} cannot take "
                      f"effect: import jaxdrones before running JAX code, or set XLA_FLAGS yourself",
                      RuntimeWarning, stacklevel=3)
    return added


def configure() -> list[str]:
    """Add `IMPORT_FLAGS` (see `add_flags`); called on ``import jaxdrones``."""
    return add_flags(IMPORT_FLAGS)
