"""``ultron fit-field`` and ``ultron render`` (stage 1: the acoustic neural field)."""

from __future__ import annotations

from pathlib import Path

from ultron.cli.common import command, fit_progress, print_lines
from ultron.errors import argument_error


def _parse_shape(text: str) -> tuple[int, int] | str:
    if text.strip().lower() in ("auto", "native"):
        return text.strip().lower()
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise argument_error(
            "--fit-shape", f"expected HxW such as 256x128, auto or native, got {text!r}"
        )
    return int(parts[0]), int(parts[1])


#: The library's names of what fit-field passes on under another name (its checks and help).
FIT_ALIASES = {
    "iterations": "iters",
    "heads.scattering_floor": "scattering_floor",
    "scattering_warmup_iters": "scattering_warmup",
    "confidence_prior_weight": "confidence_prior",
    "grid.volume_cell_mm": "volume_cell",
    "max_memory_gib": "max_memory",
}


@command(
    "dataset",
    metavars={"volume_cell": "MM"},
    aliases=FIT_ALIASES,
    documented_by=("ultron.train.field_config:FieldTrainConfig",),
)
def fit_field_command(
    dataset: Path,
    out: Path,
    preset: str = "default",
    backend: str | None = None,
    iters: int | None = None,
    scattering_floor: float | None = None,
    scattering_warmup: int | None = None,
    confidence_prior: float | None = None,
    volume_cell: float | None = None,
    orientation: str | None = None,
    seed: int = 0,
    holdout_every: int = 10,
    fit_shape: str = "auto",
    train_scatterers: str = "expected",
    check_every: int = 250,
    checkpoint_every: int | None = None,
    max_memory: float | None = None,
    threads: int | None = None,
    device: str = "auto",
    no_resume: bool = False,
) -> None:
    """Fit an acoustic neural field (Ultra-NeRF) to a dataset's frames and write FIELD_DIR.

    An existing checkpoint in --out is resumed if it was fitted on the same dataset (content
    hash in field.json) with the same settings; a larger --iters continues on the learning-rate
    schedule of the new total, one below the checkpoint's step is an error (--no-resume starts
    afresh). An option left unset takes the preset's value.

    Args:
        dataset: Dataset directory (ultron-sweeps/1).
        out: FIELD_DIR to write (resumed if it exists).
        preset: default (grid, Ultra-NeRF's heads), shadow (grid, φ floor 0.1 and a 500-step
            φ warm-up: the shadow goes into T) or paper (Ultra-NeRF as published: 8 × 128
            MLP, 75k iterations).
        backend: grid (fast) or mlp (the paper's network).
        scattering_floor: Lower bound φ_min of the scattering amplitude, below its initial
            0.5 (0: allow anechoic regions; the shadow preset's is 0.1).
        volume_cell: grid: cell of a dense 3D feature grid read beside the planes on every
            box; 0: none (default: 2 on a long box, a long bone's sweep; none on a compact
            one: docs/decisions.md).
        fit_shape: Fit at HxW pixels (frames area-resampled), native (the frames' own size)
            or auto (the frames' own, or coarser where their pixels are finer than half a
            speckle grain).
        no_resume: Start afresh even if a checkpoint exists: a previous fit's files in --out
            are removed first.
    """
    from ultron.pipeline.field import fit_field_dir, fit_lines, fit_warnings
    from ultron.train import field_preset

    changes = {
        "backend": backend,
        "iterations": iters,
        "scattering_floor": scattering_floor,
        "scattering_warmup_iters": scattering_warmup,
        "confidence_prior_weight": confidence_prior,
        "volume_cell_mm": volume_cell,
        "orientation": orientation,
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
    result = fit_field_dir(
        dataset,
        out,
        config,
        resume=not no_resume,
        device=device,
        max_memory_gib=max_memory,
        progress=lambda: fit_progress("fit-field"),
    )
    print_lines(fit_lines(result, device), fit_warnings(result))


@command("field_dir", documented_by=("ultron.pipeline.field:render_frames",))
def render_command(
    field_dir: Path,
    out: Path,
    poses: Path | None = None,
    dataset: Path | None = None,
    sweep: str | None = None,
    maps: bool = False,
    seed: int = 0,
    expected: bool = False,
    allow_other_field: bool = False,
    device: str = "auto",
    threads: int | None = None,
) -> None:
    """Render B-mode frames from a fitted field at given probe poses (field's probe geometry)."""
    from ultron.pipeline.field import render_frames, render_lines

    result = render_frames(
        field_dir,
        out,
        poses=poses,
        dataset=dataset,
        sweep=sweep,
        maps=maps,
        seed=seed,
        expected=expected,
        allow_other_field=allow_other_field,
        device=device,
    )
    print_lines(*render_lines(result, field_dir, seed, expected))
