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
