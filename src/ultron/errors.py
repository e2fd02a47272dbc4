"""Error types. Every error a user can cause is an :class:`UltronError` with a one-line message
that names the file or argument and says what was expected; the CLI prints it and exits 2."""

from __future__ import annotations

import errno
import json
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

_Config = TypeVar("_Config")


class UltronError(Exception):
    """Base class of errors a user can act on (bad input, missing files, no surface)."""


class UltronInputError(UltronError, ValueError):
    """Invalid input: a file, a field inside it, or a function argument.

    The message has the form ``"<where>: <field>: <problem>"`` where ``where`` is the file
    path (or ``argument``) and ``field`` names the offending entry.
    """

    def __init__(self, where: str | Path, field: str, problem: str) -> None:
        self.where = str(where)
        self.field = field
        self.problem = problem
        super().__init__(f"{self.where}: {field}: {problem}")


def argument_error(name: str, problem: str) -> UltronInputError:
    """An :class:`UltronInputError` about a function or CLI argument called ``name``."""
    return UltronInputError("argument", name, problem)


def config_from_dict(cls: type[_Config], data: Mapping[str, Any], name: str) -> _Config:
    """``cls(**data)`` for a config dataclass read from JSON; unknown or missing entries become
    an :func:`argument_error` naming ``name`` instead of a TypeError."""
    try:
        return cls(**data)
    except TypeError as exc:
        raise argument_error(name, f"unexpected entries ({exc})") from None


@contextmanager
def malformed_entries(where: str | Path, field: str) -> Iterator[None]:
    """Read the entry ``field`` of the file ``where`` inside this block: a missing key, a value
    of the wrong type or shape (KeyError, TypeError, ValueError, AttributeError, IndexError,
    RecursionError) or an argument error of the config it builds becomes one
    :class:`UltronInputError` naming the file and the entry."""
    try:
        yield
    except UltronInputError as exc:
        if exc.where != "argument":
            raise
        raise UltronInputError(where, f"{field}.{exc.field}", exc.problem) from None
    except KeyError as exc:
        key = exc.args[0] if exc.args else "?"
        raise UltronInputError(where, field, f"entry {key!r} is missing") from None
    except (TypeError, ValueError, AttributeError, IndexError, RecursionError) as exc:
        text = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
        raise UltronInputError(where, field, f"malformed ({text})") from None


def read_json_file(path: str | Path, field: str) -> Any:
    """The JSON value in ``path``; unreadable text, invalid JSON and nesting too deep for the
    parser are one :class:`UltronInputError` naming the file and ``field``."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UltronInputError(path, field, f"not valid JSON ({exc})") from None
    except RecursionError:
        raise UltronInputError(path, field, "JSON nested too deeply to read") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise UltronInputError(path, field, f"not readable JSON ({exc})") from None
    except OSError as exc:
        raise UltronInputError(path, field, f"cannot be read ({exc.strerror})") from None


#: errno values of a write that the disk or the file-size limit refused.
_DISK_ERRNOS = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}
#: errno values of a file or folder this user may not read or write.
_PERMISSION_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS}
#: errno values of a path that cannot be made: a folder on the way missing or a file, a file
#: where a folder is (or the reverse), a folder that takes no new entries (/proc).
_PATH_ERRNOS = {errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST}
#: What torch's and numpy's allocators say when memory runs out.
_OUT_OF_MEMORY = ("can't allocate memory", "not enough memory", "out of memory")


def resource_error(exc: BaseException) -> str | None:
    """The one-line message for a run that ran out of memory or disk, or whose output path
    cannot be made (None: another error).
    Outputs are written atomically, so what was written before is whole; a field fit resumes
    from its last checkpoint."""
    if isinstance(exc, MemoryError) or (
        isinstance(exc, RuntimeError) and any(s in str(exc).lower() for s in _OUT_OF_MEMORY)
    ):
        return (
            "memory: ran out of memory (the process's limit, ulimit -v or the cgroup's, is"
            " lower than this step needs); give --max-memory, a smaller grid, or more memory"
        )
    if isinstance(exc, OSError) and exc.errno in _PERMISSION_ERRNOS:
        return (
            f"{exc.filename or 'output'}: permission: {exc.strerror} (check the permissions of"
            " the file and its folder, or give another path)"
        )
    if isinstance(exc, OSError) and exc.errno in _PATH_ERRNOS and exc.filename:
        return (
            f"{exc.filename}: path: {exc.strerror} (a folder on the way is missing or is a"
            " file, or the file system takes no new files there); give another path"
        )
    if isinstance(exc, OSError) and exc.errno in _DISK_ERRNOS:
        where = exc.filename or "output"
        return (
            f"{where}: disk: {exc.strerror} (no space left or the file-size limit, ulimit -f,"
            " reached); free space and run again: finished outputs are whole, a fit resumes"
        )
    return None
