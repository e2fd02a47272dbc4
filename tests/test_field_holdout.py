"""What the held-out frames score without a field (copy_baselines), hand-worked; the fit logs it
beside every held-out check; fit-field prints it and warns when the field scores below the mean
training frame."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from field_configs import quick_field_config, random_sweep
from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry
from ultron.pipeline import field as field_pipeline
from ultron.train.field_fit import fit_field
from ultron.train.frames import FrameSet, checked_subset, copy_baselines

runner = CliRunner()
PROBE = ProbeGeometry(width_mm=3.0, depth_mm=2.0, height_px=2, width_px=3)

pytestmark = pytest.mark.usefixtures("one_thread")


def constant_frames(values: list[float], z_mm: list[float], held: list[int]) -> FrameSet:
    """Frames of one grey value each, the probe's origin at (0, 0, z)."""
    images = torch.tensor(values, dtype=torch.float32)[:, None, None].expand(-1, 2, 3).clone()
    poses = torch.eye(4, dtype=torch.float64).repeat(len(values), 1, 1)
    poses[:, 2, 3] = torch.tensor(z_mm, dtype=torch.float64)
    train = [i for i in range(len(values)) if i not in held]
    return FrameSet(images, poses, PROBE, torch.tensor(train), torch.tensor(held, dtype=torch.long))


def psnr_of(mse: float) -> float:
    return 10 * math.log10(1 / mse)


def test_copy_baselines_hand_worked() -> None:
    # frame 1 (0.2, at z = 1) held out; training frames 0.0 (z 0), 0.5 (z 1.5), 0.9 (z 3)
    frames = constant_frames([0.0, 0.2, 0.5, 0.9], [0.0, 1.0, 1.5, 3.0], held=[1])
    found = copy_baselines(frames)
    mean = (0.0 + 0.5 + 0.9) / 3
    assert found["mean_frame"] == pytest.approx(psnr_of((mean - 0.2) ** 2), abs=1e-4)
    # the nearest origin is z = 1.5 (0.5 mm away), not z = 0 (1 mm)
    assert found["nearest_frame"] == pytest.approx(psnr_of((0.5 - 0.2) ** 2), abs=1e-4)


def test_copy_baselines_scores_the_checked_frames_only() -> None:
    frames = constant_frames([0.0, 0.2, 0.5, 0.6, 0.9], [0, 1, 2, 3, 4], held=[1, 3])
    assert checked_subset(frames.holdout_index, 1).tolist() == [1]
    one = copy_baselines(frames, limit=1)
    mean = (0.0 + 0.5 + 0.9) / 3
    assert one["mean_frame"] == pytest.approx(psnr_of((mean - 0.2) ** 2), abs=1e-4)
    both = copy_baselines(frames)
    expected = ((mean - 0.2) ** 2 + (mean - 0.6) ** 2) / 2
    assert both["mean_frame"] == pytest.approx(psnr_of(expected), abs=1e-4)


def test_copy_baselines_without_held_out_frames_is_empty() -> None:
    assert copy_baselines(constant_frames([0.1, 0.2], [0, 1], held=[])) == {}


def test_the_fit_logs_the_baselines_beside_each_check(tmp_path: Path) -> None:
    data = random_sweep()
    fit_field(data, quick_field_config(iterations=4, check_every=2), tmp_path / "f")
    entries = [json.loads(line) for line in (tmp_path / "f" / "train_log.jsonl").open()]
    checked = [e for e in entries if "holdout_psnr" in e]
    assert [e["step"] for e in checked] == [2, 4]
    expected = copy_baselines(FrameSet.from_dataset(data, None, 5), 32)
    for entry in checked:
        assert entry["holdout_mean_frame_psnr"] == pytest.approx(expected["mean_frame"])
        assert entry["holdout_nearest_frame_psnr"] == pytest.approx(expected["nearest_frame"])
    assert not any("holdout_mean_frame_psnr" in e for e in entries if "holdout_psnr" not in e)
    check = field_pipeline.last_holdout_check(tmp_path / "f")
    assert check["psnr"] == checked[-1]["holdout_psnr"]
    assert check["mean_frame_psnr"] == checked[-1]["holdout_mean_frame_psnr"]


@pytest.mark.parametrize(("psnr", "warned"), [(15.0, True), (25.0, False)])
def test_fit_field_prints_the_baselines_and_warns_below_the_mean(
    tmp_path: Path, monkeypatch, psnr: float, warned: bool
) -> None:
    random_sweep().save(tmp_path / "d")
    check = {"psnr": psnr, "ssim": 0.5, "mean_frame_psnr": 20.0, "nearest_frame_psnr": 21.0}
    monkeypatch.setattr(field_pipeline, "last_holdout_check", lambda out: check)
    args = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--iters", "2"]
    result = runner.invoke(app, args, terminal_width=300)
    assert result.exit_code == 0, result.output
    stdout, stderr = " ".join(result.stdout.split()), " ".join(result.stderr.split())
    assert f"held-out frames: PSNR {psnr:.2f} dB" in stdout
    assert "the mean training frame 20.00 dB, the nearest 21.00 dB" in stdout
    assert stderr.count("warning:") == int(warned)
    if warned:
        assert stderr.startswith("warning: the field predicts") and "15.00 < 20.00 dB" in stderr


@pytest.mark.parametrize(("psnr", "black"), [(10.5, True), (11.5, False)])
def test_fit_field_names_a_fit_still_at_its_black_start(
    tmp_path: Path, monkeypatch, psnr: float, black: bool
) -> None:
    """Within 1 dB of the all-black frame's PSNR the warning says the fit never started (one
    warning, not two); 1.5 dB above it, the usual warning below the mean frame."""
    random_sweep().save(tmp_path / "d")
    check = {"psnr": psnr, "ssim": 0.5, "mean_frame_psnr": 20.0, "nearest_frame_psnr": 21.0,
             "black_frame_psnr": 10.0}  # fmt: skip
    monkeypatch.setattr(field_pipeline, "last_holdout_check", lambda out: check)
    args = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--iters", "2"]
    result = runner.invoke(app, args, terminal_width=300)
    assert result.exit_code == 0, result.output
    stderr = " ".join(result.stderr.split())
    assert stderr.count("warning:") == 1
    assert ("all-black image" in stderr and "another --seed" in stderr) is black
    assert stderr.startswith("warning: the field predicts") is not black


def test_copy_baselines_scores_an_all_black_frame() -> None:
    frames = constant_frames([0.0, 0.2, 0.5, 0.9], [0.0, 1.0, 1.5, 3.0], held=[1])
    assert copy_baselines(frames)["black_frame"] == pytest.approx(psnr_of(0.2**2), abs=1e-4)


def test_fit_field_without_held_out_frames_prints_no_check(tmp_path: Path) -> None:
    random_sweep().save(tmp_path / "d")
    args = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--iters", "2"]
    result = runner.invoke(app, [*args, "--holdout-every", "0"], terminal_width=300)
    assert result.exit_code == 0, result.output
    assert "held-out frames" not in result.stdout and "warning" not in result.stderr
