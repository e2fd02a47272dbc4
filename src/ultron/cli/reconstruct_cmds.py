"""``ultron reconstruct`` and ``ultron demo``."""

from __future__ import annotations

from pathlib import Path

import typer

from ultron.arguments import check_choice, check_count, check_range, check_seed
from ultron.cli.common import (
    StageLines,
    apply_threads,
    check_device,
    command,
    console,
    fit_progress,
    warning_line,
)
from ultron.errors import argument_error
from ultron.methods.catalog import method_help

#: The help of the options reconstruct and finetune share.
RUN_HELP = {
    "out": "Output directory.",
    "label_fraction": "Share of annotated frames used, in (0, 1].",
    "seed": "Seed of label selection and training.",
    "points": "Points per surface for metrics.",
    "allow_other_field": "Accept a --field fitted on another dataset (its field.json's"
    " dataset_sha256 differs); run.json records field_dataset_match false.",
    "max_memory": "GiB the run's grids may take, estimated before any work (default: the"
    " machine's memory).",
    "mesh_coordinates": "Coordinates of the mesh files: lps (ultron's world; 3D Slicer's"
    " default for models) or ras; either is tagged SPACE=… in the file header, which Slicer"
    " reads.",
}


def _check_common(
    seed: int,
    field_iters: int | None,
    points: int,
    max_memory: float | None = None,
) -> None:
    """The numeric options reconstruct and finetune share."""
    check_seed("--seed", seed)
    check_count("--field-iters", field_iters)
    check_count("--points", points)
    check_range("--max-memory", max_memory, 0.0, low_open=True)


def _field_progress():
    """The field fit's progress (:func:`~ultron.cli.common.fit_progress`)."""
    return fit_progress("fitting acoustic field")


@command(
    "dataset",
    shared={**RUN_HELP, "method": method_help()},
    metavars={"field": "FIELD_DIR", "label_support": "MM"},
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
        occupancy_iters: Occupancy iterations of ultron* and on (default: the preset's: 1500;
            paper: 50000).
        preset: Settings of every stage: fast (this project's, minutes on a CPU) or paper
            (the UltrON paper's: 8 × 128 MLP field, 75k + 50k iterations, θ alone, BCE(T·f,
            y), whole surface, RoCoSDF's paper settings; for a GPU). Options given win.
        visibility: Source of the loss's transmission T (ultron*): field (the fitted
            acoustic field), confidence (the frame's ultrasound confidence map) or labels
            (the annotation's first bone run per scanline).
        oracle_transmission: Diagnostic (ultron*): train with the simulator's true T
            (<sweep>/transmission.npy of a simulated dataset).
        surface: ultron* and compounding: observed (keep the faces some frame saw facing the
            probe with T ≥ 0.3 above them — compounding: T = 1) or all (the closed
            iso-surface) (default: the preset's: observed; paper: all).
        theta_context: ultron*: radii (mm, comma-separated) of the world-axis neighbours
            whose θ f reads besides θ(x); 'none' for θ(x) alone, as in the paper (default:
            the preset's: 1,2; paper: none).
        positive_weight: ultron*: loss weight of the bone labels: 1 (unweighted, the
            paper's), another number > 0, or 'balanced' (n_background / n_bone, at most 20:
            a fuller but less accurate surface, e.g. for very short runs) (default: 1).
        negatives: ultron: background labels in the compensated loss: 'observed' (full
            weight where T ≥ 0.3, none below: only observed free space is evidence), 'front'
            (observed, and every background label in front of its scanline's first bone
            label whatever T says) or 'weighted' (scaled by T: the paper's BCE(T·f, y))
            (default: the preset's: observed; paper: weighted).
        echo_support: ultron*: keep only surface some frame shows as bone — a bone echo or
            the onset of a shadow within ±1 mm (default: the preset's: on; paper: off).
        label_support: ultron*: surface within MM of a labelled bone surface counts as
            observed (default: the preset's: 1 mm; paper: 0, off).
        label_bridges: ultron*: with --label-support, the labelled surface also runs between
            consecutive labelled frames whose labelled cross-sections agree to within MM
            (default: on).
        label_fusion: ultron*: mesh max(f, C), C the labels f trained on compounded as
            --method compounding does: the annotated bone stays bone; --label-fusion at any
            label fraction (default: the preset's: when the labelled frames are ≥ 90 % of the
            dataset's, e.g. label --auto's labels with --label-fraction 1; paper: off).
    """
    apply_threads(threads)
    _check_common(seed, field_iters, points, max_memory)
    check_count("--occupancy-iters", occupancy_iters, 0)
    check_range("--label-support", label_support, low=0.0)
    device = check_device(device)

    from ultron.methods.registry import METHODS
    from ultron.pipeline.presets import PIPELINE_PRESETS, preset_field_config, preset_request
    from ultron.pipeline.run import reconstruct as run

    check_choice("--method", method, tuple(METHODS))
    check_choice("--preset", preset, PIPELINE_PRESETS)
    if field and len(field) > 1 and not METHODS[method].needs_field:
        raise argument_error("--field", f"given {len(field)} times; {method} uses no field")
    request = preset_request(
        preset, method, label_fraction, seed, points=points, occupancy_iters=occupancy_iters,
        visibility=visibility, oracle=oracle_transmission, surface=surface,
        theta_context=theta_context, positive_weight=positive_weight, negatives=negatives,
        echo_support=echo_support, label_support_mm=label_support, label_bridges=label_bridges,
        label_fusion=label_fusion,
        mesh_coordinates=mesh_coordinates, device=device,
    )  # fmt: skip
    lines = StageLines()
    with _field_progress() as update:
        summary = run(
            dataset,
            request,
            out,
            field,
            preset_field_config(preset, seed, field_iters),
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
        console.print(f"{name}: {timings}")


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
    apply_threads(threads)
    check_seed("--seed", seed)
    device = check_device(device)

    from ultron.pipeline.demo import DEMO_METHODS, run_demo

    def log(line: str) -> None:
        console.print(line, highlight=False)

    summaries = run_demo(out, seed, device, _field_progress, console.status, log)
    _print_summary(summaries)
    for method in DEMO_METHODS:
        console.print(
            f"{method}: {out / method / 'mesh.ply'}, {out / method / 'occupancy.nii.gz'}, "
            f"{out / method / 'metrics.json'}, {out / method / 'report.html'}"
        )


@command("model_dir", "dataset", shared=RUN_HELP)
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
        iters: Fine-tuning iterations; 0 applies the model as is.
        anchor_weight: Weight of the term that holds the network, at pixels of every frame, to
            what it predicted before fine-tuning; 0 fine-tunes as the paper does (on few
            labels the plain fit can lose surface the model had found).
        field: The dataset's FIELD_DIR (default: fit and cache one).
        field_iters: Field iterations when fitting (default: the fast preset's 3000).
        visibility: Source of the loss's T: field, confidence or labels (default: the
            model's).
    """
    apply_threads(threads)
    _check_common(seed, field_iters, points, max_memory)
    check_count("--iters", iters, 0)
    device = check_device(device)

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
    with _field_progress() as update:
        summary = run(
            model_dir,
            dataset,
            config,
            out,
            field,
            preset_field_config("fast", seed, field_iters),
            update,
            allow_other_field=allow_other_field,
            max_memory_gib=max_memory,
            warn=warning_line,
        )
    name = f"fine-tuned ({label_fraction:g}, {iters} iter)" if iters else "w/o fine-tuning"
    _print_summary({name: summary})
    console.print(f"outputs in {out}")


def register(app: typer.Typer) -> None:
    app.command("reconstruct")(reconstruct)
    app.command("finetune")(finetune)
    app.command("demo")(demo)
