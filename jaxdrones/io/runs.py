"""Output folders for training runs and examples, written so that nothing a user had is lost: a folder is written
beside its target (``<target>.partial-<pid>``) and moved into place when complete; an existing folder is replaced
only where jaxdrones wrote it (its marker file, `MARKER`) and only by a complete one; a Ctrl-C while a folder is
moved into place waits for the move (`deferred_interrupt`). Every JSON file is strict (`write_json`)."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import shutil
import signal
import threading
from collections.abc import Iterator

#: The file in every folder jaxdrones writes (a run, a flight, camera images): what makes ``--overwrite`` replace
#: it. Folders written before it are recognised by their files (`written_by_jaxdrones`).
MARKER = ".jaxdrones"


def write_file(path: str | os.PathLike, data: str | bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file beside it, moved into place when whole: a reader never
    sees half a file, and a failure leaves what ``path`` held."""
    path = os.fspath(path)
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "wb") as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)
    os.replace(tmp, path)


def write_json(path: str | os.PathLike, obj: object, indent: int | None = 2) -> None:
    """Write ``obj`` as strict JSON (no ``NaN`` or ``Infinity``: a non-finite float is written as ``null``) to
    ``path`` (`write_file`)."""
    write_file(path, json.dumps(_finite(obj), indent=indent, allow_nan=False))


def _finite(obj: object) -> object:
    """``obj`` with every non-finite float as None (strict JSON has no NaN or infinity)."""
    if isinstance(obj, float):
        return obj if obj == obj and abs(obj) != float("inf") else None
    if isinstance(obj, dict):
        return {key: _finite(value) for key, value in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(value) for value in obj]
    return obj


def check_replace(path: str, overwrite: bool, signature: bytes, read: int = 65536) -> None:
    """The rule for a file a writer replaces: ``FileExistsError`` where ``path`` exists and not ``overwrite``;
    ``ValueError`` where it exists without ``signature`` (what every file of that writer holds) in its first ``read``
    bytes: a file jaxdrones did not write is never replaced."""
    if not os.path.exists(path):
        return
    if not overwrite:
        raise FileExistsError(errno.EEXIST, "exists; pass overwrite=True to replace it", path)
    with open(path, "rb") as f:
        if signature not in f.read(read):
            raise ValueError(
                f"overwrite replaces only a file jaxdrones wrote; {path!r} is another file, which is kept: choose "
                f"another file name"
            )


def written_by_jaxdrones(path: str | os.PathLike) -> bool:
    """Whether the folder ``path`` was written by jaxdrones: it holds `MARKER`, or, from before the marker, a run's
    ``summary.json`` with its ``provenance`` or a flight's ``metrics.json`` beside ``flight.npz``."""
    path = os.fspath(path)
    if os.path.isfile(os.path.join(path, MARKER)):
        return True
    try:
        with open(os.path.join(path, "summary.json")) as f:
            if "provenance" in json.load(f):
                return True
    except (OSError, ValueError, TypeError):
        pass
    return os.path.isfile(os.path.join(path, "metrics.json")) and os.path.isfile(os.path.join(path, "flight.npz"))


@dataclasses.dataclass
class OutputFolder:
    """A folder being written (`open_output`): ``path`` (``<target>.partial-<pid>``, beside it) until `commit`
    moves it to ``target``.

    Attributes:
        target: where the folder goes when complete.
        path: where it is written meanwhile.
        replace: ``target`` exists and may be replaced by a complete folder (``overwrite`` of a folder jaxdrones
            wrote, or an empty one).
        final: where `commit` moved it (None before).
    """

    target: str
    path: str
    replace: bool
    final: str | None = None

    def destination(self, complete: bool = True) -> str:
        """Where `commit` moves the folder: ``target``, where it is free or may be replaced (``replace``, by a
        ``complete`` folder); else the next free numbered sibling (``target-1``, ...), so that nothing there is
        lost (an interrupted or failed run replaces nothing)."""
        if os.path.lexists(self.target) and not (complete and self.replace and _replaceable(self.target)):
            return free_sibling(self.target)
        return self.target

    def commit(self, complete: bool = True) -> str:
        """Move the folder to its `destination` and return it; a folder it replaces is deleted only after the new
        one is in place. A Ctrl-C meanwhile waits for the move (`deferred_interrupt`)."""
        with deferred_interrupt():
            target = self.destination(complete)
            old = None
            if os.path.lexists(target):
                old = f"{self.path}.old"
                os.replace(target, old)
            os.replace(self.path, target)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        self.final = target
        return target

    def discard(self) -> None:
        """Delete the folder being written (nothing worth keeping: e.g. stopped before any training)."""
        shutil.rmtree(self.path, ignore_errors=True)


def _replaceable(path: str) -> bool:
    return os.path.isdir(path) and (not os.listdir(path) or written_by_jaxdrones(path))


def free_sibling(path: str) -> str:
    """The first of ``path-1``, ``path-2``, ... that does not exist."""
    k = 1
    while os.path.lexists(f"{path}-{k}"):
        k += 1
    return f"{path}-{k}"


def open_output(path: str | os.PathLike, overwrite: bool = False, kind: str = "run") -> OutputFolder:
    """Start writing an output folder for ``path`` (see the module doc): checked here, before anything runs.

    Where ``path`` is a folder that is not empty: with ``overwrite``, it is replaced when the new folder is complete
    if jaxdrones wrote it (`written_by_jaxdrones`), else refused; without, the new folder goes to the first free
    numbered sibling (``path-1``, ...).

    Args:
        path: the folder wanted (a trailing separator is ignored).
        overwrite: replace an existing folder that jaxdrones wrote.
        kind: what the folder holds, written into its `MARKER` (``"run"``, ``"flight"``, ``"camera"``).

    Returns:
        The `OutputFolder`, created with its `MARKER`.

    Raises:
        ValueError: ``path`` is a file; ``overwrite`` of a folder jaxdrones did not write (naming it); the folder
            cannot be created or written (permissions, a read-only file system, ...).
    """
    target = os.path.normpath(os.fspath(path))
    if os.path.basename(target) in ("", ".", ".."):  # "." or "..": the folder by its own name
        target = os.path.abspath(target)
    if os.path.isfile(target):
        raise ValueError(f"output path {target!r} is a file, expected a folder")
    replace = False
    if os.path.isdir(target) and os.listdir(target):
        if not overwrite:
            target = free_sibling(target)
        elif written_by_jaxdrones(target):
            replace = True
        else:
            raise ValueError(
                f"--overwrite replaces only a folder jaxdrones wrote (a run or flight folder, with its {MARKER} "
                f"file); {target!r} holds other files, which are kept: choose another output folder"
            )
    elif os.path.isdir(target):
        replace = True  # an empty folder
    staging = f"{target}.partial-{os.getpid()}"
    try:
        if os.path.lexists(staging):
            shutil.rmtree(staging)  # left by an earlier process of this id, which jaxdrones named
        os.makedirs(staging)
        with open(os.path.join(staging, MARKER), "w") as f:
            json.dump({"written_by": "jaxdrones", "kind": kind}, f)
    except OSError as err:
        raise ValueError(f"cannot create the output folder {staging!r}: {err.strerror or err}") from None
    return OutputFolder(target, staging, replace)


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, overwrite: bool = False, kind: str = "run") -> Iterator[OutputFolder]:
    """`open_output` as a context: yields the `OutputFolder` (write into its ``path``), moved into place when the
    block ends (then its ``final`` says where), deleted where the block raises (a half-written folder is not kept;
    what ``path`` held is untouched)."""
    folder = open_output(path, overwrite, kind)
    try:
        yield folder
    except BaseException:
        folder.discard()
        raise
    folder.commit()


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) until the block ends, then raise ``KeyboardInterrupt``: for the steps that must not
    stop half-way (moving a folder into place, writing a run's files). Outside the main thread, no effect."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


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
