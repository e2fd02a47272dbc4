"""The field configuration (backend choice) and the factory that builds a backend."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import torch

from ultron.errors import argument_error
from ultron.fields.base import AcousticField
from ultron.fields.grid import GridField, GridFieldConfig
from ultron.fields.mlp import MLPField, MLPFieldConfig
from ultron.fields.properties import HeadConfig

BACKENDS = ("grid", "mlp")


@dataclass(frozen=True)
class FieldConfig:
    """Which backend (``grid``, the fast default, or the paper's ``mlp``) and its settings."""

    backend: str = "grid"
    learn_density: bool = False
    grid: GridFieldConfig = field(default_factory=GridFieldConfig)
    mlp: MLPFieldConfig = field(default_factory=MLPFieldConfig)
    heads: HeadConfig = field(default_factory=HeadConfig)

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise argument_error("backend", f"expected one of {BACKENDS}, got {self.backend!r}")

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        if data["grid"]["resolutions"] is not None:
            data["grid"]["resolutions"] = list(data["grid"]["resolutions"])
        if self.grid.volume_cell_mm is None and self.grid.volume_nodes is None:
            # no volume: the keys of every field.json (and field cache key) written before it
            for key in ("volume_cell_mm", "volume_features", "volume_nodes"):
                del data["grid"][key]
        if self.heads.reflection_gain == 1.0:  # as written before the gain existed
            del data["heads"]["reflection_gain"]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FieldConfig:
        try:
            grid = dict(data.get("grid", {}))
            if grid.get("resolutions") is not None:
                grid["resolutions"] = tuple(grid["resolutions"])
            if grid.get("axis_extent") is not None:
                grid["axis_extent"] = tuple(grid["axis_extent"])
            if "volume_nodes" not in grid:  # no volume (or saved before it existed)
                grid["volume_cell_mm"] = None
            grid.setdefault("long_box_volume_mm", None)  # saved before the long-box volume
            return cls(
                backend=data.get("backend", "grid"),
                learn_density=bool(data.get("learn_density", False)),
                grid=GridFieldConfig(**grid),
                mlp=MLPFieldConfig(**data.get("mlp", {})),
                # Fields saved before the heads were configurable used the paper's heads.
                heads=HeadConfig.from_dict(data["heads"])
                if "heads" in data
                else HeadConfig.paper(),
            )
        except TypeError as exc:
            raise argument_error("field config", f"unexpected or missing entries ({exc})") from None


def build_field(
    config: FieldConfig,
    half_extent_mm: float,
    pixel_mm: float,
    seed: int = 0,
    axis_extent: tuple[float, float, float] | None = None,
) -> tuple[AcousticField, FieldConfig]:
    """A freshly initialised backend and the config with derived sizes filled in.

    ``half_extent_mm`` is the unit cube's half side, ``pixel_mm`` the data's smallest pixel
    spacing (the grid's default finest cell) and ``axis_extent`` the data's box per axis in
    unit-cube units (where the grid's planes reach; None: the whole cube). Initialisation is
    seeded by ``seed`` only.
    """
    generator = torch.Generator().manual_seed(int(seed))
    if config.backend == "grid":
        grid_config = config.grid.resolved(half_extent_mm, pixel_mm, axis_extent)
        resolved = replace(config, grid=grid_config)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            module: AcousticField = GridField(
                grid_config, config.learn_density, generator, config.heads
            )
        return module, resolved
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        module = MLPField(config.mlp, config.learn_density, config.heads)
    return module, config
