"""Cheap checks of output paths, made before any work: an ``--out`` that names a directory
where a file is expected (or a file where a directory is expected), or that lies below a file
or in a directory this process may not write, is a one-line error naming the path and the
option, not a traceback after minutes of training.

Nothing is created: the checks only look at what exists (the nearest existing ancestor must be
a directory this process may write; directories below it are created when the output is
written).
"""

from __future__ import annotations

import os
from pathlib import Path

from ultron.errors import UltronInputError


def _nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (following symlinks)."""
    current = path.absolute()
    while not current.exists() and current != current.parent:
        if current.is_symlink():
            return current  # a dangling link: reported by the caller
        current = current.parent
    return current


def _check_creatable(path: Path, option: str) -> None:
    """Every missing directory above ``path`` can be created and ``path`` written there."""
    if path.is_symlink() and not path.exists():
        raise UltronInputError(path, option, "is a dangling symlink (or a symlink loop)")
    parent = _nearest_existing(path.absolute().parent)
    if parent.is_symlink() and not parent.exists():
        raise UltronInputError(parent, option, "is a dangling symlink (or a symlink loop)")
    if not parent.is_dir():
        raise UltronInputError(path, option, f"cannot be created: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UltronInputError(path, option, f"cannot be created: {parent} is not writable")


def check_output_file(path: str | Path, option: str = "--out") -> Path:
    """``path`` must be a file name this process can write: not an existing directory (or
    other non-file), below directories that exist or can be created. Returns it as a Path."""
    path = Path(path)
    if path.is_dir():
        raise UltronInputError(path, option, "is a directory; expected a file name")
    if path.exists() and not path.is_file():
        raise UltronInputError(path, option, "exists and is not a regular file")
    _check_creatable(path, option)
    if path.exists() and not os.access(path, os.W_OK):
        raise UltronInputError(path, option, "exists and is not writable")
    return path


def check_output_dir(path: str | Path, option: str = "--out") -> Path:
    """``path`` must be a directory, or absent and creatable: not an existing file. Returns it
    as a Path."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UltronInputError(path, option, "exists and is not a directory")
    _check_creatable(path, option)
    if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
        raise UltronInputError(path, option, "is not writable")
    return path


def is_inside(path: str | Path, directory: str | Path) -> bool:
    """Whether ``path`` is ``directory`` or lies below it (symlinks resolved)."""
    inner, outer = Path(path).resolve(), Path(directory).resolve()
    return inner == outer or outer in inner.parents


#: Files that mark a directory ultron writes and replaces as a whole: a field (field.json, or a
#: fit's checkpoint.pt before it) or a run (run.json).
OUTPUT_MARKERS = {"field.json": "field", "checkpoint.pt": "field", "run.json": "run"}


def check_not_inside_output(path: str | Path, option: str = "--out") -> None:
    """Refuse (one line naming ``path``) an output below a field or a run directory: those
    are replaced as a whole by their next fit or run, which would take it with them."""
    for parent in Path(path).resolve().parents:
        for marker, kind in OUTPUT_MARKERS.items():
            if (parent / marker).is_file():
                raise UltronInputError(
                    path, option, f"lies inside {parent}, an ultron {kind} ({marker}); an"
                    " output is written beside another, never into it: give another directory",
                )  # fmt: skip
