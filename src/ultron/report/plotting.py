"""Offscreen matplotlib helpers: figures drawn on an Agg canvas (no pyplot, no display)."""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.errors import argument_error


def new_figure(width_in: float, height_in: float, dpi: int = 90):
    """A ``matplotlib.figure.Figure`` attached to an Agg canvas (no global pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def figure_png(fig) -> bytes:
    """Render ``fig`` to PNG bytes."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def image_extent_mm(probe: ProbeGeometry) -> tuple[float, float, float, float]:
    """``imshow`` extent (left, right, bottom, top) of a frame in mm: lateral × depth."""
    return (-probe.width_mm / 2, probe.width_mm / 2, probe.depth_mm, 0.0)


def check_dataset(dataset: SweepDataset) -> None:
    """Raise unless ``dataset`` is a :class:`SweepDataset`."""
    if not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", f"expected a SweepDataset, got {type(dataset).__name__}")


def check_frame_indices(
    values: Sequence[int], n_frames: int, name: str, sweep_name: str
) -> list[int]:
    """``values`` as a list of ints in [0, n_frames); raises naming ``name`` and the sweep."""
    try:
        indices = [int(v) for v in values]
    except (TypeError, ValueError):
        raise argument_error(name, f"expected frame indices, got {values!r}") from None
    for value, original in zip(indices, values, strict=True):
        if isinstance(original, bool) or value != original:
            raise argument_error(name, f"frame index {original!r} is not an integer")
        if not 0 <= value < n_frames:
            raise argument_error(
                name,
                f"frame index {value} out of range for sweep {sweep_name!r} ({n_frames} frames)",
            )
    return indices


def robust_limits(values: np.ndarray) -> tuple[float, float]:
    """Colour limits spanning the 1st–99th percentile of the finite values (never empty)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = (float(v) for v in np.percentile(finite, [1, 99]))
    if high <= low:
        high = low + max(1e-6, abs(low) * 1e-3)
    return low, high
