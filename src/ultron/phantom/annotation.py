"""Simulated manual segmentation of bone in B-mode frames.

A person segmenting B-mode marks the bright band under a bone surface that the beam reaches;
bone under that band, and any bone in the acoustic shadow, looks like the dark background and
is marked 0. So, per scanline of a frame's centre plane:

* a gel→bone interface is *visible* if its displayed echo (after TGC) is at least
  ``min_echo_db`` relative to a normally incident, unattenuated one — a surface reached
  through bone, or too oblique to send an echo back, is not;
* label 1 covers depths [d_in, min(d_in + band_mm, d_out)] below a visible interface at d_in
  (d_out the next bone→gel interface), everything else 0.

Human error: the top and bottom edges of the band move by smooth random offsets along the
image (Gaussian, σ = ``jitter_mm``, lateral correlation length ``jitter_correlation_mm``);
a ``missing_fraction`` of frames are not annotated (255); and an ``error_rate`` of frames are
annotated coarsely: the whole annotation is shifted by ``error_shift_mm`` (random direction,
axial and lateral) and the band is twice as thick.

Labels follow the image (centre elevation) plane: a bone surface seen only through the beam's
elevation thickness (a faint partial-volume echo of bone ≈ 1 mm off-plane) is not labelled, so
every label-1 pixel is bone of the image plane.

Defaults model a careful annotator: 0.3 mm edge jitter (about half a pixel) correlated over
2 mm, no missing frames (label subsampling is the training stage's business) and 2 % of
frames with a coarse 2 mm error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ultron.data.dataset import ProbeGeometry
from ultron.data.validation import LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error
from ultron.phantom.simulator import BoneInterfaces


@dataclass(frozen=True)
class AnnotationConfig:
    """Every parameter of the annotation simulator (see the module docstring).

    Attributes:
        band_mm: Thickness of the labelled band under a visible bone surface, mm.
        min_echo_db: Weakest displayed echo, relative to a normally incident unattenuated
            one, that the annotator sees as bone, dB.
        jitter_mm: Annotation edge jitter σ, mm (0: exact edges).
        jitter_correlation_mm: Lateral correlation length of the edge jitter, mm.
        missing_fraction: Fraction of frames left unannotated (255).
        error_rate: Fraction of frames annotated with a coarse error.
        error_shift_mm: Shift of a coarse error's whole annotation, mm.
    """

    band_mm: float = 2.0
    min_echo_db: float = -18.0
    jitter_mm: float = 0.3
    jitter_correlation_mm: float = 2.0
    missing_fraction: float = 0.0
    error_rate: float = 0.02
    error_shift_mm: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.band_mm) and self.band_mm > 0):
            raise argument_error("band_mm", f"expected a positive thickness, got {self.band_mm}")
        if not math.isfinite(self.min_echo_db):
            raise argument_error("min_echo_db", f"expected a finite level, got {self.min_echo_db}")
        for name in ("jitter_mm", "jitter_correlation_mm", "error_shift_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise argument_error(name, f"expected a number ≥ 0, got {value}")
        for name in ("missing_fraction", "error_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise argument_error(name, f"expected a fraction in [0, 1], got {value}")


def smooth_noise(
    shape: tuple[int, int], correlation_px: float, generator: torch.Generator
) -> torch.Tensor:
    """Unit-variance Gaussian noise (rows, cols) correlated along the last axis by a Gaussian
    kernel of σ = ``correlation_px``: n = (k ∗ w)/‖k‖₂ with w white."""
    white = torch.randn(shape, generator=generator, dtype=torch.float64)
    if correlation_px <= 0.0:
        return white
    radius = max(1, math.ceil(3 * correlation_px))
    offsets = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-(offsets**2) / (2 * correlation_px**2))
    kernel = kernel / kernel.norm()
    padded = F.pad(white[:, None], (radius, radius), mode="replicate")
    return F.conv1d(padded, kernel[None, None])[:, 0]


def annotate(
    interfaces: BoneInterfaces,
    probe: ProbeGeometry,
    config: AnnotationConfig,
    generator: torch.Generator,
) -> torch.Tensor:
    """Labels (N, H, W) uint8 (1 bone, 0 background, 255 not annotated) from the centre-plane
    interfaces of simulated frames."""
    entering, exiting = interfaces.entering, interfaces.exiting
    if entering.ndim != 3 or entering.shape[1:] != probe.image_shape:
        raise argument_error(
            "interfaces", f"expected (N, {probe.height_px}, {probe.width_px}) tensors"
        )
    n, height, width = entering.shape
    step = probe.axial_spacing_mm
    depth = interfaces.depth_mm.to(torch.float64)
    visible = entering & (interfaces.echo_db >= config.min_echo_db)

    # Depth of the next bone→gel interface at or below each row (reverse running minimum).
    exit_depth = torch.where(exiting, depth, math.inf)
    next_exit = torch.flip(torch.cummin(torch.flip(exit_depth, [1]), dim=1).values, [1])
    band_end = torch.minimum(depth + config.band_mm, next_exit)
    rows = torch.arange(height)[None, :, None].expand(n, height, width)
    last_visible = torch.cummax(torch.where(visible, rows, -1), dim=1).values

    # Edge jitter, coarse errors.
    spacing = probe.lateral_spacing_mm
    correlation_px = config.jitter_correlation_mm / spacing
    top = config.jitter_mm * smooth_noise((n, width), correlation_px, generator)
    bottom = config.jitter_mm * smooth_noise((n, width), correlation_px, generator)
    coarse = torch.rand(n, generator=generator, dtype=torch.float64) < config.error_rate
    direction = torch.rand(n, generator=generator, dtype=torch.float64) * 2 * math.pi
    axial_shift = torch.where(coarse, config.error_shift_mm * torch.sin(direction), 0.0)
    lateral_shift = torch.where(coarse, config.error_shift_mm * torch.cos(direction), 0.0)
    top = top + axial_shift[:, None]
    bottom = bottom + axial_shift[:, None] + torch.where(coarse, config.band_mm, 0.0)[:, None]

    # Column c shows the annotation of column c − shift (lateral error), 0 where none.
    cols = torch.arange(width)[None, :] - torch.round(lateral_shift / spacing).long()[:, None]
    in_image = (cols >= 0) & (cols < width)
    cols = cols.clamp(0, width - 1)[:, None, :].expand(n, height, width)
    band_end = band_end.gather(2, cols)
    depth = depth.gather(2, cols)
    last_visible = last_visible.gather(2, cols)

    pixel_depth = rows.to(torch.float64) * step
    query = pixel_depth - top[:, None, :]
    query_row = (torch.floor(query / step) + 1).clamp(0, height - 1).long()
    entry_row = last_visible.gather(1, query_row)
    has_entry = entry_row >= 0
    entry_row = entry_row.clamp(min=0)
    d_in = depth.gather(1, entry_row)
    d_end = band_end.gather(1, entry_row)
    bone = (
        has_entry
        & (pixel_depth >= d_in + top[:, None, :])
        & (pixel_depth <= d_end + bottom[:, None, :])
        & in_image[:, None, :]
    )
    labels = torch.where(bone, LABEL_TARGET, LABEL_BACKGROUND).to(torch.uint8)

    n_missing = round(config.missing_fraction * n)
    if n_missing:
        missing = torch.randperm(n, generator=generator)[:n_missing]
        labels[missing] = LABEL_UNANNOTATED
    return labels
