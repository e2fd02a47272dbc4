"""An output directory is owned by one run: a re-run replaces it as a whole, a failed or
killed run leaves the previous one intact, and foreign directories are never touched."""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path

import pytest

from ultron import atomic
from ultron.benchmark.runner import _cell_done
from ultron.errors import UltronInputError
from ultron.metrics.surface import MetricsConfig
from ultron.outputs import check_output_dir, check_output_file
from ultron.pipeline.model_io import load_network
from ultron.pipeline.record import run_kind
from ultron.pipeline.run import ReconstructionRequest, reconstruct
from ultron.pipeline.rundir import check_run_dir, staged_run_dir

REQUEST = ReconstructionRequest(
    method="compounding", label_fraction=1.0, metrics=MetricsConfig(n_points=500, repeats=1)
)


def _run(data: Path, out: Path) -> dict:
    return reconstruct(data, REQUEST, out, report=False)


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _hidden_siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


def test_rerun_replaces_the_whole_directory(tmp_path: Path, tiny_dataset_dir: Path):
    out = tmp_path / "out"
    _run(tiny_dataset_dir, out)
    run = json.loads((out / "run.json").read_text())
    assert run["command"] == "reconstruct" and run["method"] == "compounding"
    # leftovers of an earlier run of another method: a network and metrics of another dataset
    (out / "network.pt").write_bytes(b"an earlier network")
    (out / "metrics.json").write_text('{"cd": 0.1}')
    _run(tiny_dataset_dir, out)
    assert not (out / "network.pt").exists() and not (out / "metrics.json").exists()
    names = sorted(p.name for p in out.iterdir())
    names = [n for n in names if n != "surface_extracted.ply"]  # when the crop dropped faces
    assert names == ["mesh.obj", "mesh.ply", "mesh.stl", "occupancy.nii.gz", "run.json"]
    assert _hidden_siblings(out) == []
    assert out.stat().st_mode & 0o777 == atomic.directory_mode()
    with pytest.raises(UltronInputError, match=r"network\.pt: missing"):
        load_network(out)  # finetune cannot pick up the stale network


def test_failed_run_leaves_the_previous_run_intact(
    tmp_path: Path, tiny_dataset_dir: Path, monkeypatch
):
    out = tmp_path / "out"
    _run(tiny_dataset_dir, out)
    before = _tree(out)

    def killed(*args, **kwargs):
        raise RuntimeError("killed while writing")

    monkeypatch.setattr("ultron.pipeline.run.write_run_json", killed)
    with pytest.raises(RuntimeError, match="killed"):
        _run(tiny_dataset_dir, out)
    assert _tree(out) == before and _hidden_siblings(out) == []
    with pytest.raises(RuntimeError, match="killed"):
        _run(tiny_dataset_dir, tmp_path / "new")
    assert not (tmp_path / "new").exists()  # a first run that fails leaves nothing


def test_into_an_empty_directory(tmp_path: Path, tiny_dataset_dir: Path):
    out = tmp_path / "empty"
    out.mkdir()
    _run(tiny_dataset_dir, out)
    assert (out / "run.json").is_file()


def test_a_run_killed_between_the_renames_is_recovered(tmp_path: Path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text('{"command": "reconstruct"}')
    out.rename(tmp_path / ".out.abcdefgh.old")  # the previous run, renamed aside
    staging = tmp_path / ".out.abcdefgh.new"
    staging.mkdir()
    (staging / "run.json").write_text('{"command": "reconstruct", "new": true}')
    (staging / ".lock").touch()  # nobody holds it: the run is dead
    check_run_dir(out, "reconstruct")
    assert json.loads((out / "run.json").read_text()) == {"command": "reconstruct"}
    assert _hidden_siblings(out) == []


def test_a_live_runs_staging_directory_is_left_alone(tmp_path: Path):
    out = tmp_path / "out"
    staging = tmp_path / ".out.abcdefgh.new"
    staging.mkdir()
    fd = os.open(staging / ".lock", os.O_CREAT | os.O_WRONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        check_run_dir(out, "reconstruct")
        assert staging.is_dir()
    finally:
        os.close(fd)
    unlocked = tmp_path / ".out.ijklmnop.new"  # no lock file: removed once a minute old
    unlocked.mkdir()
    check_run_dir(out, "reconstruct")
    assert unlocked.is_dir()
    old = time.time() - 2 * atomic.STALE_AFTER_S
    os.utime(unlocked, (old, old))
    check_run_dir(out, "reconstruct")
    assert _hidden_siblings(out) == []


def test_a_directory_changed_during_the_run_is_not_replaced(tmp_path: Path):
    out = tmp_path / "out"
    with pytest.raises(UltronInputError, match=r"holds no run\.json"):
        with staged_run_dir(out, "reconstruct") as staging:
            (staging / "run.json").write_text("{}")
            out.mkdir()
            (out / "mine.txt").write_text("not ultron's")
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    assert _hidden_siblings(out) == []


def test_run_kinds_of_run_json():
    assert run_kind({"command": "finetune", "method": "ultron-finetune"}) == "finetune"
    # run.json written before the command was recorded
    assert run_kind({"method": "ultron-finetune"}) == "finetune"
    assert run_kind({"method": "rocosdf"}) == "reconstruct"
    assert run_kind({"mesh": {}}) is None
    with pytest.raises(UltronInputError, match="kind"):
        check_run_dir("anywhere", "demo")


def test_a_failed_benchmark_cell_may_run_again(tmp_path: Path):
    cell = tmp_path / "cell"
    cell.mkdir()
    (cell / "error.log").write_text("Traceback ...")
    assert _cell_done(cell) is False and not (cell / "error.log").exists()
    check_run_dir(cell, "reconstruct")  # an empty directory
    (cell / "run.json").write_text('{"command": "reconstruct"}')
    assert _cell_done(cell) is True


def test_output_path_checks(tmp_path: Path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "dir").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    check_output_file(tmp_path / "new" / "deeper" / "x.json")
    check_output_dir(tmp_path / "new" / "deeper")
    for bad, check, problem in (
        ("dir", check_output_file, "is a directory"),
        ("file", check_output_dir, "not a directory"),
        ("file/x.json", check_output_file, "is not a directory"),
        ("link", check_output_dir, "dangling symlink"),
        ("link/x.json", check_output_file, "dangling symlink"),
    ):
        with pytest.raises(UltronInputError, match=problem):
            check(tmp_path / bad, "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir", "file", "link"]


def test_no_output_is_written_inside_a_field_or_a_run(tmp_path: Path):
    """A run or a field below a field or a run directory would go with it when that one is
    fitted or run again (replaced as a whole): refused in one line naming both; beside them,
    or below a plain folder or a dataset, is fine."""
    from ultron.models.field_dir import check_field_out

    field, run, old_run = tmp_path / "field", tmp_path / "run", tmp_path / "old"
    foreign, plain = tmp_path / "foreign", tmp_path / "plain"
    for folder, name, text in (
        (field, "field.json", '{"format": "ultron-field/1", "step": 3}'),
        (run, "run.json", '{"command": "reconstruct", "method": "ultron"}'),
        (old_run, "run.json", '{"method": "compounding"}'),  # before the command was recorded
        (foreign, "run.json", '{"epochs": 3}'),  # another tool's files of those names
        (foreign, "field.json", '["x"]'),
        (plain, "notes.txt", "{}"),
    ):
        folder.mkdir(exist_ok=True)
        (folder / name).write_text(text)
    dataset = tmp_path / "data"
    dataset.mkdir()
    for parent, kind in ((field, "field"), (run, "run"), (old_run, "run")):
        for out in (parent / "sub", parent / "a" / "b"):
            pattern = rf"^{out}: --out: lies inside {parent}, an ultron {kind} \({kind}\.json\);"
            with pytest.raises(UltronInputError, match=pattern):
                check_run_dir(out, "reconstruct")
            with pytest.raises(UltronInputError, match=pattern):
                check_field_out(out, dataset)
    for out in (tmp_path / "beside", plain / "sub", foreign / "sub", dataset / "run"):
        assert check_run_dir(out, "reconstruct") == out
        assert check_field_out(out, dataset) == out


def test_the_report_is_swapped_in_with_the_run(tmp_path: Path, tiny_dataset_dir: Path, monkeypatch):
    """report.html is built in the staging copy: a run comes with its report, which names the
    run's directory (not the staging one), and a report that cannot be written (a full disk)
    fails the run as a whole, leaving the earlier run as it was."""
    import errno

    out = tmp_path / "out"
    reconstruct(tiny_dataset_dir, REQUEST, out, report=True)
    html = (out / "report.html").read_text()
    assert f"Run directory {out.name}:" in html and str(out) in html and ".new" not in html
    before = _tree(out)

    def full_disk(run_dir, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(run_dir) / "report.html"))

    monkeypatch.setattr("ultron.pipeline.run.write_run_report", full_disk)
    with pytest.raises(OSError, match="No space left") as raised:
        reconstruct(tiny_dataset_dir, REQUEST, out, report=True)
    assert raised.value.filename == str(out.resolve() / "report.html")  # the run's own path
    assert _tree(out) == before and _hidden_siblings(out) == []
