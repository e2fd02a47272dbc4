"""PNG montage of simulated frames with their labels outlined (matplotlib, offscreen Agg)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from ultron import atomic
from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import probe_points_mm
from ultron.data.validation import LABEL_TARGET, LABEL_UNANNOTATED
from ultron.errors import argument_error


def pixel_centres_mm(probe: ProbeGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Lateral x (W,) and depth (H,) of the pixel centres in mm, ultron's one pixel ↔ probe-frame
    map (:func:`~ultron.data.geometry.probe_points_mm`: pixel (r, c) at ((c − W/2)·s_x, r·s_y))."""
    cols = torch.arange(probe.width_px, dtype=torch.float64)
    rows = torch.arange(probe.height_px, dtype=torch.float64)
    x_mm = probe_points_mm(torch.zeros(1, dtype=torch.float64), cols, probe)[:, 0]
    depth_mm = probe_points_mm(rows, torch.zeros(1, dtype=torch.float64), probe)[:, 1]
    return x_mm.numpy(), depth_mm.numpy()


def frame_extent_mm(probe: ProbeGeometry) -> tuple[float, float, float, float]:
    """matplotlib ``imshow`` extent (left, right, bottom, top) in mm that puts each pixel's
    centre where :func:`pixel_centres_mm` says: the image's edges lie half a pixel outside
    the first and last centres."""
    x_mm, depth_mm = pixel_centres_mm(probe)
    half_x, half_y = probe.lateral_spacing_mm / 2, probe.axial_spacing_mm / 2
    return (
        float(x_mm[0] - half_x),
        float(x_mm[-1] + half_x),
        float(depth_mm[-1] + half_y),
        float(depth_mm[0] - half_y),
    )


def preview_png(dataset: SweepDataset, frames_per_sweep: int = 4) -> bytes:
    """A montage: one row per sweep, ``frames_per_sweep`` evenly spaced frames, B-mode in grey
    at true aspect ratio (mm), bone labels outlined in red (unannotated frames are marked)."""
    if frames_per_sweep < 1:
        raise argument_error("frames_per_sweep", f"expected ≥ 1, got {frames_per_sweep}")
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    probe = dataset.probe
    n_rows, n_cols = len(dataset.sweeps), frames_per_sweep
    aspect = probe.depth_mm / probe.width_mm
    fig = Figure(figsize=(2.4 * n_cols, 2.4 * aspect * n_rows + 0.6), dpi=90)
    extent = frame_extent_mm(probe)
    x_mm, depth_mm = pixel_centres_mm(probe)
    for i, sweep in enumerate(dataset.sweeps):
        picks = np.linspace(0, sweep.n_frames - 1, n_cols + 2)[1:-1].round().astype(int)
        for j, frame in enumerate(picks):
            ax = fig.add_subplot(n_rows, n_cols, i * n_cols + j + 1)
            ax.imshow(sweep.images[frame], cmap="gray", vmin=0, vmax=255, extent=extent)
            if sweep.labels is not None:
                labels = sweep.labels[frame]
                if (labels == LABEL_UNANNOTATED).all():
                    ax.text(0, 5, "not annotated", color="yellow", ha="center", fontsize=7)
                elif (labels == LABEL_TARGET).any():
                    ax.contour(
                        x_mm,
                        depth_mm,
                        (labels == LABEL_TARGET).astype(float),
                        levels=[0.5],
                        colors="red",
                        linewidths=0.6,
                    )
            ax.set_title(f"{sweep.name} #{frame}", fontsize=8)
            ax.tick_params(labelsize=6)
            if j == 0:
                ax.set_ylabel("depth (mm)", fontsize=7)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return buffer.getvalue()


def write_preview(dataset: SweepDataset, path: Path | str, frames_per_sweep: int = 4) -> Path:
    """Write :func:`preview_png` atomically to ``path``."""
    path = Path(path)
    atomic.write_bytes(path, preview_png(dataset, frames_per_sweep))
    return path
