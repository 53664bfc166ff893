"""Output folders for training runs and examples: never overwrite an earlier run unless asked."""

from __future__ import annotations

import os
import shutil


def new_run_dir(path: str | os.PathLike, overwrite: bool = False) -> str:
    """Create and return a fresh output folder.

    If ``path`` exists and is not empty, a numbered sibling (``path-1``, ``path-2``, ...) is used instead, so
    nothing saved earlier is lost; with ``overwrite=True`` the existing folder is emptied first.

    Args:
        path: the desired folder.
        overwrite: replace the contents of an existing ``path``.

    Returns:
        The folder that was created (or emptied), as a string.

    Raises:
        ValueError: if ``path`` exists and is a file, or the folder cannot be created or written (permissions, a
            read-only file system, ...).
    """
    path = os.fspath(path)
    if os.path.isfile(path):
        raise ValueError(f"output path {path!r} is a file, expected a folder")
    if os.path.isdir(path) and os.listdir(path):
        if overwrite:
            shutil.rmtree(path)
        else:
            k = 1
            while os.path.exists(f"{path}-{k}"):
                k += 1
            path = f"{path}-{k}"
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the output folder {path!r}: {err.strerror or err}") from None
    if not os.access(path, os.W_OK):
        raise ValueError(f"the output folder {path!r} is not writable")
    return path


#: Environment variable naming the folder of JAX's persistent compilation cache for the ``jaxdrones`` command
#: (default: ``$XDG_CACHE_HOME/jaxdrones/xla``, i.e. ``~/.cache/jaxdrones/xla``).
CACHE_DIR_VAR = "JAXDRONES_CACHE_DIR"


def user_cache_dir() -> str:
    """Jaxdrones' folder in the user's cache: ``$XDG_CACHE_HOME/jaxdrones`` (``~/.cache/jaxdrones``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxdrones")


def default_cache_dir() -> str:
    """The folder of the command line's compilation cache: ``$JAXDRONES_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxdrones/xla`` (``~/.cache/jaxdrones/xla``)."""
    return os.environ.get(CACHE_DIR_VAR) or os.path.join(user_cache_dir(), "xla")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default `default_cache_dir`): a program compiled
    once is read back from disk by later processes instead of being compiled again (JAX's
    ``jax_compilation_cache_dir``; entries are keyed by the program, the JAX version and the device). Every program
    that took over 0.1 s to compile is cached. Returns the folder, or None (with a warning) if it cannot be
    created, in which case nothing is cached."""
    import warnings

    import jax

    path = os.fspath(path or default_cache_dir())
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        warnings.warn(
            f"compilation cache off: cannot create {path!r} ({err.strerror or err})", RuntimeWarning, stacklevel=2
        )
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def provenance() -> dict:
    """What a result depends on beyond its settings, for ``summary.json``: package versions (jaxdrones, jax,
    jaxlib, flax, optax, brax, numpy), Python, the git commit of the jaxdrones source when it is a git checkout,
    JAX's backend and devices, the number of processes, the CPU model and core count, the host's load average."""
    import importlib.metadata
    import platform
    import subprocess

    import jax

    versions = {}
    for package in ("jaxdrones", "jax", "jaxlib", "flax", "optax", "brax", "numpy"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    source = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        top, commit = (
            subprocess.run(
                ["git", "-C", source, "rev-parse", "--show-toplevel", "HEAD"], capture_output=True, text=True, timeout=5
            ).stdout.split()
            + [None, None]
        )[:2]
        if top is None or os.path.realpath(top) != os.path.realpath(source):  # not jaxdrones' own checkout
            commit = None
        if (
            commit
            and subprocess.run(
                ["git", "-C", source, "status", "--porcelain", "--untracked-files=no"],
                capture_output=True,
                text=True,
                timeout=5,
            ).stdout.strip()
        ):
            commit += "+modified"
    except (OSError, subprocess.SubprocessError):
        commit = None
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    devices = jax.devices()
    return {
        "versions": versions,
        "python": platform.python_version(),
        "git_commit": commit,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in devices],
        "device_kind": devices[0].device_kind,
        "num_processes": jax.process_count(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
