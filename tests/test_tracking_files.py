"""``import-plus --tracking``: a recording saved by 3D Slicer as a volume sequence of the frames
(times in ``axis 0 index values``, no orientation field) and one ``.seq.mha`` per tracked
transform sampled at the tracker's own times. Every frame gets the transforms at its time —
interpolated between samples, exact at a sample — and imports as the same recording with
per-frame transforms does; frames in a tracking gap or outside it are skipped and counted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import assert_refused
from plus_synthetic import Recording, calibration, rigid, write_config, write_mha
from test_bad_input_corpus import runner
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.data.tracking_files import poses_at, read_transform_sequences

#: The frames' times (s): 6 frames at 20 Hz.
FRAME_TIMES = 10.0 + 0.05 * np.arange(6)


def _probe(t: float) -> np.ndarray:
    """ProbeToTracker at time t: a constant-rate turn about a fixed axis and a straight line,
    which spherical-linear and linear interpolation reproduce exactly."""
    return rigid((1, 2, 3), 10.0 + 40.0 * (t - 10.0), (100.0 + 30.0 * (t - 10.0), -50.0, 20.0))


def _reference(t: float) -> np.ndarray:
    return rigid((0, 1, 0.2), 40.0 + 5.0 * (t - 10.0), (250.0, 90.0 + 2.0 * (t - 10.0), 3.0))


def _transform_file(path: Path, name: str, times, pose, statuses=None) -> Path:
    """A transform sequence as Slicer writes one: no pixels, per-frame fields only."""
    lines = [
        "ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
        "CompressedData = False", f"DimSize = 0 0 {len(times)}", "ElementSpacing = 1 1 1",
        "Offset = 0 0 0", "TransformMatrix = 1 0 0 0 1 0 0 0 1", "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
    ]  # fmt: skip
    for k, t in enumerate(times):
        matrix = " ".join(f"{v:.17g}" for v in pose(t).ravel())
        status = "OK" if statuses is None else statuses[k]
        lines += [f"Seq_Frame{k:04d}_{name}Transform ={matrix}",
                  f"Seq_Frame{k:04d}_{name}TransformStatus = {status}",
                  f"Seq_Frame{k:04d}_Timestamp = {t:.3f}"]  # fmt: skip
    path.write_text("\n".join([*lines, "ElementDataFile = LOCAL"]) + "\n")
    return path


def _image_sequence(path: Path, frames: np.ndarray, times) -> Path:
    """A volume sequence as Slicer's Sequences module saves one: list axis first, one slice,
    the items' times in ``axis 0 index values``, no ultrasound orientation field."""
    import nrrd

    header = {
        "type": "uint8", "dimension": 4, "space": "left-posterior-superior",
        "sizes": [len(frames), frames.shape[2], frames.shape[1], 1],
        "kinds": ["list", "domain", "domain", "domain"],
        "space directions": np.vstack([np.full(3, np.nan), np.eye(3)]),
        "space origin": np.zeros(3), "encoding": "gzip",
        "DataNodeClassName": "vtkMRMLScalarVolumeNode", "axis 0 index type": "numeric",
        "axis 0 index values": " ".join(f"{t:.3f}" for t in times),
    }  # fmt: skip
    nrrd.write(str(path), np.moveaxis(frames, 0, -1)[None], header, index_order="C")
    return path


def _import(*args: str):
    """``import-plus``, at the file's own pixels unless ``args`` set ``--downsample``."""
    native = () if "--downsample" in args else ("--downsample", "1")
    return runner.invoke(app, ["import-plus", *args, *native], terminal_width=400)


@pytest.fixture
def scene(tmp_path: Path) -> dict[str, Path]:
    """The Slicer scene (frames UN in the file, tracking at 30 and 25 Hz from before the first
    frame to after the last) and the same recording as PLUS writes it (per-frame transforms at
    the frames' own times)."""
    rng = np.random.default_rng(3)
    frames = rng.integers(1, 256, size=(6, 12, 16), dtype=np.uint8)  # MF
    probe_times = np.round(9.98 + np.arange(13) / 30.0, 3)  # written with 3 decimals
    reference_times = np.round(9.97 + np.arange(10) / 25.0, 3)
    config = write_config(tmp_path / "c.xml", calibration())
    plus = Recording(
        frames,
        {"ProbeToTracker": np.stack([_probe(t) for t in FRAME_TIMES]),
         "ReferenceToTracker": np.stack([_reference(t) for t in FRAME_TIMES])},
    )  # fmt: skip
    return {
        "image": _image_sequence(tmp_path / "Image.seq.nrrd", frames[:, ::-1, ::-1], FRAME_TIMES),
        "probe": _transform_file(tmp_path / "P.seq.mha", "ProbeToTracker", probe_times, _probe),
        "reference": _transform_file(
            tmp_path / "R.seq.mha", "ReferenceToTracker", reference_times, _reference
        ),
        "plus": write_mha(tmp_path / "plus.igs.mha", plus),
        "config": config,
    }


def test_a_slicer_scene_imports_as_the_same_recording_with_per_frame_transforms(
    scene, tmp_path: Path
):
    result = _import(str(scene["image"]), "--config", str(scene["config"]), "--out",
                     str(tmp_path / "a"), "--tracking", str(scene["probe"]), "--tracking",
                     str(scene["reference"]), "--orientation", "UN")  # fmt: skip
    assert result.exit_code == 0, result.output
    plus = _import(str(scene["plus"]), "--config", str(scene["config"]), "--out",
                   str(tmp_path / "b"))  # fmt: skip
    assert plus.exit_code == 0, plus.output
    ours, theirs = (SweepDataset.load(tmp_path / d).sweeps[0] for d in "ab")
    assert np.array_equal(ours.images, theirs.images)
    np.testing.assert_allclose(ours.probe_to_world, theirs.probe_to_world, atol=1e-9)
    meta = SweepDataset.load(tmp_path / "a").metadata["imports"]["Image"]
    assert meta["tracking"] == ["P.seq.mha", "R.seq.mha"] and meta["orientation"] == "UN"


def test_frames_without_tracking_at_their_time_are_skipped_and_counted(scene, tmp_path: Path):
    """The samples at 10.080 and 10.113 s missing (a gap of three intervals, 10.047–10.147 s,
    holding frames 1 and 2) and tracking that ends before the last frame: those three frames
    are skipped and counted, the others imported."""
    times = np.round(9.98 + np.arange(13) / 30.0, 3)
    kept = ~np.isin(times, [10.08, 10.113]) & (times < FRAME_TIMES[5] - 0.01)
    gappy = _transform_file(tmp_path / "G.seq.mha", "ProbeToTracker", times[kept], _probe)
    result = _import(str(scene["image"]), "--config", str(scene["config"]), "--out",
                     str(tmp_path / "a"), "--tracking", str(gappy), "--tracking",
                     str(scene["reference"]), "--orientation", "UN")  # fmt: skip
    assert result.exit_code == 0, result.output
    meta = SweepDataset.load(tmp_path / "a").metadata["imports"]["Image"]
    assert meta["frames"] == [0, 3, 4]
    assert meta["skipped"] == {"ProbeToTrackerTransformStatus NO_TRACKING": 3}


def test_interpolation_is_exact_at_samples_and_between_them_for_a_steady_motion(tmp_path):
    times = np.round(9.98 + np.arange(13) / 30.0, 3)
    statuses = ["OK"] * 13
    statuses[6] = "INVALID"
    path = _transform_file(tmp_path / "P.seq.mha", "ProbeToTracker", times, _probe, statuses)
    (transform,) = read_transform_sequences(path)
    assert transform.name == "ProbeToTracker" and not transform.ok[6]
    queries = np.array([times[3], 10.0, 10.1234, times[6] - 0.01, times[-1] + 0.01, 9.9])
    matrices, found = poses_at(transform, queries)
    assert found.tolist() == [True, True, True, False, False, False]
    for query, matrix in zip(queries[:3], matrices[:3], strict=True):
        np.testing.assert_allclose(matrix, _probe(float(query)), atol=1e-9)


def test_bad_tracking_and_frames_are_one_line_errors(scene, tmp_path: Path):
    base = [str(scene["image"]), "--config", str(scene["config"]), "--out", str(tmp_path / "o")]
    no_time = tmp_path / "T.seq.mha"
    no_time.write_text(scene["probe"].read_text().replace("_Timestamp = 9.980", "_Timestamp = x"))
    empty = _transform_file(tmp_path / "E.seq.mha", "X", [], _probe)
    unrelated = _transform_file(tmp_path / "F.seq.mha", "FooToBar", FRAME_TIMES, _probe)
    tracked = ["--tracking", str(scene["probe"]), "--tracking", str(scene["reference"])]
    cases = [
        ([*base, "--orientation", "UN", *tracked, "--tracking", str(unrelated)],
         "F.seq.mha: --tracking: holds FooToBarTransform; none is on the chain"),
        ([*base, "--tracking", str(scene["probe"])], "give the frames' orientation with"),
        ([*base, "--orientation", "UN"], "no per-frame transform"),
        ([*base, "--orientation", "UN", "--tracking", str(no_time)],
         "Seq_Frame0000_Timestamp: expected a time in seconds, got 'x'"),
        ([*base, "--orientation", "UN", "--tracking", str(empty)], "no per-frame transform"),
        ([*base, "--orientation", "UN", "--tracking", str(scene["image"])],
         "expected a transform sequence as Slicer saves one"),
    ]  # fmt: skip
    assert_refused(_import, cases)
    assert not (tmp_path / "o").exists()


def test_labels_of_a_slicer_scene_export_indexed_by_the_frames_times(scene, tmp_path: Path):
    """A sweep imported from a Slicer scene: label --export to .seq.nrrd with the frames' file
    as --recording is indexed by the frames' own times; a MetaImage twin of an NRRD recording
    is refused; label --auto suggests the NRRD export."""
    from ultron.data.auto_label_dataset import SweepLabelSummary

    out = tmp_path / "a"
    result = _import(str(scene["image"]), "--config", str(scene["config"]), "--out", str(out),
                     "--tracking", str(scene["probe"]), "--tracking", str(scene["reference"]),
                     "--orientation", "UN")  # fmt: skip
    assert result.exit_code == 0, result.output
    labels = np.full((6, 12, 16), 255, dtype=np.uint8)
    labels[2, 5:7, 3:12] = 1
    np.save(out / "Image" / "labels.npy", labels)
    exported = runner.invoke(app, ["label", str(out), "--export", str(tmp_path / "x.seq.nrrd"),
                                   "--recording", str(scene["image"])])  # fmt: skip
    assert exported.exit_code == 0, exported.output
    import nrrd

    index = nrrd.read_header(str(tmp_path / "x.seq.nrrd"))["axis 0 index values"].split()
    np.testing.assert_allclose([float(v) for v in index], FRAME_TIMES)
    refused = runner.invoke(app, ["label", str(out), "--export", str(tmp_path / "x.seq.mha"),
                                  "--recording", str(scene["image"])])  # fmt: skip
    assert refused.exit_code == 2 and "needs a MetaImage recording" in refused.stderr
    summary = SweepLabelSummary(
        "Image", 6, 0.1, 0.2, 0.7, False, 1.0, frames_to_check=(2,),
        recording_frames=tuple(range(6)), recording="Image.seq.nrrd",
    )  # fmt: skip
    assert "--export Image_labels.seq.nrrd" in summary.lines("a")[0][2]
