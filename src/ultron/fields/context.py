"""The input of UltrON's occupancy network: θ at a point and θ of its neighbours.

The paper's f_ω reads θ(x) alone. On ultron's phantoms θ(x) alone cannot say "bone": the
reflection β at the bone echo is matched by the field's speckle spikes in lit gel, and the
(dark) inside of a shadow looks the same under bone and below a deep echo-poor region. A
point's *neighbourhood* can: a bone echo is a bright β with a shadow (low φ / high α) on one
side and gel on the other. So f_ω reads, per point x,

    g(x) = [ θ̂(x),  θ̂(x + r·e)  for r in ``radii_mm``, e in (+x, −x, +y, −y, +z, −z) ]

with θ̂ = (θ − mean) / std the field's normalised properties (its saved statistics) and e the
world axes: C·(1 + 6·len(radii)) inputs for C channels (39 for three channels and two radii).
The stencil is fixed in the world frame, so a trained f_ω transfers to another dataset scanned
in the same frame convention (the fine-tuning setting); the neighbours are not averaged,
because the side on which the shadow lies is the information. ``radii_mm=()`` is the paper's
θ(x) alone.

On tuning data θ(x) alone let f_ω call no pixel bone, a neighbour *average* needed a class
weight and stayed imprecise, and the directional stencil at 1 and 2 mm (the default) had the
best precision and recall; meshed, it beat θ(x) alone and label compounding of the same labels
on visible CD, MAD and HD95. Figures in
docs/decisions.md#occupancy-input-the-theta-neighbourhood-fieldscontextpy.

f_ω's positional encoding γ takes θ̂(x) alone; the 36 neighbour inputs enter its trunk as they
are (``encode_neighbours=False``): encoding them too makes the first layers 351 wide and the
occupancy fit slower for no measured gain (same section of docs/decisions.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ultron.errors import argument_error
from ultron.fields.occupancy import OccupancyNetworkConfig

#: The six world-axis unit vectors of the stencil, in the order of g(x)'s blocks.
STENCIL_DIRECTIONS = (
    (1.0, 0.0, 0.0),
    (-1.0, 0.0, 0.0),
    (0.0, 1.0, 0.0),
    (0.0, -1.0, 0.0),
    (0.0, 0.0, 1.0),
    (0.0, 0.0, -1.0),
)


@dataclass(frozen=True)
class ThetaContextConfig:
    """Stencil radii (mm) of f_ω's input; ``()`` is the paper's θ(x) alone.
    ``encode_neighbours``: whether f_ω's positional encoding γ takes the neighbours' θ too
    (9× wider input, slower training) or θ(x) alone, the neighbours entering raw."""

    radii_mm: tuple[float, ...] = (1.0, 2.0)
    encode_neighbours: bool = False

    def __post_init__(self) -> None:
        radii = tuple(float(r) for r in self.radii_mm)
        if any(not np.isfinite(r) or r <= 0 for r in radii):
            raise argument_error(
                "theta_context", f"expected positive finite radii in mm, got {radii}"
            )
        object.__setattr__(self, "radii_mm", radii)

    def n_inputs(self, n_channels: int) -> int:
        """Width of g(x) for ``n_channels`` θ channels."""
        return n_channels * (1 + len(STENCIL_DIRECTIONS) * len(self.radii_mm))

    def network(self, base: OccupancyNetworkConfig, n_channels: int) -> OccupancyNetworkConfig:
        """``base`` with f_ω's input width for ``n_channels`` θ channels and γ on θ(x) alone
        unless ``encode_neighbours``."""
        encoded = None if self.encode_neighbours or not self.radii_mm else n_channels
        return replace(base, in_dim=self.n_inputs(n_channels), encoded_inputs=encoded)

    def to_dict(self) -> dict[str, Any]:
        return {"radii_mm": list(self.radii_mm), "encode_neighbours": self.encode_neighbours}

    @classmethod
    def parse(cls, text: str) -> ThetaContextConfig:
        """From the CLI: comma-separated radii in mm (``"1,2"``), or ``"none"`` for θ alone."""
        if text.strip().lower() == "none":
            return cls(radii_mm=())
        try:
            radii = tuple(float(part) for part in text.split(","))
        except ValueError:
            raise argument_error(
                "theta_context", f"expected comma-separated radii in mm or 'none', got {text!r}"
            ) from None
        return cls(radii_mm=radii)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> ThetaContextConfig:
        """A recorded context; ``None`` (a model saved before contexts existed) is θ alone; one
        recorded before ``encode_neighbours`` existed encoded them."""
        if data is None:
            return cls(radii_mm=())
        return cls(
            radii_mm=tuple(data.get("radii_mm", ())),
            encode_neighbours=bool(data.get("encode_neighbours", True)),
        )


def stencil_offsets_mm(config: ThetaContextConfig) -> torch.Tensor:
    """The (6·len(radii), 3) float64 offsets r·e, radii outer, directions inner."""
    directions = torch.tensor(STENCIL_DIRECTIONS, dtype=torch.float64)
    if not config.radii_mm:
        return torch.zeros(0, 3, dtype=torch.float64)
    return torch.cat([r * directions for r in config.radii_mm])


def theta_features(
    fitted,
    points_mm: np.ndarray | torch.Tensor,
    config: ThetaContextConfig,
    centre: torch.Tensor | None = None,
    advance: Callable[[int, int], None] | None = None,
) -> torch.Tensor:
    """g(x) (module doc) at world points (M, 3) mm → float32 (M, C·(1 + 6·len(radii))).

    ``centre`` optionally gives the raw θ(x) (M, C) already computed (e.g. by rendering the
    labelled frames); the neighbours are always queried from ``fitted``. ``advance``, when
    given, is told (queries done, queries in all) as the M points' θ is had at the centre and
    then at each neighbour (a long stage's progress: every labelled pixel of a long sweep).
    """
    if fitted.theta_stats is None:
        raise argument_error(
            "fitted",
            "the field has no θ statistics (its fit was interrupted: run fit-field again to finish it)",
        )
    points = torch.as_tensor(points_mm).to(torch.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise argument_error("points_mm", f"expected (M, 3), got {tuple(points.shape)}")
    stats = fitted.theta_stats
    if centre is None:
        centre = fitted.query(points).stack()
    elif centre.shape != (points.shape[0], len(stats.channels)):
        raise argument_error(
            "centre",
            f"expected ({points.shape[0]}, {len(stats.channels)}), got {tuple(centre.shape)}",
        )
    offsets = stencil_offsets_mm(config)
    width = len(stats.channels)
    # each block written into its columns: no list of blocks joined at the end, whose copy
    # doubled the stage's peak (every labelled pixel of a long sweep: 1.75 GB a copy)
    features = torch.empty(points.shape[0], width * (1 + len(offsets)), dtype=torch.float32)
    features[:, :width] = stats.normalise(centre.float())
    if advance is not None:
        advance(1, 1 + len(offsets))
    shifted = torch.empty_like(points) if len(offsets) else points
    for k, offset in enumerate(offsets, 1):
        torch.add(points, offset, out=shifted)
        features[:, k * width : (k + 1) * width] = stats.normalise(fitted.query(shifted).stack())
        if advance is not None:
            advance(k + 1, 1 + len(offsets))
    return features
