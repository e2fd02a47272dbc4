"""Label-fraction selection and gathering of labelled pixels (METHOD.md §3).

The label fraction is the share of annotated FRAMES used (not pixels). Frames are chosen
deterministically from a seed and spread evenly across all sweeps: the number of frames is
divided among the sweeps in proportion to their annotated frames (largest remainder, at least
one per sweep when there are enough), and within a sweep the frames are evenly spaced from a
seeded random phase, so that a small fraction still covers the whole sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ultron.arguments import check_fraction, check_integer
from ultron.data.auto_label_dataset import auto_label_records
from ultron.data.dataset import SweepDataset
from ultron.data.geometry import apply_pose, probe_points_mm
from ultron.data.validation import LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import UltronInputError, argument_error

#: How far above a band of bone labels label compounding reads its unsure pixels as background
#: (:func:`surface_outer_side`): the band's own thickness in the annotation convention (the
#: simulator's annotator and ``label --auto`` draw 2 mm bands).
OUTER_SIDE_MM = 2.0
#: Below this share of a dataset's frames annotated, the annotation is sparse already: a person
#: labelled the frames they chose (:func:`unused_label_warnings`).
SPARSE_ANNOTATION_SHARE = 0.5


@dataclass(frozen=True)
class FrameSelection:
    """Chosen frames: ``frames[sweep_name]`` is a sorted int64 array of frame indices."""

    fraction: float
    seed: int
    frames: dict[str, np.ndarray]

    @property
    def n_frames(self) -> int:
        return int(sum(len(v) for v in self.frames.values()))

    def to_dict(self) -> dict[str, object]:
        return {
            "fraction": self.fraction,
            "seed": self.seed,
            "frames": {name: idx.tolist() for name, idx in self.frames.items()},
        }


def select_label_frames(
    dataset: SweepDataset, fraction: float, seed: int, where: str | Path = "dataset"
) -> FrameSelection:
    """Choose ⌈fraction × (annotated frames)⌉ annotated frames, spread across every sweep.

    Raises a clear error, naming ``where`` (the dataset directory), when the dataset has no
    annotated frame, or ``fraction`` is not in (0, 1].
    """
    check_fraction("label_fraction", fraction)
    available = {s.name: s.labelled_frames for s in dataset.sweeps if len(s.labelled_frames)}
    total = sum(len(v) for v in available.values())
    if total == 0:
        raise UltronInputError(
            where, "labels", "no annotated frame: every sweep's labels.npy is missing or all"
            " 255 (unsure); label frames first (ultron label), or, after label --auto, see each"
            " sweep's auto_labels_quality.csv",
        )  # fmt: skip
    wanted = max(1, math.ceil(fraction * total - 1e-9))
    counts = _allocate(wanted, {name: len(v) for name, v in available.items()})
    rng = np.random.default_rng(seed)
    frames: dict[str, np.ndarray] = {}
    for name, indices in available.items():
        k = counts[name]
        if k == 0:
            frames[name] = np.zeros(0, dtype=np.int64)
            continue
        n = len(indices)
        phase = rng.random()
        positions = np.floor((np.arange(k) + phase) * n / k).astype(np.int64)
        frames[name] = np.sort(indices[np.clip(positions, 0, n - 1)])
    return FrameSelection(fraction=float(fraction), seed=int(seed), frames=frames)


def selection_warnings(dataset: SweepDataset, selection: FrameSelection) -> list[str]:
    """One line when ``selection`` leaves an annotated sweep without a labelled frame (the
    fraction picks fewer frames than there are annotated sweeps): no label of that sweep's
    views reaches the method. The line names the sweeps and the fraction that labels one frame
    of each."""
    annotated = [s for s in dataset.sweeps if len(s.labelled_frames)]
    empty = [s.name for s in annotated if len(selection.frames.get(s.name, ())) == 0]
    if not empty:
        return []
    total = sum(len(s.labelled_frames) for s in annotated)
    enough = math.ceil(len(annotated) / total * 1000) / 1000  # rounded up: one frame each
    return [
        f"label fraction {selection.fraction:g} selects {selection.n_frames} of {total} annotated"
        f" frames for {len(annotated)} annotated sweeps: {', '.join(empty)}"
        f" {'gets' if len(empty) == 1 else 'get'} no labelled frame; a label fraction of at"
        f" least {enough:g} labels one frame in each"
    ]


def unused_label_warnings(dataset: SweepDataset, selection: FrameSelection) -> list[str]:
    """One line when a label fraction below 1 leaves annotated frames unread that a user means
    to be read: automatic labels (``label --auto``: free on every frame), or an annotation
    that covers fewer than :data:`SPARSE_ANNOTATION_SHARE` of the frames (a person labelled the
    frames they chose). A fraction below 1 hides labels, as the paper's experiments do (UltrON
    at 10 %); on such data it silently drops most of them. A dataset annotated on most frames
    (a simulated one, or CT-derived labels) gets no line: there the fraction is the experiment."""
    annotated = sum(len(s.labelled_frames) for s in dataset.sweeps)
    unread = annotated - selection.n_frames
    if selection.fraction >= 1 or unread <= 0:
        return []
    automatic = sorted(auto_label_records(dataset))
    if automatic:
        why = f"automatic labels of sweep(s) {', '.join(automatic)}"
    elif annotated < SPARSE_ANNOTATION_SHARE * dataset.n_frames:
        why = f"{annotated} of the {dataset.n_frames} frames are annotated"
    else:
        return []
    return [
        f"label fraction {selection.fraction:g} reads {selection.n_frames} of the {annotated}"
        f" annotated frames ({why}); the other {unread} are not used. --label-fraction 1 reads"
        " every one (a fraction below 1 hides labels, for experiments such as the paper's 10 %)"
    ]


def check_selection_has_bone(
    dataset: SweepDataset, selection: FrameSelection, where: str | Path = "dataset"
) -> None:
    """Refuse a selection of frames without a single bone pixel (label 1) — nothing can be
    reconstructed from it (a recording without bone, or automatic labels that found none) —
    naming ``where`` (the dataset directory), the frames and what to look at."""
    if any((labels == LABEL_TARGET).any() for _, _, labels in _selected_labels(dataset, selection)):
        return
    names = ", ".join(name for name, frames in selection.frames.items() if len(frames))
    raise UltronInputError(
        where,
        "labels",
        f"the {selection.n_frames} frames chosen (label fraction {selection.fraction:g}, seed"
        f" {selection.seed}) of sweep(s) {names} contain no bone pixel (label 1): nothing to"
        " reconstruct; a recording without bone, or automatic labels that found none (see"
        " each sweep's auto_labels_quality.csv), or a label fraction too small for the"
        " frames that show bone",
    )


def _allocate(wanted: int, sizes: dict[str, int]) -> dict[str, int]:
    """Split ``wanted`` among groups in proportion to their sizes (largest remainder)."""
    total = sum(sizes.values())
    names = list(sizes)
    if wanted >= len(names):
        # everyone gets one first, the rest proportionally
        base = dict.fromkeys(names, 1)
        rest = wanted - len(names)
        spare = {n: sizes[n] - 1 for n in names}
    else:
        base = dict.fromkeys(names, 0)
        rest = wanted
        spare = dict(sizes)
    spare_total = sum(spare.values())
    if rest and spare_total:
        exact = {n: rest * spare[n] / spare_total for n in names}
        floor = {n: math.floor(exact[n]) for n in names}
        left = rest - sum(floor.values())
        order = sorted(names, key=lambda n: (exact[n] - floor[n], sizes[n]), reverse=True)
        for n in order[:left]:
            floor[n] += 1
        for n in names:
            base[n] += floor[n]
    for n in names:
        base[n] = min(base[n], sizes[n])
    assert sum(base.values()) == min(wanted, total)
    return base


@dataclass(frozen=True)
class LabelledPixels:
    """Annotated pixels of selected frames (label ≠ 255), as flat arrays of equal length."""

    sweep_index: np.ndarray  # int64, index into dataset.sweeps
    frame: np.ndarray  # int64, frame index within its sweep
    row: np.ndarray  # int64
    col: np.ndarray  # int64
    label: np.ndarray  # uint8, 0 or 1

    def __len__(self) -> int:
        return int(self.label.shape[0])

    def take(self, index: np.ndarray) -> LabelledPixels:
        """The pixels at ``index`` (integer indices or a boolean mask), every field alike."""
        return LabelledPixels(*(getattr(self, f.name)[index] for f in fields(self)))

    def frame_groups(self) -> dict[tuple[int, int], np.ndarray]:
        """The pixels' indices grouped by frame: {(sweep index, frame): ascending indices}, in
        (sweep, frame) order (one stable sort)."""
        if len(self) == 0:
            return {}
        order = np.lexsort((self.frame, self.sweep_index))
        keys = np.stack([self.sweep_index[order], self.frame[order]], axis=1)
        firsts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
        groups = np.split(order, firsts[1:])
        return {(int(s), int(f)): g for (s, f), g in zip(keys[firsts], groups, strict=True)}

    def world_mm(self, dataset: SweepDataset, subset: np.ndarray | None = None) -> np.ndarray:
        """World positions (M, 3) float64 mm of these pixels (or of ``subset`` indices), each
        through its own frame's ``probe_to_world``: one :func:`apply_pose` per frame, on its
        pixels (a pose per pixel would gather M 4 × 4 matrices first; a frame's pixels at a time
        keeps the temporaries small: docs/decisions.md, "Fresh memory")."""
        import torch

        index = np.arange(len(self)) if subset is None else np.asarray(subset, dtype=np.int64)
        out = np.zeros((index.size, 3))
        for sweep_index, sweep in enumerate(dataset.sweeps):
            sel = np.flatnonzero(self.sweep_index[index] == sweep_index)
            if sel.size == 0:
                continue
            frames = self.frame[index[sel]]
            if np.any(frames[1:] < frames[:-1]):  # gathered pixels come frame by frame already
                order = np.argsort(frames, kind="stable")
                sel, frames = sel[order], frames[order]
            bounds = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1], True])
            poses = torch.as_tensor(sweep.probe_to_world[frames[bounds[:-1]]], dtype=torch.float64)
            for pose, a, b in zip(poses, bounds[:-1], bounds[1:], strict=True):
                pick = index[sel[a:b]]
                probe = probe_points_mm(
                    torch.as_tensor(self.row[pick], dtype=torch.float64),
                    torch.as_tensor(self.col[pick], dtype=torch.float64),
                    dataset.probe,
                )
                out[sel[a:b]] = apply_pose(pose[None], probe[None])[0].numpy()
        return out

    def in_front_of_bone(self) -> np.ndarray:
        """(P,) bool: the pixel is background (0) and lies above its scanline's first bone
        label — in its own frame and column, at a row r < r₁, r₁ the shallowest row labelled 1
        there. The annotation itself says the beam crossed such a pixel to reach an echo it
        calls bone, so it is observed free space whatever T a field assigns it. Scanlines with
        no bone label, and background under the first bone label, are never in front."""
        bone = self.label == 1
        if not bone.any():
            return np.zeros(len(self), dtype=bool)
        width, frames = int(self.col.max()) + 1, int(self.frame.max()) + 1
        line = (self.sweep_index * frames + self.frame) * width + self.col  # a scanline's id
        bone_line, bone_row = line[bone], self.row[bone]
        order = np.lexsort((bone_row, bone_line))  # by scanline, then depth
        starts = np.flatnonzero(np.r_[True, np.diff(bone_line[order]) != 0])
        lines, first = bone_line[order][starts], bone_row[order][starts]  # shallowest bone row
        at = np.minimum(np.searchsorted(lines, line), len(lines) - 1)
        return (self.label == 0) & (lines[at] == line) & (self.row < first[at])


def surface_outer_side(labels: np.ndarray, rows: int) -> np.ndarray:
    """The unsure pixels (255) on the outer side of a labelled surface: bool, the shape of
    ``labels`` (..., H, W), row 0 at the transducer and one scanline per column.

    The annotation convention (a band of bone, 1, under the surface a scanline meets: the
    simulator's annotator, ``label --auto`` and the CT-derived labels alike) puts the surface at
    the band's top edge, so the pixels just above that edge are outside bone by the label's own
    account, even where the labeller left them unsure (``label --auto`` claims background only
    ≥ 1.5 mm above any echo that could be bone). Pixel (r, c) is on the outer side when it is
    255 and, for some k in 1 … ``rows``, pixel (r + k, c) is 1 and the pixels between are 255:
    the run of unsure pixels directly above each band, at most ``rows`` long.
    """
    labels = np.asarray(labels)
    if labels.ndim < 2:
        raise argument_error("labels", f"expected (..., H, W) labels, got shape {labels.shape}")
    check_integer("rows", rows)
    unsure = labels == LABEL_UNANNOTATED
    outer = np.zeros(labels.shape, dtype=bool)
    reached = labels == LABEL_TARGET  # the pixels whose upper neighbour is k rows from a band
    for _ in range(rows):
        step = np.zeros_like(reached)
        step[..., :-1, :] = reached[..., 1:, :]
        reached = step & unsure
        if not reached.any():
            break
        outer |= reached
    return outer


def outer_side_rows(dataset: SweepDataset, outer_side_mm: float) -> int:
    """Rows of ``dataset``'s frames within ``outer_side_mm`` (≥ 0) of a band's top edge."""
    if not (isinstance(outer_side_mm, int | float) and math.isfinite(outer_side_mm)) or (
        outer_side_mm < 0
    ):
        raise argument_error("outer_side_mm", f"expected a distance ≥ 0 mm, got {outer_side_mm!r}")
    return int(outer_side_mm / dataset.probe.axial_spacing_mm + 1e-9)


def _selected_labels(dataset: SweepDataset, selection: FrameSelection, outer_side_mm: float = 0.0):
    """(sweep index, selected frame indices, their labels) of every sweep with labels and
    selected frames; the :func:`surface_outer_side` pixels within ``outer_side_mm`` read as
    background (0)."""
    outer_rows = outer_side_rows(dataset, outer_side_mm)
    for sweep_index, sweep in enumerate(dataset.sweeps):
        frames = selection.frames.get(sweep.name)
        if frames is None or len(frames) == 0 or sweep.labels is None:
            continue
        labels = sweep.labels[frames]
        if outer_rows > 0:
            labels = np.where(
                surface_outer_side(labels, outer_rows), LABEL_BACKGROUND, labels
            ).astype(np.uint8)
        yield sweep_index, frames, labels


def count_labelled_pixels(
    dataset: SweepDataset, selection: FrameSelection, outer_side_mm: float = 0.0
) -> int:
    """How many pixels :func:`gather_labelled_pixels` gathers from the selected frames."""
    return sum(
        int(np.count_nonzero(labels != LABEL_UNANNOTATED))
        for _, _, labels in _selected_labels(dataset, selection, outer_side_mm)
    )


def gather_labelled_pixels(
    dataset: SweepDataset,
    selection: FrameSelection,
    only: int | None = None,
    outer_side_mm: float = 0.0,
) -> LabelledPixels:
    """Every annotated pixel of the selected frames (``only``: those with this label), with its
    sweep, frame, row and column; with ``outer_side_mm`` > 0 also, as background (0), the unsure
    pixels on the outer side of each labelled surface within that distance of its top edge
    (:func:`surface_outer_side`: the label puts the surface at that edge). Label compounding
    reads labels so; the learned methods read them as stored (docs/real-sweeps.md, "Compounding
    automatic labels")."""
    parts: list[tuple[np.ndarray, ...]] = []
    for sweep_index, frames, labels in _selected_labels(dataset, selection, outer_side_mm):
        f, r, c = np.nonzero(labels != LABEL_UNANNOTATED if only is None else labels == only)
        parts.append((np.full(f.shape, sweep_index), frames[f], r, c, labels[f, r, c]))
    if not parts:
        raise UltronInputError("dataset", "labels", "the selected frames have no annotated pixel")
    cat = [np.concatenate(p) for p in zip(*parts, strict=True)]
    return LabelledPixels(
        sweep_index=cat[0].astype(np.int64),
        frame=cat[1].astype(np.int64),
        row=cat[2].astype(np.int64),
        col=cat[3].astype(np.int64),
        label=cat[4].astype(np.uint8),
    )


def selection_chunks(
    dataset: SweepDataset, selection: FrameSelection, max_pixels: int
) -> list[FrameSelection]:
    """``selection`` cut into consecutive runs of frames (sweeps in the dataset's order, frames
    in the selection's) of at most ``max_pixels`` image pixels each (one frame at least):
    gathering the chunks' labelled pixels one after the other gives
    :func:`gather_labelled_pixels`'s pixels in its order."""
    frame_pixels = dataset.probe.height_px * dataset.probe.width_px
    per_chunk = max(1, _checked_max_pixels(max_pixels) // frame_pixels)
    chunks = []
    for sweep in dataset.sweeps:
        frames = selection.frames.get(sweep.name)
        if frames is None:
            continue
        for start in range(0, len(frames), per_chunk):
            part = {sweep.name: frames[start : start + per_chunk]}
            chunks.append(FrameSelection(selection.fraction, selection.seed, part))
    return chunks


def chunk_pixels_bound(dataset: SweepDataset, max_pixels: int) -> int:
    """The most image pixels a run of :func:`selection_chunks` holds: ``max_pixels``, or one
    frame's pixels when a frame holds more."""
    frame_pixels = dataset.probe.height_px * dataset.probe.width_px
    return max(_checked_max_pixels(max_pixels), frame_pixels)


def _checked_max_pixels(max_pixels: int) -> int:
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise argument_error("max_pixels", f"expected a positive integer, got {max_pixels!r}")
    return max_pixels


def _bone_pixels(dataset: SweepDataset, selection: FrameSelection | None) -> LabelledPixels | None:
    """The bone-labelled pixels (label 1) of the selected frames; None when ``selection`` is
    None or empty or its frames have no annotated pixel."""
    if selection is None or selection.n_frames == 0:
        return None
    try:
        return gather_labelled_pixels(dataset, selection, only=LABEL_TARGET)
    except UltronInputError:  # the selected frames have no annotated pixel
        return None


def bone_points_mm(dataset: SweepDataset, selection: FrameSelection | None) -> np.ndarray:
    """World positions (P, 3) float64 mm of the bone-labelled pixels (label 1) of the selected
    frames; (0, 3) when ``selection`` is None or holds no bone label."""
    pixels = _bone_pixels(dataset, selection)
    return np.zeros((0, 3)) if pixels is None else pixels.world_mm(dataset)


def labelled_surface_pixels(
    dataset: SweepDataset, selection: FrameSelection | None
) -> LabelledPixels | None:
    """The labelled surface's pixels in the selected frames: the top pixel of every band of
    bone labels, i.e. each bone pixel (r, c) whose upper neighbour (r − 1, c) is not bone (or
    r = 0) — where the annotation convention puts the surface (:func:`surface_outer_side`).
    None when ``selection`` is None or holds no bone label."""
    pixels = _bone_pixels(dataset, selection)
    if pixels is None:
        return None
    bone_above = np.zeros(len(pixels), dtype=bool)
    for sweep_index, sweep in enumerate(dataset.sweeps):
        pick = np.flatnonzero((pixels.sweep_index == sweep_index) & (pixels.row > 0))
        if pick.size:
            above = sweep.labels[pixels.frame[pick], pixels.row[pick] - 1, pixels.col[pick]]
            bone_above[pick] = above == LABEL_TARGET
    return pixels.take(~bone_above)


def labelled_surface_points_mm(
    dataset: SweepDataset, selection: FrameSelection | None
) -> np.ndarray:
    """World positions (P, 3) float64 mm of the labelled surface in the selected frames
    (:func:`labelled_surface_pixels`); (0, 3) when ``selection`` is None or holds no bone
    label."""
    pixels = labelled_surface_pixels(dataset, selection)
    return np.zeros((0, 3)) if pixels is None else pixels.world_mm(dataset)
