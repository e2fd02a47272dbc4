"""``ultron reconstruct`` and ``ultron demo``."""

from __future__ import annotations

from pathlib import Path

from ultron.cli.common import StageLines, command, console, fit_progress, warning_line
from ultron.methods.catalog import method_help

#: The help of the options reconstruct and finetune share.
RUN_HELP = {
    "out": "Output directory.",
    "label_fraction": "Share of annotated frames used, in (0, 1].",
    "seed": "Seed of label selection and training.",
    "points": "Points per surface for metrics.",
    "allow_other_field": "Accept a --field fitted on another dataset (its field.json's"
    " dataset_sha256 differs); run.json records field_dataset_match false.",
    "mesh_coordinates": "Coordinates of the mesh files: lps (ultron's world; 3D Slicer's"
    " default for models) or ras; either is tagged SPACE=… in the file header, which Slicer"
    " reads.",
}
#: The library's names of options reconstruct and finetune pass on under another name.
RUN_ALIASES = {
    "n_points": "points",
    "max_memory_gib": "max_memory",
    "iterations": "field_iters",
    "field_dir": "field",
}


def _field_progress():
    """The field fit's progress (:func:`~ultron.cli.common.fit_progress`)."""
    return fit_progress("fitting acoustic field")


@command(
    "dataset",
    shared={**RUN_HELP, "method": method_help()},
    metavars={"field": "FIELD_DIR", "label_support": "MM"},
    aliases=RUN_ALIASES
    | {"iters": "occupancy_iters", "oracle": "oracle_transmission"}
    | {"precision": "occupancy_precision"}
    | {"label_support_mm": "label_support"},
    documented_by=("ultron.pipeline.presets:preset_request",),
)
def reconstruct(
    dataset: Path,
    out: Path,
    method: str = "ultron",
    label_fraction: float = 0.1,
    field: list[Path] | None = None,
    seed: int = 0,
    field_iters: int | None = None,
    occupancy_iters: int | None = None,
    occupancy_precision: str | None = None,
    points: int = 100_000,
    preset: str = "fast",
    visibility: str = "field",
    oracle_transmission: bool = False,
    surface: str | None = None,
    theta_context: str | None = None,
    positive_weight: str | None = None,
    negatives: str | None = None,
    echo_support: bool | None = None,
    label_support: float | None = None,
    label_bridges: bool | None = None,
    label_fusion: bool | None = None,
    allow_other_field: bool = False,
    max_memory: float | None = None,
    mesh_coordinates: str = "lps",
    device: str = "auto",
    threads: int | None = None,
) -> None:
    """Reconstruct a bone surface: mesh.ply/.stl/.obj, occupancy.nii.gz, metrics.json, run.json.

    --out must be new, empty or an earlier reconstruct run, which the new run replaces as a
    whole.

    Args:
        dataset: Dataset directory (ultron-sweeps/1) with labels.
        field: The dataset's FIELD_DIR (default: fit and cache one). Given more than once
            (fields fitted with different --seed), UltrON trains on each and keeps the one
            whose network fits the labels best (lowest label loss; run.json
            field_candidates).
        field_iters: Field iterations when fitting (default: the preset's: 3000; paper:
            75000).
    """
    from ultron.pipeline.presets import preset_field_config, preset_request
    from ultron.pipeline.run import reconstruct as run

    request = preset_request(  # checks every option it takes
        preset, method, label_fraction, seed, points=points, occupancy_iters=occupancy_iters,
        occupancy_precision=occupancy_precision,
        visibility=visibility, oracle=oracle_transmission, surface=surface,
        theta_context=theta_context, positive_weight=positive_weight, negatives=negatives,
        echo_support=echo_support, label_support_mm=label_support, label_bridges=label_bridges,
        label_fusion=label_fusion,
        mesh_coordinates=mesh_coordinates, device=device,
    )  # fmt: skip
    field_config = preset_field_config(preset, seed, field_iters)
    lines = StageLines()
    with _field_progress() as update:
        summary = run(
            dataset,
            request,
            out,
            field,
            field_config,
            progress=update,
            allow_other_field=allow_other_field,
            max_memory_gib=max_memory,
            announce=lines,
            warn=warning_line,
            advance=lines.advance,
        )
    _print_summary({method: summary})
    for fit, done in summary.get("resumed_from_step", {}).items():
        console.print(f"{fit} fit resumed from its checkpoint after {done} updates")
    for candidate in summary.get("field_candidates", []):
        kept = " (kept)" if candidate["field_dir"] == summary["field_dir"] else ""
        console.print(
            f"field {candidate['field_dir']}: label loss {candidate['occupancy_label_loss']:.5f}"
            f"{kept}"
        )
    console.print(f"outputs in {out}")


def _print_summary(summaries: dict) -> None:
    from ultron.report.tables import metrics_table

    with_metrics = {k: v["metrics"] for k, v in summaries.items() if v.get("metrics")}
    if with_metrics:
        # the visible-reference figures lead where the dataset has a visible reference
        visible = all(m["mean"].get("cd_visible") is not None for m in with_metrics.values())
        names = ("cd_visible", "completeness_visible") if visible else ()
        title = "surface distances to the reference (mm)"
        console.print(metrics_table(with_metrics, title, (*names, "cd", "hd95", "mad")))
    for name, summary in summaries.items():
        timings = ", ".join(f"{k} {v:.1f} s" for k, v in summary["timings_s"].items())
        console.print(f"{name}: {timings}", highlight=False, soft_wrap=True)


@command()
def demo(
    out: Path = Path("runs/demo"),
    seed: int = 0,
    device: str = "auto",
    threads: int | None = None,
) -> None:
    """Simulate L3, fit the acoustic field, run UltrON and UltrON w/o loss at 10%, compare.

    --out/ultron and --out/ultron-noloss must be new, empty or earlier reconstruct runs.

    Args:
        out: Output directory.
        seed: Seed of simulation, labels and training.
    """
    from ultron.pipeline.demo import DEMO_METHODS, run_demo

    def log(line: str) -> None:
        console.print(line, highlight=False)

    lines = StageLines()
    summaries = run_demo(
        out, seed, device, _field_progress, console.status, log, lines, lines.advance
    )
    _print_summary(summaries)
    for method in DEMO_METHODS:
        console.print(
            f"{method}: {out / method / 'mesh.ply'}, {out / method / 'occupancy.nii.gz'}, "
            f"{out / method / 'metrics.json'}, {out / method / 'report.html'}"
        )


@command(
    "model_dir",
    "dataset",
    shared=RUN_HELP,
    aliases=RUN_ALIASES,
    documented_by=("ultron.methods.finetune:FinetuneConfig",),
)
def finetune(
    model_dir: Path,
    dataset: Path,
    out: Path,
    label_fraction: float = 0.01,
    iters: int = 100,
    anchor_weight: float = 1.0,
    field: Path | None = None,
    seed: int = 0,
    field_iters: int | None = None,
    points: int = 100_000,
    visibility: str | None = None,
    allow_other_field: bool = False,
    max_memory: float | None = None,
    mesh_coordinates: str = "lps",
    device: str = "auto",
    threads: int | None = None,
) -> None:
    """Adapt a trained UltrON network to a new shape: freeze its last two layers, train the rest
    on a few labelled frames through the new dataset's own acoustic field, mesh, evaluate.

    --out must be new, empty or an earlier finetune run, which the new run replaces as a
    whole.

    Args:
        model_dir: Output directory of a reconstruct --method ultron run.
        dataset: The new shape's dataset directory.
        field: The dataset's FIELD_DIR (default: fit and cache one).
        field_iters: Field iterations when fitting (default: the fast preset's 3000).
    """
    from ultron.methods.finetune import FinetuneConfig
    from ultron.metrics.surface import MetricsConfig
    from ultron.pipeline.finetune import finetune as run
    from ultron.pipeline.presets import preset_field_config
    from ultron.train.visibility import visibility_config

    config = FinetuneConfig(
        label_fraction=label_fraction,
        iters=iters,
        anchor_weight=anchor_weight,
        seed=seed,
        metrics=MetricsConfig(n_points=points),
        visibility=None if visibility is None else visibility_config(visibility),
        mesh_coordinates=mesh_coordinates,
        device=device,
    )
    field_config = preset_field_config("fast", seed, field_iters)
    lines = StageLines()
    with _field_progress() as update:
        summary = run(
            model_dir,
            dataset,
            config,
            out,
            field,
            field_config,
            update,
            allow_other_field=allow_other_field,
            max_memory_gib=max_memory,
            warn=warning_line,
            announce=lines,
            advance=lines.advance,
        )
    name = f"fine-tuned ({label_fraction:g}, {iters} iter)" if iters else "w/o fine-tuning"
    _print_summary({name: summary})
    console.print(f"outputs in {out}")
