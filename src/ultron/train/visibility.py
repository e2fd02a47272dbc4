"""Where stage 2's transmission T comes from: the "visibility" of each labelled pixel.

UltrON's attenuation-compensated loss BCE(T·f, y) (:mod:`ultron.train.occupancy`) needs, per
labelled pixel, the transmission T ∈ [0, 1] reaching it along its frame's own scanline, so that
a background label in acoustic shadow (T ≈ 0) costs nothing. The paper takes T from the fitted
acoustic field; that estimate can stay far from 0 in shadows, so the source is selectable
(``reconstruct --visibility``). Every source is a pure function of its inputs:

* ``field`` (default, METHOD.md §3) — ray-cast through the fitted field:
  T(r) = Π_{k<r} (1 − β_k)·exp(−α_k Δ) (exclusive, detached; :func:`field_theta_transmission`).
* ``confidence`` — the ultrasound confidence map of the B-mode frame itself (Karamalis et al.
  2012, random walks from the transducer row, C = 1, to the bottom row, C = 0;
  :func:`confidence_map`), T = C.
* ``labels`` — from the annotation: T = 1 down to the end of the first bone-labelled run of
  each scanline (plus a margin), exponential decay below (:func:`label_transmission`).
* ``oracle`` (diagnostic only, ``--oracle-transmission``) — the simulator's true T from
  ``<sweep>/transmission.npy`` (:mod:`ultron.data.truth`): what a perfect estimate would give.

:func:`pixel_transmission` gives T at labelled pixels; :func:`frame_transmission` gives whole
frames (N, H, W) of a sweep, e.g. to compound per-frame visibility into a 3D observed region.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ultron.arguments import check_finite
from ultron.data.dataset import SweepDataset
from ultron.data.labels import LabelledPixels
from ultron.data.truth import TRANSMISSION_FILE, load_true_transmission
from ultron.data.validation import LABEL_TARGET, LABEL_UNANNOTATED, validate_labels
from ultron.errors import UltronInputError, argument_error
from ultron.models.fitted import TransmissionMaps
from ultron.train.confidence import ConfidenceConfig, confidence_map, solver_description

#: Sources selectable with ``--visibility``; ``oracle`` is the diagnostic one.
VISIBILITY_SOURCES = ("field", "confidence", "labels")
ORACLE = "oracle"
TRANSMISSION_SOURCES = (*VISIBILITY_SOURCES, ORACLE)
#: A background pixel with T below this counts as shadowed in :func:`transmission_summary`.
SHADOW_T = 0.1


@dataclass(frozen=True)
class LabelTransmissionConfig:
    """T from the annotation (see :func:`label_transmission`).

    ``margin_mm`` 0: the label band already covers the ≈ 2 mm under a visible surface (the
    simulated annotator's ``band_mm``) and cortical bone attenuates ≈ 10 dB/mm one way at 5 MHz
    (:mod:`ultron.phantom.tissue`), so ≥ 20 dB of the beam is gone at the band's lower edge:
    below it everything is in shadow. ``decay_mm`` 1: T falls by e per mm (≈ 4.3 dB/mm, half
    of bone's one-way rate) rather than in one step, because the band's lower edge is uncertain
    (≈ 0.3 mm annotation jitter, about half a pixel; a band drawn thinner than the cortex) and a
    thin cortex transmits more: one pixel (0.55 mm) below the band T ≈ 0.58, 3 mm below 0.05.
    """

    margin_mm: float = 0.0
    decay_mm: float = 1.0

    def __post_init__(self) -> None:
        check_finite("labels.margin_mm", self.margin_mm, 0.0, strict=False)
        check_finite("labels.decay_mm", self.decay_mm, 0.0, strict=True)


@dataclass(frozen=True)
class VisibilityConfig:
    """Which source gives T (``field``, ``confidence``, ``labels`` or ``oracle``) and its
    parameters (only the chosen source's are used and recorded)."""

    source: str = "field"
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)
    labels: LabelTransmissionConfig = field(default_factory=LabelTransmissionConfig)

    def __post_init__(self) -> None:
        if self.source not in TRANSMISSION_SOURCES:
            raise argument_error(
                "visibility", f"expected one of {VISIBILITY_SOURCES}, got {self.source!r}"
            )

    @property
    def diagnostic(self) -> bool:
        """True for the oracle: the run used ground truth and is not a reconstruction method."""
        return self.source == ORACLE

    def parameters(self) -> dict[str, Any]:
        """The chosen source's parameters, as recorded in run.json and the model metadata."""
        if self.source == "confidence":
            return {**asdict(self.confidence), "implementation": solver_description()}
        if self.source == "labels":
            return asdict(self.labels)
        if self.source == ORACLE:
            return {"file": f"<sweep>/{TRANSMISSION_FILE}"}
        return {}

    def to_dict(self) -> dict[str, Any]:
        """``transmission_source``, ``transmission_parameters`` and ``diagnostic``."""
        return {
            "transmission_source": self.source,
            "transmission_parameters": self.parameters(),
            "diagnostic": self.diagnostic,
        }

    @classmethod
    def from_dict(cls, record: Mapping[str, Any], where: str | Path) -> VisibilityConfig:
        """Inverse of :meth:`to_dict` (a record without a source is ``field``, as before the
        source was recorded); a bad record raises an error naming ``where``."""
        source = record.get("transmission_source", "field")
        params = dict(record.get("transmission_parameters") or {})
        try:
            if source == "confidence":
                params.pop("implementation", None)
                return cls(source, confidence=ConfidenceConfig(**params))
            if source == "labels":
                return cls(source, labels=LabelTransmissionConfig(**params))
            return cls(source)
        except (TypeError, UltronInputError) as exc:
            raise UltronInputError(where, "transmission_source", f"bad record ({exc})") from None


def visibility_config(visibility: str = "field", oracle: bool = False) -> VisibilityConfig:
    """The config of ``--visibility`` and ``--oracle-transmission`` (which excludes any
    ``--visibility`` but the default)."""
    if visibility not in VISIBILITY_SOURCES:
        raise argument_error(
            "visibility", f"expected one of {VISIBILITY_SOURCES}, got {visibility!r}"
        )
    if oracle and visibility != "field":
        raise argument_error(
            "oracle-transmission",
            f"replaces the transmission source; drop --visibility {visibility}",
        )
    return VisibilityConfig(ORACLE if oracle else visibility)


# ---------------------------------------------------------------------------------- sources
def field_theta_transmission(
    dataset: SweepDataset, fitted, pixels: LabelledPixels, keep: TransmissionMaps | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """θ (P, C) and the field's T (P,) at labelled pixels, one rendering pass per sweep.

    T(r) = Π_{k<r} (1 − β_k)·exp(−α_k Δ) (β reflection, α attenuation per mm, Δ the step):
    exclusive, along the pixel's own scanline, without gradient
    (:meth:`~ultron.models.fitted.FittedField.pixel_theta_transmission` on the dataset's pixel
    grid, which is the field's unless the field was fitted at a reduced ``fit_shape``).
    ``keep``, when given, keeps the T of every whole frame rendered (for
    :func:`frame_transmission`'s ``rendered``).
    """
    fitted.check_probe(dataset.probe)
    theta = torch.zeros(len(pixels), len(fitted.channels))
    transmission = torch.zeros(len(pixels))
    for sweep_index, sweep in enumerate(dataset.sweeps):
        sel = np.flatnonzero(pixels.sweep_index == sweep_index)
        if sel.size == 0:
            continue
        kept = (
            None
            if keep is None
            else functools.partial(keep.add, sweep.name, n_frames=sweep.n_frames)
        )
        t, tr = fitted.pixel_theta_transmission(
            sweep.probe_to_world,
            pixels.frame[sel],
            pixels.row[sel],
            pixels.col[sel],
            probe=dataset.probe,
            on_frames=kept,
        )
        theta[sel], transmission[sel] = t, tr
    return theta, transmission


def label_transmission(
    labels: np.ndarray, axial_spacing_mm: float, config: LabelTransmissionConfig | None = None
) -> np.ndarray:
    """T (…, H, W) float32 from the annotation (…, H, W) uint8 (1 bone, 0, 255 unannotated).

    Per scanline (column), with d = r·Δ the depth of row r (Δ = ``axial_spacing_mm``) and
    d_end the depth of the last row of the FIRST run of consecutive bone-labelled rows:
        T(d) = 1                                  for d ≤ d_end + margin
        T(d) = exp(−(d − d_end − margin)/decay)   below.
    A scanline with no bone label has T = 1 everywhere; one with no annotated pixel at all
    (e.g. an unannotated frame) has T = NaN (unknown). A 255 pixel ends a run.
    """
    cfg = config or LabelTransmissionConfig()
    labels = np.asarray(labels)
    if labels.ndim < 2:
        raise argument_error("labels", f"expected (..., H, W), got {labels.shape}")
    validate_labels(labels.reshape(-1, *labels.shape[-2:]), "argument", "labels")
    check_finite("axial_spacing_mm", axial_spacing_mm, 0.0, strict=True)
    height = labels.shape[-2]
    rows = np.arange(height).reshape(height, 1)
    bone = labels == LABEL_TARGET
    has_bone = bone.any(axis=-2, keepdims=True)
    first = np.argmax(bone, axis=-2)[..., None, :]
    gap = (rows > first) & ~bone  # rows after the first bone row that are not bone
    has_gap = gap.any(axis=-2, keepdims=True)
    last = np.where(has_gap, np.argmax(gap, axis=-2)[..., None, :] - 1, height - 1)
    depth = rows * float(axial_spacing_mm)
    below = np.maximum(depth - (last * float(axial_spacing_mm) + cfg.margin_mm), 0.0)
    t = np.where(has_bone, np.exp(-below / cfg.decay_mm), 1.0)
    annotated = (labels != LABEL_UNANNOTATED).any(axis=-2, keepdims=True)
    return np.where(annotated, t, np.nan).astype(np.float32)


def load_oracle_truth(
    config: VisibilityConfig, dataset_dir: str | Path, dataset: SweepDataset
) -> dict[str, np.ndarray] | None:
    """For the oracle, every annotated sweep's true T: ``Sweep.true_transmission`` when the
    dataset was loaded with it, else ``<dataset_dir>/<sweep>/transmission.npy`` (checked against
    its images' shape); ``None`` for the other sources. Call it before any work: a missing or
    malformed file raises an error naming it."""
    if config.source != ORACLE:
        return None
    truth: dict[str, np.ndarray] = {}
    for sweep in dataset.sweeps:
        if len(sweep.labelled_frames) == 0:
            continue
        loaded = getattr(sweep, "true_transmission", None)
        truth[sweep.name] = (
            loaded
            if loaded is not None
            else load_true_transmission(dataset_dir, sweep.name, sweep.images.shape)
        )
    return truth


# ----------------------------------------------------------------------------- dispatchers
#: Whole frames whose field T is computed at a time (their pixel indices: 3 × 8 B per pixel).
_T_CHUNK_FRAMES = 64


def _frame_indices(frames: np.ndarray | None, n: int) -> np.ndarray:
    if frames is None:
        return np.arange(n, dtype=np.int64)
    index = np.asarray(frames)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        raise argument_error(
            "frames", f"expected a 1-D integer array, got {index.dtype} {index.shape}"
        )
    if index.size and (index.min() < 0 or index.max() >= n):
        raise argument_error("frames", f"indices must lie in [0, {n})")
    return index.astype(np.int64)


def frame_transmission(
    config: VisibilityConfig,
    dataset: SweepDataset,
    sweep_name: str,
    frames: np.ndarray | None = None,
    *,
    fitted=None,
    truth: Mapping[str, np.ndarray] | None = None,
    advance: Callable[[int, int], None] | None = None,
    rendered: TransmissionMaps | None = None,
) -> np.ndarray:
    """T (n, H, W) float32 of whole frames ``frames`` (default: all) of one sweep.

    ``field`` needs ``fitted`` (any frame; ``advance``, when given, is told the frames had so
    far and n after each chunk of frames); the frames that ``rendered`` holds (the same field's
    T, kept by :func:`field_theta_transmission`) are read from it, the others rendered (the
    same T either way: a frame's T does not depend on the frames rendered with it; checked in
    tests/test_visibility.py); ``confidence`` works for any frame; ``labels``
    needs the sweep's labels (NaN on scanlines without an annotated pixel); ``oracle`` takes
    ``truth[sweep_name]`` (:func:`load_oracle_truth`), else the sweep's ``true_transmission``.
    """
    sweep = dataset.sweep(sweep_name)
    index = _frame_indices(frames, sweep.n_frames)
    height, width = dataset.probe.image_shape
    if config.source == "field":
        if fitted is None:
            raise argument_error("fitted", "the 'field' visibility needs a fitted acoustic field")
        fitted.check_probe(dataset.probe)
        out = np.empty((index.size, height, width), dtype=np.float32)
        kept = [None if rendered is None else rendered.get(sweep.name, i) for i in index]
        for position, t in enumerate(kept):
            if t is not None:
                out[position] = t
        todo = np.array([k for k, t in enumerate(kept) if t is None], dtype=np.int64)
        done = index.size - todo.size
        if advance is not None and done:
            advance(done, index.size)
        for start in range(0, todo.size, _T_CHUNK_FRAMES):  # bounds the pixel index arrays
            at = todo[start : start + _T_CHUNK_FRAMES]
            f, r, c = np.meshgrid(index[at], np.arange(height), np.arange(width), indexing="ij")
            _, t = fitted.pixel_theta_transmission(
                sweep.probe_to_world, f.ravel(), r.ravel(), c.ravel(), probe=dataset.probe
            )
            out[at] = t.numpy().reshape(at.size, height, width)
            if advance is not None:
                advance(done + start + at.size, index.size)
        return out
    if config.source == "confidence":
        maps = [confidence_map(sweep.images[i], config.confidence) for i in index]
        return np.stack(maps) if maps else np.zeros((0, height, width), np.float32)
    if config.source == "labels":
        if sweep.labels is None:
            raise UltronInputError(
                f"sweep {sweep.name!r}", "labels", "the 'labels' visibility needs labels.npy"
            )
        return label_transmission(
            sweep.labels[index], dataset.probe.axial_spacing_mm, config.labels
        )
    true_t = truth.get(sweep.name) if truth is not None else None
    if true_t is None:
        true_t = getattr(sweep, "true_transmission", None)
    if true_t is None:
        raise argument_error("truth", f"the oracle needs the true transmission of {sweep.name!r}")
    return np.asarray(true_t[index], dtype=np.float32)


def pixel_transmission(
    config: VisibilityConfig,
    dataset: SweepDataset,
    pixels: LabelledPixels,
    *,
    fitted=None,
    truth: Mapping[str, np.ndarray] | None = None,
    field_transmission: torch.Tensor | None = None,
) -> torch.Tensor:
    """T (P,) float32 at labelled pixels from ``config.source``.

    For ``field``, ``field_transmission`` (the T that :func:`field_theta_transmission` computed
    with θ in the same rendering pass) is returned as it is; without it T is ray-cast from
    ``fitted``. The other sources compute whole-frame maps of the frames holding labelled
    pixels (:func:`frame_transmission`) and look the pixels up.
    """
    if config.source == "field":
        if field_transmission is not None:
            if field_transmission.shape != (len(pixels),):
                raise argument_error(
                    "field_transmission", f"expected shape ({len(pixels)},), got "
                    f"{tuple(field_transmission.shape)}",
                )  # fmt: skip
            return field_transmission.detach().float()
        if fitted is None:
            raise argument_error("fitted", "the 'field' visibility needs a fitted acoustic field")
        return field_theta_transmission(dataset, fitted, pixels)[1].float()
    transmission = np.zeros(len(pixels), dtype=np.float32)
    for sweep_index, sweep in enumerate(dataset.sweeps):
        sel = np.flatnonzero(pixels.sweep_index == sweep_index)
        if sel.size == 0:
            continue
        frames, local = np.unique(pixels.frame[sel], return_inverse=True)
        maps = frame_transmission(config, dataset, sweep.name, frames, fitted=fitted, truth=truth)
        transmission[sel] = maps[local, pixels.row[sel], pixels.col[sel]]
    return torch.from_numpy(transmission)


def in_labelled_shadow(dataset: SweepDataset, pixels: LabelledPixels) -> torch.Tensor:
    """(P,) bool: the pixel lies in its scanline's *labelled* shadow — the annotation's own T
    (:func:`label_transmission`, default margin and decay) is below ``SHADOW_T`` there, i.e.
    more than ≈ 2.3 mm under the end of the scanline's first run of bone labels. Truth-free:
    where the labels say the beam could not reach."""
    t = pixel_transmission(VisibilityConfig("labels"), dataset, pixels)
    return t < SHADOW_T


def transmission_summary(
    transmission: torch.Tensor,
    labels: torch.Tensor,
    labelled_shadow: torch.Tensor | None = None,
    observed_transmission: float | None = None,
) -> dict[str, Any]:
    """Mean T at bone and at background labels, and the share of background labels in shadow
    (T < 0.1): how much the compensated loss can discount (recorded in run.json).

    With ``observed_transmission`` τ (the observed negatives' threshold) also the share of
    background labels below τ — those the loss drops — and, with ``labelled_shadow`` (P,) bool
    (:func:`in_labelled_shadow`), how many background labels lie in the labels' own shadow and
    the share of them whose T < τ: whether the field's T calls the shadow the labels show,
    without any truth (docs/stage2-transmission.md: the loss's gain follows it).
    """
    t = transmission.detach().double()
    bone = labels.bool()

    def mean(mask: torch.Tensor) -> float | None:
        return float(t[mask].mean()) if bool(mask.any()) else None

    def share_below(mask: torch.Tensor, level: float) -> float | None:
        return float((t[mask] < level).double().mean()) if bool(mask.any()) else None

    background = ~bone
    summary: dict[str, Any] = {
        "bone_mean": mean(bone),
        "background_mean": mean(background),
        "background_shadowed": share_below(background, SHADOW_T),
        "shadow_threshold": SHADOW_T,
    }
    if observed_transmission is not None:
        summary["observed_transmission"] = float(observed_transmission)
        summary["background_dropped"] = share_below(background, observed_transmission)
        if labelled_shadow is not None:
            if labelled_shadow.shape != labels.shape:
                raise argument_error(
                    "labelled_shadow",
                    f"expected shape {tuple(labels.shape)}, got {tuple(labelled_shadow.shape)}",
                )
            in_shadow = background & labelled_shadow.bool()
            summary["labelled_shadow_background"] = int(in_shadow.sum())
            summary["labelled_shadow_dropped"] = share_below(in_shadow, observed_transmission)
    return summary
