"""``ultron simulate``: a digital vertebra phantom scanned with a simulated tracked probe."""

from __future__ import annotations

from pathlib import Path

import typer

from ultron.arguments import check_count, check_range, check_seed
from ultron.cli.common import apply_threads, command, print_lines, stage_progress


def _check_numbers(
    seed: int,
    frames: int,
    step_mm: float | None,
    probe_width_mm: float,
    depth_mm: float,
    height_px: int,
    width_px: int,
    pose_noise_mm: float,
    pose_noise_deg: float,
    label_noise_mm: float,
    label_missing: float,
    label_errors: float,
    voxel_mm: float,
) -> None:
    """``simulate``'s numeric options, each refused with a one-line error naming it."""
    from ultron.phantom.dataset import MAX_VOXEL_MM

    check_seed("--seed", seed)
    check_count("--frames", frames)
    for name, value in (
        ("--step-mm", step_mm),
        ("--probe-width-mm", probe_width_mm),
        ("--depth-mm", depth_mm),
    ):
        check_range(name, value, 0.0, low_open=True)
    check_count("--height-px", height_px)
    check_count("--width-px", width_px)
    for name, value in (
        ("--pose-noise-mm", pose_noise_mm),
        ("--pose-noise-deg", pose_noise_deg),
        ("--label-noise-mm", label_noise_mm),
    ):
        check_range(name, value, 0.0)
    check_range("--label-missing", label_missing, 0.0, 1.0)
    check_range("--label-errors", label_errors, 0.0, 1.0)
    check_range("--voxel-mm", voxel_mm, 0.0, MAX_VOXEL_MM, low_open=True)


@command()
def simulate(
    out: Path,
    phantom: str = "L3",
    seed: int = 0,
    sweeps: str = "row,column,tilt_p10,tilt_m10",
    frames: int = 60,
    step_mm: float | None = None,
    probe_width_mm: float = 38.0,
    depth_mm: float = 70.0,
    height_px: int = 128,
    width_px: int = 96,
    pose_noise_mm: float = 0.3,
    pose_noise_deg: float = 0.2,
    label_noise_mm: float = 0.3,
    label_missing: float = 0.0,
    label_errors: float = 0.02,
    voxel_mm: float = 0.3,
    preview: bool = False,
    threads: int | None = None,
) -> None:
    """Simulate a tracked multi-sweep B-mode dataset of a digital bone phantom, with labels.

    Args:
        out: Dataset directory to write (created).
        phantom: Phantom: vertebrae L2, L3, L3b, L4; condyle (end of a long bone); femur (44
            cm, long sweeps).
        seed: Random seed (same seed → same files).
        sweeps: Comma-separated sweeps: row, column, tilt_p<deg>, tilt_m<deg>.
        frames: Frames per sweep.
        step_mm: Probe step between frames, mm (default: spread over the bone extent).
        probe_width_mm: Linear probe width (lateral FOV), mm.
        depth_mm: Imaging depth, mm.
        height_px: Samples per scanline.
        width_px: Scanlines per frame.
        pose_noise_mm: Tracking error σ per axis, mm (0: exact poses).
        pose_noise_deg: Tracking error σ per axis, degrees.
        label_noise_mm: Annotation edge jitter σ, mm (0: exact edges).
        label_missing: Fraction of frames left unannotated (255).
        label_errors: Fraction of frames annotated with a coarse error.
        voxel_mm: SDF grid / reference mesh voxel, mm.
        preview: Also write OUT/preview.png (frames + labels).
    """
    apply_threads(threads)
    _check_numbers(
        seed, frames, step_mm, probe_width_mm, depth_mm, height_px, width_px, pose_noise_mm,
        pose_noise_deg, label_noise_mm, label_missing, label_errors, voxel_mm,
    )  # fmt: skip
    from ultron.phantom import AnnotationConfig, ScanConfig, SimulationConfig, TrackingNoise
    from ultron.pipeline.simulate import simulate_to

    config = SimulationConfig(
        phantom=phantom,
        seed=seed,
        sweeps=tuple(name.strip() for name in sweeps.split(",") if name.strip()),
        probe_width_mm=probe_width_mm,
        depth_mm=depth_mm,
        height_px=height_px,
        width_px=width_px,
        voxel_mm=voxel_mm,
        scan=ScanConfig(frames_per_sweep=frames, step_mm=step_mm),
        tracking=TrackingNoise(translation_mm=pose_noise_mm, rotation_deg=pose_noise_deg),
        annotation=AnnotationConfig(
            jitter_mm=label_noise_mm, missing_fraction=label_missing, error_rate=label_errors
        ),
    )
    with stage_progress("simulating") as report:
        result = simulate_to(config, out, preview, progress=report)
    print_lines(result.lines(phantom))


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate)
