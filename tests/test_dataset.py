"""SweepDataset save/load, atomic writes and importers."""

from __future__ import annotations

import json
import os
import stat
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import make_sweep
from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm
from ultron.data.importers import add_sweep_to_dataset, nearest_rotation, read_ultranerf
from ultron.errors import UltronInputError


def test_save_load_round_trip_is_bit_exact(tmp_path: Path, tiny_dataset: SweepDataset):
    tiny_dataset.save(tmp_path / "a")
    loaded = SweepDataset.load(tmp_path / "a")
    assert loaded.probe == tiny_dataset.probe
    assert loaded.metadata == tiny_dataset.metadata
    assert [s.name for s in loaded.sweeps] == ["row", "column"]
    assert [s.kind for s in loaded.sweeps] == ["row", "column"]
    for a, b in zip(tiny_dataset.sweeps, loaded.sweeps, strict=True):
        for field in ("images", "probe_to_world", "labels"):
            x, y = getattr(a, field), getattr(b, field)
            assert x.dtype == y.dtype and x.shape == y.shape
            assert x.tobytes() == y.tobytes()
    # saving the loaded dataset again reproduces every file byte for byte
    loaded.save(tmp_path / "b")
    for file in sorted((tmp_path / "a").rglob("*")):
        if file.is_file():
            assert (
                file.read_bytes()
                == (tmp_path / "b" / file.relative_to(tmp_path / "a")).read_bytes()
            )


def test_saved_layout_matches_format(tiny_dataset_dir: Path):
    meta = json.loads((tiny_dataset_dir / "dataset.json").read_text())
    assert meta["format"] == "ultron-sweeps/1"
    assert meta["units"] == "mm"
    assert meta["probe"] == {"width_mm": 12.0, "depth_mm": 16.0}
    assert meta["sweeps"] == [{"name": "row", "kind": "row"}, {"name": "column", "kind": "column"}]
    assert meta["reference"] is None
    assert "reference_visible" not in meta  # optional: only when there is one
    assert SweepDataset.load(tiny_dataset_dir).reference_visible_path is None
    assert np.load(tiny_dataset_dir / "row" / "images.npy").dtype == np.uint8
    assert np.load(tiny_dataset_dir / "column" / "labels.npy").shape == (4, 8, 6)
    assert not list(tiny_dataset_dir.rglob("*.tmp"))  # no temporary files left behind


def test_reference_is_copied_and_reloaded(tmp_path: Path, tiny_dataset: SweepDataset):
    mesh = tmp_path / "bone.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    tiny_dataset.reference = mesh
    tiny_dataset.save(tmp_path / "ds")
    loaded = SweepDataset.load(tmp_path / "ds")
    assert loaded.reference == tmp_path / "ds" / "reference.ply"
    assert loaded.reference.read_bytes() == mesh.read_bytes()


def test_ground_truth_files_round_trip(tmp_path: Path, tiny_dataset: SweepDataset):
    """transmission.npy (per sweep) and reference_visible.ply: optional, kept by save/load."""
    mesh = tmp_path / "seen.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    row = tiny_dataset.sweep("row")
    row.true_transmission = np.linspace(1, 0, row.images.size).reshape(row.images.shape)
    row.true_transmission = row.true_transmission.astype(np.float16)
    tiny_dataset.reference_visible_path = mesh
    tiny_dataset.save(tmp_path / "ds")
    meta = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert meta["reference_visible"] == "reference_visible.ply" and meta["reference"] is None
    loaded = SweepDataset.load(tmp_path / "ds")
    assert loaded.reference_visible_path == tmp_path / "ds" / "reference_visible.ply"
    assert loaded.reference_visible_path.read_bytes() == mesh.read_bytes()
    got = loaded.sweep("row").true_transmission
    assert got.dtype == np.float16 and got.tobytes() == row.true_transmission.tobytes()
    assert loaded.sweep("column").true_transmission is None
    assert not (tmp_path / "ds" / "column" / "transmission.npy").exists()
    with pytest.raises(UltronInputError, match=r"transmission.*float16"):
        row.true_transmission = row.true_transmission.astype(np.float32)
        row.__post_init__()
    with pytest.raises(UltronInputError, match=r"transmission.*\[0, 1\]"):
        row.true_transmission = np.full(row.images.shape, 1.5, np.float16)
        row.__post_init__()


def test_reference_key_may_be_absent(tiny_dataset_dir: Path):
    meta = json.loads((tiny_dataset_dir / "dataset.json").read_text())
    del meta["reference"]
    (tiny_dataset_dir / "dataset.json").write_text(json.dumps(meta))
    assert SweepDataset.load(tiny_dataset_dir).reference is None


def test_labelled_frames(tiny_dataset: SweepDataset):
    # the fixture leaves each sweep's last frame unannotated (all 255)
    assert tiny_dataset.sweep("row").labelled_frames.tolist() == [0, 1]
    assert tiny_dataset.sweep("column").labelled_frames.tolist() == [0, 1, 2]


def _interrupt_json(monkeypatch):
    import ultron.atomic

    def explode(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ultron.atomic, "write_json", explode)


def test_interrupted_new_save_leaves_nothing(
    tmp_path: Path, tiny_dataset: SweepDataset, monkeypatch
):
    _interrupt_json(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        tiny_dataset.save(tmp_path / "ds")
    assert list(tmp_path.iterdir()) == []


def test_interrupted_update_keeps_previous_dataset(
    tmp_path: Path, tiny_dataset: SweepDataset, monkeypatch
):
    path = tmp_path / "ds"
    tiny_dataset.save(path)
    before = (path / "dataset.json").read_bytes()
    _interrupt_json(monkeypatch)
    extended = SweepDataset(tiny_dataset.probe, [*tiny_dataset.sweeps, make_sweep("extra", n=2)])
    with pytest.raises(KeyboardInterrupt):
        extended.save(path, only_sweeps=["extra"])
    monkeypatch.undo()
    assert (path / "dataset.json").read_bytes() == before
    assert [s.name for s in SweepDataset.load(path).sweeps] == ["row", "column"]
    assert not list(path.rglob("*.tmp"))


def test_sweep_lookup_error_names_available(tiny_dataset: SweepDataset):
    with pytest.raises(UltronInputError, match="available"):
        tiny_dataset.sweep("nope")


def test_dataset_rejects_duplicate_names_and_size_mismatch():
    probe = ProbeGeometry(12.0, 16.0, 8, 6)
    with pytest.raises(UltronInputError, match="unique"):
        SweepDataset(probe, [make_sweep("a"), make_sweep("a")])
    with pytest.raises(UltronInputError, match="frame size"):
        SweepDataset(probe, [make_sweep("a", h=9)])


def test_nearest_rotation_repairs_shear():
    rotation = np.eye(3)
    rotation[0, 1] = 0.01  # a small shear
    repaired = nearest_rotation(rotation[None])[0]
    np.testing.assert_allclose(repaired @ repaired.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(repaired) == pytest.approx(1.0)
    assert np.abs(repaired - rotation).max() < 0.01


def test_import_ultranerf_png_folder(tmp_path: Path):
    from PIL import Image

    src = tmp_path / "un"
    (src / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, size=(12, 10, 8), dtype=np.uint8)
    for i, frame in enumerate(frames):
        Image.fromarray(frame).save(src / "images" / f"{i}.png")
    poses = np.tile(np.eye(4, dtype=np.float32), (12, 1, 1))
    poses[:, 2, 3] = np.arange(12)
    np.save(src / "poses.npy", poses)
    sweep, probe, report = read_ultranerf(src, 20.0, 30.0, name="s1")
    # numeric (not lexicographic) frame order: 10.png comes after 9.png
    assert sweep.images.tobytes() == frames.tobytes()
    assert probe == ProbeGeometry(20.0, 30.0, 10, 8)
    assert report.n_frames == 12 and report.n_poses_beyond_tolerance == 0
    dataset = add_sweep_to_dataset(tmp_path / "ds", sweep, probe)
    # a second import with another name adds a sweep; the same name is refused
    sweep2, probe2, _ = read_ultranerf(src, 20.0, 30.0, name="s2", kind="row")
    dataset = add_sweep_to_dataset(tmp_path / "ds", sweep2, probe2)
    assert [s.name for s in SweepDataset.load(tmp_path / "ds").sweeps] == ["s1", "s2"]
    with pytest.raises(UltronInputError, match="already has a sweep"):
        add_sweep_to_dataset(tmp_path / "ds", sweep2, probe2)
    replaced = add_sweep_to_dataset(tmp_path / "ds", sweep2, probe2, replace=True)
    assert [s.name for s in replaced.sweeps] == ["s1", "s2"]
    with pytest.raises(UltronInputError, match="probe"):
        other, other_probe, _ = read_ultranerf(src, 21.0, 30.0, name="s3")
        add_sweep_to_dataset(tmp_path / "ds", other, other_probe)
    assert len(dataset.sweeps) == 2


def test_import_refuses_far_from_rigid_poses(tmp_path: Path):
    src = tmp_path / "un"
    src.mkdir()
    np.save(src / "images.npy", np.zeros((2, 4, 4), dtype=np.uint8))
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, 0, 0] = 1.5  # a scale, not a rotation
    np.save(src / "poses.npy", poses)
    with pytest.raises(UltronInputError, match="pose 1 is not rigid"):
        read_ultranerf(src, 10.0, 10.0)


def test_import_shared_l2_sample(tmp_path: Path, l2_sample: Path):
    sweep, probe, report = read_ultranerf(l2_sample, 80.0, 140.0, name="l2")
    add_sweep_to_dataset(tmp_path / "l2", sweep, probe)
    dataset = SweepDataset.load(tmp_path / "l2")
    assert dataset.n_frames == 200
    assert dataset.probe.image_shape == (512, 256)
    assert dataset.probe.lateral_spacing_mm == pytest.approx(0.3125)
    assert dataset.probe.axial_spacing_mm == pytest.approx(0.2734375)
    assert report.max_rotation_deviation < 0.05
    bounds = field_of_view_bounds_mm(dataset.all_poses(), dataset.probe)
    assert torch.isfinite(bounds).all()
    origins = torch.as_tensor(dataset.all_poses()[:, :3, 3])
    assert (origins >= bounds[0]).all() and (origins <= bounds[1]).all()


# ----------------------------------------------------------------- content hash
def _variants(base: SweepDataset) -> dict[str, SweepDataset]:
    """Copies of ``base`` that differ from it in one respect each."""

    def copy() -> SweepDataset:
        return SweepDataset(
            base.probe, [replace(s, images=s.images.copy(), probe_to_world=s.probe_to_world.copy(),
                                 labels=None if s.labels is None else s.labels.copy())
                         for s in base.sweeps],
        )  # fmt: skip

    variants = {}
    variants["pixel"] = d = copy()
    d.sweeps[1].images[2, 3, 4] ^= 1
    variants["pose"] = d = copy()
    d.sweeps[0].probe_to_world[1, 0, 3] += 1e-9
    variants["label"] = d = copy()
    d.sweeps[0].labels[0, 0, 0] = 255 if d.sweeps[0].labels[0, 0, 0] != 255 else 0
    variants["no labels"] = d = copy()
    d.sweeps[0].labels = None
    variants["name"] = d = copy()
    d.sweeps[0].name = "row2"
    variants["order"] = SweepDataset(base.probe, list(reversed(copy().sweeps)))
    variants["probe"] = SweepDataset(replace(base.probe, width_mm=12.5), copy().sweeps)
    variants["frames"] = d = copy()
    sweep = d.sweeps[0]  # one frame fewer
    d.sweeps[0] = replace(sweep, images=sweep.images[:2], probe_to_world=sweep.probe_to_world[:2],
                          labels=sweep.labels[:2])  # fmt: skip
    return variants


def test_content_hash_identifies_the_data(tmp_path: Path, tiny_dataset: SweepDataset):
    digest = tiny_dataset.content_hash()
    assert len(digest) == 64 and int(digest, 16) >= 0  # SHA-256, hex
    tiny_dataset.save(tmp_path / "a")
    assert SweepDataset.load(tmp_path / "a").content_hash() == digest  # as loaded from disk
    # what a field fit does not read and the data does not hold: kinds, metadata, reference
    other = SweepDataset(
        tiny_dataset.probe,
        [replace(s, kind="other") for s in tiny_dataset.sweeps],
        metadata={"note": "x"},
    )
    assert other.content_hash() == digest
    # non-native byte order and non-contiguous arrays hash by value
    sweep = tiny_dataset.sweeps[0]
    swapped = replace(
        sweep,
        images=np.asfortranarray(sweep.images),
        probe_to_world=sweep.probe_to_world.astype(">f8"),
    )
    assert not swapped.images.flags.c_contiguous
    swapped_dataset = SweepDataset(tiny_dataset.probe, [swapped, tiny_dataset.sweeps[1]])
    assert swapped_dataset.content_hash() == digest
    hashes = {name: d.content_hash() for name, d in _variants(tiny_dataset).items()}
    for name, value in hashes.items():
        assert value != digest, name
    assert len(set(hashes.values())) == len(hashes)


def test_new_dataset_directory_is_not_private(tmp_path: Path, tiny_dataset: SweepDataset):
    previous = os.umask(0o022)
    try:
        tiny_dataset.save(tmp_path / "ds")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "ds").stat().st_mode) == 0o755  # not mkdtemp's 0700
    assert stat.S_IMODE((tmp_path / "ds" / "row" / "images.npy").stat().st_mode) == 0o644


def test_memoized_measures_once_per_dataset_object():
    dataset = SweepDataset(ProbeGeometry(6.0, 8.0, 8, 6), [make_sweep()])
    calls = []

    def measure(d: SweepDataset) -> int:
        calls.append(d)
        return len(calls)

    assert dataset.memoized("m", measure) == 1 and dataset.memoized("m", measure) == 1
    assert dataset.memoized("other", measure) == 2  # another key, another measurement
    copy = replace(dataset, metadata={"x": 1})  # a new object remembers nothing
    assert copy.memoized("m", measure) == 3 and calls == [dataset, dataset, copy]
    assert copy == replace(dataset, metadata={"x": 1})  # the memo takes no part in equality
