"""``import-plus`` without ``--config``: the frames' own Image → Reference transforms (PLUS's
``ImageToReference``, as a 3D Slicer recording of PLUS's stream holds them) carry the
calibration. They are factored into a rigid pose per frame and one calibration
(:func:`factor_image_to_world`); the import then places every pixel where the transforms do,
as the same recording with its configuration does; interpolated ``--tracking`` keeps the scale;
a changed scale or missing transforms are refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED, assert_refused
from plus_synthetic import (
    Recording,
    calibration,
    plus_world,
    recording,
    write_config,
    write_mha,
)
from test_bad_input_corpus import runner
from test_import_plus import _dataset_world, _probe_points
from test_tracking_files import FRAME_TIMES, _image_sequence, _probe, _transform_file
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.data.plus_geometry import CALIBRATION_SPREAD_MM, factor_image_to_world
from ultron.data.tracking_files import poses_at, read_transform_sequences
from ultron.errors import UltronInputError

PLUS_DIR = SHARED / "data" / "plus-spine-phantom"
PLUS_SEQUENCE = PLUS_DIR / "SpinePhantomFreehand.igs.mha"
PLUS_CONFIG = PLUS_DIR / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"


def _import(*args: str):
    """``import-plus``, at the file's own pixels unless ``args`` set ``--downsample``."""
    native = () if "--downsample" in args else ("--downsample", "1")
    return runner.invoke(app, ["import-plus", *map(str, args), *native], terminal_width=400)


def _image_to_reference(rec: Recording, cal: np.ndarray) -> np.ndarray:
    """PLUS's ImageToReference of every frame: ReferenceToTracker⁻¹ · ProbeToTracker · cal."""
    reference, probe = rec.transforms["ReferenceToTracker"], rec.transforms["ProbeToTracker"]
    return np.linalg.inv(reference) @ probe @ cal


def _image_tracked(rec: Recording, cal: np.ndarray) -> Recording:
    """``rec`` as a recording whose only per-frame transform is ImageToReference."""
    return Recording(rec.frames, {"ImageToReference": _image_to_reference(rec, cal)})


def _pixels(matrix: np.ndarray, width: int, height: int) -> np.ndarray:
    """``matrix`` (4 × 4) applied to the corners and centre of a frame: (5, 3)."""
    points = np.array([[i, j, 0.0, 1.0] for i, j in _probe_points(height, width)])
    return (points @ matrix.T)[:, :3]


# --------------------------------------------------------------------------- the factoring
@pytest.mark.parametrize("shear_deg", [0.0, 3.0])
def test_factoring_places_every_pixel_as_the_transforms_do(shear_deg: float):
    rec, cal = recording(n=5), calibration(spacing=(0.3, 0.25), shear_deg=shear_deg)
    image_to_world = _image_to_reference(rec, cal)
    factored = factor_image_to_world(image_to_world, 16, 12, "s.mha", "ImageToReference")
    assert factored.spread_mm < 1e-9
    plane = factored.plane_to_world
    np.testing.assert_allclose(plane[:, :3, :3] @ np.swapaxes(plane[:, :3, :3], 1, 2),
                               np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.linalg.det(plane[:, :3, :3]), 1.0, atol=1e-12)
    inner = factored.image_to_plane
    assert inner[1, 0] == 0.0 and np.allclose(inner[:3, 2:], np.eye(4)[:3, 2:])
    np.testing.assert_allclose([inner[0, 0], inner[1, 1] / np.cos(np.deg2rad(shear_deg))],
                               [0.3, 0.25], atol=1e-12)  # fmt: skip
    for k in range(5):
        np.testing.assert_allclose(_pixels(plane[k] @ inner, 16, 12),
                                   _pixels(image_to_world[k], 16, 12), atol=1e-9)  # fmt: skip


def test_factoring_refuses_a_scale_that_changes_and_degenerate_axes():
    rec, cal = recording(n=4), calibration(spacing=(0.3, 0.25))
    image_to_world = _image_to_reference(rec, cal)
    zoomed = image_to_world.copy()
    zoomed[2, :3, :2] *= 1.05  # 5 % larger pixels in one frame: 0.2 mm at the far corner
    with pytest.raises(UltronInputError, match="scale or shear changes across frames") as err:
        factor_image_to_world(zoomed, 16, 12, "s.mha", "ImageToReference")
    assert err.value.field == "ImageToReference"
    slightly = image_to_world.copy()  # a tracker's rounding: accepted, and reported
    slightly[1, :3, :2] *= 1 + 1e-6
    spread = factor_image_to_world(slightly, 16, 12, "s.mha", "I").spread_mm
    assert 0 < spread < CALIBRATION_SPREAD_MM
    flat = image_to_world.copy()
    flat[0, :3, 1] = 2 * flat[0, :3, 0]
    with pytest.raises(UltronInputError, match="zero or parallel"):
        factor_image_to_world(flat, 16, 12, "s.mha", "I")


def test_interpolated_image_tracking_keeps_the_pixel_scale(tmp_path: Path):
    """An ImageToTracker sequence (a turning probe times a sheared calibration) interpolated
    between samples keeps the calibration's scale and shear exactly; its origin, interpolated
    linearly as tracking is, lies off the arc it follows by at most the arc's sagitta."""
    cal = calibration(spacing=(0.3, 0.25), shear_deg=3.0)
    times = np.round(9.98 + np.arange(13) / 30.0, 3)
    path = _transform_file(tmp_path / "I.seq.mha", "ImageToTracker", times,
                           lambda t: _probe(t) @ cal)  # fmt: skip
    (transform,) = read_transform_sequences(path)
    queries = np.array([10.0, 10.0123, 10.2])
    matrices, found = poses_at(transform, queries)
    assert found.all()
    sagitta = np.linalg.norm(cal[:3, 3]) * (np.deg2rad(40.0) / 30.0) ** 2 / 8  # 40°/s, 30 Hz
    for query, matrix in zip(queries, matrices, strict=True):
        expected = _probe(float(query)) @ cal
        np.testing.assert_allclose(matrix[:3, :3], expected[:3, :3], atol=1e-9)
        assert np.linalg.norm(matrix[:3, 3] - expected[:3, 3]) <= sagitta + 1e-9
    (at_sample,), _ = poses_at(transform, times[3:4])
    np.testing.assert_allclose(at_sample, _probe(float(times[3])) @ cal, atol=1e-9)


# --------------------------------------------------------------------------- the import
@pytest.mark.parametrize("shear_deg", [0.0, 4.0])
def test_import_without_config_matches_the_import_with_it(tmp_path: Path, shear_deg: float):
    rec = recording(n=4, height=40, width=60)
    cal = calibration(spacing=(0.3, 0.3), shear_deg=shear_deg)
    config = write_config(tmp_path / "c.xml", cal)
    with_config = _import(write_mha(tmp_path / "p.mha", rec), "--config", config,
                          "--out", tmp_path / "a")  # fmt: skip
    assert with_config.exit_code == 0, with_config.output
    plain = _import(write_mha(tmp_path / "i.mha", _image_tracked(rec, cal)), "--out",
                    tmp_path / "b")  # fmt: skip
    assert plain.exit_code == 0, plain.output
    assert "Image → Reference per frame (ImageToReference, no --config" in plain.output
    assert "world frame: Reference (ImageToReference)" in plain.output
    ours, theirs = (SweepDataset.load(tmp_path / d) for d in "ba")
    assert ours.probe == theirs.probe
    np.testing.assert_allclose(ours.sweeps[0].probe_to_world, theirs.sweeps[0].probe_to_world,
                               atol=1e-9)  # fmt: skip
    # resampled (sheared) frames may round a grey level the other way: at most by one
    difference = np.abs(ours.sweeps[0].images.astype(int) - theirs.sweeps[0].images)
    assert difference.max() <= (1 if shear_deg else 0)
    for frame in range(rec.n):  # every pixel where the transforms put it (no shear: exact)
        for i, j in _probe_points(40, 60) if not shear_deg else ():
            expected = plus_world(rec, cal, frame, i, j)
            assert np.abs(_dataset_world(tmp_path / "b", frame, i, j) - expected).max() < 1e-6
    record = ours.metadata["imports"]["i"]
    assert record["config"] is None and record["calibration_from"] == "ImageToReference (per frame)"
    assert record["resampled_to_rigid_grid"] is bool(shear_deg)


def test_import_to_tracker_through_image_to_tracker(tmp_path: Path):
    rec, cal = recording(), calibration()
    tracked = Recording(
        rec.frames,
        {
            "ImageToTracker": rec.transforms["ProbeToTracker"] @ cal,
            "ReferenceToTracker": rec.transforms["ReferenceToTracker"],
        },
    )
    result = _import(write_mha(tmp_path / "s.mha", tracked), "--out", tmp_path / "t",
                     "--to", "Tracker")  # fmt: skip
    assert result.exit_code == 0, result.output
    expected = (rec.transforms["ProbeToTracker"][2] @ cal @ np.array([3.0, 5.0, 0.0, 1.0]))[:3]
    assert np.abs(_dataset_world(tmp_path / "t", 2, 3.0, 5.0) - expected).max() < 1e-6
    result = _import(write_mha(tmp_path / "s.mha", tracked), "--out", tmp_path / "r")
    assert result.exit_code == 0, result.output  # Reference: ReferenceToTracker⁻¹ · ImageTo…
    expected = plus_world(rec, cal, 1, 3.0, 5.0)
    assert np.abs(_dataset_world(tmp_path / "r", 1, 3.0, 5.0) - expected).max() < 1e-6


def test_a_slicer_scene_with_image_tracking_needs_no_config(tmp_path: Path):
    """Frames as a volume sequence and ImageToReference at the tracker's own 30 Hz: each frame
    gets the interpolated transform, and every pixel lands where the probe's pose at the
    frame's time and the calibration put it, up to the sagitta of the image origin's arc
    between samples (the translation is interpolated linearly, as tracking is)."""
    cal = calibration(spacing=(0.3, 0.25), shear_deg=0.0)
    rng = np.random.default_rng(5)
    frames = rng.integers(1, 256, size=(6, 12, 16), dtype=np.uint8)
    image = _image_sequence(tmp_path / "Image.seq.nrrd", frames, FRAME_TIMES)
    times = np.round(9.98 + np.arange(13) / 30.0, 3)
    tracking = _transform_file(tmp_path / "ImageToReference.seq.mha", "ImageToReference",
                               times, lambda t: _probe(t) @ cal)  # fmt: skip
    result = _import(image, "--tracking", tracking, "--orientation", "MF", "--out", tmp_path / "d")
    assert result.exit_code == 0, result.output
    data = SweepDataset.load(tmp_path / "d")
    assert np.array_equal(data.sweeps[0].images, frames)
    sagitta = np.linalg.norm(cal[:3, 3]) * (np.deg2rad(40.0) / 30.0) ** 2 / 8
    for frame, t in enumerate(FRAME_TIMES):
        for i, j in _probe_points(12, 16):
            expected = (_probe(float(t)) @ cal @ np.array([i, j, 0.0, 1.0]))[:3]
            ours = _dataset_world(tmp_path / "d", frame, i, j)
            assert np.linalg.norm(ours - expected) <= sagitta + 1e-9


def test_the_shared_recording_as_image_tracking_imports_as_with_its_config(tmp_path: Path):
    """The real spine phantom rewritten with PLUS's ImageToReference per frame (its sheared
    calibration inside): without --config it imports to the poses of the import with it, and
    the same frames up to a grey level where the resampling rounds the other way."""
    if not PLUS_SEQUENCE.is_file():
        pytest.skip(f"shared PLUS recording not found at {PLUS_DIR}")
    from ultron.data.plus import read_sequence
    from ultron.data.plus_config import read_config

    seq = read_sequence(PLUS_SEQUENCE)
    transforms = {name: np.stack([np.array(f[f"{name}Transform"].split(), float).reshape(4, 4)
                                  for f in seq.frame_fields])
                  for name in ("ProbeToTracker", "ReferenceToTracker")}  # fmt: skip
    rec = Recording(seq.pixels, transforms)
    cal = read_config(PLUS_CONFIG).image_to["Probe"]
    plain = _import(write_mha(tmp_path / "s.mha", _image_tracked(rec, cal)), "--out",
                    tmp_path / "b")  # fmt: skip
    assert plain.exit_code == 0, plain.output
    assert "kept columns 187–631" in plain.output
    with_config = _import(PLUS_SEQUENCE, "--config", PLUS_CONFIG, "--out", tmp_path / "a")
    assert with_config.exit_code == 0, with_config.output
    ours, theirs = (SweepDataset.load(tmp_path / d).sweeps[0] for d in "ba")
    assert ours.images.shape == theirs.images.shape == (21, 616, 445)
    # the file's rotations are rounded to 6 digits (orthonormal to ≈ 1e-6), the factored
    # poses are exact rotations: they agree to 1e-4 mm over the frame's 50 mm
    np.testing.assert_allclose(ours.probe_to_world, theirs.probe_to_world, atol=1e-4)
    difference = np.abs(ours.images.astype(int) - theirs.images)
    assert difference.max() <= 1 and (difference > 0).mean() < 1e-3


def test_missing_image_tracking_or_a_changed_scale_is_a_one_line_error(tmp_path: Path):
    rec, cal = recording(), calibration()
    zoomed = _image_tracked(rec, cal)
    zoomed.transforms["ImageToReference"][3, :3, :2] *= 1.05
    cases = [
        ([write_mha(tmp_path / "p.mha", rec), "--out", tmp_path / "o"],
         "--config: not given, and the sequence has no ImageToReference"),
        ([write_mha(tmp_path / "z.mha", zoomed), "--out", tmp_path / "o"],
         "ImageToReference (per frame): the image's scale or shear changes across frames"),
        ([write_mha(tmp_path / "p.mha", rec), "--out", tmp_path / "o", "--to", "Tracker"],
         "--config: not given, and the sequence has no ImageToTracker"),
    ]  # fmt: skip
    assert_refused(_import, cases)
    assert not (tmp_path / "o").exists()


def test_masks_and_exports_of_a_config_less_import_land_as_with_the_config(tmp_path: Path):
    """An annotator's masks of the recording's frames: read onto the config-less sweep (sheared
    calibration) they give the labels they give the import with the configuration, and the
    export puts them back on the masks they came from."""
    rec = recording(n=4, height=40, width=60)
    cal = calibration(spacing=(0.3, 0.3), shear_deg=4.0)
    masks = np.zeros((4, 40, 60), dtype=np.uint8)
    masks[:, 15:19, 8:50] = 1
    np.save(tmp_path / "m.npy", masks)
    config = write_config(tmp_path / "c.xml", cal)
    (tmp_path / "pa").mkdir(), (tmp_path / "pb").mkdir()  # both recordings named s
    imported = {"a": [write_mha(tmp_path / "pa" / "s.mha", rec), "--config", config],
                "b": [write_mha(tmp_path / "pb" / "s.mha", _image_tracked(rec, cal))]}  # fmt: skip
    labels = {}
    for name, args in imported.items():
        assert _import(*args, "--out", tmp_path / name).exit_code == 0
        result = runner.invoke(app, ["label", str(tmp_path / name), "--masks",
                                     str(tmp_path / "m.npy")])  # fmt: skip
        assert result.exit_code == 0, result.output
        labels[name] = SweepDataset.load(tmp_path / name).sweep("s").labels
    assert (labels["b"] == 1).sum() > 0
    assert np.mean(labels["a"] == labels["b"]) > 0.999
    exported = runner.invoke(app, ["label", str(tmp_path / "b"), "--export",
                                   str(tmp_path / "e.npy")])  # fmt: skip
    assert exported.exit_code == 0, exported.output
    inside = (slice(None), slice(2, 38), slice(3, 57))
    assert np.mean((np.load(tmp_path / "e.npy") == 1)[inside] == (masks == 1)[inside]) > 0.99
