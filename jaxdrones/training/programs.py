"""A disk cache of traced training programs, beside JAX's persistent compilation cache.

JAX's compilation cache skips XLA's compilation on a second run, but not the tracing of the Python code into a
program and its lowering to StableHLO, which take seconds for a trainer's chunk (the env's step traced for
collection, for the gradient and for the evaluation). `cached_jit` saves the lowered program with `jax.export`
(serialised StableHLO, JAX's stable format for exported programs) and a later process with the same program key
loads it instead of tracing; XLA then finds the compiled program in the compilation cache. As with ``jax.jit``, a
program is traced (or loaded) at its first call with inputs of new shapes, so that a warm run traces nothing.

The key of a program is a hash of everything it is built from: the caller's description of its closure (the
trainer, its config, the env's config, the evaluation's settings), the shapes, dtypes and tree structure of its
inputs, the source of every module of jaxdrones, the jax and jaxlib versions and the device kind. A program whose
inputs are spread over several devices is not cached (it is traced as usual), nor is any where the compilation
cache is off or ``flatbuffers`` (needed by `jax.export`'s serialisation) is missing.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

#: Sub-folder of JAX's compilation cache folder holding the exported programs.
FOLDER = "jaxdrones-programs"


@functools.cache
def _source_hash() -> str:
    """Hash of every ``.py`` file of the installed jaxdrones package (its code defines every program)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    digest = hashlib.sha256()
    for folder, _, files in sorted(os.walk(root)):
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                digest.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    digest.update(f.read())
    return digest.hexdigest()


def cache_folder() -> str | None:
    """The folder of the program cache (`FOLDER` in JAX's compilation cache folder), or None where it is off: no
    compilation cache, or no ``flatbuffers`` for `jax.export`'s serialisation (then `cached_jit` is ``jax.jit``)."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return None
    try:
        import flatbuffers  # noqa: F401  (jax.export's serialisation needs it)
    except ImportError:
        return None
    return os.path.join(folder, FOLDER)


def _is_key(x) -> bool:
    return jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def _signature(example: Any) -> tuple[Any, list[bool], list[jax.ShapeDtypeStruct]]:
    """``(treedef, is_key, raw_avals)`` of a tree of arrays (or ``jax.ShapeDtypeStruct``): its structure, which
    leaves are PRNG keys, and each leaf's shape and dtype (a key's as its raw data, `jax.random.key_data`)."""
    leaves, treedef = jax.tree.flatten(example)
    is_key = [_is_key(x) for x in leaves]
    raw_avals = [
        jax.eval_shape(jax.random.key_data, x) if k else jax.ShapeDtypeStruct(x.shape, x.dtype)
        for x, k in zip(leaves, is_key, strict=True)
    ]
    return treedef, is_key, raw_avals


def _key(description: str, treedef, is_key: list[bool], raw_avals: list) -> str:
    """The program key of the module doc: a hash of ``description``, the inputs' tree, shapes and dtypes
    (`_signature`), the source, the versions and the device."""
    device = jax.devices()[0]
    return hashlib.sha256(
        "\n".join(
            [
                description,
                str(treedef),
                repr(is_key),
                repr([(a.shape, str(a.dtype)) for a in raw_avals]),
                _source_hash(),
                jax.__version__,
                getattr(jax.lib, "__version__", ""),
                device.platform,
                device.device_kind,
                str(jax.config.jax_enable_x64),
            ]
        ).encode()
    ).hexdigest()


def cached_jit(fn: Callable, description: str) -> Callable:
    """``jax.jit(fn)`` whose traced program is kept in the program cache (see the module doc): at the first call
    with inputs of a given tree, shapes and dtypes, loaded where a process with the same program key traced it
    before, else traced and saved there.

    Args:
        fn: ``fn(tree) -> pytree`` of arrays (PRNG keys allowed), of one pytree argument.
        description: what ``fn`` closes over, as text (e.g. the repr of its configs); it must change whenever the
            program would.

    Returns:
        A function of a tree of arrays returning what ``fn`` returns (without the cache: ``jax.jit(fn)``).
    """
    folder = cache_folder()
    if folder is None:
        return jax.jit(fn)
    device = jax.devices()[0]
    programs: dict = {}  # (tree, shapes and dtypes) -> (jitted exported program, inputs' is_key, output structure)

    def run(tree):
        # Committed to the device, as the program's outputs are: a later call with its own outputs then reuses the
        # compiled program (jit compiles anew for inputs committed otherwise).
        leaves, treedef = jax.tree.flatten(jax.device_put(tree, device))
        signature = (treedef, tuple((x.shape, x.dtype) for x in leaves))
        if signature not in programs:
            programs[signature] = _program(fn, folder, description, *_signature(tree))
        call, is_key, out_tree = programs[signature]
        out = call(*[jax.random.key_data(x) if k else x for x, k in zip(leaves, is_key, strict=True)])
        out = [jax.random.wrap_key_data(r) if k else r for r, k in zip(out, out_tree["is_key"], strict=True)]
        return jax.tree.unflatten(out_tree["treedef"], out)

    return run


def _program(fn: Callable, folder: str, description: str, treedef, is_key: list[bool], raw_avals: list):
    """``(call, is_key, out_tree)``: ``fn``'s program for inputs of this signature (`_signature`), jitted, which
    leaves of its input are PRNG keys, and its output structure ``{"treedef", "is_key"}``; read from the program
    cache (`_load`), else traced, exported and saved there."""
    path = os.path.join(folder, _key(description, treedef, is_key, raw_avals))
    loaded = _load(path)
    if loaded is not None:
        exported, out_tree = loaded
        return jax.jit(exported.call), is_key, out_tree
    out_tree: dict = {}

    def traced_program(*raw):
        tree = jax.tree.unflatten(
            treedef, [jax.random.wrap_key_data(r) if k else r for r, k in zip(raw, is_key, strict=True)]
        )
        out_leaves, out_tree["treedef"] = jax.tree.flatten(fn(tree))
        out_tree["is_key"] = [_is_key(x) for x in out_leaves]
        return [jax.random.key_data(x) if k else x for x, k in zip(out_leaves, out_tree["is_key"], strict=True)]

    serialized = jax.export.export(jax.jit(traced_program))(*raw_avals).serialize()
    _save(path, serialized, out_tree)
    # Run what later processes will load, so that all of them share one entry of the compilation cache.
    return jax.jit(jax.export.deserialize(serialized).call), is_key, out_tree


def _load(path: str):
    """``(exported, out_tree)`` saved at ``path``, or None if absent or unreadable (then traced anew)."""
    try:
        with open(path + ".jaxexport", "rb") as f:
            exported = jax.export.deserialize(bytearray(f.read()))
        with open(path + ".tree", "rb") as f:
            return exported, pickle.load(f)
    except Exception:  # noqa: BLE001  (a damaged or foreign file, whatever its error, is only a cache miss)
        return None


def _save(path: str, serialized, out_tree: dict) -> None:
    """Write the program and its output structure, each atomically (`_write`)."""
    tree = _pickled(out_tree)
    if tree is not None:
        _write(path + ".tree", tree)
        _write(path + ".jaxexport", bytes(serialized))


def _pickled(obj) -> bytes | None:
    """``obj`` pickled, or None where it cannot be (e.g. a tree node of a class defined in a function)."""
    try:
        return pickle.dumps(obj)
    except (pickle.PicklingError, TypeError, AttributeError):
        return None


def _write(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (a reader never sees half a file); with no writable folder, nothing (a
    later run traces the program again)."""
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError:
        pass
