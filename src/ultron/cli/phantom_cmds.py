"""``ultron simulate``: a digital vertebra phantom scanned with a simulated tracked probe."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ultron.arguments import check_count, check_range, check_seed
from ultron.cli.common import ThreadsOption, apply_threads, print_lines, stage_progress, user_errors


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


Out = Annotated[Path, typer.Option("--out", help="Dataset directory to write (created).")]
PhantomName = Annotated[
    str,
    typer.Option(
        "--phantom",
        help="Phantom: vertebrae L2, L3, L3b, L4; condyle (end of a long bone); femur (44 cm, long sweeps).",
    ),
]
Seed = Annotated[int, typer.Option("--seed", help="Random seed (same seed → same files).")]
Sweeps = Annotated[
    str,
    typer.Option("--sweeps", help="Comma-separated sweeps: row, column, tilt_p<deg>, tilt_m<deg>."),
]
Frames = Annotated[int, typer.Option("--frames", help="Frames per sweep.")]
StepMm = Annotated[
    float | None,
    typer.Option(
        "--step-mm", help="Probe step between frames, mm (default: spread over the bone extent)."
    ),
]
ProbeWidthMm = Annotated[
    float, typer.Option("--probe-width-mm", help="Linear probe width (lateral FOV), mm.")
]
DepthMm = Annotated[float, typer.Option("--depth-mm", help="Imaging depth, mm.")]
HeightPx = Annotated[int, typer.Option("--height-px", help="Samples per scanline.")]
WidthPx = Annotated[int, typer.Option("--width-px", help="Scanlines per frame.")]
PoseNoiseMm = Annotated[
    float, typer.Option("--pose-noise-mm", help="Tracking error σ per axis, mm (0: exact poses).")
]
PoseNoiseDeg = Annotated[
    float, typer.Option("--pose-noise-deg", help="Tracking error σ per axis, degrees.")
]
LabelNoiseMm = Annotated[
    float, typer.Option("--label-noise-mm", help="Annotation edge jitter σ, mm (0: exact edges).")
]
LabelMissing = Annotated[
    float, typer.Option("--label-missing", help="Fraction of frames left unannotated (255).")
]
LabelErrors = Annotated[
    float, typer.Option("--label-errors", help="Fraction of frames annotated with a coarse error.")
]
VoxelMm = Annotated[float, typer.Option("--voxel-mm", help="SDF grid / reference mesh voxel, mm.")]
Preview = Annotated[
    bool, typer.Option("--preview", help="Also write OUT/preview.png (frames + labels).")
]


@user_errors
def simulate(
    out: Out,
    phantom: PhantomName = "L3",
    seed: Seed = 0,
    sweeps: Sweeps = "row,column,tilt_p10,tilt_m10",
    frames: Frames = 60,
    step_mm: StepMm = None,
    probe_width_mm: ProbeWidthMm = 38.0,
    depth_mm: DepthMm = 70.0,
    height_px: HeightPx = 128,
    width_px: WidthPx = 96,
    pose_noise_mm: PoseNoiseMm = 0.3,
    pose_noise_deg: PoseNoiseDeg = 0.2,
    label_noise_mm: LabelNoiseMm = 0.3,
    label_missing: LabelMissing = 0.0,
    label_errors: LabelErrors = 0.02,
    voxel_mm: VoxelMm = 0.3,
    preview: Preview = False,
    threads: ThreadsOption = None,
) -> None:
    """Simulate a tracked multi-sweep B-mode dataset of a digital bone phantom, with labels."""
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
