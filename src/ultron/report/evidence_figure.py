"""The observed-vs-inferred figure of a reconstruction (:mod:`ultron.mesh.evidence`).

Two orthographic views (those of :func:`~ultron.report.figures.mesh_distance_figure`) of the
surface's vertices: left, coloured observed (some frame saw it) or inferred (filled in where
no frame saw bone), with a legend and the share of each; right, coloured by the distance to
the nearest labelled bone pixel the method used.
"""

from __future__ import annotations

import numpy as np

from ultron.arguments import check_integer
from ultron.errors import argument_error
from ultron.report.figures import VIEWS, _draw_points, _style_axes, _view_limits
from ultron.report.plotting import figure_png, new_figure, place_grid, top_title

OBSERVED_RGB = np.array([0.16, 0.44, 0.78])  # blue
INFERRED_RGB = np.array([0.93, 0.49, 0.13])  # orange


def _check(vertices: np.ndarray, observed: np.ndarray, distance: np.ndarray) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise argument_error("vertices_mm", f"expected (V, 3) with V ≥ 1, got {vertices.shape}")
    if not np.isfinite(vertices).all():
        raise argument_error("vertices_mm", "vertices contain NaN or inf")
    if observed.shape != (len(vertices),):
        raise argument_error("observed", f"expected ({len(vertices)},), got {observed.shape}")
    if distance.shape != (len(vertices),):
        raise argument_error(
            "label_distance_mm", f"expected ({len(vertices)},), got {distance.shape}"
        )


def surface_evidence_figure(
    vertices_mm: np.ndarray,
    observed: np.ndarray,
    label_distance_mm: np.ndarray,
    title: str,
    max_points: int = 30_000,
    seed: int = 0,
) -> bytes:
    """PNG of the module's figure for a surface's vertices (V, 3), their ``observed`` flags
    (V,) and ``label_distance_mm`` (V,; +∞ when the method used no label: that panel then
    says so). At most ``max_points`` vertices are drawn (a seeded random subset)."""
    vertices = np.asarray(vertices_mm, dtype=np.float64)
    flags = np.asarray(observed).astype(bool)
    distance = np.asarray(label_distance_mm, dtype=np.float64)
    _check(vertices, flags, distance)
    check_integer("max_points", max_points, 1)
    if len(vertices) > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(vertices), max_points, False))
        vertices, flags, distance = vertices[pick], flags[pick], distance[pick]
    finite = np.isfinite(distance)
    vmax = max(float(np.percentile(distance[finite], 95)), 1e-3) if finite.any() else 1.0
    limits = [_view_limits([vertices], h, v) for _, _, h, v in VIEWS]
    ratios = [float(np.clip((y[1] - y[0]) / (x[1] - x[0]), 0.3, 3.0)) for x, y in limits]
    fig = new_figure(3.4 * 2 + 1.4, sum(3.4 * r + 0.8 for r in ratios) + 0.7)
    grid = fig.add_gridspec(len(VIEWS), 2, height_ratios=ratios)
    colours = np.where(flags[:, None], OBSERVED_RGB[None, :], INFERRED_RGB[None, :])
    mappable = None
    for row, (view_title, direction, h, v) in enumerate(VIEWS):
        ax = fig.add_subplot(grid[row, 0])
        _draw_points(ax, vertices, direction, h, v, limits[row], c=colours)
        _style_axes(ax, limits[row], h, v, f"observed / inferred: {view_title}")
        ax = fig.add_subplot(grid[row, 1])
        if finite.any():
            mappable = _draw_points(
                ax, vertices[finite], direction, h, v, limits[row], c=distance[finite],
                cmap="magma_r", vmin=0.0, vmax=vmax,
            )  # fmt: skip
        _style_axes(ax, limits[row], h, v, f"distance to labelled bone: {view_title}")
    share = float(flags.mean())
    handles = [
        _legend_patch(OBSERVED_RGB, f"observed ({100 * share:.0f} % of vertices)"),
        _legend_patch(INFERRED_RGB, f"inferred ({100 * (1 - share):.0f} %)"),
    ]
    fig.legend(handles=handles, loc="lower left", fontsize=8, frameon=False, ncol=2)
    top_title(fig, title)
    place_grid(fig, len(VIEWS), 2, (0.6, 0.15, 0.75, 0.65), (0.65, 0.6), 0.86)
    if mappable is not None:
        cax = fig.add_axes((0.89, 0.12, 0.022, 0.76))
        bar = fig.colorbar(mappable, cax=cax, extend="max")
        bar.set_label("distance to the nearest labelled bone pixel (mm)", fontsize=8)
        bar.ax.tick_params(labelsize=7)
    return figure_png(fig)


def _legend_patch(rgb: np.ndarray, label: str):
    from matplotlib.patches import Patch

    return Patch(facecolor=tuple(rgb), label=label)
