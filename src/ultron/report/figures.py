"""Report figures as PNG bytes, drawn offscreen (matplotlib Agg, no pyplot state, no GPU).

* :func:`mesh_distance_figure` — reconstruction next to the reference, coloured by distance;
* :func:`frames_figure` — recorded vs rendered B-mode with the field's θ and T maps;
* :func:`label_masks_figure` — the labelled frames used, with their masks overlaid;
* :func:`loss_curves_figure` — training loss against step, one panel per curve.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ultron.errors import argument_error
from ultron.metrics.surface import point_to_surface_distances, sample_surface
from ultron.report.frame_figures import frames_figure, label_masks_figure
from ultron.report.plotting import figure_png, new_figure, place_grid, top_title

__all__ = ["frames_figure", "label_masks_figure", "loss_curves_figure", "mesh_distance_figure"]

#: Orthographic views: (title, viewing direction, horizontal axis, vertical axis).
#: ultron's phantoms use x lateral, y posterior → anterior (the beam), z caudal → cranial.
VIEWS = (
    ("posterior view (along +y)", np.array([0.0, 1.0, 0.0]), 0, 2),
    ("lateral view (along −x)", np.array([-1.0, 0.0, 0.0]), 1, 2),
)
_AXIS_NAMES = ("x", "y", "z")
_GREY = np.array([1.0, 1.0, 1.0])
_BLUE_GREY = np.array([0.75, 0.85, 1.0])


def _check_mesh(mesh: Any, name: str) -> None:
    if not (hasattr(mesh, "faces") and hasattr(mesh, "vertices") and hasattr(mesh, "area")):
        raise argument_error(name, f"expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise argument_error(name, "mesh is empty (no triangles with area)")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise argument_error(name, "vertices contain NaN or inf")


def _shade(normals: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Grey level per point from the angle between its face normal and the view (two-sided)."""
    return 0.3 + 0.6 * np.abs(normals @ direction)


#: Cells along the longer side of the raster a point cloud is drawn into: about a panel's own
#: pixels (3.4 in at 90 dpi, 306). Each point covers 2 × 2 cells, a dot about as wide as the
#: scatter markers it replaced (1.1 pt), so that a lattice of mesh vertices leaves no gaps.
RASTER_SIDE = 300
_FOOTPRINT = ((0, 0), (1, 0), (0, 1), (1, 1))


def _draw_points(
    ax, points: np.ndarray, direction: np.ndarray, h: int, v: int, limits: tuple[tuple, tuple],
    c: np.ndarray, **colour,
):  # fmt: skip
    """Draw ``points`` projected on axes (h, v) within ``limits`` into a raster of
    :data:`RASTER_SIDE` cells on its longer side, each point on 2 × 2 cells: a cell shows the
    nearest point along ``direction`` that covers it (a z-buffer: what the painter's algorithm
    showed), a cell without one is transparent. ``c`` is (N, 3) RGB, or (N,) values coloured
    through ``colour``'s ``cmap``, ``vmin`` and ``vmax``. Returns the ``AxesImage`` (the colour
    bar's mappable). One image, not a marker per point: drawing a scatter of 20 000–30 000
    points took most of a report's figure time."""
    (x0, x1), (y0, y1) = limits
    cell = max(x1 - x0, y1 - y0) / RASTER_SIDE
    nx, ny = max(1, math.ceil((x1 - x0) / cell)), max(1, math.ceil((y1 - y0) / cell))
    ix = np.floor((points[:, h] - x0) / cell - 0.5).astype(np.int64)  # the 2 × 2 block's corner
    iy = np.floor((points[:, v] - y0) / cell - 0.5).astype(np.int64)
    depth = points @ direction
    pixel = np.concatenate([
        np.clip(iy + dy, 0, ny - 1) * nx + np.clip(ix + dx, 0, nx - 1) for dx, dy in _FOOTPRINT
    ])  # fmt: skip
    source = np.tile(np.arange(len(points)), len(_FOOTPRINT))
    order = np.lexsort((depth[source], pixel))  # by cell, nearest (least depth) first
    pixel_sorted = pixel[order]
    first = order[np.r_[True, pixel_sorted[1:] != pixel_sorted[:-1]]]
    cells, nearest = pixel[first], source[first]
    values = np.asarray(c)
    if values.ndim == 2:  # RGB: an RGBA image, alpha 0 where no point falls
        image = np.zeros((ny * nx, 4), dtype=np.float32)
        image[cells, :3] = values[nearest]
        image[cells, 3] = 1.0
        image = image.reshape(ny, nx, 4)
    else:  # values: NaN where no point falls (drawn transparent)
        image = np.full(ny * nx, np.nan, dtype=np.float32)
        image[cells] = values[nearest]
        image = image.reshape(ny, nx)
    extent = (x0, x0 + nx * cell, y0, y0 + ny * cell)
    return ax.imshow(image, origin="lower", extent=extent, interpolation="nearest", **colour)


def _view_limits(clouds: Sequence[np.ndarray], h: int, v: int) -> tuple[tuple, tuple]:
    """Padded (x limits, y limits) of the projected clouds on axes (h, v)."""
    stacked = np.concatenate(clouds, axis=0)
    low, high = stacked.min(axis=0), stacked.max(axis=0)
    pad = 0.04 * float(max(high[h] - low[h], high[v] - low[v], 1.0))
    return (low[h] - pad, high[h] + pad), (low[v] - pad, high[v] + pad)


def _style_axes(ax, limits: tuple[tuple, tuple], h: int, v: int, title: str) -> None:
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect("equal")
    ax.set_xlabel(f"{_AXIS_NAMES[h]} (mm)", fontsize=8)
    ax.set_ylabel(f"{_AXIS_NAMES[v]} (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title(title, fontsize=8)


def _check_distance_figure_args(
    mesh, reference, title: str, n_points: int, seed: int, clip_mm: float | None
) -> None:
    """:func:`mesh_distance_figure`'s arguments, each refused with an error naming it."""
    _check_mesh(mesh, "mesh")
    if reference is not None:
        _check_mesh(reference, "reference")
    if not isinstance(title, str):
        raise argument_error("title", "expected a string")
    if isinstance(n_points, bool) or not isinstance(n_points, int) or not 1 <= n_points <= 10**6:
        raise argument_error("n_points", f"expected an integer in [1, 1e6], got {n_points!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise argument_error("seed", f"expected a non-negative integer, got {seed!r}")
    if clip_mm is not None and not (isinstance(clip_mm, int | float) and clip_mm > 0):
        raise argument_error("clip_mm", f"expected a positive number or None, got {clip_mm!r}")


def _distance_heading_and_bar(
    fig, title: str, distances, mappable, grid_of_views: bool, clip_mm: float | None, vmax
) -> None:
    """The figure's heading (with the distance summary) and, with distances, the colour bar."""
    heading = title if title else "reconstruction"
    if distances is None:
        heading += " (no reference)"
    else:
        heading += (
            f"  —  sampled distance to reference: mean {distances.mean():.2f} mm, "
            f"95th pct {np.percentile(distances, 95):.2f} mm, max {distances.max():.2f} mm"
        )
    top_title(fig, heading)
    if grid_of_views:  # rows: views; columns: reference, reconstruction
        place_grid(fig, len(VIEWS), 2, (0.6, 0.15, 0.45, 0.65), (0.65, 0.6),
                   0.86 if mappable is not None else 1.0)  # fmt: skip
    else:
        fig.subplots_adjust(left=0.07, right=0.97, bottom=0.15, top=0.84, wspace=0.25)
    if mappable is not None:
        which = (
            f"clipped at {clip_mm:g} mm"
            if clip_mm is not None
            else (f"clipped at the 95th percentile, {vmax:.2f} mm")
        )
        cax = fig.add_axes((0.89, 0.12, 0.022, 0.76))
        bar = fig.colorbar(mappable, cax=cax, extend="max")
        bar.set_label(f"distance to reference (mm), {which}", fontsize=8)
        bar.ax.tick_params(labelsize=7)


def mesh_distance_figure(
    mesh,
    reference,
    title: str,
    n_points: int = 20_000,
    seed: int = 0,
    clip_mm: float | None = 10.0,
) -> bytes:
    """The reconstruction next to the reference (posterior and lateral orthographic views of
    ``n_points`` area-uniform surface samples), the reconstruction coloured by its
    point-to-surface distance to the reference in mm. The colour range ends at ``clip_mm``
    (``None``: at the 95th percentile of the distances); the colour bar says which.
    With ``reference=None`` the mesh is shown alone, shaded grey, marked "no reference"."""
    _check_distance_figure_args(mesh, reference, title, n_points, seed, clip_mm)
    points, faces = sample_surface(mesh, n_points, seed=2 * seed)
    normals = np.asarray(mesh.face_normals)[faces]
    columns: list[tuple[str, np.ndarray, np.ndarray]] = []
    distances = None
    if reference is not None:
        ref_points, ref_faces = sample_surface(reference, n_points, seed=2 * seed + 1)
        ref_normals = np.asarray(reference.face_normals)[ref_faces]
        distances = point_to_surface_distances(points, reference)
        columns.append(("reference", ref_points, ref_normals))
    columns.append(("reconstruction", points, normals))

    clouds = [pts for _, pts, _ in columns]
    limits = [_view_limits(clouds, h, v) for _, _, h, v in VIEWS]
    ratios = [float(np.clip((y[1] - y[0]) / (x[1] - x[0]), 0.3, 3.0)) for x, y in limits]
    panel_in = 3.4
    n_cols = len(columns)
    bar_in = 1.4 if distances is not None else 0.4
    if n_cols > 1:  # rows: views; columns: reference, reconstruction
        fig = new_figure(panel_in * n_cols + bar_in, sum(panel_in * r + 0.8 for r in ratios) + 0.5)
        grid = fig.add_gridspec(len(VIEWS), n_cols, height_ratios=ratios)
    else:  # the mesh alone: views side by side
        widths = [panel_in / r for r in ratios]
        fig = new_figure(sum(widths) + 0.9 * len(VIEWS) + bar_in, panel_in + 1.8)
        grid = fig.add_gridspec(1, len(VIEWS), width_ratios=widths)
    vmax = clip_mm
    if distances is not None and clip_mm is None:
        vmax = max(float(np.percentile(distances, 95)), 1e-3)
    mappable, axes = None, []
    for row, (view_title, direction, h, v) in enumerate(VIEWS):
        for col, (name, pts, nrm) in enumerate(columns):
            ax = fig.add_subplot(grid[row, col] if n_cols > 1 else grid[0, row])
            axes.append(ax)
            if name == "reconstruction" and distances is not None:
                mappable = _draw_points(ax, pts, direction, h, v, limits[row], c=distances,
                                       cmap="viridis", vmin=0.0, vmax=vmax)  # fmt: skip
            else:
                tint = _GREY if name == "reference" else _BLUE_GREY
                rgb = np.clip(_shade(nrm, direction)[:, None] * tint[None, :], 0.0, 1.0)
                _draw_points(ax, pts, direction, h, v, limits[row], c=rgb)
            _style_axes(ax, limits[row], h, v, f"{name}: {view_title}")
    _distance_heading_and_bar(fig, title, distances, mappable, n_cols > 1, clip_mm, vmax)
    return figure_png(fig)


def _curve_points(name: str, entries: Any) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(entries, Sequence) or isinstance(entries, str) or len(entries) == 0:
        raise argument_error("curves", f"curve {name!r}: expected a non-empty list of log entries")
    steps, losses = [], []
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping) or "step" not in entry or "loss" not in entry:
            raise argument_error(
                "curves", f"curve {name!r}: entry {i} lacks a 'step' or a 'loss' key"
            )
        try:
            step, loss = float(entry["step"]), float(entry["loss"])
        except (TypeError, ValueError):
            raise argument_error("curves", f"curve {name!r}: entry {i} is not numeric") from None
        steps.append(step)
        losses.append(loss)
    return np.asarray(steps), np.asarray(losses)


def loss_curves_figure(curves: Mapping[str, Sequence[Mapping[str, Any]]]) -> bytes:
    """One panel per curve name: ``loss`` against ``step`` from log entries (dicts with at
    least those two keys, e.g. run.json's ``occupancy_log`` or a field's ``train_log.jsonl``).
    The y axis is logarithmic when every finite loss is positive."""
    if not isinstance(curves, Mapping) or not curves:
        raise argument_error("curves", "expected a non-empty mapping of curve name → log entries")
    data = {str(name): _curve_points(str(name), entries) for name, entries in curves.items()}
    n = len(data)
    n_cols = min(n, 3)
    n_rows = math.ceil(n / n_cols)
    fig = new_figure(4.2 * n_cols, 3.0 * n_rows)
    for k, (name, (steps, losses)) in enumerate(data.items()):
        ax = fig.add_subplot(n_rows, n_cols, k + 1)
        finite = np.isfinite(losses)
        ax.plot(steps[finite], losses[finite], lw=1.2, marker="." if finite.sum() < 30 else None)
        if finite.any() and (losses[finite] > 0).all():
            ax.set_yscale("log")
        if not finite.all():
            ax.text(
                0.98, 0.95, f"{int((~finite).sum())} non-finite values hidden",
                transform=ax.transAxes, ha="right", va="top", fontsize=7, color="red",
            )  # fmt: skip
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("step", fontsize=8)
        ax.set_ylabel("loss", fontsize=8)
        ax.tick_params(which="both", labelsize=7)
        ax.grid(True, which="both", alpha=0.3)
    place_grid(fig, n_rows, n_cols, (0.8, 0.15, 0.5, 0.35), (0.9, 0.7))
    return figure_png(fig)
