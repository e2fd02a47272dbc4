"""Vectorised probe geometry in torch: pixels, scanlines and samples in world millimetres.

Frames (METHOD.md §1): probe +x is lateral (along image columns), +y is along the beam (image
rows, deeper), +z is elevation. Pixel (r, c) of an H × W frame from a probe of width W_mm and
depth D_mm lies at probe point

    p(r, c) = ((c − W/2)·W_mm/W,  r·D_mm/H,  0)

and at world point ``probe_to_world @ [p, 1]``. The scanline of column c starts at
((c − W/2)·W_mm/W, 0, 0) and runs along probe +y; it is sampled at the image rows, with the
physical step Δ = D_mm/H.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.errors import argument_error


def as_pose_tensor(
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    name: str = "probe_to_world",
) -> torch.Tensor:
    """Poses as a tensor of shape (N, 4, 4); a single (4, 4) pose becomes (1, 4, 4) and a list
    or tuple of pose arrays (e.g. one per sweep) is concatenated."""
    if isinstance(probe_to_world, list | tuple):
        probe_to_world = np.concatenate([np.asarray(p) for p in probe_to_world], axis=0)
    if torch.is_tensor(probe_to_world):
        poses = probe_to_world
    else:
        poses = torch.as_tensor(np.asarray(probe_to_world))
    if poses.ndim == 2:
        poses = poses.unsqueeze(0)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise argument_error(name, f"expected shape (N, 4, 4), got {tuple(poses.shape)}")
    if not torch.is_floating_point(poses):
        poses = poses.to(torch.float64)
    return poses


def as_bounds_mm(bounds_mm: np.ndarray | torch.Tensor, name: str = "bounds_mm") -> np.ndarray:
    """A finite float64 (2, 3) [min, max] box with min ≤ max on every axis."""
    box = np.asarray(bounds_mm, dtype=np.float64)
    if box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] < box[0]).any():
        raise argument_error(name, f"expected a finite (2, 3) [min, max] box, got {box.tolist()}")
    return box


def median_frame_gap_mm(probe_to_world: np.ndarray) -> float:
    """Median distance between the origins of consecutive frames (N ≥ 2 poses), mm."""
    origins = np.asarray(probe_to_world)[:, :3, 3]
    return float(np.median(np.linalg.norm(np.diff(origins, axis=0), axis=1)))


def probe_points_mm(rows: torch.Tensor, cols: torch.Tensor, probe: ProbeGeometry) -> torch.Tensor:
    """Probe-frame points of pixels (rows, cols) (broadcast together), shape (..., 3), in mm.

    p = ((c − W/2)·W_mm/W, r·D_mm/H, 0). Rows and columns may be fractional.
    """
    rows, cols = torch.broadcast_tensors(torch.as_tensor(rows), torch.as_tensor(cols))
    dtype = rows.dtype if torch.is_floating_point(rows) else torch.get_default_dtype()
    x = (cols.to(dtype) - probe.width_px / 2) * probe.lateral_spacing_mm
    y = rows.to(dtype) * probe.axial_spacing_mm
    return torch.stack([x, y, torch.zeros_like(x)], dim=-1)


def probe_mm_to_pixel(
    x_mm: np.ndarray, y_mm: np.ndarray, probe: ProbeGeometry
) -> tuple[np.ndarray, np.ndarray]:
    """Fractional (rows, cols) of probe-frame points (x, y) in mm, the inverse of
    :func:`probe_points_mm`: r = y·H/D_mm, c = x·W/W_mm + W/2 (NumPy, broadcast)."""
    rows = np.asarray(y_mm) / probe.axial_spacing_mm
    cols = np.asarray(x_mm) / probe.lateral_spacing_mm + probe.width_px / 2
    return rows, cols


def apply_pose(probe_to_world: torch.Tensor, points_probe: torch.Tensor) -> torch.Tensor:
    """Map probe-frame points to world, one set per pose: x_world[n] = R[n]·p[n] + t[n].

    ``probe_to_world`` is (N, 4, 4) and ``points_probe`` is (N, ..., 3): the leading axis pairs
    each point set with its pose. Returns (N, ..., 3) in the poses' dtype.
    """
    poses = as_pose_tensor(probe_to_world)
    points = torch.as_tensor(points_probe).to(poses.dtype)
    n = poses.shape[0]
    if points.ndim < 2 or points.shape[-1] != 3 or points.shape[0] != n:
        raise argument_error(
            "points_probe", f"expected ({n}, ..., 3) to match {n} poses, got {tuple(points.shape)}"
        )
    flat = points.reshape(n, -1, 3)
    world = flat @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3]
    return world.reshape(points.shape)


def pixel_to_world(
    probe_to_world: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, probe: ProbeGeometry
) -> torch.Tensor:
    """World points (N, ..., 3) of the same pixels (rows, cols), broadcast to (...), in each of N poses."""
    poses = as_pose_tensor(probe_to_world)
    points = probe_points_mm(rows, cols, probe).to(poses.dtype)
    return apply_pose(poses, points.unsqueeze(0).expand(poses.shape[0], *points.shape))


def frame_pixels_world(probe_to_world: torch.Tensor, probe: ProbeGeometry) -> torch.Tensor:
    """World points of every pixel of every frame, shape (N, H, W, 3)."""
    rows = torch.arange(probe.height_px, dtype=torch.float64)[:, None]
    cols = torch.arange(probe.width_px, dtype=torch.float64)[None, :]
    return pixel_to_world(probe_to_world, rows, cols, probe)


def scanline_rays(
    probe_to_world: torch.Tensor, probe: ProbeGeometry, cols: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions of scanlines in world mm, each (N, C, 3).

    The scanline of column c starts at probe point ((c − W/2)·W_mm/W, 0, 0) and runs along the
    probe's +y axis; ``cols`` defaults to all W columns.
    """
    poses = as_pose_tensor(probe_to_world)
    if cols is None:
        cols = torch.arange(probe.width_px, dtype=poses.dtype)
    cols = torch.as_tensor(cols).to(poses.dtype)
    origins = pixel_to_world(poses, torch.zeros_like(cols), cols, probe)
    direction = poses[:, :3, 1]
    direction = direction / direction.norm(dim=-1, keepdim=True)
    directions = direction[:, None, :].expand_as(origins)
    return origins, directions


def sample_depths_mm(
    n_samples: int, step_mm: float, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Depths k·Δ of the samples k = 0..n−1 along a scanline, mm (ordered, increasing)."""
    if n_samples < 1:
        raise argument_error("n_samples", f"expected ≥ 1, got {n_samples}")
    if not step_mm > 0:
        raise argument_error("step_mm", f"expected a positive step, got {step_mm}")
    return torch.arange(n_samples, dtype=dtype) * step_mm


def scanline_sample_points(
    origins: torch.Tensor, directions: torch.Tensor, n_samples: int, step_mm: float
) -> torch.Tensor:
    """Sample points x_k = o + k·Δ·d along each ray, shape (..., n_samples, 3), ordered by depth."""
    if origins.shape != directions.shape or origins.shape[-1] != 3:
        raise argument_error(
            "origins/directions",
            f"expected equal (..., 3) shapes, got {tuple(origins.shape)} and {tuple(directions.shape)}",
        )
    depths = sample_depths_mm(n_samples, step_mm, origins.dtype)
    return origins[..., None, :] + depths[:, None] * directions[..., None, :]


def field_of_view_bounds_mm(
    poses: np.ndarray | torch.Tensor | Sequence[np.ndarray], probe: ProbeGeometry
) -> torch.Tensor:
    """Axis-aligned bounding box (2, 3) = [min, max] of every pixel centre the probe saw, mm.

    A frame is a planar rectangle, so its four corner pixels bound it exactly.
    """
    corners = field_of_view_corners_mm(poses, probe)
    return torch.stack([corners.min(dim=0).values, corners.max(dim=0).values])


def field_of_view_corners_mm(
    poses: np.ndarray | torch.Tensor | Sequence[np.ndarray], probe: ProbeGeometry
) -> torch.Tensor:
    """World points (4N, 3), float64, of the four corner pixel centres of every frame: the
    convex hull of the field of view (a frame is a planar rectangle)."""
    tensor = as_pose_tensor(poses, "poses").to(torch.float64)
    rows = torch.tensor(
        [0.0, 0.0, probe.height_px - 1.0, probe.height_px - 1.0], dtype=torch.float64
    )
    cols = torch.tensor([0.0, probe.width_px - 1.0, 0.0, probe.width_px - 1.0], dtype=torch.float64)
    return pixel_to_world(tensor, rows, cols, probe).reshape(-1, 3)


@dataclass(frozen=True)
class UnitCube:
    """Isotropic world-mm ↔ normalised-cube transform: u = A (x − center_mm) / half_extent_mm.

    One scale for all axes (unlike the per-axis min-max of the original code, which distorts
    voxels and positional-encoding bandwidth). The box of interest maps inside [−1, 1]³.
    ``axes`` (rows: the cube's axes as world unit vectors, a rotation A) orients the cube;
    None keeps the world's axes (A = I, and no product is taken). Arithmetic is done in
    float64: with A = I, float32 world coordinates mapped to float64 unit coordinates and back
    are recovered bit-exactly, float64 ones to within a few ulp.
    """

    center_mm: tuple[float, float, float]
    half_extent_mm: float
    axes: tuple[tuple[float, float, float], ...] | None = None

    def __post_init__(self) -> None:
        if len(self.center_mm) != 3 or not all(np.isfinite(self.center_mm)):
            raise argument_error("center_mm", f"expected 3 finite numbers, got {self.center_mm}")
        if not (np.isfinite(self.half_extent_mm) and self.half_extent_mm > 0):
            raise argument_error(
                "half_extent_mm", f"expected a positive number, got {self.half_extent_mm}"
            )
        if self.axes is not None:
            axes = np.asarray(self.axes, dtype=np.float64)
            if (
                axes.shape != (3, 3)
                or not np.isfinite(axes).all()
                or not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9)
                or not np.linalg.det(axes) > 0
            ):
                raise argument_error("axes", f"expected a 3 × 3 rotation (rows), got {self.axes}")

    @classmethod
    def from_points(
        cls,
        points_mm: torch.Tensor | np.ndarray,
        margin: float = 0.05,
        axes: np.ndarray | None = None,
    ) -> UnitCube:
        """The cube along ``axes`` (None: the world's) centred on the box of ``points_mm``
        (M, 3) in those axes, whose largest half-side, grown by ``margin``, maps to 1. With
        ``axes=None`` it is :meth:`from_bounds` of the points' bounds."""
        points = _as_points(points_mm)
        if margin < 0:
            raise argument_error("margin", f"expected ≥ 0, got {margin}")
        rotation = None if axes is None else np.asarray(axes, dtype=np.float64)
        local = points if rotation is None else points @ rotation.T
        low, high = local.min(axis=0), local.max(axis=0)
        center = (low + high) / 2
        if rotation is not None:
            center = center @ rotation
        half = float((high - low).max() / 2 * (1 + margin))
        oriented = None if rotation is None else tuple(tuple(float(v) for v in r) for r in rotation)
        return cls(tuple(float(c) for c in center), max(half, 1e-6), oriented)

    def points_extent(
        self, points_mm: torch.Tensor | np.ndarray, margin: float = 0.05
    ) -> tuple[float, float, float]:
        """:meth:`box_extent` of the box of ``points_mm`` (M, 3) in this cube's axes."""
        points = _as_points(points_mm) - np.asarray(self.center_mm)
        if self.axes is not None:
            points = points @ np.asarray(self.axes).T
        half = np.abs(points).max(axis=0)
        grown = half + margin * float(half.max())
        return tuple(float(min(1.0, max(g / self.half_extent_mm, 1e-6))) for g in grown)

    @classmethod
    def from_bounds(cls, bounds_mm: torch.Tensor | np.ndarray, margin: float = 0.05) -> UnitCube:
        """The cube centred on a (2, 3) box whose largest half-side, grown by ``margin``, maps to 1."""
        return cls.from_points(as_bounds_mm(bounds_mm), margin)

    def box_extent(
        self, bounds_mm: torch.Tensor | np.ndarray, margin: float = 0.05
    ) -> tuple[float, float, float]:
        """Half-extent per axis (x, y, z), in unit-cube units, of a (2, 3) box about this cube's
        centre, each grown by ``margin`` × the box's largest half-side (as :meth:`from_bounds`
        grows the cube) and at most 1: the cube's own box gives 1 on its longest axis."""
        box = as_bounds_mm(bounds_mm)
        corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1)
                            for k in (0, 1)])  # fmt: skip
        return self.points_extent(corners, margin)

    def _center(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.center_mm, dtype=torch.float64, device=like.device)

    def _rotation(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.axes, dtype=torch.float64, device=like.device)

    def to_unit(self, points_mm: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
        """World mm → unit cube; returns ``dtype`` (default: the input's floating dtype)."""
        points = torch.as_tensor(points_mm)
        out_dtype = dtype or (points.dtype if torch.is_floating_point(points) else torch.float64)
        unit = (points.to(torch.float64) - self._center(points)) / self.half_extent_mm
        if self.axes is not None:
            unit = unit @ self._rotation(unit).T
        return unit.to(out_dtype)

    def to_world(self, points_unit: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Unit cube → world mm; returns ``dtype`` (default: the input's floating dtype)."""
        points = torch.as_tensor(points_unit)
        out_dtype = dtype or (points.dtype if torch.is_floating_point(points) else torch.float64)
        points = points.to(torch.float64)
        if self.axes is not None:
            points = points @ self._rotation(points)
        world = points * self.half_extent_mm + self._center(points)
        return world.to(out_dtype)

    def to_dict(self) -> dict[str, object]:
        data: dict[str, object] = {
            "center_mm": list(self.center_mm),
            "half_extent_mm": self.half_extent_mm,
        }
        if self.axes is not None:
            data["axes"] = [list(row) for row in self.axes]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> UnitCube:
        """From :meth:`to_dict`'s form; a cube saved before ``axes`` existed had the world's."""
        center = data.get("center_mm")
        half = data.get("half_extent_mm")
        axes = data.get("axes")
        if not isinstance(center, list | tuple) or not isinstance(half, int | float):
            raise argument_error("unit_cube", f"expected center_mm and half_extent_mm, got {data}")
        if axes is not None and not (
            isinstance(axes, list | tuple) and all(isinstance(r, list | tuple) for r in axes)
        ):
            raise argument_error("unit_cube", f"expected axes as three rows, got {axes}")
        rows = None if axes is None else tuple(tuple(float(v) for v in r) for r in axes)
        return cls(tuple(float(c) for c in center), float(half), rows)


def _as_points(points_mm: torch.Tensor | np.ndarray) -> np.ndarray:
    """``points_mm`` as a float64 (M, 3) array with M ≥ 1 of finite values."""
    points = np.asarray(
        points_mm.detach().cpu() if torch.is_tensor(points_mm) else points_mm, dtype=np.float64
    )
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise argument_error("points_mm", f"expected (M, 3) with M ≥ 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise argument_error("points_mm", "contains NaN or inf")
    return points
