"""Sources of stage 2's transmission T (field, confidence, labels, oracle) and the true T file."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.labels import (
    gather_labelled_pixels,
    outer_side_rows,
    select_label_frames,
    surface_outer_side,
)
from ultron.data.truth import TRANSMISSION_FILE, load_true_transmission
from ultron.errors import UltronInputError
from ultron.fields import FieldConfig, GridFieldConfig
from ultron.methods import ultron_method
from ultron.methods.ultron_method import UltronConfig, occupancy_training_data
from ultron.models.fitted import TransmissionMaps
from ultron.parallel import torch_threads
from ultron.pipeline.model_io import load_network
from ultron.pipeline.presets import preset_request
from ultron.pipeline.run import ReconstructionRequest, reconstruct
from ultron.render import RenderConfig, pixel_points_mm, render_properties
from ultron.train import FieldTrainConfig, fit_field
from ultron.train.confidence import ConfidenceConfig, confidence_map
from ultron.train.occupancy import OccupancyTrainConfig, rows_read
from ultron.train.visibility import (
    LabelTransmissionConfig,
    VisibilityConfig,
    frame_transmission,
    in_labelled_shadow,
    label_transmission,
    load_oracle_truth,
    pixel_transmission,
    transmission_summary,
    visibility_config,
)

PROBE = ProbeGeometry(width_mm=8.0, depth_mm=9.0, height_px=24, width_px=16)
LAYER_MM = 5.0  # depth of the reflecting layer at z = 0


def _layer_depth(z: np.ndarray) -> np.ndarray:
    return LAYER_MM + 0.3 * z


def _volume(points_mm: torch.Tensor):
    from ultron.fields import AcousticProperties

    x, y, z = points_mm.unbind(-1)
    phi = 0.45 + 0.3 * torch.sin(x * 0.9) * torch.cos(z * 0.7)
    beta = 0.6 * torch.exp(-(((y - LAYER_MM - 0.3 * z) / 0.4) ** 2))
    alpha = 0.02 + 0.8 * torch.sigmoid((y - LAYER_MM - 0.3 * z) / 0.2)
    return AcousticProperties(alpha, beta, phi)


def _dataset(n_frames: int = 10) -> SweepDataset:
    """One sweep along elevation through a tilted reflecting layer; the band 0–1 mm under the
    layer is labelled 1, everything else 0; the last frame is not annotated."""
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    poses[:, 2, 3] = np.linspace(0.0, 4.0, n_frames)
    points = pixel_points_mm(torch.as_tensor(poses), PROBE)
    rendered = render_properties(
        _volume(points), PROBE.axial_spacing_mm, RenderConfig(), expected=True
    )
    images = (rendered.intensity.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    depth = np.arange(PROBE.height_px) * PROBE.axial_spacing_mm
    top = _layer_depth(poses[:, 2, 3])[:, None] - 0.2
    band = (depth[None] >= top) & (depth[None] <= top + 1.0)
    labels = np.repeat(band[:, :, None], PROBE.width_px, axis=2).astype(np.uint8)
    labels[-1] = 255
    return SweepDataset(PROBE, [Sweep("row", "row", images, poses, labels)])


def _true_transmission(dataset: SweepDataset) -> np.ndarray:
    """A hand-made "true" T: 1 down to 1 mm under the layer (the band), 0.02 below (float16)."""
    sweep = dataset.sweeps[0]
    depth = np.arange(PROBE.height_px) * PROBE.axial_spacing_mm
    below = depth[None] > _layer_depth(sweep.probe_to_world[:, 2, 3])[:, None] + 1.0
    t = np.where(below, 0.02, 1.0)[:, :, None].repeat(PROBE.width_px, axis=2)
    return t.astype(np.float16)


@pytest.fixture(scope="module")
def fitted_case(tmp_path_factory) -> dict:
    """A tiny labelled dataset on disk, its field (30 iterations) and a hand-made true T."""
    root = tmp_path_factory.mktemp("visibility")
    dataset = _dataset()
    dataset.save(root / "dataset")
    config = FieldTrainConfig(
        field=FieldConfig(grid=GridFieldConfig(cell_mm=0.5)), iterations=30, frames_per_batch=4,
        patch_width=16, holdout_every=0, check_every=100, checkpoint_every=100, log_every=10,
        train_scatterers="expected",
    )  # fmt: skip
    with torch_threads(1):
        fitted = fit_field(dataset, config, root / "field")
        yield {"root": root, "dataset": dataset, "fitted": fitted}


def test_training_data_reads_the_unsure_gap_above_a_band_as_background(fitted_case):
    dataset, fitted = fitted_case["dataset"], fitted_case["fitted"]
    sweep = dataset.sweeps[0]
    labels = sweep.labels.copy()
    # label --auto's way: unsure (255) in the two rows directly above each band
    top = np.argmax(labels == 1, axis=1)  # (N, W): the band's first row per scanline
    for k in (1, 2):
        frames, cols = np.nonzero((top - k >= 0) & (labels[:, 0, :] != 255))
        labels[frames, top[frames, cols] - k, cols] = 255
    gapped = SweepDataset(PROBE, [Sweep("row", "row", sweep.images, sweep.probe_to_world, labels)])
    selection = select_label_frames(gapped, 0.5, 0)
    stored = occupancy_training_data(gapped, fitted, selection)
    read = occupancy_training_data(gapped, fitted, selection, outer_side_mm=1.0)
    rows = outer_side_rows(gapped, 1.0)
    assert rows >= 2  # the test's gap is within reach
    extra = sum(
        int(surface_outer_side(labels[frames], rows).sum()) for frames in selection.frames.values()
    )
    assert extra > 0 and len(read.labels) == len(stored.labels) + extra
    assert int(read.labels.sum()) == int(stored.labels.sum())  # the added pixels are background
    # the labels as stored: nothing added (the gapless dataset gathers the same with either)
    same = occupancy_training_data(dataset, fitted, selection, outer_side_mm=1.0)
    assert torch.equal(same.labels, occupancy_training_data(dataset, fitted, selection).labels)
    with pytest.raises(UltronInputError, match="label_outer_side_mm"):
        UltronConfig(label_outer_side_mm=-1.0)
    with pytest.raises(UltronInputError, match="label_outer_side_mm"):
        UltronConfig(label_outer_side_mm=float("nan"))


# ------------------------------------------------------------------------------ labels
def test_training_data_computes_the_inputs_the_fit_reads_only(fitted_case, monkeypatch):
    dataset, fitted = fitted_case["dataset"], fitted_case["fitted"]
    selection = select_label_frames(dataset, 0.5, 0)
    full = occupancy_training_data(dataset, fitted, selection)
    n = len(full.labels)
    # label_loss's pick scores every pixel of a dataset this small: score every 40th instead
    monkeypatch.setattr(ultron_method, "rows_read", partial(rows_read, max_points=n // 40))
    reads = OccupancyTrainConfig(iters=3, batch_size=64, seed=1)
    part = occupancy_training_data(dataset, fitted, selection, reads=reads)
    rows = rows_read(n, 64, 3, 1, max_points=n // 40)
    assert part.input_rows is not None and len(part.inputs) == len(rows) < n / 3
    assert torch.equal(part.input_rows >= 0, torch.isin(torch.arange(n), rows))
    # the same inputs up to the last bits of the field's batched query
    torch.testing.assert_close(part.inputs_at(rows), full.inputs[rows], rtol=0, atol=1e-5)
    assert torch.equal(part.transmission, full.transmission)
    assert torch.equal(part.labels, full.labels) and torch.equal(part.in_front, full.in_front)
    every = occupancy_training_data(dataset, fitted, selection, reads=replace(reads, iters=200))
    assert every.input_rows is None and torch.equal(every.inputs, full.inputs)


def test_label_transmission_hand_worked():
    # columns: two bone runs; bone deep down; no bone; nothing annotated; a run ended by 255
    labels = np.array(
        [[0, 0, 0, 255, 1],
         [1, 0, 0, 255, 1],
         [1, 0, 255, 255, 255],
         [0, 0, 0, 255, 1],
         [1, 1, 0, 255, 0],
         [0, 0, 0, 255, 0]], dtype=np.uint8,
    )  # fmt: skip
    t = label_transmission(labels, 0.5, LabelTransmissionConfig(margin_mm=0.25, decay_mm=1.0))
    assert t.dtype == np.float32 and t.shape == (6, 5)
    # column 0: first run rows 1–2, d_end = 1.0 mm: T = 1 down to 1.25 mm, exp(−(d − 1.25)) below
    # (the second run at row 4 changes nothing)
    expected0 = [1.0, 1.0, 1.0, np.exp(-0.25), np.exp(-0.75), np.exp(-1.25)]
    np.testing.assert_allclose(t[:, 0], expected0, rtol=1e-6)
    # column 1: run at row 4 (d_end = 2.0 mm): only row 5 (2.5 mm) lies below 2.25 mm
    np.testing.assert_allclose(t[:, 1], [1, 1, 1, 1, 1, np.exp(-0.25)], rtol=1e-6)
    np.testing.assert_array_equal(t[:, 2], 1.0)  # no bone label: T = 1 everywhere
    assert np.isnan(t[:, 3]).all()  # nothing annotated: unknown
    # column 4: the run (rows 0–1) is ended by the 255 of row 2: d_end = 0.5, T = 1 to 0.75 mm
    expected4 = [1.0, 1.0, np.exp(-0.25), np.exp(-0.75), np.exp(-1.25), np.exp(-1.75)]
    np.testing.assert_allclose(t[:, 4], expected4, rtol=1e-6)
    # defaults: no margin, 1 mm decay; a batch of frames works the same
    t0 = label_transmission(np.stack([labels, labels]), 0.5)
    np.testing.assert_allclose(t0[1, :, 0], [1, 1, 1, np.exp(-0.5), np.exp(-1.0), np.exp(-1.5)])
    with pytest.raises(UltronInputError, match="labels"):
        label_transmission(np.full((3, 3), 7, np.uint8), 0.5)
    with pytest.raises(UltronInputError, match="axial_spacing_mm"):
        label_transmission(labels, 0.0)
    with pytest.raises(UltronInputError, match="decay_mm"):
        LabelTransmissionConfig(decay_mm=0)


# -------------------------------------------------------------------------- confidence
def test_confidence_map_sees_the_shadow_under_a_bright_line():
    rng = np.random.default_rng(0)
    image = rng.integers(50, 90, size=(48, 32)).astype(np.uint8)  # speckle-like tissue
    image[20:22] = 255  # a bright reflector
    image[22:] = rng.integers(0, 6, size=(26, 32))  # its dark shadow
    c = confidence_map(image)
    assert c.shape == image.shape and c.dtype == np.float32
    np.testing.assert_allclose(c[0], 1.0, atol=1e-6)
    np.testing.assert_allclose(c[-1], 0.0, atol=1e-6)
    above, below = c[5:18].mean(), c[25:40].mean()
    assert above > 0.9 and below < 0.2 * above, (above, below)


def test_confidence_map_solves_monais_system():
    """The symmetric SuperLU solve gives MONAI's own map (its general LU) to rounding."""
    from monai.transforms import UltrasoundConfidenceMapTransform

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(37, 29)).astype(np.uint8)
    image[15:17, 5:20] = 255
    monai = UltrasoundConfidenceMapTransform(alpha=2.0, beta=90.0, gamma=0.05)(
        image[None].astype(np.float64)
    )
    expected = np.clip(np.asarray(monai, dtype=np.float64).reshape(image.shape), 0, 1)
    ours = confidence_map(image)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-6)
    assert ours[:14].mean() > ours[18:30].mean() + 0.2  # a map with a shadow, not a constant


def test_confidence_maps_on_threads_equal_one_by_one():
    from ultron.train.confidence import confidence_maps

    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(12, 20, 16)).astype(np.float32)
    images /= 255.0
    seen: list[tuple[int, int]] = []
    parallel = confidence_maps(images, workers=2, report=lambda d, n: seen.append((d, n)))
    assert parallel.dtype == np.float32 and parallel.shape == images.shape
    for k in (0, 7, len(images) - 1):
        assert np.array_equal(parallel[k], confidence_map(images[k]))
    assert seen[0] == (0, len(images)) and seen[-1] == (len(images), len(images))
    assert [d for d, _ in seen] == list(range(len(images) + 1))
    with pytest.raises(UltronInputError, match="images"):
        confidence_maps(images[0])


def test_confidence_map_uniform_column_is_monotone():
    c = confidence_map(np.full((40, 20), 100, np.uint8), ConfidenceConfig())
    np.testing.assert_allclose(c[0], 1.0, atol=1e-6)
    assert (np.diff(c, axis=0) <= 1e-6).all()
    assert c[20, 10] < c[10, 10] < 1.0
    with pytest.raises(UltronInputError, match="image"):
        confidence_map(np.zeros((2, 5)))
    with pytest.raises(UltronInputError, match="beta"):
        ConfidenceConfig(beta=0)


# ------------------------------------------------------------------------------ field
def test_field_source_equals_the_pre_refactor_values(fitted_case):
    dataset, fitted = fitted_case["dataset"], fitted_case["fitted"]
    selection = select_label_frames(dataset, 0.5, 0)
    data = occupancy_training_data(dataset, fitted, selection)
    # what occupancy_training_data computed before sources were selectable
    pixels = gather_labelled_pixels(dataset, selection)
    sweep = dataset.sweeps[0]
    theta, t = fitted.pixel_theta_transmission(
        sweep.probe_to_world, pixels.frame, pixels.row, pixels.col
    )
    assert torch.equal(data.transmission, t.float())
    n = len(fitted.channels)
    assert torch.equal(data.inputs[:, :n], fitted.theta_stats.normalise(theta).float())
    # the same T without the precomputed values, and on whole frames
    config = VisibilityConfig()
    assert torch.equal(pixel_transmission(config, dataset, pixels, fitted=fitted), t)
    frames = np.unique(pixels.frame)
    maps = frame_transmission(config, dataset, "row", frames, fitted=fitted)
    local = np.searchsorted(frames, pixels.frame)
    np.testing.assert_array_equal(maps[local, pixels.row, pixels.col], t.numpy())
    np.testing.assert_array_equal(maps[:, 0], 1.0)  # exclusive: T = 1 at the face


def test_frames_kept_by_stage_two_are_read_not_rendered(fitted_case, monkeypatch):
    """The T that field_theta_transmission keeps is each frame's whole T, as frame_transmission
    renders it; given them, frame_transmission renders only the other frames (bit for bit the
    same result: a frame's T does not depend on the frames rendered with it)."""
    dataset, fitted = fitted_case["dataset"], fitted_case["fitted"]
    selection = select_label_frames(dataset, 0.3, 0)
    kept = TransmissionMaps()
    data = occupancy_training_data(dataset, fitted, selection, keep=kept)
    labelled = np.unique(gather_labelled_pixels(dataset, selection).frame)
    assert (
        sorted(kept.maps) == ["row"]
        and np.flatnonzero(kept.kept["row"]).tolist() == labelled.tolist()
    )
    assert kept.n_frames == len(labelled) and kept.get("row", 10) is None
    config = VisibilityConfig()
    every = frame_transmission(config, dataset, "row", fitted=fitted)
    for frame in labelled:
        np.testing.assert_array_equal(kept.get("row", frame), every[frame])
    rendered_frames = []
    original = type(fitted).pixel_theta_transmission

    def counting(self, poses, frame_index, *args, **kwargs):
        rendered_frames.extend(np.unique(np.asarray(frame_index)).tolist())
        return original(self, poses, frame_index, *args, **kwargs)

    monkeypatch.setattr(type(fitted), "pixel_theta_transmission", counting)
    told = []
    again = frame_transmission(
        config, dataset, "row", fitted=fitted, rendered=kept, advance=lambda d, n: told.append(d)
    )
    np.testing.assert_array_equal(again, every)
    assert sorted(rendered_frames) == sorted(set(range(10)) - set(labelled.tolist()))
    assert told[0] == len(labelled) and told[-1] == 10
    assert data.transmission.shape[0] == len(gather_labelled_pixels(dataset, selection))
    with pytest.raises(UltronInputError, match="transmission"):
        kept.add("row", [0, 1], torch.zeros(3, 24, 16), n_frames=10)
    with pytest.raises(UltronInputError, match="frames"):
        kept.add("row", [10], torch.zeros(1, 24, 16), n_frames=10)


def test_whole_frame_sources_agree_with_the_pixel_lookup(fitted_case):
    dataset = fitted_case["dataset"]
    pixels = gather_labelled_pixels(dataset, select_label_frames(dataset, 0.3, 0))
    truth = {"row": _true_transmission(dataset)}
    for source in ("confidence", "labels", "oracle"):
        config = VisibilityConfig(source)
        t = pixel_transmission(config, dataset, pixels, truth=truth).numpy()
        full = frame_transmission(config, dataset, "row", truth=truth)
        assert full.shape == (10, 24, 16) and full.dtype == np.float32
        np.testing.assert_array_equal(t, full[pixels.frame, pixels.row, pixels.col])
        assert np.isfinite(t).all() and (0 <= t).all() and (t <= 1).all()
    # labels: the unannotated last frame is unknown; annotated frames are 1 at the face
    labels_t = frame_transmission(VisibilityConfig("labels"), dataset, "row")
    assert np.isnan(labels_t[-1]).all() and (labels_t[:-1, 0] == 1).all()
    summary = transmission_summary(torch.tensor([1.0, 0.05, 0.5]), torch.tensor([1, 0, 0]))
    assert summary["bone_mean"] == 1.0 and summary["background_shadowed"] == 0.5
    with pytest.raises(UltronInputError, match="truth"):
        frame_transmission(VisibilityConfig("oracle"), dataset, "row")
    with pytest.raises(UltronInputError, match="frames"):
        frame_transmission(VisibilityConfig("labels"), dataset, "row", np.array([10]))


def test_summary_counts_what_the_observed_negatives_drop_in_the_labelled_shadow():
    """Hand-worked: 5 background labels, 3 of them in the labels' shadow (T 0.05, 0.2, 0.6)
    and 2 lit (0.25, 0.9); with τ = 0.3 the loss drops 3 of 5 background labels, 2 of the 3
    in the labelled shadow; the bone label is not counted."""
    t = torch.tensor([0.05, 0.2, 0.6, 0.25, 0.9, 0.1])
    labels = torch.tensor([0, 0, 0, 0, 0, 1])
    shadow = torch.tensor([True, True, True, False, False, True])
    summary = transmission_summary(t, labels, shadow, observed_transmission=0.3)
    assert summary["background_dropped"] == pytest.approx(3 / 5)
    assert summary["labelled_shadow_background"] == 3
    assert summary["labelled_shadow_dropped"] == pytest.approx(2 / 3)
    assert summary["observed_transmission"] == 0.3
    # no background label in the labelled shadow: the share is undefined (None), not 0
    empty = transmission_summary(t, labels, torch.zeros(6, dtype=torch.bool), 0.3)
    assert empty["labelled_shadow_background"] == 0 and empty["labelled_shadow_dropped"] is None
    # without τ only the T < 0.1 share, as before
    assert set(transmission_summary(t, labels, shadow)) == {
        "bone_mean", "background_mean", "background_shadowed", "shadow_threshold",
    }  # fmt: skip
    with pytest.raises(UltronInputError, match="labelled_shadow"):
        transmission_summary(t, labels, shadow[:5], observed_transmission=0.3)


def test_the_labelled_shadow_lies_under_the_first_band(fitted_case):
    """A pixel is in the labelled shadow where the annotation's own T < 0.1: more than
    ln(10) · 1 mm under the band's last row (decay 1 mm, margin 0); nowhere in the band or
    above it, and nowhere in a column without a bone label."""
    dataset = fitted_case["dataset"]
    pixels = gather_labelled_pixels(dataset, select_label_frames(dataset, 0.3, 0))
    shadow = in_labelled_shadow(dataset, pixels).numpy()
    labels = dataset.sweeps[0].labels
    spacing = PROBE.axial_spacing_mm
    last = np.array(
        [
            np.flatnonzero(labels[f, :, c] == 1).max()
            for f, c in zip(pixels.frame, pixels.col, strict=True)
        ]
    )
    below_mm = (pixels.row - last) * spacing
    np.testing.assert_array_equal(shadow, below_mm > np.log(10.0))
    assert shadow.any() and not shadow[pixels.label == 1].any()
    data = occupancy_training_data(
        dataset, fitted_case["fitted"], select_label_frames(dataset, 0.3, 0)
    )
    assert torch.equal(data.labelled_shadow, torch.from_numpy(shadow))


# ----------------------------------------------------------------------------- oracle
def test_oracle_reads_transmission_npy_and_trains(fitted_case, tmp_path):
    root, dataset, fitted = fitted_case["root"], fitted_case["dataset"], fitted_case["fitted"]
    data_dir = tmp_path / "dataset"
    dataset.save(data_dir)
    true_t = _true_transmission(dataset)
    np.save(data_dir / "row" / TRANSMISSION_FILE, true_t)
    config = VisibilityConfig("oracle")
    loaded = SweepDataset.load(data_dir)
    truth = load_oracle_truth(config, data_dir, loaded)
    assert truth is not None and truth["row"].dtype == np.float16
    np.testing.assert_array_equal(truth["row"], true_t)
    np.testing.assert_array_equal(frame_transmission(config, loaded, "row"), true_t)
    selection = select_label_frames(dataset, 1.0, 0)
    data = occupancy_training_data(dataset, fitted, selection, config, truth)
    pixels = gather_labelled_pixels(dataset, selection)
    np.testing.assert_array_equal(
        data.transmission.numpy(), true_t[pixels.frame, pixels.row, pixels.col].astype(np.float32)
    )
    occupancy = OccupancyTrainConfig(iters=150, batch_size=1024, lr=1e-3, positive_weight=None)
    request = ReconstructionRequest(
        method="ultron", label_fraction=1.0, method_config=UltronConfig(occupancy=occupancy,
        visibility=config, voxel_mm=0.5),
    )  # fmt: skip
    reconstruct(data_dir, request, tmp_path / "out", field_dir=root / "field", report=False)
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["transmission_source"] == "oracle" and run["diagnostic"] is True
    assert run["transmission_parameters"] == {"file": f"<sweep>/{TRANSMISSION_FILE}"}
    stats = run["transmission_stats"]
    assert stats["bone_mean"] == 1.0 and 0 < stats["background_shadowed"] < 1
    _, meta = load_network(tmp_path / "out")
    assert meta["transmission_source"] == "oracle" and meta["diagnostic"] is True


def test_load_true_transmission_rejects_bad_files(tmp_path):
    (tmp_path / "row").mkdir()
    path = tmp_path / "row" / TRANSMISSION_FILE
    with pytest.raises(UltronInputError, match=r"transmission\.npy.*ultron simulate") as info:
        load_true_transmission(tmp_path, "row")
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    good = np.full((2, 4, 3), 0.5, np.float16)
    cases = {
        "float16": good.astype(np.float32),
        r"\(N, H, W\)": good[0],
        "differs from the sweep's images": good[:1],
        "NaN or inf": np.where(np.arange(3) == 1, np.nan, good).astype(np.float16),
        r"\[0, 1\]": good * 3,
    }
    for match, array in cases.items():
        np.save(path, array)
        with pytest.raises(UltronInputError, match=match) as info:
            load_true_transmission(tmp_path, "row", (2, 4, 3))
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    path.write_bytes(b"not an npy file")
    with pytest.raises(UltronInputError, match="readable"):
        load_true_transmission(tmp_path, "row")
    np.save(path, good)
    assert load_true_transmission(tmp_path, "row", (2, 4, 3)).dtype == np.float16
    with pytest.raises(UltronInputError, match="sweep_name"):
        load_true_transmission(tmp_path, "../row")


# ------------------------------------------------------------------------- config & CLI
def test_visibility_config_records_and_validates():
    assert visibility_config().to_dict() == {
        "transmission_source": "field", "transmission_parameters": {}, "diagnostic": False,
    }  # fmt: skip
    labels = VisibilityConfig("labels", labels=LabelTransmissionConfig(0.5, 2.0))
    assert VisibilityConfig.from_dict(labels.to_dict(), "x") == labels
    confidence = VisibilityConfig("confidence")
    assert "monai" in confidence.parameters()["implementation"]
    assert VisibilityConfig.from_dict(confidence.to_dict(), "x") == confidence
    assert VisibilityConfig.from_dict({}, "x") == VisibilityConfig()  # models saved before
    assert visibility_config("field", oracle=True).diagnostic
    with pytest.raises(UltronInputError, match=r"network\.pt"):
        VisibilityConfig.from_dict({"transmission_source": "magic"}, "network.pt")
    with pytest.raises(UltronInputError, match="visibility"):
        visibility_config("magic")
    with pytest.raises(UltronInputError, match="oracle-transmission"):
        visibility_config("labels", oracle=True)
    with pytest.raises(UltronInputError, match="ultron or ultron-noloss"):
        preset_request(method="on", visibility="labels")
    with pytest.raises(UltronInputError, match="--oracle-transmission applies to"):
        preset_request(method="compounding", oracle=True)


def _one_line_error(args: list[str]) -> str:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.output
    return lines[0]


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--visibility", "magic"], "visibility"),
        (["--visibility", "labels", "--oracle-transmission"], "oracle-transmission"),
        (["--visibility", "confidence", "--method", "compounding"], "ultron-noloss only"),
        (["--oracle-transmission"], TRANSMISSION_FILE),
    ],
)
def test_reconstruct_cli_rejects_bad_visibility(tiny_dataset_dir, tmp_path, monkeypatch, extra,
                                                expected):  # fmt: skip
    monkeypatch.setenv("ULTRON_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    line = _one_line_error(["reconstruct", str(tiny_dataset_dir), "--out", str(out), *extra])
    assert expected in line
    if "--oracle-transmission" in extra and len(extra) == 1:
        assert "ultron simulate" in line
    assert not out.exists() and not (tmp_path / "cache").exists()  # nothing written, no field


def test_reconstruct_cli_rejects_a_malformed_transmission_file(tiny_dataset_dir, tmp_path):
    np.save(tiny_dataset_dir / "row" / TRANSMISSION_FILE, np.ones((3, 8, 6), np.float32))
    np.save(tiny_dataset_dir / "column" / TRANSMISSION_FILE, np.ones((4, 8, 6), np.float16))
    out = tmp_path / "out"
    line = _one_line_error(
        ["reconstruct", str(tiny_dataset_dir), "--out", str(out), "--oracle-transmission"]
    )
    assert str(tiny_dataset_dir / "row" / TRANSMISSION_FILE) in line and "float16" in line
    assert not out.exists()


def test_reconstruct_cli_with_the_confidence_source(fitted_case, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        ["reconstruct", str(fitted_case["root"] / "dataset"), "--out", str(out),
         "--method", "ultron-noloss", "--label-fraction", "0.5", "--visibility", "confidence",
         "--field", str(fitted_case["root"] / "field"), "--occupancy-iters", "100",
         "--positive-weight", "balanced"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    assert run["transmission_source"] == "confidence" and run["diagnostic"] is False
    assert run["transmission_parameters"]["beta"] == 90.0
    assert run["occupancy_config"]["loss"] == "bce"  # the ablation ignores T, records its source
    meta = load_network(out)[1]
    assert meta["transmission_source"] == "confidence"
    assert meta["positive_weight"] is None and meta["theta_context"] == {
        "radii_mm": [1.0, 2.0],
        "encode_neighbours": False,
    }
