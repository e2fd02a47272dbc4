"""``ultron simulate``: a digital vertebra phantom scanned with a simulated tracked probe."""

from __future__ import annotations

from pathlib import Path

from ultron.cli.common import command, print_lines, stage_progress

#: The library's names of what simulate passes on under another name (its checks and help).
SIMULATE_ALIASES = {
    "frames_per_sweep": "frames",
    "width_mm": "probe_width_mm",
    "translation_mm": "pose_noise_mm",
    "rotation_deg": "pose_noise_deg",
    "jitter_mm": "label_noise_mm",
    "missing_fraction": "label_missing",
    "error_rate": "label_errors",
}


@command(
    aliases=SIMULATE_ALIASES,
    documented_by=(
        "ultron.phantom.dataset:SimulationConfig",
        "ultron.phantom.protocols:ScanConfig",
        "ultron.phantom.protocols:TrackingNoise",
        "ultron.phantom.annotation:AnnotationConfig",
    ),
)
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
        sweeps: Comma-separated sweeps: row, column, tilt_p<deg>, tilt_m<deg>.
        preview: Also write OUT/preview.png (frames + labels).
    """
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
