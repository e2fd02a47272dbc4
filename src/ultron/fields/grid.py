"""The ``grid`` backend (default): multi-resolution factorised planes + a tiny decoder.

Features at a unit-cube point u = (x, y, z) are read by bilinear interpolation from three
axis-aligned feature planes per level and combined by a Hadamard product (as in K-planes),

    f_ℓ(u) = P_ℓ^{xy}(x, y) ⊙ P_ℓ^{xz}(x, z) ⊙ P_ℓ^{yz}(y, z),

which is a rank-limited trilinear-like 3D feature at the memory cost of 2D planes; the levels
are concatenated and decoded by a small ReLU MLP into the raw θ outputs. The finest level's
cell is at most the data's pixel size (``cell_mm``), so the field can hold pixel-scale detail.
A dense 3D grid at that cell size would need (2·half_extent/cell)³ voxels (≈ 2·10⁸ for the l2
sweep), which does not fit a CPU budget; planes need 3·R² per level.

Smoothness prior: the mean squared difference between neighbouring plane cells (total
variation, squared), weighted by ``smoothness_weight``. Without it the pixel-scale planes
memorise each training frame's speckle and render a noisy texture between frames. The default
(1.0) was chosen among {1e-3, 1e-2, 0.1, 1, 10} by the held-out frames of the default
simulated phantom (best SSIM; bone edges stay sharp), never on the l2 benchmark frames.
Defaults (8 features per plane at the finest level, 4 at the coarser one, 2 levels ÷4, a
16-wide one-layer decoder) were chosen for step time (profiled on 2 threads: grid_sample's
backward, then the decoder, dominate), checking on the simulated phantom's held-out frames
that the fit stays comparable (18.6 dB / SSIM 0.243 vs 18.6 dB / 0.250 with 8 + 8 features and
a 32-wide decoder; one level, or 4 features everywhere, fitted worse).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from ultron.errors import argument_error
from ultron.fields.base import AcousticField
from ultron.fields.properties import HeadConfig, initial_raw_bias, n_raw_channels

#: Upper bound on a plane's side (memory guard: 3 planes × C × R² floats per level).
MAX_RESOLUTION = 2048
#: Side of the random window on which the smoothness prior is evaluated each step.
TV_WINDOW = 96
#: Probability of evaluating the prior on a plane larger than the window in a given step.
TV_LARGE_PLANE_PROBABILITY = 0.25


@dataclass(frozen=True)
class GridFieldConfig:
    """Plane resolutions (finest first) or how to derive them, features and decoder size.

    ``resolutions`` is filled in by :meth:`resolved` from ``cell_mm`` (default: the data's
    smallest pixel spacing) and the unit cube's size: the finest level has
    R = ⌈2·half_extent_mm / cell_mm⌉ + 1 nodes, each coarser level ``level_factor`` fewer.
    """

    resolutions: tuple[int, ...] | None = None
    cell_mm: float | None = None
    n_levels: int = 2
    level_factor: float = 4.0
    features: int = 8
    coarse_features: int = 4
    decoder_width: int = 16
    decoder_depth: int = 1
    smoothness_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.resolutions is not None:
            resolutions = tuple(int(r) for r in self.resolutions)
            if not resolutions or any(r < 2 or r > MAX_RESOLUTION for r in resolutions):
                raise argument_error(
                    "grid.resolutions",
                    f"expected sides in [2, {MAX_RESOLUTION}], got {resolutions}",
                )
            object.__setattr__(self, "resolutions", resolutions)
        if self.cell_mm is not None and not self.cell_mm > 0:
            raise argument_error("grid.cell_mm", f"expected > 0, got {self.cell_mm}")
        if not isinstance(self.n_levels, int) or self.n_levels < 1:
            raise argument_error("grid.n_levels", f"expected ≥ 1, got {self.n_levels!r}")
        if not self.level_factor > 1:
            raise argument_error("grid.level_factor", f"expected > 1, got {self.level_factor}")
        for name in ("features", "coarse_features", "decoder_width", "decoder_depth"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise argument_error(f"grid.{name}", f"expected a positive integer, got {value!r}")
        if self.smoothness_weight < 0:
            raise argument_error("grid.smoothness_weight", "expected ≥ 0")

    def resolved(self, half_extent_mm: float, pixel_mm: float) -> GridFieldConfig:
        """This config with ``resolutions`` computed for a cube of ``half_extent_mm``."""
        if self.resolutions is not None:
            return self
        cell = self.cell_mm if self.cell_mm is not None else pixel_mm
        finest = math.ceil(2 * half_extent_mm / cell) + 1
        if finest > MAX_RESOLUTION:
            raise argument_error(
                "grid.cell_mm",
                f"a {cell:.3g} mm cell over {2 * half_extent_mm:.1f} mm needs {finest} nodes"
                f" per side (max {MAX_RESOLUTION}); choose a larger cell",
            )
        sides = [max(2, round(finest / self.level_factor**i)) for i in range(self.n_levels)]
        return replace(self, resolutions=tuple(sides))


class GridField(AcousticField):
    """Multi-resolution factorised planes read bilinearly + a tiny ReLU decoder."""

    def __init__(
        self,
        config: GridFieldConfig,
        learn_density: bool = False,
        generator: torch.Generator | None = None,
        heads: HeadConfig | None = None,
    ) -> None:
        super().__init__(learn_density, heads)
        if config.resolutions is None:
            raise argument_error("config", "call GridFieldConfig.resolved(...) first")
        self.config = config
        channels = [config.features] + [config.coarse_features] * (len(config.resolutions) - 1)
        self.planes = nn.ParameterList(
            nn.Parameter(1.0 + 0.1 * torch.randn(3, c, r, r, generator=generator))
            for c, r in zip(channels, config.resolutions, strict=True)
        )
        layers: list[nn.Module] = []
        fan_in = sum(channels)
        for _ in range(config.decoder_depth):
            layers += [nn.Linear(fan_in, config.decoder_width), nn.ReLU()]
            fan_in = config.decoder_width
        last = nn.Linear(fan_in, n_raw_channels(learn_density))
        with torch.no_grad():
            last.weight.mul_(0.1)
            last.bias.copy_(initial_raw_bias(learn_density, self.head_config))
        self.decoder = nn.Sequential(*layers, last)

    def features(self, points_unit: torch.Tensor) -> torch.Tensor:
        """Concatenated plane-product features (…, Σ_levels C_level)."""
        shape = points_unit.shape[:-1]
        u = points_unit.reshape(-1, 3).to(torch.float32)
        # grid_sample reads (x → last axis, y → second-last axis) of each plane.
        x, y, z = u.unbind(-1)
        coords = torch.stack([x, y, x, z, y, z], dim=-1).view(-1, 3, 2).transpose(0, 1)[:, None]
        parts = []
        for plane in self.planes:
            sampled = F.grid_sample(
                plane, coords, mode="bilinear", padding_mode="border", align_corners=True
            )  # (3, C, 1, N)
            parts.append(sampled[0, :, 0] * sampled[1, :, 0] * sampled[2, :, 0])  # (C, N)
        feats = torch.cat(parts, dim=0).transpose(0, 1)
        return feats.reshape(*shape, feats.shape[-1])

    def raw(self, points_unit: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.features(points_unit))

    def regularization(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Squared total variation of the planes, × ``smoothness_weight``.

            TV = Σ_levels mean_window[(P[i+1, j] − P[i, j])² + (P[i, j+1] − P[i, j])²]

        A stochastic, unbiased estimate of the whole-plane means (``generator`` draws it): a plane
        larger than ``TV_WINDOW`` is evaluated on one random window, and only with probability
        ``TV_LARGE_PLANE_PROBABILITY`` (then scaled by its inverse), because the gradient of a
        window still costs a pass over the whole plane. The draws are made on ``generator``'s
        device (the fit's CPU generator), the penalty on the planes'.
        """
        total = torch.zeros((), device=self.planes[0].device)
        if self.config.smoothness_weight == 0:
            return total
        for plane in self.planes:
            side = plane.shape[-1]
            scale = 1.0
            if side > TV_WINDOW:
                draw = torch.rand((), generator=generator)
                i, j = torch.randint(0, side - TV_WINDOW + 1, (2,), generator=generator).tolist()
                if float(draw) >= TV_LARGE_PLANE_PROBABILITY:
                    continue
                plane = plane[:, :, i : i + TV_WINDOW, j : j + TV_WINDOW]
                scale = 1.0 / TV_LARGE_PLANE_PROBABILITY
            dy = plane[:, :, 1:, :] - plane[:, :, :-1, :]
            dx = plane[:, :, :, 1:] - plane[:, :, :, :-1]
            total = total + scale * (dy.pow(2).mean() + dx.pow(2).mean())
        return self.config.smoothness_weight * total
