"""Atomic file output: write to a temporary file beside the target, fsync, then rename.

A reader (or an interrupted run) therefore sees either the old file or the complete new one,
never a truncated file.

Files get the mode an ordinary ``open()`` would give them, ``0o666 & ~umask`` (0644 under the
usual umask 022), not :func:`tempfile.mkstemp`'s private 0600, so that outputs are readable by
whoever may read the directory (see :func:`current_umask`).

The temporary file is ``.<name>.<8 random characters>.tmp`` in the target's directory. A
process killed mid-write (SIGKILL, out of memory, power loss) leaves it behind; the next write of
the same target removes such orphans (:func:`remove_stale_temps`): only files of exactly that
pattern, unlocked and older than :data:`STALE_AFTER_S` (a live writer holds an ``flock`` on its
temporary file from its first microseconds, so a concurrent write of the same target is never
disturbed). A directory written whole (:func:`staged_directory`, the simulator's and an
importer's output) is staged in ``.<name>.XXXXXXXX.tmp/`` and cleaned up the same way.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

try:  # advisory locks mark temporary files that a live writer still owns (POSIX only)
    import fcntl
except ImportError:  # pragma: no cover - Windows: no orphan clean-up
    fcntl = None  # type: ignore[assignment]

#: Orphaned temporary files younger than this are left alone (seconds).
STALE_AFTER_S = 60.0

_TEMP_SUFFIX = ".tmp"
#: tempfile's random part: 8 characters of "abcdefghijklmnopqrstuvwxyz0123456789_".
_RANDOM_PART = r"[a-z0-9_]{8}"


def current_umask() -> int:
    """The process's file-mode creation mask.

    Read from ``/proc/self/status`` (``Umask:``, Linux ≥ 4.7) where available; otherwise by
    setting it and restoring it at once (``os.umask``), which is not thread-safe: a file created
    by another thread in that instant would get mode 0666. Acceptable here (ultron creates files
    from one thread at a time), and never taken on Linux.
    """
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a newly created regular file gets from ``open()``: ``0o666 & ~umask``."""
    return 0o666 & ~current_umask()


def directory_mode() -> int:
    """The mode a newly created directory gets from ``mkdir()``: ``0o777 & ~umask``."""
    return 0o777 & ~current_umask()


def _temp_pattern(name: str) -> re.Pattern[str]:
    return re.compile(rf"\.{re.escape(name)}\.{_RANDOM_PART}{re.escape(_TEMP_SUFFIX)}")


def remove_stale_temps(path: str | Path, older_than_s: float = STALE_AFTER_S) -> list[Path]:
    """Remove orphaned temporary files and staging directories of target ``path`` left by
    interrupted writes.

    Only regular files and directories named exactly as :func:`atomic_open` and
    :func:`staged_directory` name their temporaries of ``path`` (``.<name>.XXXXXXXX.tmp``),
    last modified more than ``older_than_s`` ago and not locked by a live writer, are removed.
    Returns the removed paths (nothing without ``fcntl``).
    """
    path = Path(path)
    if fcntl is None or not path.parent.is_dir():
        return []
    pattern = _temp_pattern(path.name)
    with os.scandir(path.parent) as entries:
        candidates = [e for e in entries if pattern.fullmatch(e.name)]
    return [Path(e.path) for e in candidates if _remove_if_stale(e, older_than_s)]


def _remove_if_stale(entry: os.DirEntry, older_than_s: float) -> bool:
    """Remove the temporary file or staging directory ``entry`` if it is older than
    ``older_than_s`` and no live writer holds its lock; whether it was removed."""
    with contextlib.suppress(OSError):
        folder = entry.is_dir(follow_symlinks=False)
        if not (folder or entry.is_file(follow_symlinks=False)):
            return False
        if time.time() - entry.stat(follow_symlinks=False).st_mtime <= older_than_s:
            return False
        fd = os.open(entry.path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # raises if a writer holds it
            if folder:
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            return True
        finally:
            os.close(fd)
    return False


@contextlib.contextmanager
def _naming(path: Path) -> Iterator[None]:
    """An :class:`OSError` raised while the temporary file or folder of ``path`` is created
    (a read-only or pseudo file system) names ``path``, the output asked for, not the
    temporary name the user never gave."""
    try:
        yield
    except OSError as exc:
        exc.filename = str(path)
        raise


@contextlib.contextmanager
def atomic_open(path: str | Path) -> Iterator[BinaryIO]:
    """Open a binary temporary file next to ``path``; on clean exit it replaces ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched. The new file
    has mode ``0o666 & ~umask``; orphaned temporary files of ``path`` are removed first
    (:func:`remove_stale_temps`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    with _naming(path):
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=_TEMP_SUFFIX, dir=path.parent
        )
    try:
        with os.fdopen(fd, "wb") as handle:
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_EX)  # released when the file is closed (or we die)
            if hasattr(os, "fchmod"):
                os.fchmod(fd, file_mode())
            else:  # pragma: no cover - Windows
                os.chmod(tmp_name, file_mode())
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        if exc.filename is None:  # a write that failed (e.g. a full disk) names its target
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


@contextlib.contextmanager
def staged_directory(path: str | Path) -> Iterator[Path]:
    """A new hidden sibling of ``path`` (mode ``0o777 & ~umask``, not mkdtemp's 0700) to
    write a whole directory into, renamed to ``path`` on success and removed on any failure,
    so ``path`` never holds half of it. ``path`` must not exist yet. The writer holds an
    ``flock`` on the staging directory, so that a later write of ``path`` removes the staging
    directory of a killed one (:func:`remove_stale_temps`) and never a live one's."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    with _naming(path):
        staging = Path(
            tempfile.mkdtemp(prefix=f".{path.name}.", suffix=_TEMP_SUFFIX, dir=path.parent)
        )
    lock = os.open(staging, os.O_RDONLY)
    try:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when closed (or we die)
        os.chmod(staging, directory_mode())
        yield staging
        staging.rename(path)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):  # name the output the user asked for, not the staging
            exc.filename = staged_as_output(exc.filename, staging, path)
        raise
    finally:
        os.close(lock)


def staged_as_output(filename: object, staging: Path, output: Path) -> object:
    """An :class:`OSError`'s ``filename`` inside a ``staging`` directory, as the same path
    under ``output``, the directory the staging becomes (and the user named); any other
    filename unchanged."""
    if not isinstance(filename, str | os.PathLike):
        return filename
    try:
        inside = Path(os.fspath(filename)).relative_to(staging)
    except ValueError:
        return filename
    return str(output / inside)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Atomically write ``data`` to ``path``."""
    with atomic_open(path) as handle:
        handle.write(data)


def write_text(path: str | Path, text: str) -> None:
    """Atomically write UTF-8 ``text`` to ``path``."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, default: Callable[[Any], Any] | None = None) -> None:
    """Atomically write ``obj`` as indented JSON (trailing newline) to ``path``; ``default``
    as ``json.dumps``' (e.g. ``float`` for NumPy scalars)."""
    write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=default) + "\n")


def save_npy(path: str | Path, array: np.ndarray) -> None:
    """Atomically save ``array`` in ``.npy`` format (no pickles) to ``path``."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    write_bytes(path, buffer.getvalue())
