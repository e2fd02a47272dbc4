"""Automatic bone labels from the B-mode alone (``ultron label --auto``).

A classical detector of what a person labels as bone in B-mode: a bright echo with an
acoustic shadow under it. Per frame (row 0 at the transducer, one scanline per column), every
length given in mm and converted to pixels with the probe's spacings:

1. **Features.** S = G_σ ∗ I, I the frame in [0, 1] and G_σ a Gaussian of σ
   (``smooth_axial_mm``, ``smooth_lateral_mm``) that averages speckle out of the echoes;
   S_ref the 99th percentile of S in the frame; per pixel B, the mean of S over the window
   below it (rows r + ``gap_mm`` … r + ``gap_mm`` + ``shadow_mm``: the region under the
   echo's tail) and A, the mean of S over a window as long above it (ending
   ``peak_window_mm`` above r); the ultrasound confidence C (random walks, Karamalis et al.
   2012: :func:`ultron.train.visibility.confidence_map`) and C_B, its mean over the window
   below.
2. **Shadow-casting ridges.** A pixel is a candidate when the ridge score Q = S − B is the
   largest along its scanline within ±``peak_window_mm`` (on a thin echo Q peaks at its
   brightest row; on a bright region ending in a shadow, at its lower edge) and

       S ≥ bright·S_ref,   B ≤ shadow_ratio·S,   B ≤ above_ratio·A,   C_B ≤ confidence_ratio·C,

   i.e. bright, much darker below than the echo itself and than the tissue above it, and the
   confidence falls across it; at least half of the window below must lie inside the frame.
3. **Surface.** Bone is the first (shallowest) candidate of each scanline. A surface is a
   laterally continuous curve: runs of adjacent columns whose rows differ by at most
   ``max_jump_mm`` from column to column and that are narrower than ``min_width_mm`` are
   dropped (speckle). Its depth is refined to the brightest row of S at or up to
   ``peak_window_mm`` above, then to sub-pixel by a parabola through S on three rows.
4. **Labels**, in the simulator's annotation convention (:mod:`ultron.phantom.annotation`:
   the band under a visible surface, 2 mm thick): 1 on rows of depth d_s ≤ d ≤ d_s +
   ``band_mm`` below the surface depth d_s; 255 (unsure) below the band (in the shadow, where
   bone may continue), on ``margin_mm`` above it, wherever C < ``min_confidence`` and, on a
   scanline without a surface, from its first *shadowed* row down — B ≤ above_ratio·A over at
   least ``min_width_mm`` of adjacent scanlines (a shadow whose bone sent no echo back, e.g. a
   steep wall) or no echo at all below (B ≤ ``empty_level``, as in the black margins of real
   frames); 0 (background) elsewhere: the lit tissue above the bone and bone-free scanlines.

Every step is vectorised over the frame (cumulative sums along the scanlines, 1-D maximum
filters, a morphological opening); only the confidence map is solved frame by frame (a sparse
linear system), on a copy area-averaged to at most ``confidence_max_pixels`` pixels and
interpolated back. ``benchmarks/auto_labels.py`` measures the labels against the simulator's
(:func:`bone_precision_recall`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from ultron.data.dataset import ProbeGeometry
from ultron.data.plus_import import downsample_frames
from ultron.data.validation import LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error
from ultron.train.visibility import ConfidenceConfig, confidence_map

#: Names the algorithm in the dataset's metadata (bumped when its definition changes).
AUTO_LABELS_METHOD = "ultron-auto-labels/1"


def _check(name: str, value: Any, low: float, high: float | None = None, open_low=False) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if open_low else value >= low)
    ok = ok and (high is None or value <= high)
    if not ok:
        bound = f"{'>' if open_low else '≥'} {low:g}" + (f" and ≤ {high:g}" if high else "")
        raise argument_error(
            f"auto_labels.{name}", f"expected a finite number {bound}, got {value!r}"
        )


_FRACTIONS = (
    "bright",
    "shadow_ratio",
    "above_ratio",
    "empty_level",
    "confidence_ratio",
    "min_confidence",
)


@dataclass(frozen=True)
class AutoLabelConfig:
    """Every parameter of the detector (see the module docstring); lengths in mm, levels as
    fractions of the frame's bright level S_ref, ratios and confidence in [0, 1]."""

    smooth_axial_mm: float = 0.3
    smooth_lateral_mm: float = 0.5
    peak_window_mm: float = 1.0
    bright: float = 0.5
    gap_mm: float = 1.5
    shadow_mm: float = 5.0
    shadow_ratio: float = 0.35
    above_ratio: float = 0.6
    empty_level: float = 0.02
    confidence_ratio: float = 0.95
    max_jump_mm: float = 1.5
    min_width_mm: float = 2.0
    band_mm: float = 2.0
    margin_mm: float = 0.0
    min_confidence: float = 0.1
    confidence_max_pixels: int = 40_000
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)

    def __post_init__(self) -> None:
        for name in ("smooth_axial_mm", "smooth_lateral_mm", "margin_mm", "min_width_mm"):
            _check(name, getattr(self, name), 0.0)
        for name in ("peak_window_mm", "gap_mm", "shadow_mm", "max_jump_mm", "band_mm"):
            _check(name, getattr(self, name), 0.0, open_low=True)
        for name in _FRACTIONS:
            _check(name, getattr(self, name), 0.0, 1.0)
        pixels = self.confidence_max_pixels
        if isinstance(pixels, bool) or not isinstance(pixels, int) or pixels < 9:
            raise argument_error(
                "auto_labels.confidence_max_pixels", f"expected an integer ≥ 9, got {pixels!r}"
            )
        if not isinstance(self.confidence, ConfidenceConfig):
            raise argument_error("auto_labels.confidence", "expected a ConfidenceConfig")

    def to_dict(self) -> dict[str, Any]:
        """The parameters as plain JSON (recorded in the dataset's metadata)."""
        return asdict(self)


# ------------------------------------------------------------------------------ features
def _rows(mm: float, spacing_mm: float, minimum: int = 1) -> int:
    return max(minimum, round(mm / spacing_mm))


def window_mean(values: np.ndarray, start: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (r, c) the mean of ``values`` over rows [r + start, r + start + length) of its
    column, clipped to the frame, and the number of rows it covered (0: none; mean 0 there).
    One cumulative sum along the rows: M = (Σ_{k < b} v − Σ_{k < a} v) / (b − a)."""
    height = values.shape[0]
    cumulative = np.concatenate([np.zeros((1, *values.shape[1:])), np.cumsum(values, axis=0)])
    rows = np.arange(height)
    a = np.clip(rows + start, 0, height)
    b = np.clip(rows + start + length, 0, height)
    count = (b - a).reshape(-1, *([1] * (values.ndim - 1)))
    total = cumulative[b] - cumulative[a]
    mean = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    return mean, np.broadcast_to(count, values.shape)


def frame_confidence(image: np.ndarray, config: AutoLabelConfig) -> np.ndarray:
    """Confidence map C (H, W) of a frame (:func:`confidence_map`), solved on an area-averaged
    copy of at most ``confidence_max_pixels`` pixels when the frame is larger and interpolated
    back (bilinear; pixel (r, c) of the frame lies at (r·H'/H, c·W'/W) of the copy, as
    :func:`~ultron.data.plus_import.downsample_frames` places it)."""
    height, width = image.shape
    factor = math.sqrt(height * width / config.confidence_max_pixels)
    if factor <= 1.0:
        return confidence_map(image, config.confidence)
    small_shape = (max(3, round(height / factor)), max(3, round(width / factor)))
    small = downsample_frames(image[None], small_shape)[0]
    conf = confidence_map(small, config.confidence)
    rows = np.arange(height) * small_shape[0] / height  # the format's pixel positions
    cols = np.arange(width) * small_shape[1] / width
    grid = np.meshgrid(rows, cols, indexing="ij")
    return ndimage.map_coordinates(conf, grid, order=1, mode="nearest").astype(np.float32)


# ----------------------------------------------------------------------------- detector
@dataclass(frozen=True)
class FrameFeatures:
    """What the detector measures on one frame (H, W), step 1: the smoothed image S, the
    confidence C, the mean B of S over the window below each pixel (``below``: rows r + g …
    r + g + L − 1, g = ``gap_mm``, L = ``shadow_mm`` in rows) and A over the window above it
    (``above``: rows r − p − L … r − p − 1, p = ``peak_window_mm`` in rows; S itself where no
    row is above), the rows of the window below inside the frame, L, and S_ref."""

    smoothed: np.ndarray
    confidence: np.ndarray
    below: np.ndarray
    above: np.ndarray
    below_rows: np.ndarray
    window_rows: int
    ref: float


def frame_features(
    image: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig
) -> FrameFeatures:
    """:class:`FrameFeatures` of a uint8 frame (H, W) (step 1 of the module docstring)."""
    axial, lateral = probe.axial_spacing_mm, probe.lateral_spacing_mm
    intensity = image.astype(np.float64) / 255.0
    sigma = (config.smooth_axial_mm / axial, config.smooth_lateral_mm / lateral)
    smoothed = ndimage.gaussian_filter(intensity, sigma, mode="nearest")
    length = _rows(config.shadow_mm, axial)
    below, count = window_mean(smoothed, _rows(config.gap_mm, axial, 0), length)
    start_above = -_rows(config.peak_window_mm, axial) - length
    above, count_above = window_mean(smoothed, start_above, length)
    return FrameFeatures(
        smoothed=smoothed,
        confidence=frame_confidence(image, config),
        below=below,
        above=np.where(count_above > 0, above, smoothed),
        below_rows=count,
        window_rows=length,
        ref=float(np.percentile(smoothed, 99.0)),
    )


def bone_candidates(
    features: FrameFeatures, axial_mm: float, config: AutoLabelConfig
) -> np.ndarray:
    """The shadow-casting ridges (H, W) bool (step 2): pixels where the ridge score Q = S − B
    is the largest along the scanline within ±``peak_window_mm`` and

        S ≥ bright·S_ref,  B ≤ shadow_ratio·S,  B ≤ above_ratio·A,  C_B ≤ confidence_ratio·C,

    with B (A) the mean of S over the window below (above), C_B the mean of C over the window
    below, and at least half of the window below inside the frame."""
    f = features
    half = _rows(config.peak_window_mm, axial_mm)
    score = f.smoothed - f.below
    peak = score >= ndimage.maximum_filter1d(score, 2 * half + 1, axis=0, mode="nearest")
    length = f.window_rows
    gap = _rows(config.gap_mm, axial_mm, 0)
    conf_below, _ = window_mean(f.confidence, gap, length)
    return (
        peak
        & (f.below_rows >= max(1, length // 2))
        & (f.smoothed >= config.bright * f.ref)
        & (f.below <= config.shadow_ratio * f.smoothed)
        & (f.below <= config.above_ratio * f.above)
        & (conf_below <= config.confidence_ratio * f.confidence)
        & (f.ref > 0)
    )


def shadowed(features: FrameFeatures, lateral_mm: float, config: AutoLabelConfig) -> np.ndarray:
    """Pixels (H, W) under which the scanline darkens (B ≤ above_ratio·A, window below at
    least half inside the frame) over at least ``min_width_mm`` of adjacent scanlines, or that
    see no echo at all (S ≤ ``empty_level`` over the window below): where an undetected
    reflector may cast a shadow (unsure)."""
    f = features
    dark = (f.below_rows >= max(1, f.window_rows // 2)) & (f.below <= config.above_ratio * f.above)
    width = _rows(config.min_width_mm, lateral_mm)
    dark = ndimage.binary_opening(dark, structure=np.ones((1, width), dtype=bool))
    return dark | ((f.below_rows > 0) & (f.below <= config.empty_level))


def first_rows(mask: np.ndarray) -> np.ndarray:
    """Per column the first row where ``mask`` holds, −1 where it never does."""
    first = np.argmax(mask, axis=0)
    return np.where(mask.any(axis=0), first, -1)


def continuous_surface(
    surface: np.ndarray, axial_mm: float, lateral_mm: float, config: AutoLabelConfig
) -> np.ndarray:
    """``surface`` (W,) rows (−1: none) with the runs narrower than ``min_width_mm`` removed; a
    run is a maximal set of adjacent detected columns whose rows differ by ≤ ``max_jump_mm``
    between neighbours."""
    found = surface >= 0
    jump = np.abs(np.diff(surface)) * axial_mm > config.max_jump_mm
    joined = found[1:] & found[:-1] & ~jump
    starts = np.concatenate([[True], ~joined])
    run = np.cumsum(starts) - 1
    widths = np.bincount(run, weights=found.astype(np.float64)) * lateral_mm
    keep = found & (widths[run] >= config.min_width_mm)
    return np.where(keep, surface, -1)


def echo_peak_rows(smoothed: np.ndarray, surface: np.ndarray, window: int) -> np.ndarray:
    """Per column the row of the largest S among rows r − ``window`` … r of its surface row r
    (−1 stays −1): the bright echo's peak at or above where its ridge score peaked."""
    height, width = smoothed.shape
    rows = np.clip(surface[None, :] - np.arange(window + 1)[:, None], 0, height - 1)
    best = np.argmax(smoothed[rows, np.arange(width)], axis=0)
    return np.where(surface >= 0, rows[best, np.arange(width)], -1)


def subpixel_rows(smoothed: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """The surface's depth (W,) in fractional rows (NaN where none): the vertex of the
    parabola through S at rows r − 1, r, r + 1 of its peak row r,
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


def labels_from_surface(
    surface: np.ndarray,
    dark: np.ndarray,
    conf: np.ndarray,
    axial_mm: float,
    config: AutoLabelConfig,
) -> np.ndarray:
    """Labels (H, W) uint8 from the surface depths (W,) in fractional rows (NaN: none), step 4:
    1 on rows r with d_s ≤ r ≤ d_s + band (rows), 255 from ⌊d_s⌋ − margin down (the band
    excepted), where C < ``min_confidence`` and, on scanlines without a surface, from their
    first ``dark`` row down; 0 elsewhere."""
    height = dark.shape[0]
    rows = np.arange(height)[:, None]
    margin = _rows(config.margin_mm, axial_mm, 0)
    has_bone = np.isfinite(surface)
    top = np.where(has_bone, surface, np.inf)
    bone = (rows >= top) & (rows <= top + config.band_mm / axial_mm)
    surface = np.where(has_bone, np.floor(top), -1).astype(np.int64)
    dark_onset = np.where(dark.any(axis=0), first_rows(dark), height)
    onset = np.where(has_bone, surface - margin, dark_onset)
    unsure = (rows >= onset) | (conf < config.min_confidence)
    labels = np.where(unsure, LABEL_UNANNOTATED, LABEL_BACKGROUND).astype(np.uint8)
    labels[bone] = LABEL_TARGET
    return labels


def auto_label_frame(
    image: np.ndarray, probe: ProbeGeometry, config: AutoLabelConfig | None = None
) -> np.ndarray:
    """Labels (H, W) uint8 (1 bone, 0 background, 255 unsure) of one B-mode frame (H, W)."""
    cfg = config or AutoLabelConfig()
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != probe.image_shape or min(image.shape) < 3:
        raise argument_error(
            "image",
            f"expected a uint8 frame of {probe.image_shape} (at least 3 × 3), got"
            f" {image.dtype} {image.shape}",
        )
    if not isinstance(cfg, AutoLabelConfig):
        raise argument_error("config", f"expected an AutoLabelConfig, got {type(cfg).__name__}")
    axial, lateral = probe.axial_spacing_mm, probe.lateral_spacing_mm
    features = frame_features(image, probe, cfg)
    candidates = bone_candidates(features, axial, cfg)
    surface = continuous_surface(first_rows(candidates), axial, lateral, cfg)
    surface = echo_peak_rows(features.smoothed, surface, _rows(cfg.peak_window_mm, axial))
    surface = subpixel_rows(features.smoothed, surface)
    dark = shadowed(features, lateral, cfg)
    return labels_from_surface(surface, dark, features.confidence, axial, cfg)


def auto_label_frames(
    images: np.ndarray,
    probe: ProbeGeometry,
    config: AutoLabelConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Labels (N, H, W) uint8 of the frames (N, H, W) (:func:`auto_label_frame` per frame)."""
    images = np.asarray(images)
    if images.ndim != 3:
        raise argument_error("images", f"expected (N, H, W) frames, got shape {images.shape}")
    out = np.empty(images.shape, dtype=np.uint8)
    for i, frame in enumerate(images):
        out[i] = auto_label_frame(frame, probe, config)
        if progress is not None:
            progress(i + 1, len(images))
    return out


def bone_precision_recall(
    predicted: np.ndarray, truth: np.ndarray, tolerance_px: int = 1
) -> tuple[float, float, int, int]:
    """Precision and recall of bone pixels (label 1) of ``predicted`` against ``truth`` (same
    shape, …, H, W): a predicted bone pixel is correct when a true bone pixel lies within
    ±``tolerance_px`` rows (depth) in the same column of the same frame, and a true one is found
    when a predicted one does. Frames whose truth is all 255 (unannotated) are left out. Returns
    (precision, recall, predicted bone pixels, true bone pixels); NaN where a count is 0."""
    predicted, truth = np.asarray(predicted), np.asarray(truth)
    if predicted.shape != truth.shape or predicted.ndim < 2:
        raise argument_error("predicted", f"shape {predicted.shape} differs from {truth.shape}")
    if isinstance(tolerance_px, bool) or not isinstance(tolerance_px, int) or tolerance_px < 0:
        raise argument_error("tolerance_px", f"expected an integer ≥ 0, got {tolerance_px!r}")
    frames = truth.reshape(-1, *truth.shape[-2:])
    annotated = (frames != LABEL_UNANNOTATED).any(axis=(1, 2))
    pred = predicted.reshape(frames.shape)[annotated] == LABEL_TARGET
    true = frames[annotated] == LABEL_TARGET
    size = 2 * tolerance_px + 1
    near_true = ndimage.maximum_filter1d(true, size, axis=1, mode="constant")
    near_pred = ndimage.maximum_filter1d(pred, size, axis=1, mode="constant")
    n_pred, n_true = int(pred.sum()), int(true.sum())
    precision = float((pred & near_true).sum() / n_pred) if n_pred else math.nan
    recall = float((true & near_pred).sum() / n_true) if n_true else math.nan
    return precision, recall, n_pred, n_true
