"""Atomic writes: the user's umask decides the mode, orphaned temporary files are cleaned up."""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ultron import atomic


@contextlib.contextmanager
def umask(mask: int):
    previous = os.umask(mask)
    try:
        yield
    finally:
        os.umask(previous)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def age(path: Path, seconds: float) -> Path:
    """Create ``path`` if missing and set its modification time ``seconds`` in the past."""
    if not path.exists():
        path.write_bytes(b"partial")
    then = time.time() - seconds
    os.utime(path, (then, then))
    return path


@pytest.mark.parametrize(("mask", "expected"), [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_written_files_honour_the_umask(tmp_path: Path, mask: int, expected: int) -> None:
    with umask(mask):
        assert atomic.current_umask() == mask
        atomic.write_text(tmp_path / "a.txt", "x")
        atomic.save_npy(tmp_path / "b.npy", np.zeros(3))
        atomic.write_json(tmp_path / "a.txt", {"again": True})  # a replaced file too
    assert mode(tmp_path / "a.txt") == expected
    assert mode(tmp_path / "b.npy") == expected


@pytest.mark.parametrize(("mask", "expected"), [(0o022, 0o755), (0o077, 0o700)])
def test_a_staged_directory_honours_the_umask_and_leaves_nothing_on_failure(
    tmp_path: Path, mask: int, expected: int
) -> None:
    with umask(mask), atomic.staged_directory(tmp_path / "whole") as staging:
        (staging / "a.txt").write_text("x")
    assert mode(tmp_path / "whole") == expected
    assert (tmp_path / "whole" / "a.txt").read_text() == "x"
    with pytest.raises(OSError), atomic.staged_directory(tmp_path / "half") as staging:
        (staging / "a.txt").write_text("x")
        raise OSError(28, "No space left on device")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["whole"]


def test_simulate_into_a_new_directory_honours_the_umask(tmp_path: Path) -> None:
    from ultron.phantom.dataset import SimulationConfig, simulate_dataset
    from ultron.phantom.protocols import ScanConfig

    config = SimulationConfig(sweeps=("row",), scan=ScanConfig(frames_per_sweep=3), height_px=16,
                              width_px=12)  # fmt: skip
    with umask(0o022):
        simulate_dataset(config, out=tmp_path / "sim")
    assert mode(tmp_path / "sim") == 0o755


def test_umask_fallback_without_proc(monkeypatch) -> None:
    real_open = open

    def no_proc(path, *args, **kwargs):
        if str(path).startswith("/proc/"):
            raise FileNotFoundError(path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", no_proc)
    with umask(0o027):
        assert atomic.current_umask() == 0o027
        assert os.umask(0o027) == 0o027  # restored


def test_stale_temporary_files_of_the_target_are_removed(tmp_path: Path) -> None:
    target = tmp_path / "field.json"
    stale = age(tmp_path / ".field.json.ab_d12x9.tmp", 3600)
    young = tmp_path / ".field.json.zzzzzzzz.tmp"
    young.write_bytes(b"another writer, just started")
    locked = age(tmp_path / ".field.json.lockedxx.tmp", 3600)
    kept = [
        young,
        locked,
        tmp_path / ".other.json.abcdefgh.tmp",  # another target's
        tmp_path / ".field.json.tmp",  # not atomic's pattern
        tmp_path / ".field.json.abcdefgh.tmp.bak",
        tmp_path / "field.json.abcdefgh.tmp",
    ]
    for path in kept[2:]:
        age(path, 3600)
    staging = tmp_path / ".field.json.dir45678.tmp"  # a killed staged_directory's, unlocked
    staging.mkdir()
    (staging / "half.npy").write_bytes(b"partial")
    age(staging, 3600)
    with open(locked, "rb") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # a live writer's file, however old
        atomic.write_json(target, {"ok": 1})
    assert target.is_file() and not stale.exists()
    assert all(path.exists() for path in kept)
    assert not staging.exists()


def killed_mid_write(block: str, target: Path) -> None:
    """Run ``block`` (a ``with`` statement of :mod:`ultron.atomic` writing ``sys.argv[1]``)
    in a new process with ``target`` as its argument, SIGKILLed inside the block."""
    code = "import os, signal, sys\nfrom ultron import atomic\n" + block
    code += "    os.kill(os.getpid(), signal.SIGKILL)\n"
    result = subprocess.run([sys.executable, "-c", code, str(target)], check=False)
    assert result.returncode == -9


def test_orphan_of_a_killed_writer_is_removed_on_the_next_write(tmp_path: Path) -> None:
    target = tmp_path / "checkpoint.pt"
    killed_mid_write(
        "with atomic.atomic_open(sys.argv[1]) as handle:\n"
        "    handle.write(b'half a checkpoint')\n"
        "    handle.flush()\n",
        target,
    )
    orphans = list(tmp_path.glob(".checkpoint.pt.*.tmp"))
    assert len(orphans) == 1 and not target.exists()
    atomic.write_bytes(target, b"new")  # too young to be called stale: kept
    assert orphans[0].exists()
    age(orphans[0], atomic.STALE_AFTER_S + 5)
    atomic.write_bytes(target, b"newer")
    assert not orphans[0].exists() and target.read_bytes() == b"newer"


def test_the_staging_directory_of_a_killed_writer_is_removed_and_a_live_ones_kept(
    tmp_path: Path,
) -> None:
    """``simulate`` killed mid-write leaves ``.OUT.XXXXXXXX.tmp/``; the next staged write of
    ``OUT`` removes it once stale, while a live writer's (locked) staging is never touched."""
    out = tmp_path / "sim"
    killed_mid_write(
        "with atomic.staged_directory(sys.argv[1]) as staging:\n"
        "    (staging / 'frames.npy').write_bytes(b'half a sweep')\n",
        out,
    )
    (orphan,) = tmp_path.glob(".sim.*.tmp")
    assert orphan.is_dir() and not out.exists()
    with atomic.staged_directory(tmp_path / "sim2") as live:
        age(live, atomic.STALE_AFTER_S + 5)
        assert atomic.remove_stale_temps(tmp_path / "sim2") == []  # locked by this writer
    with atomic.staged_directory(out) as staging:  # too young to be called stale: kept
        (staging / "a").write_bytes(b"1")
    assert orphan.is_dir()
    shutil.rmtree(out)
    age(orphan, atomic.STALE_AFTER_S + 5)
    with atomic.staged_directory(out) as staging:
        (staging / "a").write_bytes(b"2")
    assert not orphan.exists() and (out / "a").read_bytes() == b"2"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim", "sim2"]


def test_failed_write_leaves_no_temporary_file(tmp_path: Path) -> None:
    (tmp_path / "a.bin").write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic.atomic_open(tmp_path / "a.bin") as handle:
        handle.write(b"new")
        raise RuntimeError("interrupted")
    assert (tmp_path / "a.bin").read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


@pytest.mark.parametrize("maker", ["mkstemp", "mkdtemp"])
def test_a_temporary_that_cannot_be_made_names_the_output(tmp_path: Path, monkeypatch, maker):
    """A file system that takes no new entries (/proc) fails at the temporary's creation: the
    error names the output asked for, not the temporary name."""
    import tempfile

    def refuse(prefix: str, suffix: str, dir: str):
        raise FileNotFoundError(2, "No such file or directory", f"{dir}/{prefix}abc{suffix}")

    monkeypatch.setattr(tempfile, maker, refuse)
    out = tmp_path / "out.npy"
    with pytest.raises(FileNotFoundError) as caught:
        if maker == "mkstemp":
            atomic.save_npy(out, np.zeros(3))
        else:
            with atomic.staged_directory(out):
                pass
    assert caught.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []
