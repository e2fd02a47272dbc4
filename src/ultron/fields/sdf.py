"""The signed-distance network of the RoCoSDF baseline (ROCOSDF.md, stage 1 and 3).

An MLP 3 → ``layers`` × ``hidden`` → 1 on normalised coordinates (no positional encoding):
linear layer l maps h_l to h_{l+1}, ReLU after every layer but the last; the input of layer
``skip_at`` is [h, x] / √2 (layer ``skip_at − 1`` outputs ``hidden − 3`` features so the width
stays ``hidden``). Every linear layer is weight-normalised (w = g·v/‖v‖, per output row).

Geometric initialisation (IGR, Gropp et al. 2020; SAL, Atzmon & Lipman 2020), as in RoCoSDF's
and Neural-Pull's code: hidden layers W ~ N(0, 2/n_out), b = 0; output layer
W ~ N(√π/√n_in, 10⁻⁸) (all weights ≈ equal), b = −r. For wide layers this gives

    f(x) ≈ ‖x‖ − r,

a sphere of radius r (default 0.5) with f < 0 inside; f(0) = −r exactly, because every hidden
activation of x = 0 is ReLU(0) = 0.

Activation: ReLU, as the RoCoSDF code (``models/model.py``) and ROCOSDF.md specify. IGR's and
NeuS's networks use Softplus(β = 100) instead (a smooth ReLU with a well-defined second
derivative); Neural-Pull's and RoCoSDF's released code use ReLU, which we follow: the pull
loss needs ∇f and its derivative with respect to the weights, which ReLU provides (its second
derivative in x vanishes, which the losses never need).

:class:`SDFDiscriminator` is the adversarial term's small critic of SDF values (UNSR).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.parametrizations import weight_norm

from ultron.arguments import check_integer
from ultron.errors import argument_error

IN_DIM = 3


@dataclass(frozen=True)
class SDFNetworkConfig:
    """Width, depth, skip layer, initial sphere radius and weight normalisation of the SDF MLP."""

    hidden: int = 256
    layers: int = 8
    skip_at: int | None = 4
    geometric_init_radius: float = 0.5
    weight_norm: bool = True

    def __post_init__(self) -> None:
        for name, low in (("hidden", IN_DIM + 1), ("layers", 1)):
            check_integer(f"sdf.{name}", getattr(self, name), low)
        if self.skip_at is not None and not (
            isinstance(self.skip_at, int) and 0 < self.skip_at < self.layers
        ):
            raise argument_error(
                "sdf.skip_at",
                f"expected None or 0 < skip_at < layers={self.layers}, got {self.skip_at!r}",
            )
        if not (math.isfinite(self.geometric_init_radius) and self.geometric_init_radius > 0):
            raise argument_error(
                "sdf.geometric_init_radius", f"expected > 0, got {self.geometric_init_radius}"
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class SDFNetwork(nn.Module):
    """f: normalised points (M, 3) → signed distance (M,), negative inside (see module doc)."""

    def __init__(self, config: SDFNetworkConfig, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.config = config
        self.skip_at = config.skip_at
        # dims[l] → dims[l + 1]: input, `layers` hidden widths, output
        dims = [IN_DIM] + [config.hidden] * config.layers + [1]
        linears = []
        for index in range(len(dims) - 1):
            out_dim = dims[index + 1]
            if self.skip_at is not None and index + 1 == self.skip_at:
                out_dim -= IN_DIM
            linear = nn.Linear(dims[index], out_dim)
            self._geometric_init(linear, last=index == len(dims) - 2, generator=generator)
            if config.weight_norm:
                linear = weight_norm(linear)
            linears.append(linear)
        self.linears = nn.ModuleList(linears)

    def _geometric_init(self, linear: nn.Linear, last: bool, generator: torch.Generator | None):
        with torch.no_grad():
            n_out, n_in = linear.weight.shape
            if last:
                nn.init.normal_(
                    linear.weight, mean=math.sqrt(math.pi) / math.sqrt(n_in), std=1e-4,
                    generator=generator,
                )  # fmt: skip
                nn.init.constant_(linear.bias, -self.config.geometric_init_radius)
            else:
                nn.init.normal_(
                    linear.weight, 0.0, math.sqrt(2) / math.sqrt(n_out), generator=generator
                )
                nn.init.zeros_(linear.bias)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance f(x) of points (M, 3) in normalised coordinates, shape (M,)."""
        if points.ndim != 2 or points.shape[-1] != IN_DIM:
            raise argument_error("points", f"expected shape (M, 3), got {tuple(points.shape)}")
        x = points.to(self.linears[0].bias.dtype)
        h = x
        last = len(self.linears) - 1
        for index, linear in enumerate(self.linears):
            if index == self.skip_at:
                h = torch.cat([h, x], dim=-1) / math.sqrt(2)
            h = linear(h)
            if index < last:
                h = torch.relu(h)
        return h[:, 0]

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """Alias of :meth:`forward`: f(x), shape (M,)."""
        return self.forward(points)

    def sdf_and_gradient(
        self, points: torch.Tensor, create_graph: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """f(x) (M,) and ∇ₓf(x) (M, 3).

        With ``create_graph`` the gradient is differentiable with respect to the weights (the
        pull loss needs it); the points themselves are treated as constants (a detached copy is
        differentiated), so callers need not set ``requires_grad``.
        """
        x = points.detach().requires_grad_(True)
        with torch.enable_grad():
            f = self.forward(x)
            (grad,) = torch.autograd.grad(
                f, x, grad_outputs=torch.ones_like(f), create_graph=create_graph
            )
        return f, grad

    def gradient(self, points: torch.Tensor, create_graph: bool = False) -> torch.Tensor:
        """∇ₓf(x), shape (M, 3) (see :meth:`sdf_and_gradient`)."""
        return self.sdf_and_gradient(points, create_graph)[1]


class SDFDiscriminator(nn.Module):
    """D: SDF value (M,) → probability (M,) that it is the ideal 0; 1 → w → w → w → 1 MLP,
    LeakyReLU(0.2), sigmoid. PyTorch's default Linear initialisation, drawn from ``generator``."""

    def __init__(self, hidden: int = 256, generator: torch.Generator | None = None) -> None:
        super().__init__()
        sizes = ((1, hidden), (hidden, hidden), (hidden, hidden), (hidden, 1))
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in sizes)
        with torch.no_grad():
            for layer in self.layers:
                bound = 1.0 / math.sqrt(layer.in_features)
                # kaiming_uniform_(a=√5) of nn.Linear.reset_parameters ≡ U(−1/√fan_in, 1/√fan_in)
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.uniform_(-bound, bound, generator=generator)

    def forward(self, values: torch.Tensor) -> torch.Tensor:
        h = values.reshape(-1, 1)
        for layer in self.layers[:-1]:
            h = F.leaky_relu(layer(h), 0.2)
        return torch.sigmoid(self.layers[-1](h))[:, 0]
