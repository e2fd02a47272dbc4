"""``ultron import-plus``: PLUS / 3D Slicer sequences (MetaImage and NRRD, raw and compressed),
their orientation, statuses, calibration and clip rectangle; the pixel → world map against
PLUS's ``ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe · [i, j, 0, 1]``; bad input."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import SHARED
from plus_synthetic import (
    Recording,
    calibration,
    frame_fields,
    plus_world,
    recording,
    write_config,
    write_mha,
    write_nrrd,
)
from test_bad_input_corpus import check_refused, runner, snapshot
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.data.geometry import pixel_to_world
from ultron.data.plus import read_sequence
from ultron.data.plus_geometry import downsample_frames, fit_image_plane
from ultron.data.resolution import lit_column_range, signal_columns
from ultron.errors import UltronError

PLUS_DIR = SHARED / "data" / "plus-spine-phantom"
PLUS_SEQUENCE = PLUS_DIR / "SpinePhantomFreehand.igs.mha"
PLUS_CONFIG = PLUS_DIR / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
#: The columns [start, stop) of the shared recording's frames that hold signal.
KEPT = (187, 632)


def _import(sequence: Path, config: Path, out: Path, *more: str):
    """``import-plus``, at the file's own pixels unless ``more`` sets ``--downsample``."""
    native = () if "--downsample" in more else ("--downsample", "1")
    args = ["import-plus", str(sequence), "--config", str(config), "--out", str(out), *more]
    return runner.invoke(app, [*args, *native], terminal_width=400)


def _dataset_world(out: Path, frame: int, i: float, j: float, sweep: int = 0) -> np.ndarray:
    """Where ultron's geometry path puts pixel (row j, column i) of frame ``frame``."""
    data = SweepDataset.load(out)
    poses = torch.as_tensor(data.sweeps[sweep].probe_to_world[frame : frame + 1])
    rows = torch.tensor(float(j), dtype=torch.float64)
    cols = torch.tensor(float(i), dtype=torch.float64)
    return pixel_to_world(poses, rows, cols, data.probe)[0].numpy()


def _probe_points(height: int, width: int) -> list[tuple[float, float]]:
    """(i, j) of the four corners and the centre of a frame."""
    corners = [(i, j) for i in (0.0, width - 1.0) for j in (0.0, height - 1.0)]
    return [*corners, ((width - 1) / 2, (height - 1) / 2)]


# --------------------------------------------------------------------------- the real file
def _plus_oracle(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-frame transforms read with a regex and the calibration with ElementTree: an
    implementation of PLUS's formula independent of the importer."""
    import xml.etree.ElementTree as ET

    head = path.read_bytes().split(b"ElementDataFile")[0].decode("latin-1")
    transforms: dict[str, dict[int, np.ndarray]] = {}
    for frame, name, values in re.findall(r"Seq_Frame(\d+)_(\w+)Transform = ([^\n]+)", head):
        matrix = np.array(values.split(), dtype=np.float64).reshape(4, 4)
        transforms.setdefault(name, {})[int(frame)] = matrix
    stacked = {name: np.stack([m[k] for k in sorted(m)]) for name, m in transforms.items()}
    root = ET.parse(PLUS_CONFIG).getroot()
    element = next(e for e in root.iter("Transform") if e.get("From") == "Image")
    image_to_probe = np.array(element.get("Matrix").split(), dtype=np.float64).reshape(4, 4)
    return stacked, image_to_probe


@pytest.fixture(scope="module")
def real_import(tmp_path_factory) -> tuple[Path, str]:
    if not PLUS_SEQUENCE.is_file() or not PLUS_CONFIG.is_file():
        pytest.skip(f"shared PLUS recording not found at {PLUS_DIR}")
    out = tmp_path_factory.mktemp("plus") / "spine"
    result = _import(PLUS_SEQUENCE, PLUS_CONFIG, out)
    assert result.exit_code == 0, result.output
    return out, result.output


def test_real_file_imports(real_import):
    out, output = real_import
    data = SweepDataset.load(out)
    sweep = data.sweeps[0]
    # the file's columns outside 187–631 are 0 in every frame (MFA → MF: no flip): dropped
    pixels = read_sequence(PLUS_SEQUENCE).pixels
    lit = np.flatnonzero(pixels.any(axis=(0, 1)))
    assert (lit[0], lit[-1]) == (KEPT[0], KEPT[1] - 1) and pixels.shape[2] == 820
    assert sweep.name == "SpinePhantomFreehand" and sweep.images.shape == (21, 616, 445)
    assert "orientation MFA → MF (no flip)" in output
    assert "kept columns 187–631" in output and "clip rectangle: origin (187, 0)" in output
    assert "skipped 0 of 21 frames" in output
    assert re.search(r"at most 0\.7\d\d mm \(RMS 0\.4\d\d mm\)", output), output
    imports = data.metadata["imports"][sweep.name]
    assert imports["kept_columns"] == list(KEPT)
    assert imports["world"] == "Reference" and imports["frames"] == list(range(21))
    assert math.isclose(abs(imports["shear_deg"]), 2.745, abs_tol=1e-3)


def test_real_file_pixel_to_world_matches_plus(real_import):
    """At the corners and the centre of every frame, ultron's map equals PLUS's formula with
    the rigid-factored calibration to 1e-6 mm; against PLUS's own (sheared) calibration it is
    exact at the centre and off by the reported residual at the corners — which is why the
    frames are resampled (next test)."""
    out, _ = real_import
    transforms, image_to_probe = _plus_oracle(PLUS_SEQUENCE)
    data = SweepDataset.load(out)
    imports = data.metadata["imports"]["SpinePhantomFreehand"]
    fitted = np.array(imports["fitted_image_to_probe"])
    axes = fitted[:3, :2] / np.linalg.norm(fitted[:3, :2], axis=0)
    assert abs(axes[:, 0] @ axes[:, 1]) < 1e-12  # a scaled rotation
    residual = imports["rigid_fit_residual_mm"]["max"]
    worst = 0.0
    for frame in range(21):
        chain = np.linalg.inv(transforms["ReferenceToTracker"][frame])
        chain = chain @ transforms["ProbeToTracker"][frame]
        for i, j in _probe_points(616, KEPT[1] - KEPT[0]):
            ours = _dataset_world(out, frame, i, j)
            pixel = np.array([i, j, 0.0, 1.0])  # the fit maps the kept columns' pixels
            assert np.abs(ours - (chain @ fitted @ pixel)[:3]).max() < 1e-6
            in_file = np.array([i + KEPT[0], j, 0.0, 1.0])  # PLUS maps the file's pixels
            deviation = float(np.linalg.norm(ours - (chain @ image_to_probe @ in_file)[:3]))
            if (i, j) == (222.0, 307.5):  # the kept frame's centre
                assert deviation < 1e-6
            worst = max(worst, deviation)
    assert residual - 1e-3 < worst < residual + 1e-3


def test_real_file_frames_are_resampled_so_corners_land_where_plus_puts_them(real_import):
    """Issue 31, item 5: the grey level of every original corner pixel is imported at the rigid
    grid's pixel whose world point is PLUS's own placement of that corner (within 0.3 mm; by
    construction to 1e-6 mm), on every frame."""
    from ultron.data.plus_geometry import rigid_to_image_pixels

    out, output = real_import
    assert "resampled onto the rigid grid" in output
    transforms, image_to_probe = _plus_oracle(PLUS_SEQUENCE)
    data = SweepDataset.load(out)
    imports = data.metadata["imports"]["SpinePhantomFreehand"]
    assert imports["resampled_to_rigid_grid"] is True
    fitted = np.array(imports["fitted_image_to_probe"])
    # the rigid grid's pixel (i', j') holds original pixel M·(i', j'): invert for the corners
    from ultron.data.plus_geometry import ImagePlaneFit

    axes = fitted[:3, :2]
    spacing = tuple(float(s) for s in np.linalg.norm(axes, axis=0))
    rotation = np.stack([axes[:, 0] / spacing[0], axes[:, 1] / spacing[1], fitted[:3, 2]], 1)
    fit = ImagePlaneFit(rotation, fitted[:3, 3], spacing, 0.0, 0.0, 0.0)
    to_original = rigid_to_image_pixels(image_to_probe, fit)
    for frame in range(21):
        chain = np.linalg.inv(transforms["ReferenceToTracker"][frame])
        chain = chain @ transforms["ProbeToTracker"][frame]
        for i, j in _probe_points(616, KEPT[1] - KEPT[0]):
            rigid = np.linalg.solve(to_original, np.array([i + KEPT[0], j, 1.0]))
            ours = _dataset_world(out, frame, rigid[0], rigid[1])  # the file's pixel → kept grid
            theirs = (chain @ image_to_probe @ np.array([i + KEPT[0], j, 0.0, 1.0]))[:3]
            assert np.linalg.norm(ours - theirs) < 0.3


def test_real_file_masks_land_on_the_echo_they_mark(real_import, tmp_path: Path):
    """``label --masks`` on the real recording (MFA, a 2.74° shear, blank columns): masks of
    every 5th frame, a threshold of the file's frames standing in for an annotator, become
    labels that agree with the same threshold of the imported (resampled) frames on ≥ 99 % of
    the annotated pixels, and the other frames stay unsure."""
    import shutil

    out = tmp_path / "spine"
    shutil.copytree(real_import[0], out)
    masks = (read_sequence(PLUS_SEQUENCE).pixels > 180).astype(np.uint8)  # MFA: as MF
    masks[np.arange(21) % 5 != 0] = 0
    np.save(tmp_path / "m.npy", masks)
    result = runner.invoke(app, ["label", str(out), "--masks", str(tmp_path / "m.npy")])
    assert result.exit_code == 0, result.output
    sweep = SweepDataset.load(out).sweeps[0]
    annotated = (sweep.labels != 255).any(axis=(1, 2))
    assert np.flatnonzero(annotated).tolist() == [0, 5, 10, 15, 20]
    known = sweep.labels != 255
    agree = (sweep.labels == 1) == (sweep.images > 180)
    assert agree[known].mean() > 0.99
    assert known[annotated].mean() > 0.98  # but the resampled grid's corners, outside the file


# --------------------------------------------------------------------------- synthetic
def _files(tmp: Path, rec: Recording, fmt: str, orientation="MF", compressed=False) -> Path:
    writer = write_mha if fmt == "mha" else write_nrrd
    return writer(tmp / f"s.seq.{fmt}", rec, orientation, compressed)


@pytest.mark.parametrize("fmt", ["mha", "nrrd"])
@pytest.mark.parametrize("compressed", [False, True])
def test_synthetic_round_trip(tmp_path: Path, fmt: str, compressed: bool):
    rec = recording()
    cal = calibration()
    sequence = _files(tmp_path, rec, fmt, compressed=compressed)
    seq = read_sequence(sequence)
    assert np.array_equal(seq.pixels, rec.frames)
    assert seq.transform_names() == ["ProbeToTracker", "ReferenceToTracker"]
    assert seq.frame_fields[2]["ProbeToTrackerTransformStatus"] == "OK"
    out = tmp_path / "ds"
    result = _import(sequence, write_config(tmp_path / "c.xml", cal), out, "--kind", "row")
    assert result.exit_code == 0, result.output
    data = SweepDataset.load(out)
    assert np.array_equal(data.sweeps[0].images, rec.frames)
    assert data.sweeps[0].name == "s" and data.sweeps[0].kind == "row"
    for frame in range(rec.n):
        for i, j in _probe_points(12, 16):
            expected = plus_world(rec, cal, frame, i, j)
            assert np.abs(_dataset_world(out, frame, i, j) - expected).max() < 1e-6


def _centroid(image: np.ndarray) -> tuple[float, float]:
    """(column i, row j) of the intensity-weighted centre of the frame's bright pixels."""
    weights = np.where(image > 20, image.astype(np.float64), 0.0)
    rows, cols = np.indices(image.shape)
    return float((cols * weights).sum() / weights.sum()), float(
        (rows * weights).sum() / weights.sum()
    )


@pytest.mark.parametrize(
    ("at", "shear_deg"), [((4.0, 4.0), 4.0), ((55.0, 35.0), 4.0), ((4.0, 35.0), -5.0)]
)
def test_sheared_calibration_puts_every_echo_where_plus_does(tmp_path: Path, at, shear_deg):
    """A 3 × 3 marker near a corner of a 40 × 60 frame: with a sheared ImageToProbe the rigid
    pose alone would misplace it by up to the fit's residual; the importer resamples the frames
    onto the rigid grid, and the marker's centre lands where PLUS's own formula puts it."""
    rec = recording(n=2, height=40, width=60)
    rec.frames[:] = 0
    i, j = at
    rec.frames[:, int(j) - 1 : int(j) + 2, int(i) - 1 : int(i) + 2] = 255
    cal = calibration(spacing=(0.3, 0.3), shear_deg=shear_deg)
    fit = fit_image_plane(cal, 60, 40, "c.xml", "Transform")
    assert fit.residual_max_mm > 0.3  # the rigid factorisation alone would miss by this much
    out = tmp_path / "ds"
    config = write_config(tmp_path / "c.xml", cal)  # the blank columns kept: a whole frame
    result = _import(_files(tmp_path, rec, "mha"), config, out, "--keep-blank-columns")
    assert result.exit_code == 0, result.output
    assert "resampled onto the rigid grid" in result.output
    data = SweepDataset.load(out)
    assert data.metadata["imports"]["s"]["resampled_to_rigid_grid"] is True
    for frame in range(rec.n):
        col, row = _centroid(data.sweeps[0].images[frame])
        expected = plus_world(rec, cal, frame, i, j)
        assert np.linalg.norm(_dataset_world(out, frame, col, row) - expected) < 0.05


def test_import_progress_and_threaded_resampling(tmp_path: Path, monkeypatch):
    """A sheared recording of 70 frames (two runs of resampling): the import tells each stage
    in order and counts the frames resampled; the frames resampled on threads equal those
    resampled one at a time; off a terminal the log names each stage as it starts."""
    import ultron.data.plus_geometry as plus_geometry
    from ultron.pipeline.sweep_import import import_plus_sweep

    rec = recording(n=70, height=20, width=30)
    sequence = _files(tmp_path, rec, "mha")
    config = write_config(tmp_path / "c.xml", calibration(spacing=(0.3, 0.3), shear_deg=4.0))
    events: list[tuple[str, int, int]] = []
    import_plus_sweep(sequence, config, tmp_path / "a", progress=lambda *e: events.append(e))
    run = plus_geometry.RESAMPLE_RUN
    assert events == [("reading", 0, 1), ("resampling", 0, 70), ("resampling", run, 70),
                      ("resampling", 70, 70), ("writing", 0, 1)]  # fmt: skip
    threaded = SweepDataset.load(tmp_path / "a").sweeps[0].images
    one = plus_geometry.thread_map
    monkeypatch.setattr(plus_geometry, "thread_map", lambda f, items: one(f, items, workers=1))
    import_plus_sweep(sequence, config, tmp_path / "b")
    assert np.array_equal(SweepDataset.load(tmp_path / "b").sweeps[0].images, threaded)
    result = _import(sequence, config, tmp_path / "c")
    assert result.exit_code == 0, result.output
    starts = [line for line in result.stdout.splitlines() if line.endswith("…")]
    assert starts == ["import reading …", "import resampling …", "import writing …"]


def test_an_exact_scaled_rotation_keeps_the_frames_as_they_are(tmp_path: Path):
    rec = recording()
    out = tmp_path / "ds"
    result = _import(
        _files(tmp_path, rec, "mha"), write_config(tmp_path / "c.xml", calibration()), out
    )
    assert result.exit_code == 0 and "resampled" not in result.output
    data = SweepDataset.load(out)
    assert np.array_equal(data.sweeps[0].images, rec.frames)
    assert data.metadata["imports"]["s"]["resampled_to_rigid_grid"] is False


def test_nrrd_with_the_frame_list_first(tmp_path: Path):
    """A NRRD written by pynrrd with the frames on the first (fastest) axis, as Slicer's
    volume sequences store them, and the per-frame fields as key-value pairs."""
    import nrrd

    rec = recording()
    cal = calibration()
    fields = dict(frame_fields(rec))
    header = {"kinds": ["list", "domain", "domain"], "ultrasound image orientation": "MF"}
    sequence = tmp_path / "slicer.seq.nrrd"
    nrrd.write(str(sequence), rec.frames.transpose(1, 2, 0), {**header, **fields}, index_order="C")
    assert np.array_equal(read_sequence(sequence).pixels, rec.frames)
    out = tmp_path / "ds"
    result = _import(sequence, write_config(tmp_path / "c.xml", cal), out)
    assert result.exit_code == 0, result.output
    expected = plus_world(rec, cal, 3, 15.0, 0.0)
    assert np.abs(_dataset_world(out, 3, 15.0, 0.0) - expected).max() < 1e-6


@pytest.mark.parametrize("orientation", ["UF", "MN", "UN", "MFA", "UFD", "UNA", "mn"])
def test_orientation_flips_back_to_the_same_world_points(tmp_path: Path, orientation: str):
    """A sequence stored flipped (as PLUS defines the orientation strings) imports to the same
    frames and poses as its MF original: every pixel lands on the same world point."""
    rec = recording(seed=3)
    cal = calibration()
    config = write_config(tmp_path / "c.xml", cal)
    assert _import(write_mha(tmp_path / "mf.mha", rec, "MF"), config, tmp_path / "a").exit_code == 0
    flipped = write_mha(tmp_path / "other.mha", rec, orientation.upper())
    if orientation == "mn":  # orientation strings are case-insensitive, as in PLUS
        flipped.write_bytes(flipped.read_bytes().replace(b"= MN\n", b"= mn\n"))
    result = _import(flipped, config, tmp_path / "b")
    assert result.exit_code == 0, result.output
    a, b = SweepDataset.load(tmp_path / "a"), SweepDataset.load(tmp_path / "b")
    assert np.array_equal(a.sweeps[0].images, b.sweeps[0].images)
    assert np.allclose(a.sweeps[0].probe_to_world, b.sweeps[0].probe_to_world, atol=1e-12)
    # the brightest pixel of MF frame 1 lands where PLUS puts it
    j, i = np.unravel_index(int(np.argmax(rec.frames[1])), rec.frames[1].shape)
    expected = plus_world(rec, cal, 1, float(i), float(j))
    assert np.abs(_dataset_world(tmp_path / "b", 1, i, j) - expected).max() < 1e-6


@pytest.mark.parametrize(
    ("option", "message"),
    [  # --orientation is used only where the file records none, but is checked when given
        (["--orientation", "QQ"], "--orientation: unknown orientation 'QQ'"),
        (["--downsample", "1e9"], "--downsample: 1e+09 leaves frames of 1 × 1 pixels"),
    ],
)
def test_an_option_that_cannot_apply_is_refused_before_any_work(tmp_path: Path, option, message):
    sequence = write_mha(tmp_path / "mf.mha", recording(), "MF")
    config = write_config(tmp_path / "c.xml", calibration())
    result = _import(sequence, config, tmp_path / "ds", *option)
    assert result.exit_code == 2
    assert message in result.stderr
    assert not (tmp_path / "ds").exists()


def test_a_calibration_given_twice_must_agree(tmp_path: Path):
    """The same Image → Probe twice, or once each way, is one calibration; two that differ
    are refused naming the second (PLUS's choice between them is not ultron's to guess)."""
    from plus_synthetic import _matrix_text
    from ultron.data.plus_config import read_config

    cal = calibration()
    config = write_config(tmp_path / "c.xml", cal)
    text = config.read_text()
    line = next(t for t in text.splitlines() if 'From="Image" To="Probe"' in t)
    inverse = f'<Transform From="Probe" To="Image" Matrix="{_matrix_text(np.linalg.inv(cal))}"/>'
    same = tmp_path / "same.xml"
    same.write_text(text.replace(line, f"{line}\n{line}\n    {inverse}"))
    assert np.allclose(read_config(same).image_to["Probe"], cal, atol=1e-9)
    other = tmp_path / "other.xml"
    identity = '<Transform From="Image" To="Probe" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>'
    other.write_text(text.replace(line, f"    {identity}\n{line}"))
    with pytest.raises(UltronError, match=r"other\.xml: Transform Image → Probe: differs from"):
        read_config(other)


def test_invalid_frames_are_skipped_and_counted(tmp_path: Path):
    rec = recording(n=5)
    rec.statuses["ProbeToTracker"] = ["OK", "INVALID", "OK", "OK", "MISSING"]
    rec.transforms["ProbeToTracker"][1] = np.nan  # NaN is fine when the status is not OK
    rec.image_status = ["OK", "OK", "INVALID", "OK", "OK"]
    out = tmp_path / "ds"
    result = _import(
        write_nrrd(tmp_path / "s.seq.nrrd", rec),
        write_config(tmp_path / "c.xml", calibration()),
        out,
    )
    assert result.exit_code == 0, result.output
    assert "skipped 3 of 5 frames" in result.output
    assert "ProbeToTrackerTransformStatus INVALID" in result.output
    assert "Status INVALID" in result.output
    data = SweepDataset.load(out)
    assert np.array_equal(data.sweeps[0].images, rec.frames[[0, 3]])
    assert data.metadata["imports"]["s"]["frames"] == [0, 3]


def test_to_tracker(tmp_path: Path):
    rec = recording()
    cal = calibration()
    out = tmp_path / "ds"
    sequence = write_mha(tmp_path / "s.igs.mha", rec, compressed=True)
    result = _import(sequence, write_config(tmp_path / "c.xml", cal), out, "--to", "Tracker")
    assert result.exit_code == 0, result.output
    pixel = np.array([3.0, 5.0, 0.0, 1.0])
    expected = (rec.transforms["ProbeToTracker"][2] @ cal @ pixel)[:3]
    assert np.abs(_dataset_world(out, 2, 3.0, 5.0) - expected).max() < 1e-6


def _assert_plus_pixels(out: Path, rec, cal, frame: int, origin, pixels) -> None:
    """Pixel (c, r) of the import at ``out`` is PLUS's pixel (i0 + c, j0 + r) of the file,
    ``origin`` = (i0, j0), to 1e-6 mm on ``frame``, for each (c, r) of ``pixels``."""
    for c, r in pixels:
        expected = plus_world(rec, cal, frame, origin[0] + c, origin[1] + r)
        assert np.abs(_dataset_world(out, frame, c, r) - expected).max() < 1e-6


def _import_clipped(tmp_path: Path, rec: Recording, cal, clip) -> tuple[Path, SweepDataset]:
    """``rec`` written as s.mha with a configuration clipping it to ``clip``, imported into
    tmp_path/ds (the import must succeed): the dataset's folder and the dataset."""
    config = write_config(tmp_path / "c.xml", cal, clip=clip)
    out = tmp_path / "ds"
    result = _import(write_mha(tmp_path / "s.mha", rec), config, out)
    assert result.exit_code == 0, result.output
    return out, SweepDataset.load(out)


def test_clip_rectangle(tmp_path: Path):
    rec = recording()
    cal = calibration()
    out, data = _import_clipped(tmp_path, rec, cal, ((2, 3), (10, 6)))
    assert np.array_equal(data.sweeps[0].images, rec.frames[:, 3:9, 2:12])
    _assert_plus_pixels(out, rec, cal, 1, (2, 3), ((0, 0), (9, 5), (4, 2)))


def _blank_sides(rec: Recording, start: int, stop: int) -> Recording:
    """``rec`` with every frame's columns outside [start, stop) set to 0, and the first kept
    column 0 except for one pixel of one frame (so it is kept because of that pixel alone)."""
    rec.frames[:, :, :start] = 0
    rec.frames[:, :, stop:] = 0
    rec.frames[:, :, start : start + 1] = 0
    rec.frames[1, 5, start] = 9
    return rec


def test_blank_columns_are_dropped_and_every_pixel_stays_where_plus_puts_it(tmp_path: Path):
    """Columns 0 in every frame (outside the aperture) are dropped, the first kept column is
    lit on one frame only; pixel (r, c) of the import is PLUS's pixel (c + start, r), and the
    clip rectangle recorded is the kept one. ``--keep-blank-columns`` keeps the frame whole."""
    rec = _blank_sides(recording(), 3, 13)
    cal = calibration()
    config = write_config(tmp_path / "c.xml", cal)
    out = tmp_path / "ds"
    result = _import(write_mha(tmp_path / "s.mha", rec), config, out)
    assert result.exit_code == 0, result.output
    assert "kept columns 3–12" in result.output
    data = SweepDataset.load(out)
    assert np.array_equal(data.sweeps[0].images, rec.frames[:, :, 3:13])
    assert data.probe.image_shape == (12, 10)
    imports = data.metadata["imports"]["s"]
    assert imports["kept_columns"] == [3, 13] and imports["clip"]["origin"] == [3, 0]
    _assert_plus_pixels(out, rec, cal, 1, (3, 0), ((0, 0), (9, 11), (4, 2)))
    whole = tmp_path / "whole"
    result = _import(tmp_path / "s.mha", config, whole, "--keep-blank-columns")
    assert result.exit_code == 0 and "kept columns" not in result.output
    kept = SweepDataset.load(whole)
    assert (
        kept.probe.image_shape == (12, 16) and kept.metadata["imports"]["s"]["kept_columns"] is None
    )
    assert np.allclose(_dataset_world(whole, 1, 3 + 4, 2), _dataset_world(out, 1, 4, 2), atol=1e-9)


def test_blank_columns_inside_a_clip_rectangle(tmp_path: Path):
    """Blank columns of the clipped frame move the clip rectangle's origin by the first kept
    column; pixel (r, c) is PLUS's pixel (i0 + start + c, j0 + r)."""
    rec = recording()
    rec.frames[:, :, :4] = 0  # the clip (origin column 2) starts with two blank columns
    rec.frames[:, :, 10:] = 0
    cal = calibration()
    out, data = _import_clipped(tmp_path, rec, cal, ((2, 3), (12, 6)))
    assert np.array_equal(data.sweeps[0].images, rec.frames[:, 3:9, 4:10])
    clip = data.metadata["imports"]["s"]["clip"]
    assert clip == {"origin": [4, 3], "size": [6, 6]}
    assert data.metadata["imports"]["s"]["kept_columns"] == [2, 8]
    _assert_plus_pixels(out, rec, cal, 2, (4, 3), ((0, 0), (5, 5), (2, 1)))


@pytest.mark.parametrize("columns", ["all", (3, 3), (-1, 4), (0, 17)])
def test_read_plus_refuses_bad_columns(tmp_path: Path, columns):
    from ultron.data.plus_import import read_plus

    sequence = write_mha(tmp_path / "s.mha", recording())
    with pytest.raises(UltronError, match="columns") as error:
        read_plus(sequence, write_config(tmp_path / "c.xml", calibration()), columns=columns)
    if columns != "all":  # a pair outside the frames names the recording
        assert "s.mha" in str(error.value) and "16 columns" in str(error.value)


def test_a_sweep_added_keeps_the_first_sweeps_columns(tmp_path: Path):
    """A second recording lit over other columns is narrowed to the first sweep's columns, so
    the dataset keeps one probe geometry; a dataset whose first sweep kept every column keeps
    every column of the next."""
    config = write_config(tmp_path / "c.xml", calibration())
    first = write_mha(tmp_path / "a.mha", _blank_sides(recording(), 3, 13))
    second = write_mha(tmp_path / "b.mha", _blank_sides(recording(seed=1), 1, 15))
    out, whole = tmp_path / "ds", tmp_path / "whole"
    for sequence in (first, second):
        assert _import(sequence, config, out).exit_code == 0
    data = SweepDataset.load(out)
    assert [s.images.shape[2] for s in data.sweeps] == [10, 10]
    assert data.metadata["imports"]["b"]["kept_columns"] == [3, 13]
    assert _import(first, config, whole, "--keep-blank-columns").exit_code == 0
    assert _import(second, config, whole).exit_code == 0
    assert [s.images.shape[2] for s in SweepDataset.load(whole).sweeps] == [16, 16]
    # a recording narrower than the kept columns is refused, naming it; nothing is written
    narrow = write_mha(tmp_path / "c.mha", recording(width=10))
    before = snapshot(tmp_path / "ds")
    result = _import(narrow, config, out)
    check_refused(result, ("c.mha", "columns 3–12", "10 columns"))
    assert snapshot(tmp_path / "ds") == before


def test_signal_columns():
    frames = np.zeros((2, 3, 6), dtype=np.uint8)
    assert signal_columns(frames) == (0, 6)  # nothing lit: nothing dropped
    frames[1, 2, 4] = 1
    frames[0, 0, 2] = 200
    assert signal_columns(frames) == (2, 5)
    assert lit_column_range(np.array([False, True, False, True])) == (1, 4)
    with pytest.raises(UltronError, match="lit"):
        lit_column_range(frames)
    with pytest.raises(UltronError, match="frames"):
        signal_columns(frames[0])


def test_downsample_keeps_geometry_and_anti_aliases(tmp_path: Path):
    rec = recording(n=2, height=12, width=16)
    rec.frames[:] = 0
    rec.frames[0, :, 8] = 255  # a vertical line at column 8
    rec.frames[1] = np.indices((12, 16)).sum(axis=0) % 2 * 255  # a pixel checkerboard
    cal = calibration()
    config = write_config(tmp_path / "c.xml", cal)
    full, half = tmp_path / "full", tmp_path / "half"
    assert _import(write_mha(tmp_path / "s.mha", rec), config, full).exit_code == 0
    result = _import(tmp_path / "s.mha", config, half, "--downsample", "2")
    assert result.exit_code == 0, result.output
    a, b = SweepDataset.load(full), SweepDataset.load(half)
    assert b.probe.image_shape == (6, 8)
    assert math.isclose(b.probe.width_mm, a.probe.width_mm)
    assert math.isclose(b.probe.lateral_spacing_mm, 2 * a.probe.lateral_spacing_mm)
    line = b.sweeps[0].images[0]
    assert (line.argmax(axis=1) == 4).all()  # the line stays at its world position
    checker = b.sweeps[0].images[1].astype(int)[1:, 1:]  # row and column 0 see the edge
    assert np.abs(checker - 128).max() <= 1  # no aliasing: a 1-pixel checkerboard averages out
    # the same world point for old pixel (r, c) = (4, 8) and new pixel (2, 4)
    assert np.allclose(_dataset_world(half, 0, 4, 2), _dataset_world(full, 0, 8, 4), atol=1e-9)


def test_downsample_auto_leaves_two_pixels_per_speckle_grain(tmp_path: Path):
    """Frames whose speckle is Gaussian-filtered white noise (σ = 3 pixels on both axes: an
    axial autocorrelation FWHM of 2·√(2 ln 2)·√2·σ ≈ 10 pixels) at 0.05 mm pixels are shrunk
    by grain / 2; a second sweep added with auto takes the first sweep's factor; noise without
    grain (independent pixels) is kept as it is."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(1)
    rec = recording(n=4, height=120, width=96)
    noise = gaussian_filter(rng.normal(size=rec.frames.shape), (0, 3.0, 3.0))
    rec.frames[:] = np.clip(128 + noise / noise.std() * 30, 0, 255).astype(np.uint8)
    config = write_config(tmp_path / "c.xml", calibration(spacing=(0.05, 0.05)))
    out = tmp_path / "ds"
    result = _import(write_mha(tmp_path / "s.mha", rec), config, out, "--downsample", "auto")
    assert result.exit_code == 0, result.output
    record = SweepDataset.load(out).metadata["imports"]["s"]
    expected = 2 * math.sqrt(2 * math.log(2)) * math.sqrt(2) * 3.0
    factor = record["downsample"]
    assert expected / 2 * 0.85 < factor < expected / 2 * 1.15, factor
    data = SweepDataset.load(out)
    assert data.probe.image_shape == (round(120 / factor), round(96 / factor))
    assert "axial speckle grain" in result.output and f"downsampled by {factor:g}" in result.output
    default = runner.invoke(app, ["import-plus", str(tmp_path / "s.mha"), "--config", str(config),
                                  "--out", str(tmp_path / "d")])  # fmt: skip
    assert default.exit_code == 0, default.output  # auto is the default
    assert SweepDataset.load(tmp_path / "d").metadata["imports"]["s"]["downsample"] == factor
    added = _import(tmp_path / "s.mha", config, out, "--downsample", "auto", "--sweep-name", "b")
    assert added.exit_code == 0, added.output
    assert SweepDataset.load(out).metadata["imports"]["b"]["downsample"] == factor
    other = _import(tmp_path / "s.mha", config, out, "--downsample", "2", "--sweep-name", "c")
    assert other.exit_code == 2 and "ProbeGeometry" not in other.output
    assert f"the dataset's frames are {data.probe.height_px} × {data.probe.width_px} pixels" in (
        other.output
    )
    one = tmp_path / "one"  # the file's pixels kept: the import suggests auto, once
    kept = _import(tmp_path / "s.mha", config, one, "--downsample", "1")
    assert kept.exit_code == 0 and "--downsample auto shrinks them" in kept.output
    second = _import(tmp_path / "s.mha", config, one, "--sweep-name", "b")  # the dataset's 1
    assert second.exit_code == 0 and "--downsample auto shrinks" not in second.output
    assert SweepDataset.load(one).probe.image_shape == (120, 96)
    rec.frames[:] = rng.integers(0, 256, size=rec.frames.shape, dtype=np.uint8)
    plain = tmp_path / "plain"
    result = _import(write_mha(tmp_path / "w.mha", rec), config, plain, "--downsample", "auto")
    assert result.exit_code == 0, result.output
    assert SweepDataset.load(plain).probe.image_shape == (120, 96)


def test_downsample_frames_non_integer_factor():
    frames = np.full((1, 10, 15), 77, dtype=np.uint8)
    assert (downsample_frames(frames, (4, 6)) == 77).all()


def test_calling_again_adds_a_sweep_and_replace(tmp_path: Path):
    rec = recording()
    config = write_config(tmp_path / "c.xml", calibration())
    sequence = write_mha(tmp_path / "s.mha", rec)
    out = tmp_path / "ds"
    assert _import(sequence, config, out).exit_code == 0
    assert _import(sequence, config, out, "--sweep-name", "second").exit_code == 0
    assert [s.name for s in SweepDataset.load(out).sweeps] == ["s", "second"]
    before = snapshot(tmp_path)
    check_refused(_import(sequence, config, out), ("--sweep-name", "already has a sweep"))
    assert snapshot(tmp_path) == before
    result = _import(sequence, config, out, "--replace", "--downsample", "1")
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "dataset.json").read_text())
    assert sorted(meta["metadata"]["imports"]) == ["s", "second"]


def test_fit_image_plane_is_exact_for_a_scaled_rotation_and_optimal_otherwise():
    exact = fit_image_plane(calibration((0.2, 0.3)), 40, 30, "c.xml", "Transform")
    assert exact.residual_max_mm < 1e-12 and abs(exact.shear_deg) < 1e-9
    assert np.allclose(exact.spacing_mm, (0.2, 0.3), atol=1e-12)
    sheared = calibration((0.2, 0.3), shear_deg=3.0)
    fit = fit_image_plane(sheared, 40, 30, "c.xml", "Transform")
    assert math.isclose(fit.shear_deg, 3.0, abs_tol=1e-9)
    cols, rows = np.meshgrid(np.arange(40.0), np.arange(30.0))
    pixels = np.stack([cols, rows, 0 * cols, 1 + 0 * cols], axis=-1)
    error = np.linalg.norm((pixels @ (sheared - fit.image_to_probe()).T)[..., :3], axis=-1)
    assert math.isclose(error.max(), fit.residual_max_mm, rel_tol=1e-9)
    assert math.isclose(np.sqrt((error**2).mean()), fit.residual_rms_mm, rel_tol=1e-9)
    # least squares: the polar decomposition's pose is no better
    u, _, vt = np.linalg.svd(sheared[:3, :2], full_matrices=False)
    polar = fit.image_to_probe().copy()
    polar[:3, :2] = (u @ vt) * np.diag(sheared[:3, :2].T @ (u @ vt))
    centre = np.array([19.5, 14.5, 0.0, 1.0])
    polar[:3, 3] += ((sheared - polar) @ centre)[:3]
    other = np.linalg.norm((pixels @ (sheared - polar).T)[..., :3], axis=-1)
    assert np.sqrt((other**2).mean()) >= fit.residual_rms_mm - 1e-12


# --------------------------------------------------------------------------- bad input
def _edit(key: str, value: str | None) -> Callable[[list], list]:
    """A header edit: set ``key`` to ``value`` (remove it when None)."""

    def edit(pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
        if value is None:
            return [(k, v) for k, v in pairs if k != key]
        return [(k, value if k == key else v) for k, v in pairs]

    return edit


def _case(
    writer=write_mha,
    rec: Recording | None = None,
    cal: np.ndarray | None = None,
    more: tuple[str, ...] = (),
    **kwargs,
) -> Callable[[Path], list[str]]:
    def build(tmp: Path) -> list[str]:
        suffix = "seq.mha" if writer is write_mha else "seq.nrrd"
        sequence = writer(tmp / f"bad.{suffix}", rec or recording(), **kwargs)
        config = write_config(tmp / "plus.xml", calibration() if cal is None else cal)
        return [
            "import-plus",
            str(sequence),
            "--config",
            str(config),
            "--out",
            str(tmp / "ds"),
            *more,
        ]

    return build


def _nan_ok() -> Recording:
    rec = recording()
    rec.transforms["ProbeToTracker"][2, 0, 3] = np.nan
    return rec


def _all_invalid() -> Recording:
    rec = recording()
    rec.statuses["ReferenceToTracker"] = ["INVALID"] * rec.n
    return rec


def _not_rigid() -> Recording:
    rec = recording()
    rec.transforms["ProbeToTracker"][1, :3, 0] *= 1.01  # a 1 % stretch
    return rec


def _garbage(tmp: Path) -> list[str]:
    args = _case()(tmp)
    (tmp / "bad.seq.mha").write_bytes(bytes(range(256)) * 8)
    return args


def _clip_outside(tmp: Path) -> list[str]:
    args = _case()(tmp)
    write_config(tmp / "plus.xml", calibration(), clip=((10, 0), (10, 12)))
    return args


def _dimsize_swapped(tmp: Path) -> list[str]:
    """DimSize with width and height swapped (16 × 12 frames written, read as 12 × 16); the
    configuration's whole-frame clip rectangle tells."""
    args = _case(edit=_edit("DimSize", "12 16 4"))(tmp)
    write_config(tmp / "plus.xml", calibration(), clip=((0, 0), (16, 12)))
    return args


def _no_calibration(tmp: Path) -> list[str]:
    args = _case()(tmp)
    write_config(tmp / "plus.xml", None)
    return args


def _config_15_numbers(tmp: Path) -> list[str]:
    args = _case()(tmp)
    write_config(tmp / "plus.xml", None, matrix_text=" ".join(["1"] * 15))
    return args


#: case → (build(tmp) → CLI arguments, hints the one error line must hold). Also run by
#: ``benchmarks/bad_input_corpus.py``.
BAD_CASES: dict[str, tuple[Callable[[Path], list[str]], tuple[str, ...]]] = {
    "plus_no_dimsize": (_case(edit=_edit("DimSize", None)), ("bad.seq.mha", "DimSize", "missing")),
    "plus_nrrd_no_sizes": (
        _case(write_nrrd, edit=_edit("sizes", None)),
        ("bad.seq.nrrd", "sizes", "missing"),
    ),
    "plus_fewer_transforms_than_frames": (
        _case(edit=_edit("Seq_Frame0003_ProbeToTrackerTransform", None)),
        ("bad.seq.mha", "DimSize", "4 frames", "given for 3", "does not match"),
    ),
    "plus_transform_beyond_frames": (
        _case(edit=lambda p: [*p, ("Seq_Frame0004_ProbeToTrackerTransform", "1")]),
        ("bad.seq.mha", "Seq_Frame0004_ProbeToTrackerTransform", "beyond the 4 frames"),
    ),
    "plus_transform_15_numbers": (
        _case(edit=_edit("Seq_Frame0001_ReferenceToTrackerTransform", " ".join(["0"] * 15))),
        ("bad.seq.mha", "Seq_Frame0001_ReferenceToTrackerTransform", "16 numbers", "got 15"),
    ),
    "plus_nan_transform_status_ok": (
        _case(rec=_nan_ok()),
        ("bad.seq.mha", "Seq_Frame0002_ProbeToTrackerTransform", "NaN", "status is OK"),
    ),
    "plus_config_without_image_to_probe": (
        _no_calibration,
        ("plus.xml", "CoordinateDefinitions", "no Image → Probe transform"),
    ),
    "plus_config_matrix_15_numbers": (
        _config_15_numbers,
        ("plus.xml", "Transform Image → Probe", "16 numbers", "got 15"),
    ),
    "plus_image_to_probe_far_from_scaled_rotation": (
        _case(cal=calibration(shear_deg=30.0)),
        ("plus.xml", "Transform Image → Probe", "far from a scaled rotation", "30.00°", "mm"),
    ),
    "plus_unknown_orientation": (
        _case(edit=_edit("UltrasoundImageOrientation", "XY")),
        ("bad.seq.mha", "UltrasoundImageOrientation", "unknown orientation 'XY'"),
    ),
    "plus_truncated_compressed_payload": (
        _case(compressed=True, payload_edit=lambda b: b[: len(b) // 2]),
        ("bad.seq.mha", "CompressedDataSize", "truncated compressed payload"),
    ),
    "plus_nrrd_truncated_gzip_payload": (
        _case(write_nrrd, compressed=True, payload_edit=lambda b: b[: len(b) // 2]),
        ("bad.seq.nrrd", "data", "truncated"),
    ),
    "plus_to_missing_transform": (
        _case(more=("--to", "Phantom")),
        (
            "bad.seq.mha",
            "--to",
            "Phantom",
            "PhantomToTracker",
            "ProbeToTracker, ReferenceToTracker",
        ),
    ),
    "plus_truncated_zlib_stream": (
        _case(
            compressed=True,
            edit=_edit("CompressedDataSize", None),
            payload_edit=lambda b: b[: len(b) // 2],
        ),
        ("bad.seq.mha", "CompressedData", "truncated compressed payload", "of the 768 bytes"),
    ),
    "plus_truncated_raw_payload": (
        _case(payload_edit=lambda b: b[:-5]),
        ("bad.seq.mha", "ElementDataFile", "truncated payload: 763 bytes where DimSize needs 768"),
    ),
    "plus_not_a_sequence": (_garbage, ("bad.seq.mha", "header", "not a MetaImage header")),
    "plus_rf_orientation": (
        _case(edit=_edit("UltrasoundImageOrientation", "FM")),
        ("bad.seq.mha", "UltrasoundImageOrientation", "'FM'", "RF"),
    ),
    "plus_tracker_transform_not_rigid": (
        _case(rec=_not_rigid()),
        ("bad.seq.mha", "Seq_Frame0001_ProbeToTrackerTransform", "not rigid"),
    ),
    "plus_clip_outside_frame": (
        _clip_outside,
        ("plus.xml", "ClipRectangleSize", "exceeds the 16 × 12 frames"),
    ),
    "plus_dimsize_swapped": (
        _dimsize_swapped,
        (
            "plus.xml",
            "ClipRectangleSize",
            "exceeds the 12 × 16 frames",
            "fits 16 × 12 frames",
            "DimSize",
        ),
    ),
    "plus_downsample_below_one": (
        _case(more=("--downsample", "0.5")),
        ("argument", "--downsample", "≥ 1"),
    ),
    "plus_downsample_nan": (_case(more=("--downsample", "nan")), ("argument", "--downsample")),
    "plus_downsample_word": (
        _case(more=("--downsample", "half")),
        ("argument", "--downsample", "a number ≥ 1 or auto"),
    ),
    "plus_unknown_kind": (_case(more=("--kind", "diagonal")), ("argument", "--kind", "diagonal")),
    "plus_all_frames_invalid": (
        _case(rec=_all_invalid()),
        ("bad.seq.mha", "frames", "all 4 frames are invalid", "ReferenceToTrackerTransformStatus"),
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_refused(case: str, tmp_path: Path):
    build, hints = BAD_CASES[case]
    args = build(tmp_path)
    before = snapshot(tmp_path)
    check_refused(runner.invoke(app, args), hints)
    assert snapshot(tmp_path) == before  # nothing written


def test_failed_import_leaves_an_existing_dataset_untouched(tmp_path: Path):
    args = _case()(tmp_path)
    assert runner.invoke(app, args).exit_code == 0
    before = snapshot(tmp_path)
    bad = _case(rec=_nan_ok(), more=("--sweep-name", "two"))(tmp_path)
    check_refused(runner.invoke(app, bad), ("NaN",))
    assert snapshot(tmp_path) == {**before, "bad.seq.mha": (tmp_path / "bad.seq.mha").read_bytes()}


def test_adding_a_sweep_keeps_the_visible_reference(tmp_path: Path):
    """add_sweep_to_dataset (shared by the importers) keeps ``reference_visible``."""
    from conftest import build_tiny_dataset, make_sweep
    from ultron.data.importers import add_sweep_to_dataset

    mesh = tmp_path / "visible.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    data = build_tiny_dataset()
    data.reference_visible_path = mesh
    data.save(tmp_path / "ds")
    add_sweep_to_dataset(tmp_path / "ds", make_sweep("third", "other"), data.probe)
    meta = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert meta["reference_visible"] == "reference_visible.ply"
    assert [s["name"] for s in meta["sweeps"]] == ["row", "column", "third"]
