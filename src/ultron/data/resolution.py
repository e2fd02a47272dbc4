"""The resolution the frames really carry: their own pixels, or coarser where the images hold
no finer detail than their speckle. The field is fitted there (``fit_shape="auto"``,
:mod:`ultron.train.fit_shape`) and no meshing voxel is finer (:mod:`ultron.mesh.grid`).

A scanner may store its B-mode frames on a grid much finer than the imaging system resolves
(the PLUS recordings: docs/decisions.md#speckle-resolution-dataresolutionpy-trainfit_shapepy).
Fitted there, every speckle grain spans many pixels the renderer's per-pixel scatterers cannot
reproduce, the grid field gets a node per pixel (``GridFieldConfig.cell_mm`` defaults to the
pixel size) that few frames constrain, and each step costs the pixels' square. The speckle
grain's axial length is measured on the data itself:

    g = FWHM of the mean axial autocorrelation of  i − G_σ ∗ i,   σ = 1 mm per axis,

over up to eight evenly spaced frames (``i − G_σ ∗ i`` keeps the sub-millimetre content, the
speckle, and drops the tissue layers' slow variation). The fit samples each grain with two
pixels (Nyquist): the pixel spacing is raised to at least g / 2 on both axes, never lowered.
Frames whose pixels are already that coarse are fitted at their own size, unchanged.

The columns the frames carry (:func:`signal_columns`): a probe's image is often stored wider
than its aperture, with columns that are 0 in every frame. ``import-plus`` drops them and the
field fit draws no patch from them (docs/real-sweeps.md, "Blank columns").
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.errors import argument_error
from ultron.parallel import thread_map

#: Pixels per speckle grain (axial autocorrelation FWHM) at the fitting resolution.
PIXELS_PER_GRAIN = 2.0
#: Scale (mm, Gaussian σ) above which image content counts as structure, not speckle.
STRUCTURE_SIGMA_MM = 1.0
#: Frames the grain is measured on (evenly spaced over the dataset).
GRAIN_FRAMES = 8


def axial_grain_px(frames: np.ndarray, probe: ProbeGeometry) -> float:
    """Axial speckle length of ``frames`` (N, H, W) in pixels: the full width at half maximum
    of the column-averaged axial autocorrelation of the high-passed frames (module doc), median
    over the frames; ``nan`` where no frame has a measurable grain (a flat image)."""
    frames = np.asarray(frames)
    if frames.ndim != 3 or min(frames.shape) < 1:
        raise argument_error("frames", f"expected (N, H, W), got {frames.shape}")
    sigma_px = (
        STRUCTURE_SIGMA_MM / probe.axial_spacing_mm,
        STRUCTURE_SIGMA_MM / probe.lateral_spacing_mm,
    )

    def grain(frame: np.ndarray) -> float:
        """One frame's FWHM (nan where its high-passed image is flat)."""
        frame = frame.astype(np.float64)
        rows = frame.shape[0]
        detail = frame - gaussian_filter(frame, sigma_px, mode="nearest")
        spectrum = np.fft.rfft(detail, n=2 * rows, axis=0)
        correlation = np.fft.irfft(np.abs(spectrum) ** 2, axis=0)[:rows].sum(axis=1)
        if not correlation[0] > 0:
            return math.nan
        return _full_width_at_half(correlation / correlation[0])

    widths = thread_map(grain, list(frames))  # the filter and the FFTs release the GIL
    finite = [w for w in widths if math.isfinite(w)]
    return float(np.median(finite)) if finite else math.nan


def _full_width_at_half(correlation: np.ndarray) -> float:
    """2 × the first lag where a normalised autocorrelation falls to ½ (linear between lags)."""
    below = np.flatnonzero(correlation < 0.5)
    if below.size == 0:
        return math.nan
    lag = int(below[0])
    before, after = correlation[lag - 1], correlation[lag]
    return 2.0 * (lag - 1 + (before - 0.5) / (before - after))


def resolved_shape(dataset: SweepDataset) -> tuple[int, int] | None:
    """The frame shape that samples ``dataset``'s speckle (module doc), measured once per
    dataset object (:meth:`SweepDataset.memoized`)."""
    if not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", "expected a SweepDataset")
    return dataset.memoized("resolved_shape", measure_resolved_shape)


def measure_resolved_shape(dataset: SweepDataset) -> tuple[int, int] | None:
    """The measurement behind :func:`resolved_shape`: None where ``dataset``'s own pixels
    already sample the axial grain with at most :data:`PIXELS_PER_GRAIN` pixels, else (H, W)
    with both spacings raised to at least grain / 2."""
    probe = dataset.probe
    grain = dataset_grain_px(dataset)
    if not grain > PIXELS_PER_GRAIN:
        return None
    spacing_mm = grain / PIXELS_PER_GRAIN * probe.axial_spacing_mm
    rows = min(probe.height_px, max(1, round(probe.depth_mm / spacing_mm)))
    cols = min(probe.width_px, max(1, round(probe.width_mm / spacing_mm)))
    return None if (rows, cols) == probe.image_shape else (rows, cols)


def dataset_grain_px(dataset: SweepDataset) -> float:
    """The axial speckle grain (pixels, :func:`axial_grain_px`) of up to :data:`GRAIN_FRAMES`
    frames evenly spaced over ``dataset``'s sweeps, measured once per dataset object
    (:meth:`SweepDataset.memoized`); nan where no frame has a measurable grain."""
    if not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", "expected a SweepDataset")
    return dataset.memoized("axial_grain_px", _measure_grain_px)


def _measure_grain_px(dataset: SweepDataset) -> float:
    """The measurement behind :func:`dataset_grain_px`."""
    counts = [len(sweep.images) for sweep in dataset.sweeps]
    picks = np.linspace(0, sum(counts) - 1, min(GRAIN_FRAMES, sum(counts))).round().astype(int)
    starts = np.cumsum([0, *counts])
    frames = [
        dataset.sweeps[s].images[k - starts[s]]
        for k in picks
        for s in [int(np.searchsorted(starts, k, side="right")) - 1]
    ]
    return axial_grain_px(np.stack(frames), dataset.probe)


def resolved_spacing_mm(dataset: SweepDataset) -> float:
    """The finer pixel spacing at :func:`resolved_shape` (the probe's own where it is None):
    the finest detail the frames carry, in mm."""
    shape = resolved_shape(dataset)
    probe = dataset.probe
    if shape is not None:
        probe = ProbeGeometry(probe.width_mm, probe.depth_mm, int(shape[0]), int(shape[1]))
    return min(probe.axial_spacing_mm, probe.lateral_spacing_mm)


def signal_columns(frames: np.ndarray) -> tuple[int, int]:
    """[start, stop) of the columns of (N, H, W) ``frames`` in which some frame has a pixel
    other than 0: the columns outside are blank in every frame (never insonified). All
    columns, (0, W), when every pixel is 0."""
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise argument_error("frames", f"expected (N, H, W) frames, got shape {frames.shape}")
    return lit_column_range(frames.any(axis=(0, 1)))


def lit_column_range(lit: np.ndarray) -> tuple[int, int]:
    """[start, stop) spanning the true entries of the (W,) column mask ``lit`` (a column with
    signal in some frame: :func:`signal_columns`); (0, W) when none is true."""
    lit = np.asarray(lit)
    if lit.ndim != 1:
        raise argument_error("lit", f"expected a (W,) column mask, got shape {lit.shape}")
    columns = np.flatnonzero(lit)
    if columns.size == 0:
        return 0, int(lit.shape[0])
    return int(columns[0]), int(columns[-1]) + 1
