"""Signed distance primitives in millimetres (torch, vectorised) and their smooth union."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


def smooth_union(a: torch.Tensor, b: torch.Tensor, k_mm: float) -> torch.Tensor:
    """Polynomial smooth minimum of two SDFs (Quilez):

    h = clamp(½ + ½(b − a)/k, 0, 1),   d = b·(1 − h) + a·h − k·h·(1 − h).

    Equals min(a, b) where |a − b| ≥ k and is smooth in between (a fillet of radius ≈ k).
    """
    if k_mm <= 0:
        return torch.minimum(a, b)
    h = (0.5 + 0.5 * (b - a) / k_mm).clamp(0.0, 1.0)
    return b * (1.0 - h) + a * h - k_mm * h * (1.0 - h)


def _box_sdf(local: torch.Tensor, half: torch.Tensor, radius: float) -> torch.Tensor:
    """Rounded box centred at the origin: d = |max(q, 0)| + min(max_i q_i, 0) − r with
    q = |p| − (half − r)."""
    q = local.abs() - (half - radius)
    outside = q.clamp(min=0.0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp(max=0.0)
    return outside + inside - radius


@dataclass(frozen=True)
class SegmentBox:
    """A rounded box spanning the segment start→end (its long axis u), ``half_v`` along the
    direction ``up`` made orthogonal to u, and ``half_w`` along w = u × v. Corner radius
    ``radius_mm``."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    up: tuple[float, float, float]
    half_v: float
    half_w: float
    radius_mm: float

    def _frame(self) -> tuple[np.ndarray, np.ndarray, float]:
        start, end = np.asarray(self.start, float), np.asarray(self.end, float)
        u = end - start
        length = float(np.linalg.norm(u))
        u = u / length
        up = np.asarray(self.up, float)
        v = up - up.dot(u) * u
        v = v / np.linalg.norm(v)
        w = np.cross(u, v)
        return (start + end) / 2, np.stack([u, v, w]), length

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        center, rot, length = self._frame()
        local = (points - torch.as_tensor(center, dtype=points.dtype)) @ torch.as_tensor(
            rot.T, dtype=points.dtype
        )
        half = torch.tensor([length / 2, self.half_v, self.half_w], dtype=points.dtype)
        return _box_sdf(local, half, self.radius_mm)

    def bounds(self) -> np.ndarray:
        center, rot, length = self._frame()
        half = np.array([length / 2, self.half_v, self.half_w])
        extent = np.abs(rot.T) @ half
        return np.stack([center - extent, center + extent])


def _radius_ratio(
    k0: torch.Tensor, k1: torch.Tensor, smallest: float | torch.Tensor
) -> torch.Tensor:
    """k0/k1 = |p/r| / |p/r²|, a radius between the smallest and largest semi-axis; at the
    centre (0/0) the smallest semi-axis."""
    tiny = k1 < 1e-9
    ratio = k0 / torch.where(tiny, 1.0, k1)
    return torch.where(tiny, torch.as_tensor(smallest, dtype=k0.dtype), ratio)


@dataclass(frozen=True)
class Ellipsoid:
    """Axis-aligned ellipsoid, SDF bound (Quilez): k0 = |p/r|, k1 = |p/r²|, d = k0(k0 − 1)/k1
    (written (k0 − 1)·(k0/k1) so that the centre, 0/0, is defined)."""

    center: tuple[float, float, float]
    radii: tuple[float, float, float]

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        radii = torch.as_tensor(self.radii, dtype=points.dtype)
        p = points - torch.as_tensor(self.center, dtype=points.dtype)
        k0 = (p / radii).norm(dim=-1)
        k1 = (p / radii**2).norm(dim=-1)
        return (k0 - 1.0) * _radius_ratio(k0, k1, min(self.radii))

    def bounds(self) -> np.ndarray:
        c, r = np.asarray(self.center, float), np.asarray(self.radii, float)
        return np.stack([c - r, c + r])


@dataclass(frozen=True)
class VertebralBody:
    """Elliptic cylinder along z centred at the origin with rounded end-plate rims and a concave
    waist: semi-axes a(z) = a₀·(1 − waist·(1 − (z/h)²)), likewise b. The cross-section SDF is
    the ellipse bound d₂ = k0(k0 − 1)/k1 and the extrusion is
    d = min(max(d₂ + r, |z| − h + r), 0) + |max((d₂ + r, |z| − h + r), 0)| − r."""

    width_mm: float
    depth_mm: float
    height_mm: float
    waist: float
    rim_radius_mm: float

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        x, y, z = points.unbind(-1)
        half_h = self.height_mm / 2
        zr = (z / half_h).clamp(-1.0, 1.0)
        scale = 1.0 - self.waist * (1.0 - zr * zr)
        a = self.width_mm / 2 * scale
        b = self.depth_mm / 2 * scale
        k0 = torch.sqrt((x / a) ** 2 + (y / b) ** 2)
        k1 = torch.sqrt((x / a**2) ** 2 + (y / b**2) ** 2)
        d2 = (k0 - 1.0) * _radius_ratio(k0, k1, torch.minimum(a, b))
        r = self.rim_radius_mm
        w = torch.stack([d2 + r, z.abs() - half_h + r], dim=-1)
        return w.max(dim=-1).values.clamp(max=0.0) + w.clamp(min=0.0).norm(dim=-1) - r

    def bounds(self) -> np.ndarray:
        half = np.array([self.width_mm / 2, self.depth_mm / 2, self.height_mm / 2])
        return np.stack([-half, half])


Primitive = SegmentBox | Ellipsoid | VertebralBody


def union_sdf(
    primitives: tuple[Primitive, ...], points: torch.Tensor, blend_mm: float
) -> torch.Tensor:
    """Smooth union of the primitives' SDFs at ``points`` (..., 3), left to right."""
    result = primitives[0].sdf(points)
    for primitive in primitives[1:]:
        result = smooth_union(result, primitive.sdf(points), blend_mm)
    return result
