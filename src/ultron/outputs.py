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


def check_dataset_out(path: str | Path, option: str = "--out") -> Path:
    """``path`` must be a directory a dataset can be written into: new, empty or holding a
    dataset (``dataset.json``) already, never a folder of other files, which a dataset's
    sweep folders would mix with. Returns it as a Path."""
    path = check_output_dir(path, option)
    check_not_inside_output(path, option)  # a run's or field's directory is replaced whole
    if path.is_dir() and not (path / "dataset.json").exists() and any(path.iterdir()):
        raise UltronInputError(
            path, option, "exists, is not empty and holds no dataset.json; give a new or empty"
            " directory",
        )  # fmt: skip
    return path


def is_inside(path: str | Path, directory: str | Path) -> bool:
    """Whether ``path`` is ``directory`` or lies below it (symlinks resolved)."""
    inner, outer = Path(path).resolve(), Path(directory).resolve()
    return inner == outer or outer in inner.parents


def ultron_output_kind(directory: str | Path) -> str | None:
    """ "field" or "run" when ``directory`` holds an ultron field (a ``field.json`` of format
    ``ultron-field/…``, written with every checkpoint of a fit) or an ultron run (a
    ``run.json`` naming its command or method); None otherwise — files of those names written
    by other tools do not count."""
    import json

    for name, kind in (("field.json", "field"), ("run.json", "run")):
        try:
            record = json.loads((Path(directory) / name).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(record, dict):
            continue
        if kind == "field" and str(record.get("format", "")).startswith("ultron-field"):
            return kind
        if kind == "run" and ("command" in record or "method" in record):
            return kind
    return None


def _dataset_sweeps(directory: Path) -> list[str] | None:
    """The sweep names of the ultron dataset whose ``dataset.json`` is in ``directory`` (format
    ``ultron-sweeps/…``), None where there is none."""
    import json

    try:
        meta = json.loads((directory / "dataset.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or not str(meta.get("format", "")).startswith("ultron-sweeps"):
        return None
    sweeps = meta.get("sweeps")
    entries = sweeps if isinstance(sweeps, list) else []
    return [str(e.get("name")) for e in entries if isinstance(e, dict)]


def check_not_a_dataset_file(path: str | Path, option: str = "--out") -> None:
    """Refuse (one line naming ``path``) an output that would replace a file of an ultron
    dataset: an existing file in the dataset's own directory (``dataset.json``, its reference
    meshes) or in one of its sweeps' folders. A new file beside them is allowed."""
    path = Path(path)
    if not path.exists():
        return
    resolved = path.resolve()
    folder = resolved.parent
    owners = [folder] if _dataset_sweeps(folder) is not None else []
    sweeps = _dataset_sweeps(folder.parent)
    if sweeps is not None and folder.name in sweeps:
        owners.append(folder.parent)
    if owners:
        raise UltronInputError(
            path, option, f"is a file of the dataset at {owners[0]}: the output would replace"
            " it; write it elsewhere",
        )  # fmt: skip


def check_not_inside_output(path: str | Path, option: str = "--out") -> None:
    """Refuse (one line naming ``path``) an output below an ultron field or run directory
    (:func:`ultron_output_kind`): those are replaced as a whole by their next fit or run,
    which would take it with them."""
    for parent in Path(path).resolve().parents:
        kind = ultron_output_kind(parent)
        if kind is not None:
            raise UltronInputError(
                path, option, f"lies inside {parent}, an ultron {kind} ({kind}.json); an output"
                " is written beside another, never into it: give another directory",
            )  # fmt: skip
