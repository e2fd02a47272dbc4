"""A dataset or a recording cannot make ultron read outside itself: every path a file names
(dataset.json's reference and sweep folders, a sweep's true poses, a sequence's detached data
file) resolves inside its own folder or is refused in one line, exit 2, with nothing outside
opened and nothing written."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import build_tiny_dataset
from plus_synthetic import mha_header, recording, write_config
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.data.validation import contained_path
from ultron.errors import UltronInputError

runner = CliRunner()


@pytest.fixture
def opened(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The resolved paths opened while the test runs (``open``, ``io.open``, ``os.open``)."""
    import builtins
    import io
    import os

    paths: list[str] = []

    def recording(original):
        def opener(file, *args, **kwargs):
            if isinstance(file, str | bytes | os.PathLike):
                paths.append(str(Path(os.fsdecode(file)).resolve()))
            return original(file, *args, **kwargs)

        return opener

    monkeypatch.setattr(builtins, "open", recording(builtins.open))
    monkeypatch.setattr(io, "open", recording(io.open))
    monkeypatch.setattr(os, "open", recording(os.open))
    return paths


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A folder beside the dataset holding a secret mesh, poses and raw bytes."""
    folder = tmp_path / "secret"
    folder.mkdir()
    (folder / "ref.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    np.save(folder / "poses.npy", np.tile(np.eye(4), (3, 1, 1)))
    (folder / "outside.raw").write_bytes(bytes(4 * 12 * 16))
    return folder


@pytest.fixture
def dataset_dir(tmp_path: Path) -> Path:
    path = tmp_path / "data" / "ds"
    build_tiny_dataset().save(path)
    return path


def _edit(data: Path, change: Callable[[dict], None]) -> None:
    meta = json.loads((data / "dataset.json").read_text())
    change(meta)
    (data / "dataset.json").write_text(json.dumps(meta))


def _relative_reference(data: Path, outside: Path) -> str:
    _edit(data, lambda m: m.update(reference="../../secret/ref.ply"))
    return "reference"


def _absolute_reference(data: Path, outside: Path) -> str:
    _edit(data, lambda m: m.update(reference=str(outside / "ref.ply")))
    return "reference"


def _symlinked_reference(data: Path, outside: Path) -> str:
    (data / "reference.ply").symlink_to(outside / "ref.ply")
    _edit(data, lambda m: m.update(reference="reference.ply"))
    return "reference"


def _true_poses_outside(data: Path, outside: Path) -> str:
    _edit(data, lambda m: m["sweeps"][0].update(true_poses="../../../secret/poses.npy"))
    return "sweeps[0].true_poses"


def _sweep_folder_symlinked_out(data: Path, outside: Path) -> str:
    target = outside / "row"
    (data / "row").rename(target)
    (data / "row").symlink_to(target)
    return "sweeps[0].name"


DATASET_CASES = {
    "reference ../": _relative_reference,
    "reference absolute": _absolute_reference,
    "reference symlink": _symlinked_reference,
    "true_poses ../": _true_poses_outside,
    "sweep folder symlink": _sweep_folder_symlinked_out,
}


@pytest.mark.parametrize("case", DATASET_CASES)
def test_a_dataset_naming_a_file_outside_itself_is_refused(
    case: str, dataset_dir: Path, outside: Path, opened: list[str]
) -> None:
    field = DATASET_CASES[case](dataset_dir, outside)
    with pytest.raises(UltronInputError) as caught:
        SweepDataset.load(dataset_dir)
    assert caught.value.field == field
    assert caught.value.where.endswith("dataset.json")
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]


def test_the_cli_refuses_in_one_line_and_writes_nothing(
    dataset_dir: Path, outside: Path, tmp_path: Path, opened: list[str]
) -> None:
    _relative_reference(dataset_dir, outside)
    out = tmp_path / "run"
    result = runner.invoke(app, ["reconstruct", str(dataset_dir), "--out", str(out)])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "reference" in lines[0] and "outside" in lines[0]
    assert "Traceback" not in result.output
    assert not out.exists()
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]


def _detached_mha(folder: Path, data_file: str) -> Path:
    rec = recording(n=4, height=12, width=16)
    header = "".join(f"{k} = {v}\n" for k, v in mha_header(rec))
    path = folder / "rec.igs.mha"
    path.write_text(header + f"ElementDataFile = {data_file}\n", encoding="latin-1")
    return path


@pytest.mark.parametrize("name", ["../secret/outside.raw", "ABSOLUTE", "link.raw"])
def test_a_sequence_whose_data_file_lies_outside_its_folder_is_refused(
    name: str, tmp_path: Path, outside: Path, opened: list[str]
) -> None:
    folder = tmp_path / "rec"
    folder.mkdir()
    if name == "ABSOLUTE":
        name = str(outside / "outside.raw")
    if name == "link.raw":
        (folder / name).symlink_to(outside / "outside.raw")
    sequence = _detached_mha(folder, name)
    config = write_config(folder / "config.xml", np.diag([0.3, 0.25, 1.0, 1.0]))
    out = tmp_path / "ds"
    args = ["import-plus", str(sequence), "--config", str(config), "--out", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "ElementDataFile" in lines[0] and "rec.igs.mha" in lines[0]
    assert not out.exists()
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]


def test_a_data_file_inside_the_folder_is_still_read(tmp_path: Path) -> None:
    from ultron.data.plus import read_sequence

    folder = tmp_path / "rec"
    (folder / "raw").mkdir(parents=True)
    rec = recording(n=4, height=12, width=16)
    (folder / "raw" / "frames.raw").write_bytes(rec.frames.tobytes())
    sequence = read_sequence(_detached_mha(folder, "raw/frames.raw"))
    assert np.array_equal(sequence.pixels, rec.frames)


def test_contained_path_names_the_file_and_field(tmp_path: Path) -> None:
    where = tmp_path / "dataset.json"
    assert contained_path(tmp_path, "a/b.npy", where, "f") == tmp_path / "a" / "b.npy"
    for name in ("", "../x", "/etc/passwd", "~/x", 3):
        with pytest.raises(UltronInputError) as caught:
            contained_path(tmp_path, name, where, "f")
        assert caught.value.field == "f" and caught.value.where == str(where)


def test_an_nrrd_whose_detached_data_file_lies_outside_is_refused(
    tmp_path: Path, outside: Path, opened: list[str]
) -> None:
    from plus_synthetic import write_nrrd
    from ultron.data.plus import read_sequence

    folder = tmp_path / "rec"
    folder.mkdir()
    rec = recording(n=4, height=12, width=16)

    def detached(pairs: list) -> list:  # the header fields only, not the key-values
        return [*pairs, ("data file", "../secret/x")] if pairs[0][0] == "dimension" else pairs

    path = write_nrrd(folder / "rec.seq.nrrd", rec, edit=detached)
    with pytest.raises(UltronInputError) as caught:
        read_sequence(path)
    assert caught.value.field == "data file" and caught.value.where == str(path)
    assert not [p for p in opened if p.startswith(str(outside.resolve()))]
