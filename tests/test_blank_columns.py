"""Columns that are 0 in every frame (outside the probe's aperture): the field fit draws no
patch from them and its held-out checks and baselines do not score them; a sweep without such
columns draws exactly the patches it drew before."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from field_configs import random_sweep
from ultron.data.dataset import ProbeGeometry
from ultron.data.resolution import signal_columns
from ultron.train.field_batch import sample_patches
from ultron.train.field_fit import evaluate_frames
from ultron.train.frames import FrameSet, copy_baselines
from ultron.train.losses import METRIC_SSIM_K2, ssim

pytestmark = pytest.mark.usefixtures("one_thread")


def blank_sided_sweep(start: int = 3, stop: int = 12):
    """``random_sweep``'s 24 × 16 frames with every column outside [start, stop) set to 0."""
    data = random_sweep()
    images = data.sweeps[0].images
    images[:, :, :start] = 0
    images[:, :, stop:] = 0
    return data


def test_the_fit_frames_know_their_lit_columns() -> None:
    frames = FrameSet.from_dataset(blank_sided_sweep(3, 12), None, 5)
    assert frames.lit_columns == (3, 12) and frames.lit == slice(3, 12)
    whole = FrameSet.from_dataset(random_sweep(), None, 5)
    assert whole.lit_columns == (0, 16)


def test_patches_are_drawn_among_the_lit_columns_only() -> None:
    frames = FrameSet.from_dataset(blank_sided_sweep(3, 12), None, 5)
    generator = torch.Generator().manual_seed(0)
    for _ in range(200):
        _, cols = sample_patches(frames, 4, 4, generator)
        assert cols.min() >= 3 and cols.max() <= 11
        assert (cols[:, 1:] - cols[:, :-1] == 1).all()  # adjacent columns
    seen = set()
    for _ in range(200):
        seen.update(sample_patches(frames, 4, 4, generator)[1][:, 0].tolist())
    assert seen == set(range(3, 9))  # every start from the first lit column to stop − patch
    _, cols = sample_patches(frames, 2, 32, generator)  # wider than the lit columns
    assert cols.tolist() == [list(range(3, 12))] * 2


def test_a_sweep_without_blank_columns_draws_the_same_patches_as_before() -> None:
    """The draws of the formula before lit columns existed, from the same generator state."""
    frames = FrameSet.from_dataset(random_sweep(), None, 5)
    ours = sample_patches(frames, 8, 5, torch.Generator().manual_seed(7))
    generator = torch.Generator().manual_seed(7)
    pick = torch.randint(0, frames.train_index.shape[0], (8,), generator=generator)
    start = torch.randint(0, 16 - 5 + 1, (8,), generator=generator)
    assert torch.equal(ours[0], frames.train_index[pick])
    assert torch.equal(ours[1], start[:, None] + torch.arange(5))


PROBE = ProbeGeometry(width_mm=12.0, depth_mm=8.0, height_px=8, width_px=12)


def middle_lit_frames(values: list[float], held: list[int]) -> FrameSet:
    """8 × 12 frames whose columns 2–9 hold one grey value each, the side columns 0."""
    images = torch.zeros(len(values), 8, 12)
    images[:, :, 2:10] = torch.tensor(values)[:, None, None]
    poses = torch.eye(4, dtype=torch.float64).repeat(len(values), 1, 1)
    poses[:, 2, 3] = torch.arange(len(values), dtype=torch.float64)
    train = [i for i in range(len(values)) if i not in held]
    lit = signal_columns(images.numpy())
    return FrameSet(images, poses, PROBE, torch.tensor(train), torch.tensor(held), lit_columns=lit)


def test_the_baselines_score_the_lit_columns_only() -> None:
    frames = middle_lit_frames([0.1, 0.5, 0.7], held=[1])
    assert frames.lit_columns == (2, 10)
    mean = (0.1 + 0.7) / 2
    found = copy_baselines(frames)
    # over the lit columns only: mse (mean − 0.5)²; the blank columns would scale it by 8/12
    assert found["mean_frame"] == pytest.approx(10 * math.log10(1 / (mean - 0.5) ** 2), abs=1e-4)


class _WhiteField:
    """A stand-in fitted field that renders every pixel 1."""

    def render(self, poses, expected: bool = True) -> np.ndarray:
        return np.ones((len(poses), 8, 12), dtype=np.float32)


def test_the_held_out_check_scores_the_lit_columns_only() -> None:
    frames = middle_lit_frames([0.1, 0.5, 0.7], held=[1])
    found = evaluate_frames(_WhiteField(), frames, frames.holdout_index)  # type: ignore[arg-type]
    # lit columns: (1 − 0.5)²; with the blank columns (1 − 0)² would raise the mse to 0.5
    assert found["psnr"] == pytest.approx(10 * math.log10(1 / 0.25), abs=1e-4)
    # exactly the SSIM of the lit columns, computed alone
    lit = frames.images[1:2, :, 2:10]
    assert found["ssim"] == float(ssim(torch.ones_like(lit), lit, k1=0.01, k2=METRIC_SSIM_K2))
    # constant images: SSIM is the luminance term alone, on every window, up to float32's
    # rounding of σ² = E[x²] − μ² against C2 = 9e-4 (≈ 1e-5 here, with the CPU's kernels);
    # with the blank columns it would be 0.30
    c1 = 0.01**2
    assert found["ssim"] == pytest.approx((2 * 0.5 + c1) / (1 + 0.25 + c1), abs=1e-4)


def test_info_names_the_blank_columns(tmp_path) -> None:
    from typer.testing import CliRunner

    from ultron.cli.main import app

    runner = CliRunner()
    blank_sided_sweep(3, 12).save(tmp_path / "blank")
    random_sweep().save(tmp_path / "whole")
    result = runner.invoke(app, ["info", str(tmp_path / "blank")], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "columns with signal: 3–11 of 16; the other 7 are 0 in every frame" in result.output
    result = runner.invoke(app, ["info", str(tmp_path / "whole")], terminal_width=200)
    assert result.exit_code == 0 and "columns with signal" not in result.output
