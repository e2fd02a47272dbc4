"""The automatic fit resolution: the speckle grain measured on the frames, and the shape a fit
takes from it (``fit_shape="auto"``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from conftest import make_pose
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.errors import UltronInputError
from ultron.train import field_preset
from ultron.train.field_config import FieldTrainConfig
from ultron.train.fit_shape import (
    PIXELS_PER_GRAIN,
    auto_fit_shape,
    axial_grain_px,
    resolve_fit_shape,
)

#: Gaussian-filtered white noise of axial σ has the autocorrelation exp(−τ²/4σ²), whose full
#: width at half maximum is 4σ·√(ln 2).
FWHM_PER_SIGMA = 4 * math.sqrt(math.log(2))


def speckle_frames(n: int, shape: tuple[int, int], sigma_px: float, seed: int = 0) -> np.ndarray:
    """Frames of white noise blurred axially by a Gaussian of ``sigma_px`` (uint8)."""
    noise = np.random.default_rng(seed).normal(size=(n, *shape))
    blurred = gaussian_filter1d(noise, sigma_px, axis=1) if sigma_px > 0 else noise
    scaled = 128 + 40 * blurred / blurred.std()
    return np.clip(scaled, 0, 255).astype(np.uint8)


def speckle_dataset(sigma_px: float, spacing_mm: float = 0.05) -> SweepDataset:
    rows, cols = 160, 120
    probe = ProbeGeometry(cols * spacing_mm, rows * spacing_mm, rows, cols)
    images = speckle_frames(4, (rows, cols), sigma_px)
    poses = np.stack([make_pose(translation=(0.0, float(i), 0.0)) for i in range(4)])
    return SweepDataset(probe, [Sweep("row", "row", images, poses)])


@pytest.mark.parametrize("sigma_px", [2.0, 4.0])
def test_the_grain_of_blurred_noise_is_its_autocorrelation_width(sigma_px: float) -> None:
    probe = ProbeGeometry(6.0, 8.0, 160, 120)  # 0.05 mm pixels: the 1 mm high-pass keeps σ
    grain = axial_grain_px(speckle_frames(4, (160, 120), sigma_px), probe)
    assert grain == pytest.approx(FWHM_PER_SIGMA * sigma_px, rel=0.1)


def test_a_flat_frame_has_no_grain_and_bad_shapes_are_refused() -> None:
    probe = ProbeGeometry(6.0, 8.0, 16, 12)
    assert math.isnan(axial_grain_px(np.full((2, 16, 12), 80, np.uint8), probe))
    with pytest.raises(UltronInputError, match="frames"):
        axial_grain_px(np.zeros((16, 12)), probe)


def test_oversampled_frames_are_fitted_at_two_pixels_per_grain() -> None:
    sigma_px, spacing_mm = 3.0, 0.05
    dataset = speckle_dataset(sigma_px, spacing_mm)
    rows, cols = auto_fit_shape(dataset)
    expected_mm = FWHM_PER_SIGMA * sigma_px * spacing_mm / PIXELS_PER_GRAIN
    assert dataset.probe.depth_mm / rows == pytest.approx(expected_mm, rel=0.12)
    assert dataset.probe.width_mm / cols == pytest.approx(expected_mm, rel=0.12)


def test_frames_whose_pixels_already_sample_the_grain_keep_their_size() -> None:
    dataset = speckle_dataset(0.0)  # white noise: a grain of about one pixel
    assert auto_fit_shape(dataset) is None
    assert resolve_fit_shape(field_preset(), dataset).fit_shape is None


def test_resolving_keeps_explicit_shapes_and_native_and_refuses_other_words() -> None:
    dataset = speckle_dataset(3.0)
    assert field_preset().fit_shape == "auto"
    resolved = resolve_fit_shape(field_preset(), dataset)
    assert resolved.fit_shape == auto_fit_shape(dataset)
    assert resolve_fit_shape(resolved, dataset) == resolved
    explicit = FieldTrainConfig(fit_shape=(40, 30))
    assert resolve_fit_shape(explicit, dataset) is explicit
    assert FieldTrainConfig(fit_shape="native").fit_shape is None
    with pytest.raises(UltronInputError, match="fit_shape"):
        FieldTrainConfig(fit_shape="coarse")
    with pytest.raises(UltronInputError, match="dataset"):
        auto_fit_shape("not a dataset")  # type: ignore[arg-type]


def test_a_resolved_config_round_trips_through_field_json() -> None:
    resolved = resolve_fit_shape(field_preset(), speckle_dataset(3.0))
    assert FieldTrainConfig.from_dict(resolved.to_dict()) == resolved
    legacy = {k: v for k, v in resolved.to_dict().items() if k != "fit_shape"}
    assert FieldTrainConfig.from_dict(legacy).fit_shape is None  # fitted before "auto"


def test_the_meshing_voxel_is_no_finer_than_the_detail_the_frames_carry() -> None:
    from ultron.data.resolution import resolved_spacing_mm
    from ultron.mesh.grid import meshing_voxel_mm

    sigma_px, spacing_mm = 3.0, 0.05
    oversampled = speckle_dataset(sigma_px, spacing_mm)
    finest = resolved_spacing_mm(oversampled)
    expected_mm = FWHM_PER_SIGMA * sigma_px * spacing_mm / PIXELS_PER_GRAIN
    assert finest == pytest.approx(expected_mm, rel=0.12)
    assert meshing_voxel_mm(oversampled.probe, None, 1.0, finest_mm=finest) == finest
    assert meshing_voxel_mm(oversampled.probe, None, 1.0) == spacing_mm  # the pixel alone
    assert meshing_voxel_mm(oversampled.probe, 0.7, 1.0, finest_mm=finest) == 0.7  # given
    white = speckle_dataset(0.0, spacing_mm)
    assert resolved_spacing_mm(white) == pytest.approx(spacing_mm)


def test_info_names_the_grain_and_the_shape_the_field_is_fitted_at(tmp_path) -> None:
    from typer.testing import CliRunner

    from ultron.cli.main import app

    for sigma_px, name in ((3.0, "coarse"), (0.0, "white")):
        dataset = speckle_dataset(sigma_px)
        dataset.save(tmp_path / name)
        result = CliRunner().invoke(app, ["info", str(tmp_path / name)], terminal_width=200)
        assert result.exit_code == 0, result.output
        grain = axial_grain_px(np.stack(dataset.sweeps[0].images), dataset.probe)
        assert f"axial speckle grain: {grain:.2f} pixels ({grain * 0.05:.3f} mm)" in result.output
        shape = resolve_fit_shape(field_preset(), dataset).fit_shape
        fitted = "their own size" if shape is None else f"{shape[0]} × {shape[1]}"
        assert f"the field is fitted at {fitted} (fit-field" in result.output
        assert (shape is None) == (sigma_px == 0.0)
