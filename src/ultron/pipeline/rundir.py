"""A run directory (``reconstruct``, ``finetune``) is owned by one run and replaced as a whole.

Before any work, :func:`check_run_dir` accepts as ``--out`` a new or empty directory, or one
holding an earlier run of the same kind (its ``run.json``'s ``command``,
:func:`~ultron.pipeline.record.run_kind`). Anything else — a file, a non-empty directory
without a readable run.json, another kind's run, a directory holding one of the run's inputs —
is a one-line error naming the directory.

:func:`staged_run_dir` then collects the new run's files in a hidden sibling
``.<name>.XXXXXXXX.new`` and swaps it in at the end: the previous run (if any) is renamed to
``.<name>.XXXXXXXX.old``, the new one to ``<name>``, and the old one deleted. So no file of an
earlier run survives into a later one (no stale ``network.pt`` or ``metrics.json``), and a run
that fails or is killed before the swap leaves the previous complete run untouched. A live run
holds an ``flock`` on ``.lock`` in its staging directory; the next run into the same ``--out``
removes the staging directories of dead runs and, should a run have died between the two
renames, puts the previous run back first.

What a run's stages save to resume from (:func:`resume_dir`: its network fits' checkpoints)
lives in a third hidden sibling, ``.<name>.resume``, which survives a failed or killed run and
is removed once a run has been swapped in.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from ultron import atomic
from ultron.errors import UltronInputError
from ultron.outputs import check_not_inside_output, check_output_dir, is_inside
from ultron.pipeline.record import RUN_JSON, RUN_KINDS, run_kind

try:  # advisory locks mark a live run's staging directory (POSIX only)
    import fcntl
except ImportError:  # pragma: no cover - Windows: orphans are removed by age only
    fcntl = None  # type: ignore[assignment]

_STAGING, _BACKUP, _LOCK = ".new", ".old", ".lock"


def _previous_kind(out: Path) -> str | None:
    """The command of the run in ``out`` (:func:`~ultron.pipeline.record.run_kind`; only it is
    read, so a run.json of any release counts), None without a readable run.json."""
    try:
        run = json.loads((out / RUN_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return run_kind(run) if isinstance(run, dict) else None


def _is_output_dir(path: Path) -> bool:
    """Whether ``path`` is a directory ultron writes as a whole (a field or a run)."""
    return path.is_dir() and any((path / name).exists() for name in ("field.json", RUN_JSON))


def check_run_dir(
    out: str | Path, kind: str, inputs: Iterable[str | Path | None] = (), option: str = "--out"
) -> Path:
    """Refuse (one-line error naming ``out``) an output directory that this ``kind`` of run
    may not replace as a whole (module doc); creates nothing. Returns ``out`` as a Path."""
    if kind not in RUN_KINDS:
        raise UltronInputError("argument", "kind", f"expected one of {RUN_KINDS}, got {kind!r}")
    out = Path(out)
    recover_interrupted_swap(out)
    check_output_dir(out, option)
    for given in inputs:
        if given is not None and Path(given).exists() and is_inside(given, out):
            raise UltronInputError(
                out, option, f"holds the input {given}; the output directory is replaced as a"
                " whole, give another one",
            )  # fmt: skip
        if given is not None and _is_output_dir(Path(given)) and is_inside(out, given):
            raise UltronInputError(
                out, option, f"lies inside the input {given}, itself an ultron output; a run"
                " is written beside it, never into it: give another directory",
            )  # fmt: skip
    check_not_inside_output(out, option)  # nor into any other field or run
    if not out.is_dir() or not any(out.iterdir()):
        return out
    previous = _previous_kind(out)
    if previous is None:
        raise UltronInputError(
            out, option, f"is not empty and holds no {RUN_JSON} of an earlier ultron run;"
            " give a new or empty directory (a run replaces its output directory as a whole)",
        )  # fmt: skip
    if previous != kind:
        raise UltronInputError(
            out, option, f"holds an earlier {previous} run, not a {kind} run; give another"
            " directory",
        )  # fmt: skip
    return out


def _siblings(out: Path, suffix: str) -> list[Path]:
    pattern = re.compile(rf"\.{re.escape(out.name)}\.[a-z0-9_]{{8}}{re.escape(suffix)}")
    if not out.parent.is_dir():
        return []
    return [p for p in out.parent.iterdir() if pattern.fullmatch(p.name) and p.is_dir()]


def _is_live(directory: Path) -> bool:
    """Whether a live run holds the lock in ``directory`` (or it is too young to tell)."""
    lock = directory / _LOCK
    if fcntl is None or not lock.is_file():
        with contextlib.suppress(OSError):
            return time.time() - directory.stat().st_mtime <= atomic.STALE_AFTER_S
        return False
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def recover_interrupted_swap(out: str | Path) -> None:
    """Undo what dead runs into ``out`` left: put a previous run renamed aside back when
    ``out`` is missing, then remove their backup and staging directories."""
    out = Path(out).absolute()
    for backup in _siblings(out, _BACKUP):
        staging = backup.with_name(backup.name.removesuffix(_BACKUP) + _STAGING)
        if staging.is_dir() and _is_live(staging):
            continue  # a live run between its two renames
        if out.exists():
            shutil.rmtree(backup, ignore_errors=True)
        else:  # never deleted while it is the only copy of the previous run
            with contextlib.suppress(OSError):
                backup.rename(out)
    for staging in _siblings(out, _STAGING):
        if not _is_live(staging):
            shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def staged_run_dir(out: str | Path, kind: str) -> Iterator[Path]:
    """A fresh hidden staging directory beside ``out``; on clean exit it replaces ``out`` as a
    whole (after :func:`check_run_dir` passes again), on an exception it is removed."""
    target = Path(out).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    recover_interrupted_swap(target)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=_STAGING, dir=target.parent))
    lock = os.open(staging / _LOCK, os.O_CREAT | os.O_WRONLY, 0o600)
    try:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
        os.chmod(staging, atomic.directory_mode())  # mkdtemp's 0700 would hide the run
        yield staging
        check_run_dir(target, kind)  # the directory may have changed during the run
        backup = staging.with_name(staging.name.removesuffix(_STAGING) + _BACKUP)
        if target.exists():
            target.rename(backup)
        staging.rename(target)
        shutil.rmtree(backup, ignore_errors=True)
        (target / _LOCK).unlink(missing_ok=True)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):  # name the output the user asked for, not the staging
            exc.filename = atomic.staged_as_output(exc.filename, staging, target)
        raise
    finally:
        os.close(lock)


def resume_dir(out: str | Path) -> Path:
    """The hidden sibling ``.<name>.resume`` of ``out`` where a run into ``out`` keeps what
    it can resume from (module doc); nothing is created."""
    target = Path(out).resolve()
    return target.with_name(f".{target.name}.resume")
