"""Stage 1 as a library: fit an acoustic field into FIELD_DIR and render frames from one.

:func:`fit_field_dir` is ``ultron fit-field`` and :func:`render_frames` is ``ultron render``
without the command line: they check every input before any work (naming the CLI's options,
so that a command prints their errors as they are), do the work, write the files and return
what a caller reports. The command line only parses options, calls one of them and prints
the lines :func:`fit_lines`, :func:`fit_warnings` and :func:`render_lines` make of the result.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ultron import atomic
from ultron.arguments import check_seed
from ultron.data.dataset import SweepDataset
from ultron.data.outliers import check_pose_array_outliers
from ultron.data.validation import load_npy, validate_poses
from ultron.errors import UltronInputError, argument_error
from ultron.models.field_dir import (
    check_field_dataset,
    check_field_out,
    read_field_json,
    read_train_log,
    read_transmission_check,
)
from ultron.models.fitted import FitProgress, FittedField, load_field
from ultron.outputs import (
    check_not_a_dataset_file,
    check_not_inside_output,
    check_output_file,
    is_inside,
)
from ultron.pipeline.resources import check_run_resources
from ultron.train.field_config import FieldTrainConfig
from ultron.train.field_fit import check_resumable, fit_field
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.loop import Progress

#: The files ``render_frames(..., maps=True)`` writes beside OUT (OUT's ``.npy`` replaced).
MAP_SUFFIXES = (".theta.npy", ".transmission.npy", ".maps.json")


@dataclass(frozen=True)
class FieldFitResult:
    """What :func:`fit_field_dir` did: the fitted field, where it went, on a simulated dataset
    the fitted T against the simulator's (``transmission_check.json``, else None), and the
    last held-out check (``holdout``: ``psnr``, ``ssim`` and, from fits since these were
    logged, ``mean_frame_psnr`` / ``nearest_frame_psnr``, what copying a training frame onto
    the held-out frames scores: :func:`ultron.train.frames.copy_baselines`; None without
    held-out frames), and the checkpoint the fit resumed (``resumed_from``: its step of the
    fit's iterations; None for a fit from scratch)."""

    fitted: FittedField
    out: Path
    transmission_check: dict[str, Any] | None
    holdout: dict[str, float] | None = None
    resumed_from: FitProgress | None = None


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_frames` wrote: ``frames`` B-mode frames of ``frame_shape`` (H, W)
    into ``paths`` (OUT first, then the maps' files), the field's θ ``channels`` and how far
    its fit got (``fit_progress``; None where unknown), so that an unfinished field is told."""

    frames: int
    frame_shape: tuple[int, int]
    channels: tuple[str, ...]
    paths: tuple[Path, ...]
    fit_progress: FitProgress | None


def fit_field_dir(
    dataset_dir: str | Path,
    out: str | Path,
    config: FieldTrainConfig,
    *,
    resume: bool = True,
    device: str = "cpu",
    max_memory_gib: float | None = None,
    progress: Callable[[], AbstractContextManager[Progress | None]] | None = None,
) -> FieldFitResult:
    """Fit a field with ``config`` to the dataset in ``dataset_dir`` and write FIELD_DIR
    ``out`` (:func:`ultron.train.field_fit.fit_field`), resuming a checkpoint there unless
    not ``resume`` (then a previous fit's files are removed first).

    Everything that can fail cheaply fails before the fit starts, so that a mistake costs no
    minutes: ``out`` (new, empty or an earlier fit's, not the dataset), the dataset, a
    checkpoint of another dataset or configuration, and the memory the fit would take
    against ``max_memory_gib`` (default: what the machine has). ``config.fit_shape="auto"`` is
    resolved on the dataset first, so that a resumed fit compares like with like.
    ``progress()`` wraps the fit alone and gives the callback of its per-step dicts (e.g. a
    progress bar's, opened only once the checks passed)."""
    if not isinstance(config, FieldTrainConfig):
        raise argument_error("config", f"expected a FieldTrainConfig, got {type(config).__name__}")
    out = Path(out)
    check_field_out(out, dataset_dir)
    data = SweepDataset.load(dataset_dir)
    config = resolve_fit_shape(config, data)
    resumed_from = None
    if resume and check_resumable(out, config, data.content_hash()):
        resumed_from = FitProgress(int(read_field_json(out)["step"]), config.iterations)
    check_run_resources(
        data, Path(dataset_dir), mesh=False, field_config=config, max_memory_gib=max_memory_gib
    )
    with (progress or nullcontext)() as update:
        fitted = fit_field(data, config, out, progress=update, resume=resume, device=device)
    holdout = last_holdout_check(out)
    return FieldFitResult(fitted, out, read_transmission_check(out), holdout, resumed_from)


def last_holdout_check(field_dir: Path) -> dict[str, float] | None:
    """The last held-out check of FIELD_DIR ``field_dir``'s ``train_log.jsonl`` without its
    ``holdout_`` prefixes (:class:`FieldFitResult`), or None when the fit checked none."""
    checks = [e for e in read_train_log(field_dir, sys.maxsize) if "holdout_psnr" in e]
    if not checks:
        return None
    prefix = "holdout_"
    return {k[len(prefix) :]: v for k, v in checks[-1].items() if k.startswith(prefix)}


def render_frames(
    field_dir: str | Path,
    out: str | Path,
    *,
    poses: str | Path | None = None,
    dataset: str | Path | None = None,
    sweep: str | None = None,
    maps: bool = False,
    seed: int = 0,
    expected: bool = False,
    allow_other_field: bool = False,
    device: str = "cpu",
) -> RenderResult:
    """Render B-mode frames from a fitted field at the field's probe geometry and write them
    atomically. The poses come from exactly one of ``poses`` or ``dataset`` with ``sweep``
    (the dataset's probe must be the field's). Every output is checked before the field is
    loaded, so a bad path costs no rendering.

    Args:
        field_dir: FIELD_DIR written by ultron fit-field.
        out: Output .npy: (N, H, W) float32 in [0, 1].
        poses: POSES.npy: (N, 4, 4) or (4, 4) probe-to-world, mm (checked like a dataset's).
        dataset: Dataset whose sweep's poses to render.
        sweep: Sweep name (with --dataset).
        maps: Also write OUT.theta.npy (N,H,W,C), OUT.transmission.npy and OUT.maps.json (the
            channel names).
        seed: Seed of the scatterer draw.
        expected: Render the scatterer expectation (no speckle).
        allow_other_field: With --dataset: accept a field fitted on another dataset (its
            field.json's dataset_sha256 differs).
        device: Where the field renders.
    """
    if (poses is None) == (dataset is None):
        raise argument_error("--poses/--dataset", "give exactly one of --poses or --dataset")
    check_seed("seed", seed)
    out = Path(out)
    if out.suffix != ".npy":
        raise argument_error("--out", f"expected a .npy file name, got {out}")
    paths = (out, *(out.with_suffix(suffix) for suffix in MAP_SUFFIXES)) if maps else (out,)
    for target in paths:
        check_output_file(target, "--out")
        check_not_a_dataset_file(target, "--out")
        if poses is not None and Path(poses).exists() and is_inside(target, poses):
            raise UltronInputError(target, "--out", "is the --poses file it renders from")
    check_not_inside_output(out, "--out")  # a field's directory is its next fit's to replace
    pose_array = read_pose_file(poses, sweep) if poses is not None else None
    fitted = load_field(field_dir, device)
    if pose_array is None:
        pose_array = _dataset_poses(fitted, field_dir, dataset, sweep, allow_other_field)
    if maps:
        result = fitted.render_maps(pose_array, seed=seed, expected=expected)
        images = result.bmode
        atomic.save_npy(paths[1], result.theta)
        atomic.save_npy(paths[2], result.transmission)
        atomic.write_json(paths[3], {"theta_channels": list(result.channels)})
    else:
        images = fitted.render(pose_array, seed=seed, expected=expected)
    atomic.save_npy(out, np.asarray(images, dtype=np.float32))
    return RenderResult(
        frames=int(images.shape[0]),
        frame_shape=(int(images.shape[1]), int(images.shape[2])),
        channels=tuple(fitted.channels),
        paths=paths,
        fit_progress=fitted.fit_progress,
    )


def read_pose_file(poses: str | Path, sweep: str | None = None) -> np.ndarray:
    """``poses``' (N, 4, 4) probe-to-world poses (one (4, 4) pose: N = 1), checked like a
    dataset's: rigid and finite, no outlier frame (:mod:`ultron.data.outliers`). ``sweep``
    must be None: a sweep name only selects poses of a dataset."""
    if sweep is not None:
        raise argument_error("--sweep", "only valid with --dataset")
    poses = Path(poses)
    pose_array = load_npy(poses, "poses")
    if pose_array.ndim == 2:
        pose_array = pose_array[None]
    validate_poses(pose_array, poses, "poses")
    check_pose_array_outliers(pose_array, poses)
    return pose_array


def _dataset_poses(
    fitted: FittedField,
    field_dir: str | Path,
    dataset: str | Path,
    sweep: str | None,
    allow_other_field: bool,
) -> np.ndarray:
    """Sweep ``sweep``'s poses of ``dataset``, once its probe and content match the field."""
    if sweep is None:
        raise argument_error("--sweep", "required with --dataset")
    data = SweepDataset.load(dataset)
    fitted.check_probe(data.probe, str(dataset))
    check_field_dataset(field_dir, data.content_hash(), str(dataset), allow_other_field)
    return data.sweep(sweep).probe_to_world


def fit_lines(result: FieldFitResult, device: str) -> list[str]:
    """What ``fit-field`` prints: whether it resumed a checkpoint (and from which step), the
    files written, the fitted θ's statistics, the last held-out check against copying a
    training frame, and on a simulated dataset the fitted T against the simulator's."""
    fitted, out = result.fitted, result.out
    lines = []
    resumed = result.resumed_from
    if resumed is not None:
        lines.append(
            f"the fit in {out} had finished its {resumed.iterations} steps; loaded it"
            if resumed.finished
            else f"resumed the fit in {out} from its checkpoint at step {resumed.step} of"
            f" {resumed.iterations}"
        )
    lines.append(
        f"wrote {out}: field.json, checkpoint.pt, theta_stats.json, train_log.jsonl"
        f" ({fitted.field_config.backend}, fitted at {fitted.probe.height_px}×"
        f"{fitted.probe.width_px} px on {device})"
    )
    stats = fitted.theta_stats
    if stats is not None:
        summary = ", ".join(
            f"{c} {m:.4g}±{s:.3g}"
            for c, m, s in zip(stats.channels, stats.mean, stats.std, strict=True)
        )
        lines.append(f"θ statistics: {summary}")
    check = result.holdout
    if check is not None:
        line = f"held-out frames: PSNR {check['psnr']:.2f} dB, SSIM {check['ssim']:.3f}"
        mean, nearest = check.get("mean_frame_psnr"), check.get("nearest_frame_psnr")
        if mean is not None and nearest is not None:
            line += (
                f"; copying onto them the mean training frame {mean:.2f} dB, the nearest"
                f" {nearest:.2f} dB"
            )
        lines.append(line)
    if result.transmission_check is not None:
        lines.append(_transmission_line(out, result.transmission_check))
    return lines


#: A held-out PSNR within this many dB of the all-black frame's is a fit still at its black
#: start (docs/real-sweeps.md, "Blank columns": such fits sat within 0.1 dB of it).
BLACK_MARGIN_DB = 1.0


def fit_warnings(result: FieldFitResult) -> list[str]:
    """A warning when the held-out frames are rendered about as well as an all-black frame
    (within :data:`BLACK_MARGIN_DB`) or worse than the mean training frame."""
    check = result.holdout or {}
    psnr, mean, black = (check.get(k) for k in ("psnr", "mean_frame_psnr", "black_frame_psnr"))
    if psnr is None or mean is None or check.get("nearest_frame_psnr") is None:
        return []
    if black is not None and psnr < black + BLACK_MARGIN_DB:
        return [
            f"the field renders its held-out frames about as an all-black image does"
            f" ({psnr:.2f} dB against {black:.2f} dB): the fit has not left its black"
            " start; fit again with another --seed, and check the frames for regions that are"
            " 0 in every frame (ultron info; docs/field.md)"
        ]
    if psnr < mean:
        return [
            f"the field predicts its held-out frames worse than the mean training frame does"
            f" ({psnr:.2f} < {mean:.2f} dB): what it learned between the frames is not"
            " borne out by them (too few iterations, too few frames, or frames far apart for"
            " its resolution; docs/field.md)"
        ]
    return []


def _transmission_line(out: Path, check: dict[str, Any]) -> str:
    """On a simulated dataset: the fitted T against the simulator's (transmission_check.json)."""
    from ultron.metrics.transmission import TARGET_RELATIONS, TARGETS
    from ultron.models.field_dir import TRANSMISSION_CHECK

    verdict = {True: "met", False: "missed", None: "n/a"}
    met = check.get("met", {})

    def figure(name: str, spec: str) -> str:
        value = check.get(name)
        return "n/a" if value is None else format(value, spec)

    def judged(name: str) -> str:
        return f"({verdict[met.get(name)]}: {TARGET_RELATIONS[name]} {TARGETS[name]:g})"

    return (
        f"T against the simulator's truth ({out / TRANSMISSION_CHECK}): median |T − T_true|"
        f" {figure('median_abs_error', '.3f')} {judged('median_abs_error')},"
        f" shadowed-vs-lit ROC AUC {figure('roc_auc', '.3f')} {judged('roc_auc')},"
        f" deep shadow (true T < 0.1) with T < 0.3: {figure('deep_shadow_share', '.0%')},"
        f" lit T median {figure('lit_median', '.2f')}"
    )


def render_lines(
    result: RenderResult, field_dir: str | Path, seed: int, expected: bool
) -> tuple[list[str], list[str]]:
    """What ``render`` prints (lines, warnings): the frames written, and a warning when the
    field's fit stopped before its iterations."""
    height, width = result.frame_shape
    what = "expected" if expected else f"seed {seed}"
    maps = f" (+ θ {list(result.channels)} and T maps)" if len(result.paths) > 1 else ""
    lines = [
        f"rendered {result.frames} frames of {height}×{width} ({what}) to {result.paths[0]}{maps}"
    ]
    progress, warnings = result.fit_progress, []
    if progress is not None and not progress.finished:
        warnings.append(
            f"{Path(field_dir) / 'field.json'}: the field's fit stopped at step {progress.step}"
            f" of {progress.iterations} (interrupted?), so these frames come from an unfinished"
            " field; run `ultron fit-field` again with the same --out to finish it"
        )
    return lines, warnings
