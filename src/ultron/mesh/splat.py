"""Forward compounding ("splatting") of scattered samples into a voxel grid, as PLUS does it.

One implementation for every compounding in ultron: B-mode grey levels (``ultron compound``,
:mod:`ultron.mesh.image_compounding`) and bone labels (the label-compounding baseline,
:mod:`ultron.mesh.compounding`). It follows PLUS's ``vtkPlusPasteSliceIntoVolume``:

* **nearest**: a sample goes to the voxel whose centre is nearest (weight 1);
* **linear**: a sample at fractional voxel index (i + fx, j + fy, k + fz) goes to its 8
  neighbours with the trilinear weights (1 − fx or fx)·(1 − fy or fy)·(1 − fz or fz)
  ("reverse trilinear interpolation"); neighbours outside the grid are dropped.

and reduces what a voxel received by

* **mean**: Σ w·value / Σ w (PLUS's MEAN, without its per-insertion rounding to the output type
  and its 16-bit accumulation buffer: here the sums are float64);
* **max**: the largest value received. With linear interpolation only neighbours of weight
  ≥ 1/8 take part (PLUS's MAXIMUM rule: a sample at the centre of a cell still reaches all 8);
  a voxel counts as filled once such a sample reached it, whatever its value (PLUS marks it
  only when the value raised the maximum, so a voxel that only ever saw 0 stays a "hole").

A voxel is *filled* when it received a sample (mean: a positive total weight); every other voxel
reads 0 (PLUS's background) and is a hole that :mod:`ultron.mesh.holes` may fill.

Memory: 16 bytes per voxel (mean: float64 weight and weighted sum; max: float32 maximum and
float64 weight), plus what one :meth:`Splatter.add` call is given (callers pass chunks of
frames) and, per call, one int64 index and weight per sample at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ultron.errors import argument_error
from ultron.mesh.grid import GridSpec

INTERPOLATIONS = ("nearest", "linear")
REDUCTIONS = ("mean", "max")
#: Smallest trilinear weight that takes part in MAX compounding (PLUS's ``minWeight``).
MAX_MIN_WEIGHT = 0.125


@dataclass(frozen=True)
class SplatConfig:
    """How samples are spread over voxels and combined.

    Attributes:
        interpolation: nearest (a pixel fills its nearest voxel) or linear (its 8 neighbours,
            with trilinear weights).
        reduce: How a voxel combines its pixels: mean (weighted) or max.
    """

    interpolation: str = "nearest"
    reduce: str = "mean"

    def __post_init__(self) -> None:
        if self.interpolation not in INTERPOLATIONS:
            raise argument_error(
                "interpolation",
                f"expected one of {', '.join(INTERPOLATIONS)}, got {self.interpolation!r}",
            )
        if self.reduce not in REDUCTIONS:
            raise argument_error(
                "reduce", f"expected one of {', '.join(REDUCTIONS)}, got {self.reduce!r}"
            )


def _as_numpy(array: np.ndarray | torch.Tensor) -> np.ndarray:
    return array.detach().cpu().numpy() if torch.is_tensor(array) else np.asarray(array)


class Splatter:
    """Accumulates samples (world points and values) into ``grid`` (see module doc).

    Call :meth:`add` once per chunk of samples, then :meth:`result`.
    """

    def __init__(self, grid: GridSpec, config: SplatConfig | None = None) -> None:
        self.grid = grid
        self.config = config or SplatConfig()
        n = grid.n_voxels
        self._weight = torch.zeros(n, dtype=torch.float64)
        if self.config.reduce == "mean":
            self._total = torch.zeros(n, dtype=torch.float64)
        else:
            self._peak = torch.full((n,), -torch.inf, dtype=torch.float32)

    def add(self, points_mm: np.ndarray | torch.Tensor, values: np.ndarray | torch.Tensor) -> None:
        """Splat samples at ``points_mm`` (M, 3) world mm with ``values`` (M,).

        The per-sample arithmetic is numpy's (several times faster than torch's on this CPU
        build); the accumulation is torch's in-place ``index_add_`` (O(M), whatever the grid).
        """
        points = _as_numpy(points_mm).astype(np.float64, copy=False).reshape(-1, 3)
        vals = _as_numpy(values).astype(np.float64, copy=False).reshape(-1)
        if vals.shape[0] != points.shape[0]:
            raise argument_error(
                "values", f"expected {points.shape[0]} values for the points, got {vals.shape[0]}"
            )
        # (3, M): one contiguous row per axis
        index = (points.T - np.asarray(self.grid.origin_mm)[:, None]) / self.grid.voxel_mm
        shape = np.asarray(self.grid.shape)[:, None]
        if self.config.interpolation == "nearest":
            ijk = np.rint(index).astype(np.int64)
            inside = ((ijk >= 0) & (ijk < shape)).all(axis=0)
            self._scatter(self._flat(ijk), inside, inside.astype(np.float64), vals)
            return
        base = np.floor(index)
        weights = (1.0 - (index - base), index - base)  # towards the lower, the upper neighbour
        base = base.astype(np.int64)
        inside = ((base >= 0) & (base < shape), (base >= -1) & (base < shape - 1))
        flat = self._flat(base)
        ny, nz = self.grid.shape[1], self.grid.shape[2]
        for dx, dy, dz in np.ndindex(2, 2, 2):
            weight = weights[dx][0] * weights[dy][1] * weights[dz][2]
            ok = inside[dx][0] & inside[dy][1] & inside[dz][2]
            ok &= (weight >= MAX_MIN_WEIGHT) if self.config.reduce == "max" else (weight > 0)
            self._scatter(flat + (dx * ny + dy) * nz + dz, ok, weight, vals)

    def _flat(self, ijk: np.ndarray) -> np.ndarray:
        """C-order flat indices of voxels (3, M) (meaningless outside the grid)."""
        ny, nz = self.grid.shape[1], self.grid.shape[2]
        return (ijk[0] * ny + ijk[1]) * nz + ijk[2]

    def _scatter(
        self, flat: np.ndarray, ok: np.ndarray, weight: np.ndarray, values: np.ndarray
    ) -> None:
        """Add samples at flat voxel indices where ``ok``, with ``weight`` (masked samples go
        to voxel 0 with weight 0, so nothing is gathered or copied)."""
        index = torch.from_numpy(np.where(ok, flat, 0))
        weight = np.where(ok, weight, 0.0)
        self._weight.index_add_(0, index, torch.from_numpy(weight))
        if self.config.reduce == "mean":
            self._total.index_add_(0, index, torch.from_numpy(weight * values))
        else:
            peak = np.where(ok, values, -np.inf).astype(np.float32)
            self._peak.scatter_reduce_(0, index, torch.from_numpy(peak), reduce="amax")

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """(volume float32, filled bool), both of ``grid.shape``; holes read 0."""
        filled = self._weight > 0
        if self.config.reduce == "mean":
            volume = torch.where(filled, self._total / self._weight.clamp_min(1e-300), 0.0)
        else:
            volume = torch.where(filled, self._peak, 0.0)
        shape = self.grid.shape
        return (
            volume.to(torch.float32).numpy().reshape(shape),
            filled.numpy().reshape(shape),
        )
