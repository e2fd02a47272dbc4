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


def place_grid(
    fig,
    n_rows: int,
    n_cols: int,
    margins_in: tuple[float, float, float, float],
    gaps_in: tuple[float, float],
    right_fraction: float = 1.0,
) -> None:
    """Lay out ``fig``'s grid of subplots with fixed margins (left, right, bottom, top) and
    gaps (between columns, between rows) in inches, the grid ending at ``right_fraction`` of
    the width before the right margin (room for a colour bar). A fixed layout, not
    ``tight_layout``, which measures every tick label of every figure (its cost: docs/decisions.md,
    "Report figures: a fixed layout")."""
    width, height = (float(v) for v in fig.get_size_inches())
    left, right, bottom, top = margins_in
    gap_w, gap_h = gaps_in
    right_edge = right_fraction * width - right
    axis_w = max((right_edge - left - (n_cols - 1) * gap_w) / n_cols, 1e-3)
    axis_h = max((height - top - bottom - (n_rows - 1) * gap_h) / n_rows, 1e-3)
    fig.subplots_adjust(
        left=left / width,
        right=right_edge / width,
        bottom=bottom / height,
        top=1 - top / height,
        wspace=gap_w / axis_w,
        hspace=gap_h / axis_h,
    )


def top_title(fig, text: str, fontsize: float = 9) -> None:
    """``fig``'s title, its top 0.1 in below the figure's edge (whatever the figure's height)."""
    fig.suptitle(text, fontsize=fontsize, y=1 - 0.1 / float(fig.get_size_inches()[1]), va="top")


def figure_png(fig) -> bytes:
    """Render ``fig`` to PNG bytes."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def image_extent_mm(probe: ProbeGeometry) -> tuple[float, float, float, float]:
    """``imshow`` extent (left, right, bottom, top) of a frame in mm: lateral × depth."""
    return (-probe.width_mm / 2, probe.width_mm / 2, probe.depth_mm, 0.0)


def display_factor(width_px: int, panel_px: float) -> int:
    """The integer factor k ≥ 1 by which a frame ``width_px`` columns wide can be reduced
    before it is drawn into a panel ``panel_px`` pixels wide, keeping at least the panel's
    own pixels (drawing resamples a frame far larger than its panel, at a cost that grows with
    the frame)."""
    if width_px < 1 or not panel_px > 0:
        raise argument_error("panel_px", f"expected a positive panel and frame, got {panel_px}")
    return max(1, int(width_px // panel_px))


def reduced_frame(
    image: np.ndarray, labels: np.ndarray | None, k: int, extent: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray | None, tuple[float, float, float, float]]:
    """``image`` (H, W) as the mean of its k × k blocks, ``labels`` as each block's centre
    pixel, and the ``imshow`` extent of the ⌊H/k⌋·k × ⌊W/k⌋·k pixels they cover (the
    remainder rows and columns, fewer than k, are not drawn)."""
    height, width = image.shape
    rows, cols = height // k, width // k
    blocks = image[: rows * k, : cols * k].reshape(rows, k, cols, k)
    mean = blocks.mean(axis=(1, 3), dtype=np.float32)
    centre = None if labels is None else labels[k // 2 : rows * k : k, k // 2 : cols * k : k]
    left, right, bottom, top = extent
    shown = (
        left,
        left + (right - left) * cols * k / width,
        top + (bottom - top) * rows * k / height,
        top,
    )
    return mean, centre, shown


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
