"""Automatic bone labels from the B-mode alone (``ultron label --auto``).

A classical detector of what a person labels as bone in B-mode: the *last dominant echo* of a
scanline — a bright echo brighter than everything beneath it, because bone reflects most of the
sound and lets little through — traced across the scanlines as one continuous surface. Per
frame (row 0 at the transducer, one scanline per column), every length in mm converted to
pixels with the probe's spacings:

1. **Evidence.** S = G_σ ∗ I, I the frame in [0, 1] and G_σ a Gaussian of σ
   (``smooth_axial_mm``, ``smooth_lateral_mm``) that averages speckle out of the echoes;
   S_ref the 99th percentile of S in the frame; M(r) = max S over rows ≥ r + ``gap_mm`` of the
   column (what lies beneath the echo, from one reverse cumulative maximum). The bone score of
   a pixel is

       E = (S − M / dominance) / S_ref + b − τ

   where S ≥ ``bright``·S_ref and at least ``min_below_mm`` of the frame lies below the pixel
   (else min(E, −τ)): positive where the echo exceeds everything below it by the factor
   1/``dominance``. b = +``shadow_bonus`` where the deep shadow (nothing below brighter than
   ``shadow_level``·S_ref) begins within ``shadow_onset_mm`` under the pixel, −``shadow_bonus``
   elsewhere; τ = ``min_score``.
2. **Surface** (dynamic programming over the scanlines, Viterbi): a path takes, per column,
   one row or "no bone" and maximises Σ E·Δx along its bone columns (Δx the lateral spacing
   in mm) minus ``segment_cost`` for each run of bone columns it opens; between neighbouring
   bone columns its row moves by at most ``max_slope``·Δx/Δz rows (a surface at most
   atan(``max_slope``) steep). Runs narrower than ``min_width_mm`` are dropped. The depth is
   refined to sub-pixel by a parabola through S on three rows.
3. **Labels**, in the simulator's annotation convention (:mod:`ultron.phantom.annotation`: the
   band under a visible surface, 2 mm thick): 1 on rows of depth d_s ≤ d ≤ d_s + ``band_mm``;
   0 (background) only on rows shallower, by ``margin_mm``, than both the detected surface and
   the first row where bone is at all *possible* (S ≥ ``possible_bright``·S_ref and S ≥ M: an
   echo nothing beneath outshines, with a deep shadow within ``shadow_max_mm``), and above the
   deep shadow's onset; 255 (unsure) everywhere
   else — under the band (in the shadow, where bone may continue), below any echo that could be
   an undetected bone, and in the deep shadow. Labelling bone "background" is the harmful error
   (negative evidence on the surface), so background is claimed only where the scanline has
   shown nothing bone-like yet.

Every step is vectorised over the frame (one cumulative maximum and sum along the scanlines);
the dynamic programme loops over the columns only. Each frame also gets a quality summary
(:class:`FrameQuality`: the share of scanlines with a surface and the mean evidence along it);
:func:`frames_to_check` flags the frames whose surface dropped out where their neighbours see
one, so that a user sees which frames to check. The defaults were set on the real fibula sweep's
``pass1`` (``../shared/data/ultrabones-fibula``, CT-derived labels) and on the simulated
tuning seeds 11–13, never on ``pass2``, the benchmark's seeds or the PLUS phantom;
``benchmarks/auto_labels.py`` and ``benchmarks/real_fibula.py`` measure them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from ultron.arguments import check_integer
from ultron.data.dataset import ProbeGeometry
from ultron.data.validation import LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error
from ultron.parallel import thread_map

#: Names the algorithm in the dataset's metadata (bumped when its definition changes).
AUTO_LABELS_METHOD = "ultron-auto-labels/2"
#: A frame is flagged for checking when its share of scanlines with bone falls below this
#: fraction of the median over its neighbours (:func:`frames_to_check`).
CHECK_DROP = 0.7
#: Frames on either side whose median :func:`frames_to_check` compares with.
CHECK_NEIGHBOURS = 5


def _check(name: str, value: Any, low: float, high: float | None = None, open_low=False) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if open_low else value >= low)
    ok = ok and (high is None or value <= high)
    if not ok:
        bound = f"{'>' if open_low else '≥'} {low:g}" + (f" and ≤ {high:g}" if high else "")
        raise argument_error(
            f"auto_labels.{name}", f"expected a finite number {bound}, got {value!r}"
        )


_LENGTHS = ("smooth_axial_mm", "smooth_lateral_mm", "margin_mm", "min_width_mm", "gap_mm")
_POSITIVE_LENGTHS = (
    "min_below_mm",
    "shadow_window_mm",
    "shadow_onset_mm",
    "shadow_max_mm",
    "band_mm",
)
_FRACTIONS = ("bright", "dominance", "possible_bright", "shadow_level")


@dataclass(frozen=True)
class AutoLabelConfig:
    """Every parameter of the detector (see the module docstring); lengths in mm, levels as
    fractions of the frame's bright level S_ref, scores in units of S_ref."""

    smooth_axial_mm: float = 0.3
    smooth_lateral_mm: float = 0.5
    gap_mm: float = 1.0
    bright: float = 0.4
    dominance: float = 0.75
    min_score: float = 0.1
    min_below_mm: float = 5.0
    shadow_level: float = 0.15
    shadow_window_mm: float = 3.0
    shadow_onset_mm: float = 4.0
    shadow_max_mm: float = 15.0
    shadow_bonus: float = 0.05
    max_slope: float = 4.0
    segment_cost: float = 0.27
    min_width_mm: float = 2.0
    band_mm: float = 2.0
    margin_mm: float = 1.5
    possible_bright: float = 0.5

    def __post_init__(self) -> None:
        for name in _LENGTHS:
            _check(name, getattr(self, name), 0.0)
        for name in _POSITIVE_LENGTHS:
            _check(name, getattr(self, name), 0.0, open_low=True)
        for name in _FRACTIONS:
            _check(name, getattr(self, name), 0.0, 1.0)
        _check("dominance", self.dominance, 0.0, 1.0, open_low=True)
        for name in ("min_score", "shadow_bonus", "segment_cost"):
            _check(name, getattr(self, name), 0.0)
        _check("max_slope", self.max_slope, 0.0, open_low=True)

    def to_dict(self) -> dict[str, Any]:
        """The parameters as plain JSON (recorded in the dataset's metadata)."""
        return asdict(self)


def _rows(mm: float, spacing_mm: float, minimum: int = 1) -> int:
    return max(minimum, round(mm / spacing_mm))


# ------------------------------------------------------------------------------ evidence
@dataclass(frozen=True)
class FrameEvidence:
    """Step 1 of one frame (H, W): the smoothed image S, the bone score E, the first row per
    column where bone is possible (H: none) and the deep shadow's onset row (H: none); S_ref,
    the deep shadow D (:func:`shadow_masks`), the pixels whose window from there down,
    clipped to the frame, is as dark (``shadowed``, D without the coverage rule), and that
    window's mean S̄ (``shadow_mean``)."""

    smoothed: np.ndarray
    score: np.ndarray
    first_possible: np.ndarray
    shadow_onset: np.ndarray
    ref: float
    dark: np.ndarray
    shadowed: np.ndarray
    shadow_mean: np.ndarray


def window_mean(values: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (r, c) the mean of ``values`` over rows [r, r + ``length``) of its column,
    clipped to the frame, and the number of rows it covered: one cumulative sum along the rows,
    M = (Σ_{k < b} v − Σ_{k < r} v) / (b − r)."""
    height = values.shape[0]
    cumulative = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
    start = np.arange(height)
    stop = np.minimum(start + length, height)
    count = (stop - start)[:, None]
    return (cumulative[stop] - cumulative[start]) / count, np.broadcast_to(count, values.shape)


def max_below(values: np.ndarray, gap: int) -> np.ndarray:
    """Per pixel (r, c) the largest value of ``values`` (H, W) over rows ≥ r + ``gap`` of its
    column (0 where no row is left): one reverse cumulative maximum."""
    height = values.shape[0]
    reverse = np.maximum.accumulate(values[::-1], axis=0)[::-1]
    out = np.zeros_like(values)
    if gap < height:
        out[: height - gap] = reverse[gap:]
    return out


def next_rows(mask: np.ndarray) -> np.ndarray:
    """Per pixel (r, c) the first row r' ≥ r of its column where ``mask`` holds (H where
    none): one reverse cumulative minimum."""
    height = mask.shape[0]
    index = np.where(mask, np.arange(height)[:, None], height)
    return np.minimum.accumulate(index[::-1], axis=0)[::-1]


def first_rows(mask: np.ndarray, none: int) -> np.ndarray:
    """Per column the first row where ``mask`` holds, ``none`` where it never does."""
    return np.where(mask.any(axis=0), np.argmax(mask, axis=0), none)


def shadow_masks(
    smoothed: np.ndarray, ref: float, axial_mm: float, config: AutoLabelConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bool (H, W) twice, from one window mean, and that mean S̄ (H, W): the deep shadow D —
    the mean of S over the ``shadow_window_mm`` from the pixel down (at least half of it inside
    the frame) is at most ``shadow_level``·S_ref (step 1 of the module docstring) — and the
    pixels where that mean, the window clipped to the frame, is at most the level (D without
    the half-window rule)."""
    window = _rows(config.shadow_window_mm, axial_mm)
    dark_mean, rows_in = window_mean(smoothed, window)
    shadowed = dark_mean <= config.shadow_level * ref
    return shadowed & (rows_in * 2 >= window), shadowed, dark_mean


def echo_tail_rows(height: int, axial_mm: float, config: AutoLabelConfig) -> np.ndarray:
    """(H,): each row's echo tail, ``gap_mm`` below it, clipped to the frame's last row."""
    return np.minimum(np.arange(height) + _rows(config.gap_mm, axial_mm, 0), height - 1)


def frame_evidence(
    image: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig
) -> FrameEvidence:
    """:class:`FrameEvidence` of a uint8 frame (H, W) (step 1 of the module docstring)."""
    axial, lateral = probe.axial_spacing_mm, probe.lateral_spacing_mm
    intensity = image.astype(np.float32) / 255.0
    sigma = (config.smooth_axial_mm / axial, config.smooth_lateral_mm / lateral)
    smoothed = ndimage.gaussian_filter(intensity, sigma, mode="nearest")
    height = smoothed.shape[0]
    ref = float(np.percentile(smoothed, 99.0))
    gap = _rows(config.gap_mm, axial, 0)
    beneath = max_below(smoothed, gap)
    dark, shadowed, shadow_mean = shadow_masks(smoothed, ref, axial, config)
    onset = first_rows(dark, height)
    if ref <= 0:  # a blank frame: nothing is bone, nothing is lit
        blank = np.full(smoothed.shape, -np.inf, dtype=np.float32)
        no_rows = np.zeros(smoothed.shape[1], int)
        return FrameEvidence(smoothed, blank, no_rows, onset * 0, ref, dark, shadowed, shadow_mean)
    rows = np.arange(height)[:, None]
    # the deep shadow's nearest onset at or below the echo's tail, mm under the echo
    tail = echo_tail_rows(height, axial, config)
    to_shadow_mm = (next_rows(dark)[tail] - rows) * axial
    score = (smoothed - beneath / config.dominance) / ref - config.min_score
    near = to_shadow_mm <= config.shadow_onset_mm
    score += np.where(near, config.shadow_bonus, -config.shadow_bonus)
    room = rows < height - _rows(config.min_below_mm, axial)
    casts_shadow = to_shadow_mm <= config.shadow_max_mm
    eligible = room & casts_shadow & (smoothed >= config.bright * ref)
    score = np.where(eligible, score, np.minimum(score, -config.min_score)).astype(np.float32)
    possible = room & casts_shadow & (smoothed >= config.possible_bright * ref)
    possible &= smoothed >= beneath
    first = first_rows(possible, height)
    return FrameEvidence(smoothed, score, first, onset, ref, dark, shadowed, shadow_mean)


# ------------------------------------------------------------------------------- surface
def trace_surface(score: np.ndarray, max_step: int, column_mm: float, open_cost: float):
    """The path (W,) of rows (−1: no bone) maximising Σ score·``column_mm`` over its bone
    columns minus ``open_cost`` per run of bone columns, moving ≤ ``max_step`` rows between
    neighbouring bone columns (step 2 of the module docstring; Viterbi over the columns)."""
    return trace_surfaces(np.asarray(score)[None], max_step, column_mm, open_cost)[0]


def trace_surfaces(
    scores: np.ndarray, max_step: int, column_mm: float, open_cost: float
) -> np.ndarray:
    """:func:`trace_surface` of each frame's score (B, H, W) at once → paths (B, W): the same
    operations, each on all B frames, so that a column's step costs numpy's overhead once per
    batch rather than once per frame (the same paths as frame by frame, to the bit)."""
    n, height, width = scores.shape
    gain = scores.astype(np.float64) * column_mm
    steps = np.arange(-max_step, max_step + 1)
    frames, rows = np.arange(n)[:, None], np.arange(height)
    best = gain[:, :, 0] - open_cost  # (B, H): best total ending at (row, column) in bone
    none = np.zeros(n)  # best total ending at the column with no bone
    came_from = np.empty((n, width, height), dtype=np.int32)  # −1: from "no bone"
    none_from = np.full((n, width), -1, dtype=np.int64)  # row "no bone" left, −1: stayed
    came_from[:, 0] = -1
    padded = np.full((n, height + 2 * max_step), -np.inf)
    for column in range(1, width):
        padded[:, max_step : max_step + height] = best
        # candidates[b, k, r] = best[b, r + steps[k]]: the predecessor row r + steps[k]
        candidates = np.stack([padded[:, max_step + s : max_step + s + height] for s in steps], 1)
        pick = np.argmax(candidates, axis=1)
        stay = np.take_along_axis(candidates, pick[:, None], axis=1)[:, 0]
        opened = none - open_cost
        from_none = opened[:, None] > stay
        ending = np.argmax(best, axis=1)
        top = best[frames[:, 0], ending]
        none_from[:, column] = np.where(top > none, ending, -1)
        none = np.maximum(none, top)
        came_from[:, column] = np.where(from_none, -1, rows + steps[pick])
        best = np.where(from_none, opened[:, None], stay) + gain[:, :, column]
    paths = np.full((n, width), -1, dtype=np.int64)
    ending = np.argmax(best, axis=1)
    state = np.where(best[frames[:, 0], ending] > none, ending, -1)
    for column in range(width - 1, -1, -1):
        paths[:, column] = state
        back = came_from[frames[:, 0], column, np.maximum(state, 0)]
        state = np.where(state >= 0, back, none_from[:, column])
    return paths


def drop_narrow_runs(path: np.ndarray, min_columns: int) -> np.ndarray:
    """``path`` with every run of adjacent bone columns narrower than ``min_columns`` removed."""
    found = path >= 0
    starts = np.concatenate([[True], found[1:] != found[:-1]])
    run = np.cumsum(starts) - 1
    widths = np.bincount(run)
    return np.where(found & (widths[run] >= min_columns), path, -1)


def subpixel_rows(smoothed: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """The surface's depth (W,) in fractional rows (NaN where none): the vertex of the
    parabola through S at rows r − 1, r, r + 1 of its row r,
    r + ½·(S₋ − S₊)/(S₋ − 2S₀ + S₊), the offset clipped to [−½, ½] (0 on the first and last
    rows and where S is not concave there)."""
    height, width = smoothed.shape
    inner = (surface >= 1) & (surface <= height - 2)
    r = np.clip(surface, 1, height - 2)
    cols = np.arange(width)
    above, centre, below = (smoothed[r + k, cols] for k in (-1, 0, 1))
    curvature = above - 2 * centre + below
    concave = inner & (curvature < 0)
    safe = np.where(concave, curvature, -1.0)
    offset = np.where(concave, np.clip(0.5 * (above - below) / safe, -0.5, 0.5), 0.0)
    return np.where(surface >= 0, surface + offset, np.nan)


# -------------------------------------------------------------------------------- labels
def labels_from_surface(
    surface: np.ndarray, evidence: FrameEvidence, axial_mm: float, config: AutoLabelConfig
) -> np.ndarray:
    """Labels (H, W) uint8 from the surface depths (W,) in fractional rows (NaN: none), step 3:
    1 on rows d_s ≤ r ≤ d_s + band; 0 above min(d_s, first possible row) − margin and above the
    deep shadow; 255 elsewhere."""
    height = evidence.smoothed.shape[0]
    rows = np.arange(height)[:, None]
    has_bone = np.isfinite(surface)
    top = np.where(has_bone, surface, np.inf)
    bone = (rows >= top) & (rows <= top + config.band_mm / axial_mm)
    margin = config.margin_mm / axial_mm
    free_until = np.minimum(np.where(has_bone, surface, height), evidence.first_possible) - margin
    free = (rows < free_until) & (rows < evidence.shadow_onset[None, :])
    labels = np.where(free, LABEL_BACKGROUND, LABEL_UNANNOTATED).astype(np.uint8)
    labels[bone] = LABEL_TARGET
    return labels


@dataclass(frozen=True)
class FrameQuality:
    """How much a frame's labels rest on: the share of its scanlines with a surface, the mean
    evidence E (step 1) along that surface (NaN without one) and the share of unsure pixels."""

    bone_scanlines: float
    evidence: float
    unsure: float


def frames_to_check(
    qualities: list[FrameQuality],
    drop: float = CHECK_DROP,
    neighbours: int = CHECK_NEIGHBOURS,
) -> np.ndarray:
    """Which frames of a sweep (bool per frame) to look at: those whose share of scanlines
    with bone falls below ``drop`` × the median over the ``neighbours`` frames on either side
    (the frame included) — the surface dropped out where the sweep's neighbouring frames see
    it. On the fibula's ``pass1`` the frames it flagged had a much lower bone recall against the
    CT-derived labels than the rest
    (docs/decisions.md#auto-labels-frames-to-check-dataauto_labelspy)."""
    shares = np.array([q.bone_scanlines for q in qualities], dtype=np.float64)
    if shares.size == 0:
        return np.zeros(0, dtype=bool)
    median = ndimage.median_filter(shares, size=2 * neighbours + 1, mode="nearest")
    return shares < drop * median


def _validate_frame(image: np.ndarray, probe: ProbeGeometry, config: Any) -> None:
    if image.dtype != np.uint8 or image.shape != probe.image_shape or min(image.shape) < 3:
        raise argument_error(
            "image",
            f"expected a uint8 frame of {probe.image_shape} (at least 3 × 3), got"
            f" {image.dtype} {image.shape}",
        )
    if not isinstance(config, AutoLabelConfig):
        raise argument_error("config", f"expected an AutoLabelConfig, got {type(config).__name__}")


def detect_frame(
    image: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig | None = None
) -> tuple[np.ndarray, FrameQuality]:
    """Labels (H, W) uint8 (1 bone, 0 background, 255 unsure) of one B-mode frame (H, W) and
    its :class:`FrameQuality`."""
    return detect_frames(np.asarray(image)[None], probe, config)[0]


def detect_frames(
    images: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig | None = None
) -> list[tuple[np.ndarray, FrameQuality]]:
    """:func:`detect_frame` of each frame (B, H, W): each frame's evidence on
    :func:`~ultron.parallel.thread_map`'s threads (its filters release the GIL), the surfaces
    of all B traced at once (:func:`trace_surfaces`), the same labels as frame by frame."""
    cfg = config or AutoLabelConfig()
    for image in images:
        _validate_frame(np.asarray(image), probe, cfg)
    axial, lateral = probe.axial_spacing_mm, probe.lateral_spacing_mm
    evidences = thread_map(lambda image: frame_evidence(np.asarray(image), probe, cfg), images)
    max_step = max(1, math.ceil(cfg.max_slope * lateral / axial))
    scores = np.stack([evidence.score for evidence in evidences])
    paths = trace_surfaces(scores, max_step, lateral, cfg.segment_cost)
    return [
        _labelled(evidence, path, axial, lateral, cfg)
        for evidence, path in zip(evidences, paths, strict=True)
    ]


def _labelled(
    evidence: FrameEvidence, path: np.ndarray, axial: float, lateral: float, cfg: AutoLabelConfig
) -> tuple[np.ndarray, FrameQuality]:
    """A frame's labels and quality from its evidence and traced path (steps 2–3)."""
    path = drop_narrow_runs(path, _rows(cfg.min_width_mm, lateral))
    surface = subpixel_rows(evidence.smoothed, path)
    labels = labels_from_surface(surface, evidence, axial, cfg)
    found = path >= 0
    columns = np.flatnonzero(found)
    along = evidence.score[path[columns], columns]
    quality = FrameQuality(
        bone_scanlines=float(found.mean()),
        evidence=float(along.mean() + cfg.min_score) if len(columns) else math.nan,
        unsure=float(np.count_nonzero(labels == LABEL_UNANNOTATED) / labels.size),
    )
    return labels, quality


def auto_label_frame(
    image: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig | None = None
) -> np.ndarray:
    """Labels (H, W) uint8 (1 bone, 0 background, 255 unsure) of one B-mode frame (H, W)."""
    return detect_frame(image, probe, config)[0]


#: At most this many frames, and :data:`DETECT_RUN_PIXELS` pixels, are detected at once by
#: :func:`auto_label_frames` (evidence ≈ 18 bytes per pixel, back-pointers 4; docs/auto-labels.md).
DETECT_RUN = 32
DETECT_RUN_PIXELS = 1 << 24


def auto_label_frames(
    images: np.ndarray,
    probe: ProbeGeometry,
    config: AutoLabelConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, list[FrameQuality]]:
    """Labels (N, H, W) uint8 of the frames (N, H, W) and each frame's quality
    (:func:`detect_frames`, a run of :data:`DETECT_RUN` frames, fewer where they would exceed
    :data:`DETECT_RUN_PIXELS`, at a time; ``progress``, when given, is told (frames done, N)
    after each run)."""
    images = np.asarray(images) if not hasattr(images, "shape") else images
    if len(images.shape) != 3:
        raise argument_error("images", f"expected (N, H, W) frames, got shape {images.shape}")
    n = images.shape[0]
    out = np.empty(images.shape, dtype=np.uint8)
    qualities = []
    run = max(1, min(DETECT_RUN, DETECT_RUN_PIXELS // max(1, images.shape[1] * images.shape[2])))
    for start in range(0, n, run):
        stop = min(start + run, n)
        for offset, (labels, quality) in enumerate(
            detect_frames(np.asarray(images[start:stop]), probe, config)
        ):
            out[start + offset] = labels
            qualities.append(quality)
        if progress is not None:
            progress(stop, n)
    return out, qualities


def bone_precision_recall(
    predicted: np.ndarray, truth: np.ndarray, tolerance_px: int = 1, where_annotated=False
) -> tuple[float, float, int, int]:
    """Precision and recall of bone pixels (label 1) of ``predicted`` against ``truth`` (same
    shape, …, H, W): a predicted bone pixel is correct when a true bone pixel lies within
    ±``tolerance_px`` rows (depth) in the same column of the same frame, and a true one is found
    when a predicted one does. Frames whose truth is all 255 (unannotated) are left out; with
    ``where_annotated`` predicted bone pixels are counted only where the truth says bone or
    background (a truth that leaves other bones unknown, e.g. CT-derived labels of one bone).
    Returns (precision, recall, predicted bone pixels counted, true bone pixels); NaN where a
    count is 0."""
    predicted, truth = np.asarray(predicted), np.asarray(truth)
    if predicted.shape != truth.shape or predicted.ndim < 2:
        raise argument_error("predicted", f"shape {predicted.shape} differs from {truth.shape}")
    check_integer("tolerance_px", tolerance_px)
    frames = truth.reshape(-1, *truth.shape[-2:])
    annotated = (frames != LABEL_UNANNOTATED).any(axis=(1, 2))
    true_frames = frames[annotated]
    pred = predicted.reshape(frames.shape)[annotated] == LABEL_TARGET
    true = true_frames == LABEL_TARGET
    size = 2 * tolerance_px + 1
    near_true = ndimage.maximum_filter1d(true, size, axis=1, mode="constant")
    near_pred = ndimage.maximum_filter1d(pred, size, axis=1, mode="constant")
    counted = pred & (true_frames != LABEL_UNANNOTATED) if where_annotated else pred
    n_pred, n_true = int(counted.sum()), int(true.sum())
    precision = float((counted & near_true).sum() / n_pred) if n_pred else math.nan
    recall = float((true & near_pred).sum() / n_true) if n_true else math.nan
    return precision, recall, n_pred, n_true
