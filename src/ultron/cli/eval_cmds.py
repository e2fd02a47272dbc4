"""``ultron evaluate``: surface metrics of a mesh against a reference."""

from __future__ import annotations

from pathlib import Path

from ultron.cli.common import command, console, warning_line


@command(
    "mesh",
    "reference",
    aliases={"n_points": "points"},
    documented_by=("ultron.metrics.surface:MetricsConfig",),
)
def evaluate(
    mesh: Path,
    reference: Path,
    reference_visible: Path | None = None,
    crop_mm: float | None = None,
    points: int = 100_000,
    repeats: int = 3,
    seed: int = 0,
    out: Path | None = None,
) -> None:
    """Compare MESH with REFERENCE: CD, HD, MAD, RMSE, HD95 (one-sided and symmetric),
    completeness, F-scores and, with --reference-visible, CD and completeness against the
    visible part (mean ± std).

    Args:
        mesh: Reconstructed mesh (.ply, .stl, .obj), world mm.
        reference: Reference mesh, world mm.
        reference_visible: The part of the reference the sweeps could see (e.g. a simulated
            dataset's reference_visible.ply): adds CD vis. and Comp. vis. (default: n/a).
        out: JSON output (default: MESH with .metrics.json).
    """
    from ultron.metrics.surface import MetricsConfig
    from ultron.pipeline.evaluate import evaluate_files
    from ultron.report.tables import metrics_column_table

    config = MetricsConfig(n_points=points, repeats=repeats, seed=seed, crop_mm=crop_mm)
    done = evaluate_files(mesh, reference, config, reference_visible, out, warning_line)
    console.print(metrics_column_table(done.result, title=f"{mesh.name} vs {reference.name} (mm)"))
    crop_line = done.crop_line()
    if crop_line is not None:
        console.print(crop_line)
    console.print(f"wrote {done.out}")
