"""Reusable network building blocks: NeRF positional encoding and the skip MLP.

Used by the acoustic field's ``mlp`` backend (Ultra-NeRF), and reused by the occupancy
network and the ON baseline of later stages.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ultron.errors import argument_error


class PositionalEncoding(nn.Module):
    """NeRF positional encoding γ(x) of each input coordinate.

        γ(x) = (x, sin(2⁰πx), cos(2⁰πx), …, sin(2^{L−1}πx), cos(2^{L−1}πx))

    with L = ``n_frequencies``; the input itself is kept when ``include_input``. Maps
    (…, D) to (…, D·(2L + include_input)), frequencies grouped per band (sin of all D, then
    cos of all D).
    """

    def __init__(self, n_frequencies: int, include_input: bool = True) -> None:
        super().__init__()
        if not isinstance(n_frequencies, int) or n_frequencies < 0:
            raise argument_error("n_frequencies", f"expected an integer ≥ 0, got {n_frequencies!r}")
        self.n_frequencies = n_frequencies
        self.include_input = include_input
        bands = math.pi * 2.0 ** torch.arange(n_frequencies, dtype=torch.float32)
        self.register_buffer("bands", bands, persistent=False)

    def output_dim(self, in_dim: int) -> int:
        """Width of γ(x) for an input of ``in_dim`` coordinates."""
        return in_dim * (2 * self.n_frequencies + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        parts = [x] if self.include_input else []
        if self.n_frequencies:
            scaled = x[..., None, :] * self.bands.to(x.dtype)[:, None]  # (…, L, D)
            encoded = torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)  # (…, L, 2D)
            parts.append(encoded.flatten(-2))
        return torch.cat(parts, dim=-1)


class SkipMLP(nn.Module):
    """ReLU MLP of ``depth`` hidden layers of ``width``, input re-concatenated at ``skip_at``.

    The NeRF/Ultra-NeRF/UltrON trunk: layer i (0-based) takes the previous activation, and
    layer ``skip_at`` takes [activation, input]. The output layer is linear (no activation).
    """

    def __init__(
        self, in_dim: int, out_dim: int, width: int = 128, depth: int = 8, skip_at: int = 4
    ) -> None:
        super().__init__()
        for name, value in (("in_dim", in_dim), ("out_dim", out_dim), ("width", width)):
            if not isinstance(value, int) or value < 1:
                raise argument_error(name, f"expected a positive integer, got {value!r}")
        if not isinstance(depth, int) or depth < 1:
            raise argument_error("depth", f"expected a positive integer, got {depth!r}")
        if not (isinstance(skip_at, int) and 0 < skip_at < depth) and skip_at is not None:
            raise argument_error("skip_at", f"expected 0 < skip_at < depth={depth}, got {skip_at}")
        self.skip_at = skip_at
        layers = []
        for i in range(depth):
            fan_in = in_dim if i == 0 else width
            if i == skip_at:
                fan_in += in_dim
            layers.append(nn.Linear(fan_in, width))
        self.hidden = nn.ModuleList(layers)
        self.output = nn.Linear(width, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x
        for i, layer in enumerate(self.hidden):
            if i == self.skip_at:
                h = torch.cat([h, x], dim=-1)
            h = torch.relu(layer(h))
        return self.output(h)
