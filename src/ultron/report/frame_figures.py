"""Per-frame report figures: recorded vs rendered B-mode with θ / T maps, and label masks."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.data.validation import LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error
from ultron.report.plotting import (
    check_dataset,
    check_frame_indices,
    display_factor,
    figure_png,
    image_extent_mm,
    new_figure,
    place_grid,
    reduced_frame,
    robust_limits,
    top_title,
)

#: Overlay colours (RGBA) of the label classes; background (0) is left untinted.
BONE_RGBA = (1.0, 0.1, 0.1, 0.6)
IGNORED_RGBA = (0.2, 0.5, 1.0, 0.35)


def _sweep(dataset: SweepDataset, sweep_name: str, name: str = "sweep_name"):
    if not isinstance(sweep_name, str):
        raise argument_error(name, f"expected a sweep name, got {sweep_name!r}")
    for sweep in dataset.sweeps:
        if sweep.name == sweep_name:
            return sweep
    raise argument_error(
        name,
        f"no sweep {sweep_name!r} in the dataset; available: {[s.name for s in dataset.sweeps]}",
    )


def _panel(fig, ax, image, extent, title, cmap, vmin, vmax, bar_label, show_ylabel):
    shown = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax, extent=extent, aspect="equal")
    ax.set_title(title, fontsize=8)
    ax.set_xlabel("lateral (mm)", fontsize=7)
    if show_ylabel:
        ax.set_ylabel("depth (mm)", fontsize=7)
    ax.tick_params(labelsize=6)
    bar = fig.colorbar(shown, ax=ax, fraction=0.08, pad=0.03)
    bar.set_label(bar_label, fontsize=6)
    bar.ax.tick_params(labelsize=6)


def frames_figure(
    dataset: SweepDataset, fitted, sweep_name: str, frame_indices: Sequence[int], seed: int = 0
) -> bytes:
    """One row per frame of ``sweep_name``: the recorded B-mode, the field's rendered B-mode,
    each θ channel (named) and the transmission T, each with a colour bar, in mm (lateral ×
    depth). ``fitted`` (a :class:`ultron.models.fitted.FittedField`) may be ``None``: then only
    the recorded frames are shown. θ colour limits are shared down each column (1st–99th pct)."""
    check_dataset(dataset)
    sweep = _sweep(dataset, sweep_name)
    if isinstance(frame_indices, np.ndarray):
        frame_indices = frame_indices.reshape(-1).tolist()
    if isinstance(frame_indices, str | bytes) or not isinstance(frame_indices, Sequence):
        raise argument_error("frame_indices", "expected a sequence of frame indices")
    if len(frame_indices) == 0:
        raise argument_error("frame_indices", "expected at least one frame index")
    indices = check_frame_indices(frame_indices, sweep.n_frames, "frame_indices", sweep.name)
    if fitted is not None and not hasattr(fitted, "render_maps"):
        raise argument_error("fitted", f"expected a FittedField, got {type(fitted).__name__}")

    recorded_extent = image_extent_mm(dataset.probe)
    columns: list[tuple[str, np.ndarray, str, float, float, str]] = [
        ("recorded B-mode", sweep.images[indices], "gray", 0.0, 255.0, "intensity (0–255)")
    ]
    field_extent = recorded_extent
    if fitted is not None:
        fitted.check_probe(dataset.probe, "dataset")
        field_extent = image_extent_mm(fitted.probe)
        maps = fitted.render_maps(sweep.probe_to_world[indices], seed=seed)
        columns.append(("rendered B-mode", maps.bmode, "gray", 0.0, 1.0, "intensity (0–1)"))
        for c, channel in enumerate(maps.channels):
            values = maps.theta[..., c]
            low, high = robust_limits(values)
            columns.append((f"θ: {channel}", values, "magma", low, high, channel))
        columns.append(("transmission T", maps.transmission, "viridis", 0.0, 1.0, "T (0–1)"))

    n_rows, n_cols = len(indices), len(columns)
    aspect = dataset.probe.depth_mm / dataset.probe.width_mm
    fig = new_figure(2.5 * n_cols, (1.5 * aspect + 0.7) * n_rows + 0.4)
    for row, frame in enumerate(indices):
        for col, (name, stack, cmap, vmin, vmax, bar_label) in enumerate(columns):
            ax = fig.add_subplot(n_rows, n_cols, row * n_cols + col + 1)
            extent = recorded_extent if col == 0 else field_extent
            # the sweep's name on a line of its own: PLUS names run long
            title = f"{sweep.name} #{frame}\n{name}" if col == 0 else name
            _panel(fig, ax, stack[row], extent, title, cmap, vmin, vmax, bar_label, col == 0)
    if fitted is None:
        top_title(fig, "recorded frames\n(no acoustic field)")
    top = 0.45 if fitted is not None else 0.8
    place_grid(fig, n_rows, n_cols, (0.5, 0.55, 0.45, top), (0.8, 0.7))
    return figure_png(fig)


def _spread(
    selection: dict[str, list[int]], with_bone: dict[str, set[int]], max_frames: int
) -> list[tuple[str, int]]:
    """Up to ``max_frames`` (sweep, frame) picks, shared round-robin among the sweeps, evenly
    spaced within each, frames showing bone (``with_bone``) first."""
    counts = dict.fromkeys(selection, 0)
    remaining = max_frames
    while remaining > 0:
        progressed = False
        for name, frames in selection.items():
            if remaining > 0 and counts[name] < len(frames):
                counts[name] += 1
                remaining -= 1
                progressed = True
        if not progressed:
            break
    picks: list[tuple[str, int]] = []
    for name, frames in selection.items():
        chosen: list[int] = []
        bony = [f for f in frames if f in with_bone[name]]
        rest = [f for f in frames if f not in with_bone[name]]
        for pool, n in ((bony, min(counts[name], len(bony))), (rest, counts[name] - len(bony))):
            if n > 0:
                # centres of n equal bins: distinct, evenly spread, endpoints avoided
                positions = ((np.arange(n) + 0.5) * len(pool) / n).astype(int)
                chosen.extend(pool[p] for p in positions)
        picks.extend((name, frame) for frame in sorted(chosen))
    return picks


def _overlay(labels: np.ndarray) -> np.ndarray:
    rgba = np.zeros((*labels.shape, 4), dtype=np.float32)
    rgba[labels == LABEL_TARGET] = BONE_RGBA
    rgba[labels == LABEL_UNANNOTATED] = IGNORED_RGBA
    return rgba


def label_masks_figure(
    dataset: SweepDataset, selection_frames: Mapping[str, Sequence[int]], max_frames: int = 8
) -> bytes:
    """B-mode of the labelled frames used (``selection_frames``: sweep name → frame indices,
    as in run.json's ``selection.frames``), at most ``max_frames`` spread over the sweeps, with
    the label mask overlaid: bone (1) red, ignored / not annotated (255) blue, background (0)
    untinted."""
    from matplotlib.patches import Patch

    check_dataset(dataset)
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
        raise argument_error("max_frames", f"expected a positive integer, got {max_frames!r}")
    if not isinstance(selection_frames, Mapping):
        raise argument_error("selection_frames", "expected a mapping sweep name → frame indices")
    selection: dict[str, list[int]] = {}
    for name, frames in selection_frames.items():
        sweep = _sweep(dataset, name, "selection_frames")
        if isinstance(frames, str | bytes) or not isinstance(frames, Sequence | np.ndarray):
            raise argument_error("selection_frames", f"sweep {name!r}: expected frame indices")
        selection[name] = check_frame_indices(
            list(frames), sweep.n_frames, "selection_frames", name
        )
    with_bone = {}
    for name, frames in selection.items():
        labels = dataset.sweep(name).labels
        bone = (
            set()
            if labels is None
            else set(np.flatnonzero((labels == LABEL_TARGET).any(axis=(1, 2))).tolist())
        )
        with_bone[name] = bone & set(frames)
    picks = _spread(selection, with_bone, max_frames)
    if not picks:
        raise argument_error("selection_frames", "no frames selected")

    n_cols = min(4, len(picks))
    n_rows = math.ceil(len(picks) / n_cols)
    probe = dataset.probe
    extent = image_extent_mm(probe)
    aspect = probe.depth_mm / probe.width_mm
    fig = new_figure(2.4 * n_cols, (1.9 * aspect + 0.6) * n_rows + 0.6)
    factor = display_factor(probe.width_px, 2.4 * fig.dpi)
    for k, (name, frame) in enumerate(picks):
        sweep = dataset.sweep(name)
        ax = fig.add_subplot(n_rows, n_cols, k + 1)
        labels = None if sweep.labels is None else sweep.labels[frame]
        image, shown, shown_extent = reduced_frame(sweep.images[frame], labels, factor, extent)
        ax.imshow(image, cmap="gray", vmin=0, vmax=255, extent=shown_extent)
        if labels is None:
            note = "no labels"
            ax.text(0, probe.depth_mm * 0.08, note, color="yellow", ha="center", fontsize=7)
        else:
            ax.imshow(_overlay(shown), extent=shown_extent, interpolation="nearest")
            note = f"{int((labels == LABEL_TARGET).sum())} bone px"
            if (labels == LABEL_UNANNOTATED).all():
                note = "not annotated"
        ax.set_title(f"{name} #{frame}\n({note})", fontsize=8)
        ax.set_xlabel("lateral (mm)", fontsize=7)
        if k % n_cols == 0:
            ax.set_ylabel("depth (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    handles = [
        Patch(facecolor=BONE_RGBA, label="bone (1)"),
        Patch(facecolor=IGNORED_RGBA, label="ignored / not annotated (255)"),
        Patch(facecolor="none", edgecolor="grey", label="background (0): untinted"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=7, frameon=False)
    place_grid(fig, n_rows, n_cols, (0.55, 0.15, 0.8, 0.45), (0.35, 0.75))
    return figure_png(fig)
