"""What ``fit-field`` and ``render`` print, as the library's pure functions make it
(:func:`ultron.pipeline.field.fit_lines`, :func:`~ultron.pipeline.field.fit_warnings`,
:func:`~ultron.pipeline.field.render_lines`): hand-made results, every branch."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from ultron.models.fitted import FitProgress, ThetaStatistics
from ultron.pipeline.field import (
    BLACK_MARGIN_DB,
    FieldFitResult,
    RenderResult,
    fit_lines,
    fit_warnings,
    render_lines,
)


def _result(holdout: dict | None, stats: ThetaStatistics | None = None) -> FieldFitResult:
    fitted = SimpleNamespace(
        field_config=SimpleNamespace(backend="grid"),
        probe=SimpleNamespace(height_px=208, width_px=162),
        theta_stats=stats,
    )
    return FieldFitResult(fitted, Path("F"), None, holdout)  # type: ignore[arg-type]


def _check(psnr: float, mean: float = 21.31, black: float | None = 10.10) -> dict:
    check = {"psnr": psnr, "ssim": 0.5, "mean_frame_psnr": mean, "nearest_frame_psnr": 19.0}
    if black is not None:
        check["black_frame_psnr"] = black
    return check


def test_a_fit_at_its_black_start_is_named() -> None:
    (warning,) = fit_warnings(_result(_check(10.10 + BLACK_MARGIN_DB - 0.01)))
    assert "has not left its black start" in warning
    assert "(11.09 dB against 10.10 dB)" in warning


def test_a_fit_below_the_mean_frame_but_off_black_is_told_so() -> None:
    (warning,) = fit_warnings(_result(_check(10.10 + BLACK_MARGIN_DB + 0.01)))
    assert "worse than the mean training frame" in warning
    assert "(11.11 < 21.31 dB)" in warning
    # a log from before the black frame was scored: the mean frame's warning alone
    (older,) = fit_warnings(_result(_check(10.5, black=None)))
    assert "worse than the mean training frame" in older


@pytest.mark.parametrize(
    "holdout",
    [None, _check(21.32), {"psnr": 5.0, "ssim": 0.1}, {**_check(5.0), "nearest_frame_psnr": None}],
)
def test_no_warning_without_the_baselines_or_above_the_mean(holdout: dict | None) -> None:
    assert fit_warnings(_result(holdout)) == []


def test_fit_lines() -> None:
    stats = ThetaStatistics(channels=("alpha", "beta"), mean=(0.5, 0.25), std=(0.1, 0.05))
    lines = fit_lines(_result(_check(15.94), stats), "cpu")
    assert lines[0] == (
        "wrote F: field.json, checkpoint.pt, theta_stats.json, train_log.jsonl"
        " (grid, fitted at 208×162 px on cpu)"
    )
    assert lines[1] == "θ statistics: alpha 0.5±0.1, beta 0.25±0.05"
    assert lines[2] == (
        "held-out frames: PSNR 15.94 dB, SSIM 0.500; copying onto them the mean training"
        " frame 21.31 dB, the nearest 19.00 dB"
    )
    assert len(lines) == 3
    assert fit_lines(_result(None), "cuda:0")[0].endswith("on cuda:0)")
    assert len(fit_lines(_result({"psnr": 15.0, "ssim": 0.5}), "cpu")) == 2


@pytest.mark.parametrize(
    ("progress", "warned"),
    [(None, False), (FitProgress(3000, 3000), False), (FitProgress(250, 3000), True)],
)
def test_render_lines(progress: FitProgress | None, warned: bool) -> None:
    paths = (Path("o.npy"), Path("o.theta.npy"), Path("o.transmission.npy"), Path("o.maps.json"))
    result = RenderResult(4, (128, 96), ("alpha", "beta"), paths, progress)
    lines, warnings = render_lines(result, "F", 3, expected=False)
    assert lines == [
        "rendered 4 frames of 128×96 (seed 3) to o.npy (+ θ ['alpha', 'beta'] and T maps)"
    ]
    assert bool(warnings) == warned
    if warned:
        assert "stopped at step 250 of 3000" in warnings[0]
    plain = RenderResult(1, (8, 4), ("alpha",), paths[:1], None)
    assert render_lines(plain, "F", 0, expected=True) == (
        ["rendered 1 frames of 8×4 (expected) to o.npy"],
        [],
    )
