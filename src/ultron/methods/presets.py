"""Whole-pipeline presets: one name sets the field fit, UltrON, ON and RoCoSDF together.

- ``fast`` (the default): this project's settings, measured on tuning seeds (each
  component's defaults; RoCoSDF's ``fast`` preset). Minutes on 2 CPU cores.
- ``paper``: the configuration of the UltrON paper (``ultron-paper.tex``, METHOD.md): the
  Ultra-NeRF field as published (8 × 128 MLP, 75k iterations,
  :func:`~ultron.train.field_config.field_preset` ``"paper"``); f_ω on θ(x) alone
  (no neighbourhood), 50k iterations of the paper's BCE(T·f, y) with background labels scaled
  by T and unweighted classes; the whole extracted iso-surface (no observed-surface crop);
  ON with 50k iterations; RoCoSDF's ``paper`` preset. The paper does not give its batch sizes:
  the field renders four whole frames per step (the batching a GPU wants; a patch wider than
  the frame is the whole frame) and f_ω keeps 4096 labelled pixels per step. Days on a CPU,
  minutes on one GPU (``--device cuda``; ``benchmarks/device.py`` measures it).

Presets are built anew on every call, never mutated.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ultron.errors import argument_error
from ultron.fields.context import ThetaContextConfig
from ultron.mesh.observed import ObservedSurfaceConfig
from ultron.methods.on_method import ONConfig
from ultron.methods.ultron_method import UltronConfig
from ultron.train.field_config import FieldTrainConfig, field_preset
from ultron.train.occupancy import OccupancyTrainConfig

PIPELINE_PRESETS = ("fast", "paper")
#: "we optimize UltrON for 50k iterations" (the paper, §3).
PAPER_OCCUPANCY_ITERS = 50_000
#: Whole frames per field step in the paper preset (patches as wide as any frame).
PAPER_FRAMES_PER_BATCH = 4
WHOLE_FRAME = 1 << 16


@dataclass(frozen=True)
class PipelinePreset:
    """The settings of every stage under one name (:func:`pipeline_preset`)."""

    name: str
    field: FieldTrainConfig
    ultron: UltronConfig
    on: ONConfig
    rocosdf_preset: str


def pipeline_preset(name: str = "fast", seed: int = 0) -> PipelinePreset:
    """The preset ``name`` (module doc) with every stage seeded by ``seed``."""
    if name not in PIPELINE_PRESETS:
        raise argument_error("preset", f"expected one of {PIPELINE_PRESETS}, got {name!r}")
    if name == "fast":
        occupancy = OccupancyTrainConfig(seed=seed)
        return PipelinePreset(
            name, FieldTrainConfig(seed=seed), UltronConfig(occupancy=occupancy), ONConfig(), "fast"
        )
    field = field_preset(
        "paper", seed=seed, frames_per_batch=PAPER_FRAMES_PER_BATCH, patch_width=WHOLE_FRAME
    )
    occupancy = OccupancyTrainConfig(
        iters=PAPER_OCCUPANCY_ITERS, negatives="weighted", positive_weight=1.0, seed=seed
    )
    ultron = UltronConfig(
        occupancy=occupancy,
        context=ThetaContextConfig(radii_mm=()),
        observed=ObservedSurfaceConfig(surface="all"),
    )
    on = ONConfig()
    on = replace(on, occupancy=replace(on.occupancy, iters=PAPER_OCCUPANCY_ITERS))
    return PipelinePreset(name, field, ultron, on, "paper")


__all__ = ["PAPER_OCCUPANCY_ITERS", "PIPELINE_PRESETS", "PipelinePreset", "pipeline_preset"]
