"""Where a frame's B-mode shows bone: the echo support of a reconstructed surface.

A bone surface leaves two marks on the scanlines that cross it: a bright echo that nothing
beneath outshines, and the acoustic shadow that begins under it. Per frame (row 0 at the
transducer, one scanline per column), with the evidence of ``label --auto``'s detector
(:func:`ultron.data.auto_labels.frame_evidence`: S the smoothed frame, S_ref its 99th
percentile, E the bone score, and the deep shadow D where the mean of S over the next
``shadow_window_mm`` is at most ``shadow_level``·S_ref), pixel (r, c) *shows bone* when

    ( E(r, c) > 0  and  ( o_z(r + g, c) − r ≤ ``shadow_max_mm`` / Δz  or
                          o(r + g, c) − r ≤ ``shadow_onset_mm`` / Δz ) )   or
    ( S̄(r, c) > ``shadow_level``·S_ref  and  o_z(r, c) − r ≤ ``shadow_onset_mm`` / Δz ),

    o(r, c) = min{r' ≥ r : D(r', c)},   o_z(r, c) = min{r' ≥ r : D_z(r', c)},

    D_z(r, c) = D(r, c)  and  S̄(r, c) ≤ ``shadow_depth_ratio``·L(r),
    L(r) = the ``DEPTH_LEVEL_PERCENTILE``-th percentile of S̄(r, c') over the image columns c'

(a bone echo that casts a shadow — one dark against its depth within ``shadow_max_mm``, or any
deep shadow directly under the echo — or lit tissue under which a shadow begins within
``shadow_onset_mm``; the shadow itself shows nothing: S̄ is S's mean over the window from the
pixel down, clipped to the frame; g = ``gap_mm``/Δz and ``shadow_max_mm`` are the detector's,
whose score E asks the same of D).

A shadow is dark against the tissue at its own depth: L(r) is the frame's lit level at row r,
over the columns that hold image (S exceeds ``shadow_level``·S_ref somewhere in them; a convex
or sector probe's blank margins do not count). Where the echoes fade with depth across the whole
frame (attenuation the gain does not make up), the fade's floor is as dark as L and is no
shadow, so neither the tissue above it nor a bright speckle over it is called bone. A shadow as
wide as the frame's image at its depth (a long bone imaged along its axis) is as dark as L too:
its echo still shows bone through the shadow directly beneath it, the lit tissue over it does
not.

The frame's end counts as an onset (the minimum over no rows is H): within ``shadow_onset_mm``
of its last row a frame cannot show whether a shadow follows. An echo there keeps its support,
and so does lit tissue that is an echo by its brightness alone — with ``frame_end_echo`` = m,

    S(r, c) ≥ m · M(r),   M(r) = the median of S(r, c') over the image columns c'

(m = 3: three times the speckle at its depth, a median that an echo narrower than half the
frame does not move): the deep walls at the bottom of the frames keep their support, while
plain speckle over the frame's end — where an occupancy fitted on few labels runs on as a slab
along the bottom of the field of view — no longer shows bone (None: every lit pixel there does,
as before; docs/decisions.md, "Echo support at the frame's end").

A pixel is *supported* when some pixel of its column within ±``depth_window_mm`` shows bone (a
maximum filter along the scanline: the tracked pose and the surface's depth each err by about a
millimetre). A blank frame (S_ref = 0) supports nothing.

UltrON keeps the part of its iso-surface that some frame observed (:mod:`ultron.mesh.observed`)
and, with echo support on, that some frame supports: a surface f(θ) places in lit soft tissue
that no frame shows as bone is dropped with the shadow walls. Measured in docs/real-sweeps.md
(echo support of UltrON's surface).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from ultron.data.auto_labels import (
    AutoLabelConfig,
    FrameEvidence,
    echo_tail_rows,
    frame_evidence,
    next_rows,
)
from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.errors import argument_error


@dataclass(frozen=True)
class EchoSupportConfig:
    """Echo support (module docstring): the depth window and the shadow's onset in mm; the
    detector's evidence from ``detector`` (``label --auto``'s defaults). The onset is not the
    detector's (4 mm, how far below an echo its shadow may begin): 2 mm keeps less lit tissue
    above a shadow (docs/decisions.md, "Echo support: the shadow's onset").
    ``shadow_depth_ratio``: how dark against the tissue at its depth a shadow must be (ρ in the
    module docstring; ``math.inf`` drops the test; docs/decisions.md, "Echo support: a shadow
    against its depth"). ``frame_end_echo``: how bright against its row lit tissue over the
    frame's end must be to show bone (m in the module docstring; None: any lit pixel)."""

    depth_window_mm: float = 1.0
    shadow_onset_mm: float = 2.0
    shadow_depth_ratio: float = 0.3
    frame_end_echo: float | None = 3.0
    detector: AutoLabelConfig = field(default_factory=AutoLabelConfig)

    def __post_init__(self) -> None:
        for name in ("depth_window_mm", "shadow_onset_mm"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise argument_error(name, f"expected a finite length ≥ 0 mm, got {value!r}")
        ratio = self.shadow_depth_ratio
        if not (isinstance(ratio, int | float) and not math.isnan(ratio) and ratio > 0):
            raise argument_error(
                "shadow_depth_ratio", f"expected a ratio > 0 (inf: no test), got {ratio!r}"
            )
        end = self.frame_end_echo
        if end is not None and (
            isinstance(end, bool) or not isinstance(end, int | float) or not 0 <= end < math.inf
        ):
            raise argument_error(
                "frame_end_echo", f"expected a finite factor ≥ 0 or None, got {end!r}"
            )
        if not isinstance(self.detector, AutoLabelConfig):
            raise argument_error(
                "detector", f"expected an AutoLabelConfig, got {type(self.detector).__name__}"
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: L(r) of the module docstring: this percentile of a row's window means over the image columns.
DEPTH_LEVEL_PERCENTILE = 90.0


def depth_relative_shadow(
    evidence: FrameEvidence, probe: ProbeGeometry, config: EchoSupportConfig
) -> np.ndarray:
    """Bool (H, W): D_z of the module docstring, the deep shadow D of ``evidence`` where it is
    also at most ``shadow_depth_ratio`` × the frame's lit level L(r) at its row."""
    if not isinstance(config, EchoSupportConfig):
        raise argument_error(
            "config", f"expected an EchoSupportConfig, got {type(config).__name__}"
        )
    if np.shape(evidence.dark) != probe.image_shape:
        raise argument_error(
            "evidence", f"expected a frame of {probe.image_shape}, got {np.shape(evidence.dark)}"
        )
    if math.isinf(config.shadow_depth_ratio):
        return evidence.dark
    mean = evidence.shadow_mean
    image = _image_columns(evidence, config)
    if not image.any():
        return np.zeros_like(evidence.dark)
    level = np.percentile(mean[:, image], DEPTH_LEVEL_PERCENTILE, axis=1, keepdims=True)
    return evidence.dark & (mean <= config.shadow_depth_ratio * level)


def _image_columns(evidence: FrameEvidence, config: EchoSupportConfig) -> np.ndarray:
    """Bool (W,): the columns that hold image (S exceeds the shadow level somewhere in them)."""
    return evidence.smoothed.max(axis=0) > config.detector.shadow_level * evidence.ref


def _echo_at_frame_end(evidence: FrameEvidence, config: EchoSupportConfig) -> np.ndarray:
    """Bool (H, W): S(r, c) ≥ ``frame_end_echo`` · M(r) (module docstring); all true with
    ``frame_end_echo`` None or in a frame without image columns."""
    image = _image_columns(evidence, config)
    if config.frame_end_echo is None or not image.any():
        return np.ones(evidence.smoothed.shape, dtype=bool)
    smoothed = evidence.smoothed
    level = np.median(smoothed[:, image], axis=1, keepdims=True)
    return smoothed >= config.frame_end_echo * level


def echo_support_map(
    image: np.ndarray, probe: ProbeGeometry, config: EchoSupportConfig | None = None
) -> np.ndarray:
    """Bool (H, W): the pixels of a uint8 frame (H, W) that are supported (module docstring)."""
    cfg = config or EchoSupportConfig()
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != probe.image_shape:
        raise argument_error(
            "image",
            f"expected a uint8 frame of {probe.image_shape}, got {image.dtype} {image.shape}",
        )
    axial = probe.axial_spacing_mm
    evidence = frame_evidence(image, probe, cfg.detector)
    if evidence.ref <= 0:
        return np.zeros(image.shape, dtype=bool)
    height = image.shape[0]
    rows = np.arange(height)[:, None]
    # H (the frame's end) where no shadow follows in the frame
    onset = next_rows(depth_relative_shadow(evidence, probe, cfg))
    # an echo casting a shadow: dark against its depth within shadow_max_mm under the echo's
    # tail, or any deep shadow within shadow_onset_mm under it
    tail = echo_tail_rows(height, axial, cfg.detector)
    casts = (onset[tail] - rows) * axial <= cfg.detector.shadow_max_mm
    casts |= (next_rows(evidence.dark)[tail] - rows) * axial <= cfg.shadow_onset_mm
    shows = (evidence.score > 0) & casts
    # lit (not in the shadow, the window clipped at the frame's end) over a near onset; over
    # the frame's end (no onset in the frame) only where it is an echo by its brightness
    lit = ~evidence.shadowed & ((onset - rows) * axial <= cfg.shadow_onset_mm)
    lit &= (onset < height) | _echo_at_frame_end(evidence, cfg)
    shows |= lit
    reach = round(cfg.depth_window_mm / axial)
    if reach == 0:
        return shows
    return ndimage.maximum_filter1d(shows, 2 * reach + 1, axis=0, mode="constant")


def echo_support_maps(dataset: SweepDataset, config: EchoSupportConfig | None = None) -> np.ndarray:
    """Bool (N, H, W): :func:`echo_support_map` of every frame of ``dataset``, its sweeps in
    order (as :meth:`~ultron.data.dataset.SweepDataset.all_poses`)."""
    out = np.empty((dataset.n_frames, *dataset.probe.image_shape), dtype=bool)
    done = 0
    for sweep in dataset.sweeps:
        for image in sweep.images:
            out[done] = echo_support_map(np.asarray(image), dataset.probe, config)
            done += 1
    return out
