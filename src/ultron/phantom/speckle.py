"""A world-anchored 3D field of sub-resolution scatterers (the source of speckle).

Each node of the infinite lattice ``voxel_mm · (i, j, k)`` holds, per tissue, a complex
scatterer amplitude drawn from a counter-based hash of (seed, i, j, k) — not from a sequential
random stream — so a world point has the same scatterers whichever sweeps are simulated, and
every view of it sees correlated speckle. The field is read with trilinear interpolation.

Per node, with λ = density · voxel³ expected scatterers, the amplitude is

    s = a · g · √max(λ, 1) · [u < min(λ, 1)],

g a unit-variance circular complex Gaussian (the incoherent sum of many randomly phased
scatterers), a the tissue's per-scatterer amplitude and u uniform: dense media (λ ≥ 1) give
fully developed (Rayleigh) speckle, sparse ones isolated bright points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ultron.data.geometry import as_bounds_mm
from ultron.errors import argument_error
from ultron.phantom.tissue import Tissue

_MASK64 = (1 << 64) - 1


def _signed(value: int) -> int:
    """A 64-bit unsigned constant as the int64 with the same bits."""
    value &= _MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


_GOLDEN = _signed(0x9E3779B97F4A7C15)
_MIX1 = _signed(0xBF58476D1CE4E5B9)
_MIX2 = _signed(0x94D049BB133111EB)


def _shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 bit patterns."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def splitmix64(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64 finaliser (Steele et al. 2014) on int64 tensors (wrapping arithmetic):
    z = x + φ; z = (z ⊕ z≫30)·m₁; z = (z ⊕ z≫27)·m₂; z ⊕ z≫31."""
    z = x + _GOLDEN
    z = (z ^ _shift_right(z, 30)) * _MIX1
    z = (z ^ _shift_right(z, 27)) * _MIX2
    return z ^ _shift_right(z, 31)


def hashed_uniform(
    seed: int, i: torch.Tensor, j: torch.Tensor, k: torch.Tensor, stream: int
) -> torch.Tensor:
    """Uniform numbers in (0, 1) from a hash of (seed, i, j, k, stream), float64, broadcast."""
    h = splitmix64(torch.full((), _signed(seed * 0x2545F4914F6CDD1D + stream), dtype=torch.int64))
    h = splitmix64(h ^ i)
    h = splitmix64(h ^ j)
    h = splitmix64(h ^ k)
    h = splitmix64(h + stream)
    top = _shift_right(h, 11).to(torch.float64)  # 53 random bits
    return (top + 0.5) / float(1 << 53)


@dataclass(frozen=True)
class ScattererField:
    """Complex scatterer amplitudes of gel and bone on a world lattice box.

    ``values`` is (4, nz, ny, nx) float32: (gel real, gel imaginary, bone real, bone
    imaginary); node (i, j, k) of the box lies at ``origin_mm + voxel_mm · (i, j, k)``.
    """

    values: torch.Tensor
    origin_mm: tuple[float, float, float]
    voxel_mm: float

    def sample(self, points_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear (gel, bone) complex amplitudes at world points (..., 3), each (..., 2)."""
        points = torch.as_tensor(points_mm)
        if not torch.is_floating_point(points):
            points = points.to(torch.float64)
        nz, ny, nx = self.values.shape[1:]
        size = torch.tensor([nx - 1, ny - 1, nz - 1], dtype=points.dtype)
        origin = torch.as_tensor(self.origin_mm, dtype=points.dtype)
        grid = 2.0 * (points - origin) / (size * self.voxel_mm) - 1.0
        out = F.grid_sample(
            self.values[None],
            grid.to(torch.float32).reshape(1, -1, 1, 1, 3),
            mode="bilinear",
            padding_mode="zeros",
            align_corners=True,
        )  # (1, 4, P, 1, 1)
        channels = out[0, :, :, 0, 0].T.reshape(*points.shape[:-1], 4)
        return channels[..., :2], channels[..., 2:]


def scatterer_field(
    box_mm: np.ndarray | torch.Tensor, voxel_mm: float, gel: Tissue, bone: Tissue, seed: int
) -> ScattererField:
    """The world-anchored scatterer field over ``box_mm`` (2, 3) (see the module docstring)."""
    box = as_bounds_mm(box_mm, "box_mm")
    if not (math.isfinite(voxel_mm) and voxel_mm > 0):
        raise argument_error("voxel_mm", f"expected a positive lattice spacing, got {voxel_mm}")
    lo = np.floor(box[0] / voxel_mm).astype(np.int64) - 1
    hi = np.ceil(box[1] / voxel_mm).astype(np.int64) + 1
    n_nodes = int(np.prod(hi - lo + 1))
    if n_nodes > 200_000_000:
        raise argument_error("voxel_mm", f"{voxel_mm} mm gives {n_nodes} lattice nodes; too many")
    i = torch.arange(lo[0], hi[0] + 1)[None, None, :]
    j = torch.arange(lo[1], hi[1] + 1)[None, :, None]
    k = torch.arange(lo[2], hi[2] + 1)[:, None, None]
    radius = torch.sqrt(-2.0 * torch.log(hashed_uniform(seed, i, j, k, 1)))
    angle = 2.0 * math.pi * hashed_uniform(seed, i, j, k, 2)
    presence = hashed_uniform(seed, i, j, k, 3)
    # Box–Muller: (r cos φ, r sin φ) are independent N(0, 1); /√2 gives E|g|² = 1.
    g_re = (radius * torch.cos(angle) / math.sqrt(2.0)).to(torch.float32)
    g_im = (radius * torch.sin(angle) / math.sqrt(2.0)).to(torch.float32)
    del radius, angle
    channels = []
    for tissue in (gel, bone):
        lam = tissue.scatterer_density_per_mm3 * voxel_mm**3
        scale = tissue.scatterer_amplitude * math.sqrt(max(lam, 1.0))
        mask = (presence < min(lam, 1.0)).to(torch.float32) * scale
        channels += [g_re * mask, g_im * mask]
    values = torch.stack(channels).contiguous()
    return ScattererField(values, tuple(float(v) for v in lo * voxel_mm), float(voxel_mm))
