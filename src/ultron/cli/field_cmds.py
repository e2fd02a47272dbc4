"""``ultron fit-field`` and ``ultron render`` (stage 1: the acoustic neural field)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ultron.cli.common import (
    DeviceOption,
    ThreadsOption,
    apply_threads,
    check_count,
    check_device,
    check_range,
    check_seed,
    console,
    err_console,
    fit_progress,
    user_errors,
)
from ultron.errors import argument_error
from ultron.models.field_dir import check_field_out
from ultron.outputs import check_output_file

if TYPE_CHECKING:
    import numpy as np

    from ultron.models.fitted import FitProgress, FittedField


def _parse_shape(text: str) -> tuple[int, int] | str:
    if text.strip().lower() in ("auto", "native"):
        return text.strip().lower()
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise argument_error(
            "--fit-shape", f"expected HxW such as 256x128, auto or native, got {text!r}"
        )
    return int(parts[0]), int(parts[1])


FieldDirOut = Annotated[
    Path, typer.Option("--out", help="FIELD_DIR to write (resumed if it exists).")
]
FieldPreset = Annotated[
    str,
    typer.Option(
        "--preset",
        help="default (grid, Ultra-NeRF's heads), shadow (grid, φ floor 0.1 and a 500-step"
        " φ warm-up: the shadow goes into T) or paper (Ultra-NeRF as published: 8 × 128"
        " MLP, 75k iterations).",
    ),
]
Backend = Annotated[
    str | None,
    typer.Option("--backend", help="grid (fast) or mlp (the paper's network); default: preset's."),
]
Iters = Annotated[
    int | None, typer.Option("--iters", help="Training iterations (default: preset's).")
]
ScatteringFloor = Annotated[
    float | None,
    typer.Option(
        "--scattering-floor",
        help="Lower bound φ_min of the scattering amplitude (0: allow anechoic regions);"
        " default: preset's (shadow 0.1, else 0).",
    ),
]
ScatteringWarmup = Annotated[
    int | None,
    typer.Option(
        "--scattering-warmup",
        help="Steps with φ held constant before it is learned (default: preset's).",
    ),
]
ConfidencePrior = Annotated[
    float | None,
    typer.Option(
        "--confidence-prior",
        help="Weight of the one-sided prior T ≤ C + 0.3, C the frame's ultrasound confidence"
        " map (0: off); default: preset's.",
    ),
]
FitSeed = Annotated[int, typer.Option("--seed", help="Seed of initialisation and batches.")]
HoldoutEvery = Annotated[
    int, typer.Option("--holdout-every", help="Hold out every K-th frame for checks (0: none).")
]
FitShape = Annotated[
    str,
    typer.Option(
        "--fit-shape",
        help="Fit at HxW pixels (frames area-resampled), native (the frames' own size) or auto"
        " (the frames' own, or coarser where their pixels are finer than half a speckle grain).",
    ),
]
TrainScatterers = Annotated[
    str,
    typer.Option(
        "--train-scatterers",
        help="expected (E[S], default) or sample (Ultra-NeRF's per-step draw) in training.",
    ),
]
CheckEvery = Annotated[int, typer.Option("--check-every", help="Held-out check every N steps.")]
CheckpointEvery = Annotated[
    int | None,
    typer.Option(
        "--checkpoint-every",
        help="Save checkpoint.pt (with train_log.jsonl and field.json) every N steps and at"
        " the last; an interrupted fit resumes from the latest (default: the preset's, 500).",
    ),
]
FitMaxMemory = Annotated[
    float | None,
    typer.Option(
        "--max-memory",
        help="GiB the fit may take: its planes, frames and working memory are estimated"
        " before any work (default: the machine's memory, or the cgroup's limit).",
    ),
]
NoResume = Annotated[
    bool,
    typer.Option(
        "--no-resume",
        help="Start afresh even if a checkpoint exists: a previous fit's files in --out"
        " are removed first.",
    ),
]


@user_errors
def fit_field_command(
    dataset: Annotated[Path, typer.Argument(help="Dataset directory (ultron-sweeps/1).")],
    out: FieldDirOut,
    preset: FieldPreset = "default",
    backend: Backend = None,
    iters: Iters = None,
    scattering_floor: ScatteringFloor = None,
    scattering_warmup: ScatteringWarmup = None,
    confidence_prior: ConfidencePrior = None,
    seed: FitSeed = 0,
    holdout_every: HoldoutEvery = 10,
    fit_shape: FitShape = "auto",
    train_scatterers: TrainScatterers = "expected",
    check_every: CheckEvery = 250,
    checkpoint_every: CheckpointEvery = None,
    max_memory: FitMaxMemory = None,
    threads: ThreadsOption = None,
    device: DeviceOption = "auto",
    no_resume: NoResume = False,
) -> None:
    """Fit an acoustic neural field (Ultra-NeRF) to a dataset's frames and write FIELD_DIR.

    An existing checkpoint in --out is resumed if it was fitted on the same dataset (content
    hash in field.json) with the same settings; a larger --iters continues on the learning-rate
    schedule of the new total, one below the checkpoint's step is an error (--no-resume starts
    afresh)."""
    check_count("--iters", iters)
    check_range("--scattering-floor", scattering_floor, 0.0, 1.0, high_open=True)
    check_count("--scattering-warmup", scattering_warmup, 0)
    check_range("--confidence-prior", confidence_prior, 0.0)
    check_seed("--seed", seed)
    _check_holdout(holdout_every)
    check_count("--check-every", check_every)
    check_count("--checkpoint-every", checkpoint_every)
    check_range("--max-memory", max_memory, 0.0, low_open=True)
    apply_threads(threads)
    check_field_out(out, dataset)
    device = check_device(device)

    from ultron.data.dataset import SweepDataset
    from ultron.pipeline.resources import check_run_resources
    from ultron.train import field_preset, fit_field
    from ultron.train.field_fit import check_resumable
    from ultron.train.fit_shape import resolve_fit_shape

    data = SweepDataset.load(dataset)
    changes = {
        "backend": backend,
        "iterations": iters,
        "scattering_floor": scattering_floor,
        "scattering_warmup_iters": scattering_warmup,
        "confidence_prior_weight": confidence_prior,
        "checkpoint_every": checkpoint_every,
    }
    config = field_preset(
        preset,
        **{k: v for k, v in changes.items() if v is not None},
        seed=seed,
        holdout_every=holdout_every,
        fit_shape=_parse_shape(fit_shape),
        train_scatterers=train_scatterers,
        check_every=check_every,
    )
    config = resolve_fit_shape(config, data)
    if not no_resume:  # a checkpoint of another dataset or configuration: error before the bar
        check_resumable(out, config, data.content_hash())
    check_run_resources(data, dataset, mesh=False, field_config=config, max_memory_gib=max_memory)
    with fit_progress("fit-field") as progress:
        fitted = fit_field(
            data, config, out, progress=progress, resume=not no_resume, device=device
        )
    _print_fitted(fitted, out, device)


def _check_holdout(holdout_every: int) -> None:
    check_count("--holdout-every", holdout_every, 0)
    if holdout_every == 1:
        raise argument_error(
            "--holdout-every", "expected 0 (none) or an integer ≥ 2 (1 holds out every frame)"
        )


def _print_fitted(fitted: FittedField, out: Path, device: str) -> None:
    """The files fit-field wrote and the fitted θ's statistics."""
    stats = fitted.theta_stats
    console.print(
        f"wrote {out}: field.json, checkpoint.pt, theta_stats.json, train_log.jsonl"
        f" ({fitted.field_config.backend}, fitted at {fitted.probe.height_px}×{fitted.probe.width_px} px"
        f" on {device})",
        highlight=False,
    )
    if stats is not None:
        summary = ", ".join(
            f"{c} {m:.4g}±{s:.3g}"
            for c, m, s in zip(stats.channels, stats.mean, stats.std, strict=True)
        )
        console.print(f"θ statistics: {summary}", highlight=False)
    _print_transmission_check(out)


def _print_transmission_check(out: Path) -> None:
    """On a simulated dataset: the fitted T against the simulator's (transmission_check.json)."""
    from ultron.models.field_dir import TRANSMISSION_CHECK, read_transmission_check

    check = read_transmission_check(out)
    if check is None:
        return
    from ultron.metrics.transmission import TARGET_RELATIONS, TARGETS

    verdict = {True: "met", False: "missed", None: "n/a"}
    met = check.get("met", {})

    def figure(name: str, spec: str) -> str:
        value = check.get(name)
        return "n/a" if value is None else format(value, spec)

    def judged(name: str) -> str:
        return f"({verdict[met.get(name)]}: {TARGET_RELATIONS[name]} {TARGETS[name]:g})"

    console.print(
        f"T against the simulator's truth ({out / TRANSMISSION_CHECK}): median |T − T_true|"
        f" {figure('median_abs_error', '.3f')} {judged('median_abs_error')},"
        f" shadowed-vs-lit ROC AUC {figure('roc_auc', '.3f')} {judged('roc_auc')},"
        f" deep shadow (true T < 0.1) with T < 0.3: {figure('deep_shadow_share', '.0%')},"
        f" lit T median {figure('lit_median', '.2f')}",
        highlight=False,
    )


@user_errors
def render_command(
    field_dir: Annotated[Path, typer.Argument(help="FIELD_DIR written by ultron fit-field.")],
    out: Annotated[Path, typer.Option("--out", help="Output .npy: (N, H, W) float32 in [0, 1].")],
    poses: Annotated[
        Path | None, typer.Option("--poses", help="POSES.npy: (N, 4, 4) probe-to-world, mm.")
    ] = None,
    dataset: Annotated[
        Path | None, typer.Option("--dataset", help="Dataset whose sweep's poses to render.")
    ] = None,
    sweep: Annotated[
        str | None, typer.Option("--sweep", help="Sweep name (with --dataset).")
    ] = None,
    maps: Annotated[
        bool,
        typer.Option("--maps", help="Also write OUT.theta.npy (N,H,W,C) and OUT.transmission.npy."),
    ] = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the scatterer draw.")] = 0,
    expected: Annotated[
        bool, typer.Option("--expected", help="Render the scatterer expectation (no speckle).")
    ] = False,
    allow_other_field: Annotated[
        bool,
        typer.Option(
            "--allow-other-field",
            help="With --dataset: accept a field fitted on another dataset (its field.json's"
            " dataset_sha256 differs).",
        ),
    ] = False,
    device: DeviceOption = "auto",
    threads: ThreadsOption = None,
) -> None:
    """Render B-mode frames from a fitted field at given probe poses (field's probe geometry)."""
    apply_threads(threads)
    check_seed("--seed", seed)
    device = check_device(device)

    import numpy as np

    from ultron import atomic
    from ultron.data.dataset import SweepDataset
    from ultron.models import load_field
    from ultron.models.field_dir import check_field_dataset

    if (poses is None) == (dataset is None):
        raise argument_error("--poses/--dataset", "give exactly one of --poses or --dataset")
    if out.suffix != ".npy":
        raise argument_error("--out", f"expected a .npy file name, got {out}")
    extras = (".theta.npy", ".transmission.npy", ".maps.json") if maps else ()
    for target in (out, *(out.with_suffix(suffix) for suffix in extras)):
        check_output_file(target, "--out")
    pose_array = _read_poses(poses, sweep) if poses is not None else None
    fitted = load_field(field_dir, device)
    if pose_array is None:
        if sweep is None:
            raise argument_error("--sweep", "required with --dataset")
        data = SweepDataset.load(dataset)
        fitted.check_probe(data.probe, str(dataset))
        check_field_dataset(field_dir, data.content_hash(), str(dataset), allow_other_field)
        pose_array = data.sweep(sweep).probe_to_world
    if maps:
        result = fitted.render_maps(pose_array, seed=seed, expected=expected)
        images = result.bmode
        atomic.save_npy(out.with_suffix(".theta.npy"), result.theta)
        atomic.save_npy(out.with_suffix(".transmission.npy"), result.transmission)
        atomic.write_json(out.with_suffix(".maps.json"), {"theta_channels": list(result.channels)})
    else:
        images = fitted.render(pose_array, seed=seed, expected=expected)
    atomic.save_npy(out, np.asarray(images, dtype=np.float32))
    _warn_unfinished(field_dir, fitted.fit_progress)
    what = "expected" if expected else f"seed {seed}"
    console.print(
        f"rendered {images.shape[0]} frames of {images.shape[1]}×{images.shape[2]} ({what}) to {out}"
        + (f" (+ θ {list(fitted.channels)} and T maps)" if maps else ""),
        highlight=False,
    )


def _read_poses(poses: Path, sweep: str | None) -> np.ndarray:
    """``--poses``' (N, 4, 4) probe-to-world poses (one (4, 4) pose: N = 1), checked like a
    dataset's: rigid and finite, no outlier frame (:mod:`ultron.data.outliers`)."""
    from ultron.data.outliers import check_pose_array_outliers
    from ultron.data.validation import load_npy, validate_poses

    if sweep is not None:
        raise argument_error("--sweep", "only valid with --dataset")
    pose_array = load_npy(poses, "poses")
    if pose_array.ndim == 2:
        pose_array = pose_array[None]
    validate_poses(pose_array, poses, "poses")
    check_pose_array_outliers(pose_array, poses)
    return pose_array


def _warn_unfinished(field_dir: Path, progress: FitProgress | None) -> None:
    """One ``warning:`` line on stderr when the field's fit stopped before its iterations."""
    if progress is None or progress.finished:
        return
    err_console.print(
        f"warning: {field_dir / 'field.json'}: the field's fit stopped at step {progress.step}"
        f" of {progress.iterations} (interrupted?), so these frames come from an unfinished"
        " field; run `ultron fit-field` again with the same --out to finish it",
        markup=False,
        highlight=False,
    )


def register(app: typer.Typer) -> None:
    app.command("fit-field")(fit_field_command)
    app.command("render")(render_command)
