"""``ultron evaluate``: surface metrics of a mesh against a reference."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ultron.cli.common import console, user_errors


@user_errors
def evaluate(
    mesh: Annotated[Path, typer.Argument(help="Reconstructed mesh (.ply, .stl, .obj), world mm.")],
    reference: Annotated[Path, typer.Argument(help="Reference mesh, world mm.")],
    points: Annotated[int, typer.Option("--points", help="Points sampled per surface.")] = 100_000,
    repeats: Annotated[int, typer.Option("--repeats", help="Repeats with different seeds.")] = 3,
    seed: Annotated[int, typer.Option("--seed", help="First sampling seed.")] = 0,
    out: Annotated[
        Path | None, typer.Option("--out", help="JSON output [default: MESH with .metrics.json].")
    ] = None,
) -> None:
    """Compare MESH with REFERENCE: CD, HD, MAD, RMSE, HD95, completeness, F-scores (mean ± std)."""
    from ultron import atomic
    from ultron.mesh.export import load_mesh
    from ultron.metrics.surface import MetricsConfig, evaluate_meshes
    from ultron.report.tables import metrics_table

    config = MetricsConfig(n_points=points, repeats=repeats, seed=seed)
    recon = load_mesh(mesh, allow_empty=True)
    ref = load_mesh(reference)
    result = evaluate_meshes(recon, ref, config)
    result["mesh"], result["reference"] = str(mesh), str(reference)
    console.print(metrics_table({mesh.name: result}, title=f"{mesh.name} vs {reference.name} (mm)"))
    target = out or mesh.with_name(mesh.stem + ".metrics.json")
    atomic.write_json(target, result)
    console.print(f"wrote {target}")


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate)
