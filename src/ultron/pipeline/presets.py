"""Whole-pipeline presets: one name sets the field fit, UltrON, ON and RoCoSDF together.

- ``fast`` (the default): this project's settings, chosen on tuning seeds (each
  component's defaults, whose figures docs/decisions.md gathers; RoCoSDF's ``fast`` preset).
  Minutes on 2 CPU cores.
- ``paper``: the configuration of the UltrON paper (``ultron-paper.tex``, METHOD.md): the
  Ultra-NeRF field as published (8 × 128 MLP, 75k iterations,
  :func:`~ultron.train.field_config.field_preset` ``"paper"``); f_ω on θ(x) alone
  (no neighbourhood), 50k iterations of the paper's BCE(T·f, y) with background labels scaled
  by T and unweighted classes; the whole extracted iso-surface (no observed-surface crop;
  pieces under 5 % of the largest dropped; no label fusion);
  ON with 50k iterations; RoCoSDF's ``paper`` preset. The paper does not give its batch sizes:
  the field renders four whole frames per step (the batching a GPU wants; a patch wider than
  the frame is the whole frame) and f_ω keeps 4096 labelled pixels per step. Days on a CPU,
  minutes on one GPU (``--device cuda``; ``benchmarks/device.py`` measures it).

Presets are built anew on every call, never mutated.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ultron.arguments import check_integer
from ultron.errors import argument_error
from ultron.fields.context import ThetaContextConfig
from ultron.mesh.echo_support import EchoSupportConfig
from ultron.mesh.label_fusion import LabelFusionConfig
from ultron.mesh.observed import ObservedSurfaceConfig
from ultron.methods.catalog import FIELD_METHODS
from ultron.methods.on_method import ONConfig
from ultron.methods.registry import get_method
from ultron.methods.request import ReconstructionRequest
from ultron.methods.ultron_method import UltronConfig
from ultron.metrics.surface import MetricsConfig
from ultron.train.field_config import FieldTrainConfig, field_preset
from ultron.train.occupancy import OccupancyTrainConfig, parse_positive_weight
from ultron.train.visibility import visibility_config

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
        observed=ObservedSurfaceConfig(surface="all", label_support_mm=0.0, label_bridges=False),
        label_outer_side_mm=0.0,
        echo_support=None,
        label_fusion=None,
    )
    on = ONConfig()
    on = replace(on, occupancy=replace(on.occupancy, iters=PAPER_OCCUPANCY_ITERS))
    return PipelinePreset(name, field, ultron, on, "paper")


def preset_field_config(
    preset: str = "fast", seed: int = 0, iterations: int | None = None
) -> FieldTrainConfig:
    """The field fit of ``preset``, seeded by ``seed``, with ``iterations`` when given."""
    config = pipeline_preset(preset, seed).field
    return config if iterations is None else replace(config, iterations=iterations)


def preset_request(
    preset: str = "fast",
    method: str = "ultron",
    label_fraction: float = 0.1,
    seed: int = 0,
    *,
    points: int = 100_000,
    occupancy_iters: int | None = None,
    occupancy_precision: str | None = None,
    visibility: str = "field",
    oracle: bool = False,
    surface: str | None = None,
    theta_context: str | None = None,
    positive_weight: str | None = None,
    negatives: str | None = None,
    echo_support: bool | None = None,
    label_support_mm: float | None = None,
    label_bridges: bool | None = None,
    label_fusion: bool | None = None,
    mesh_coordinates: str = "lps",
    device: str = "cpu",
) -> ReconstructionRequest:
    """The reconstruction request of ``preset`` for ``method``, with the options given (None:
    the preset's); the request carries ``method``'s settings alone
    (:meth:`~ultron.methods.registry.Method.config_of`). ``ultron reconstruct`` shows these
    entries as its options' help.

    Args:
        preset: Settings of every stage: fast (this project's, minutes on a CPU) or paper
            (the UltrON paper's: 8 × 128 MLP field, 75k + 50k iterations, θ alone, BCE(T·f,
            y), whole surface, RoCoSDF's paper settings; for a GPU). Options given win.
        occupancy_iters: Occupancy iterations of ultron* and on (default: the preset's: 1500;
            paper: 50000).
        occupancy_precision: Arithmetic of the occupancy fit of ultron* and on: float32, or
            bfloat16 (mixed precision: faster where the CPU multiplies bfloat16 natively,
            AVX512-BF16 or AMX, and on GPUs; slower elsewhere) (default: float32).
        visibility: Source of the loss's transmission T (ultron*): field (the fitted
            acoustic field), confidence (the frame's ultrasound confidence map) or labels
            (the annotation's first bone run per scanline).
        oracle: Diagnostic (ultron*): train with the simulator's true T
            (<sweep>/transmission.npy of a simulated dataset).
        surface: ultron* and compounding: observed (keep the faces some frame saw facing the
            probe with T ≥ 0.3 above them — compounding: T = 1) or all (the closed
            iso-surface) (default: the preset's: observed; paper: all).
        theta_context: ultron*: radii (mm, comma-separated) of the world-axis neighbours
            whose θ f reads besides θ(x); 'none' for θ(x) alone, as in the paper (default:
            the preset's: 1,2; paper: none).
        positive_weight: ultron*: loss weight of the bone labels: 1 (unweighted, the
            paper's), another number > 0, or 'balanced' (n_background / n_bone, at most 20:
            a fuller but less accurate surface, e.g. for very short runs) (default: 1).
        negatives: ultron: background labels in the compensated loss: 'observed' (full
            weight where T ≥ 0.3, none below: only observed free space is evidence), 'front'
            (observed, and every background label in front of its scanline's first bone
            label whatever T says) or 'weighted' (scaled by T: the paper's BCE(T·f, y))
            (default: the preset's: observed; paper: weighted).
        echo_support: ultron*: keep only surface some frame shows as bone — a bone echo or
            the onset of a shadow within ±1 mm (default: the preset's: on; paper: off).
        label_support_mm: ultron*: surface within MM of a labelled bone surface counts as
            observed (default: the preset's: 1 mm; paper: 0, off).
        label_bridges: ultron*: with --label-support, the labelled surface also runs between
            consecutive labelled frames whose labelled cross-sections agree to within MM
            (default: on).
        label_fusion: ultron*: mesh max(f, C), C the labels f trained on compounded as
            --method compounding does: the annotated bone stays bone; --label-fusion at any
            label fraction (default: the preset's: when the labelled frames are ≥ 90 % of the
            dataset's, e.g. label --auto's labels with --label-fraction 1; paper: off).
    """
    chosen = get_method(method)
    source = visibility_config(visibility, oracle)
    if source.source != "field" and not chosen.needs_field:  # T is UltrON's alone
        flag = "--oracle-transmission" if oracle else f"--visibility {visibility}"
        raise argument_error(
            "visibility",
            f"{flag} applies to --method {' or '.join(FIELD_METHODS)} only, not {method!r}",
        )
    if occupancy_iters is not None:  # 0 would mesh an untrained network
        check_integer("occupancy_iters", occupancy_iters, 1)
    base = pipeline_preset(preset, seed)
    occupancy, on = base.ultron.occupancy, base.on
    given = {"iters": occupancy_iters, "precision": occupancy_precision}  # ultron* and on
    shared = {k: v for k, v in given.items() if v is not None}
    own = {} if negatives is None else {"negatives": negatives}
    occupancy = replace(occupancy, **shared, **own)
    if positive_weight is not None:  # "balanced" parses to None: n_background / n_bone
        occupancy = replace(occupancy, positive_weight=parse_positive_weight(positive_weight))
    on = replace(on, occupancy=replace(on.occupancy, **shared))
    ultron = _with_options(
        replace(base.ultron, occupancy=occupancy, visibility=source), theta_context,
        echo_support, label_fusion,
        {"surface": surface, "label_support_mm": label_support_mm, "label_bridges": label_bridges},
    )  # fmt: skip
    return ReconstructionRequest(
        method=method,
        label_fraction=label_fraction,
        seed=seed,
        method_config=chosen.config_of(replace(base, ultron=ultron, on=on)),
        metrics=MetricsConfig(n_points=points),
        mesh_coordinates=mesh_coordinates,
        device=device,
    )


def _with_options(
    ultron: UltronConfig,
    theta_context: str | None,
    echo_support: bool | None,
    label_fusion: bool | None,
    observed: dict[str, object],
) -> UltronConfig:
    """``ultron`` with :func:`preset_request`'s options that were given (not None); ``observed``
    holds those of its observed-surface crop."""
    if theta_context is not None:
        ultron = replace(ultron, context=ThetaContextConfig.parse(theta_context))
    if echo_support is not None:
        ultron = replace(ultron, echo_support=EchoSupportConfig() if echo_support else None)
    if label_fusion is not None:
        fusion = LabelFusionConfig(min_frame_share=0.0) if label_fusion else None
        ultron = replace(ultron, label_fusion=fusion)
    given = {name: value for name, value in observed.items() if value is not None}
    return replace(ultron, observed=replace(ultron.observed, **given)) if given else ultron


__all__ = [
    "PAPER_OCCUPANCY_ITERS",
    "PIPELINE_PRESETS",
    "PipelinePreset",
    "pipeline_preset",
    "preset_field_config",
    "preset_request",
]
