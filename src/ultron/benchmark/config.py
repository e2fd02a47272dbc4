"""The settings of ``ultron benchmark`` and the rows of its tables.

Which frames a cell labels: a row that uses a share of the annotated frames (UltrON (10%),
compounding (10%), the fine-tuning's 1 %, …) draws them with :func:`selection_seed` of its phantom
and seed (``label_selection="per-phantom"``, the default), so that every phantom × seed labels
its own frames. With the seed alone (``"shared"``, the benchmark before 2026-11-28) every phantom's
60-frame sweeps labelled the same frame indices, so the three seeds were three selections shared
by all five phantoms. Rows that use every frame keep the seed itself (it only seeds training).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ultron.arguments import check_count
from ultron.data.auto_labels import AutoLabelConfig
from ultron.device import resolve_device
from ultron.errors import argument_error
from ultron.methods.on_method import ONConfig
from ultron.methods.rocosdf import ROCOSDF_PRESETS
from ultron.methods.ultron_method import UltronConfig
from ultron.metrics.surface import METRIC_NAMES, MetricsConfig
from ultron.phantom.annotation import AnnotationConfig
from ultron.phantom.dataset import SimulationConfig
from ultron.phantom.protocols import TrackingNoise
from ultron.phantom.shapes import BENCHMARK_PHANTOMS
from ultron.pipeline.presets import pipeline_preset
from ultron.train.field_fit import FieldTrainConfig
from ultron.train.occupancy import OccupancyTrainConfig

TABLE1, TABLE2, ROBUSTNESS = "table1", "table2", "robustness"
#: Metrics aggregated in the tables, in column order (each cell contributes the mean over its
#: metric repeats): the visible-reference figures lead (what the sweeps could see), then the
#: whole-reference ones. HD and HD95 are one-sided (reconstruction → reference).
METRICS = METRIC_NAMES[: METRIC_NAMES.index("completeness") + 1]

#: Robustness conditions: the default dataset and two perturbed re-simulations of L3.
DEFAULT, ANNOTATION, POSE = "default", "annotation errors", "pose misalignment"
CONDITION_TAGS = {DEFAULT: "", ANNOTATION: "annot", POSE: "pose"}
ROBUSTNESS_PHANTOM = "L3"
SOURCE_PHANTOM, TARGET_PHANTOM = "L3", "L2"  # Table 2: train on L3, apply to L2


@dataclass(frozen=True)
class Row:
    """A table row: how each of its cells is computed. A row with ``finetune_iters`` (Table 2)
    fine-tunes the model trained on the source phantom for that many iterations (0: applies it
    as it is) on ``label_fraction`` of the target's frames; ``method`` names the registered
    method the model was trained with."""

    name: str
    slug: str
    method: str
    label_fraction: float
    finetune_iters: int | None = None
    #: ``"manual"``: the simulated annotator's labels; ``"auto"``: ``ultron label --auto``'s.
    labels: str = "manual"


TABLE1_ROWS = (
    Row("RoCoSDF (100%)", "rocosdf-100", "rocosdf", 1.0),
    Row("ON (100%)", "on-100", "on", 1.0),
    Row("UltrON w/o loss (10%)", "ultron-noloss-10", "ultron-noloss", 0.1),
    Row("UltrON (10%)", "ultron-10", "ultron", 0.1),
    Row("UltrON (5%)", "ultron-5", "ultron", 0.05),
    Row("UltrON (1%)", "ultron-1", "ultron", 0.01),
    Row("compounding (10%)", "compounding-10", "compounding", 0.1),
    Row("compounding (100%)", "compounding-100", "compounding", 1.0),
    Row("UltrON (auto labels, 100%)", "ultron-auto-100", "ultron", 1.0, labels="auto"),
    Row(
        "compounding (auto labels, 100%)", "compounding-auto-100", "compounding", 1.0, labels="auto"
    ),
)
ROW = {row.name: row for row in TABLE1_ROWS}
ULTRON_10, ULTRON_5, NOLOSS_10 = (
    ROW["UltrON (10%)"],
    ROW["UltrON (5%)"],
    ROW["UltrON w/o loss (10%)"],
)
ON_100, ROCOSDF_100, COMPOUNDING_10 = (
    ROW["ON (100%)"],
    ROW["RoCoSDF (100%)"],
    ROW["compounding (10%)"],
)
TABLE2_ROWS = (
    Row("w/o fine-tuning", "finetune-direct", ULTRON_10.method, 0.01, 0),
    Row("1% + 100 iter", "finetune-1pct-100", ULTRON_10.method, 0.01, 100),
    Row("full training", ULTRON_10.slug, ULTRON_10.method, ULTRON_10.label_fraction),
)
ROBUSTNESS_METHODS = (ULTRON_10, ROCOSDF_100)


def robustness_row(method_row: Row, condition: str) -> str:
    """The robustness table's row name, e.g. ``"UltrON (10%), annotation errors"``."""
    return f"{method_row.name}, {condition}"


#: The benchmark's datasets carry the imperfections of a real acquisition (issue 32): tracking
#: error of 0.3 mm and 0.3° per axis (a robot arm's or a good optical tracker's; the simulator's
#: default rotation is 0.2°), the annotator's 0.3 mm edge jitter and 2 % coarse frames, and 5 %
#: of the frames left unannotated.
BENCHMARK_TRACKING = TrackingNoise(translation_mm=0.3, rotation_deg=0.3)
BENCHMARK_ANNOTATION = AnnotationConfig(missing_fraction=0.05)


def _benchmark_simulation() -> SimulationConfig:
    return SimulationConfig(tracking=BENCHMARK_TRACKING, annotation=BENCHMARK_ANNOTATION)


def _robust_annotation() -> AnnotationConfig:
    return replace(BENCHMARK_ANNOTATION, jitter_mm=1.0, error_rate=0.10, error_shift_mm=4.0)


def _robust_tracking() -> TrackingNoise:
    return TrackingNoise(translation_mm=1.5, rotation_deg=1.0)


@dataclass(frozen=True)
class BenchmarkConfig:
    """Every setting of a benchmark (immutable; derive variants with ``dataclasses.replace``).

    ``simulation`` and ``field_fit`` are templates: each dataset replaces their phantom and seed.
    ``ultron``, ``on`` and ``metrics`` go into every cell's ``ReconstructionRequest`` (the
    fine-tuning cells mesh with ``ultron`` and measure with ``metrics`` too). ``device`` and
    ``cell_reports`` are not settings of the results' identity: a DIR resumed on another device
    or without cell reports keeps its finished cells.

    Attributes:
        phantoms: The phantoms simulated and reconstructed.
        seeds: Seeds 0..K-1 per phantom.
        jobs: Tasks run in parallel (spawned worker processes).
        threads: torch threads per task (default: cores // jobs, at least 1).
        robustness: Also UltrON (10%) vs RoCoSDF (100%) on L3 with larger annotation errors
            and with pose misalignment.
        generalisation: Table 2: train on L3, apply to L2.
        quick: Fewer field and occupancy iterations and metric points (:func:`quick_config`).
        rocosdf_preset: RoCoSDF's settings: fast or paper.
        device: Where every task's networks compute.
        cell_reports: Every cell's run directory gets its own report.html, as reconstruct
            writes it (seconds of figures per cell); DIR's report.html shows every row either
            way.
        simulation: The simulated datasets' template.
        field_fit: The field fits' template.
        ultron: UltrON's settings in every cell.
        on: ON's settings.
        metrics: How every cell is scored.
        robust_annotation: The robustness study's perturbed annotation.
        robust_tracking: The robustness study's perturbed tracking.
        auto_labels: label --auto's settings for the auto-labelled cells.
        label_selection: How a cell's labelled frames are drawn (module doc): per-phantom or
            shared.
    """

    phantoms: tuple[str, ...] = BENCHMARK_PHANTOMS
    seeds: int = 3
    jobs: int = 1
    threads: int | None = None
    robustness: bool = False
    generalisation: bool = True
    quick: bool = False
    rocosdf_preset: str = "fast"
    device: str = "cpu"
    cell_reports: bool = True
    simulation: SimulationConfig = field(default_factory=_benchmark_simulation)
    field_fit: FieldTrainConfig = field(default_factory=FieldTrainConfig)
    ultron: UltronConfig = field(default_factory=UltronConfig)
    on: ONConfig = field(default_factory=ONConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    robust_annotation: AnnotationConfig = field(default_factory=_robust_annotation)
    robust_tracking: TrackingNoise = field(default_factory=_robust_tracking)
    auto_labels: AutoLabelConfig = field(default_factory=AutoLabelConfig)
    label_selection: str = "per-phantom"

    def __post_init__(self) -> None:
        phantoms = self.phantoms
        if isinstance(phantoms, str) or not phantoms:
            raise argument_error(
                "phantoms", f"expected a non-empty list of names, got {phantoms!r}"
            )
        unknown = [p for p in phantoms if p not in BENCHMARK_PHANTOMS]
        if unknown:
            raise argument_error(
                "phantoms",
                f"unknown phantom(s) {unknown}; expected some of {list(BENCHMARK_PHANTOMS)}",
            )
        if len(set(phantoms)) != len(phantoms):
            raise argument_error("phantoms", f"phantoms must be unique, got {list(phantoms)}")
        object.__setattr__(self, "phantoms", tuple(phantoms))
        for name in ("seeds", "jobs"):
            check_count(name, getattr(self, name))
        if self.threads is not None:
            check_count("threads", self.threads)
        if self.rocosdf_preset not in ROCOSDF_PRESETS:
            raise argument_error(
                "preset", f"expected one of {ROCOSDF_PRESETS}, got {self.rocosdf_preset!r}"
            )
        resolve_device(self.device, "device")
        if self.label_selection not in LABEL_SELECTIONS:
            raise argument_error(
                "label_selection",
                f"expected one of {LABEL_SELECTIONS}, got {self.label_selection!r}",
            )

    def settings(self) -> dict[str, Any]:
        """The settings that shape a cell's result (a resumed DIR must have been made with
        the same ones); phantoms, seeds, jobs and the tables chosen only add or drop cells."""
        keep = ("rocosdf_preset", "simulation", "field_fit", "ultron", "on", "metrics")
        keep += ("auto_labels", "label_selection")
        data = {name: _plain(getattr(self, name)) for name in keep}
        if self.robustness:
            data["robust_annotation"] = _plain(self.robust_annotation)
            data["robust_tracking"] = _plain(self.robust_tracking)
        return data

    def to_dict(self) -> dict[str, Any]:
        """Every setting as plain JSON-able data."""
        return _plain(self)


#: The ways a cell's labelled frames can be drawn (module doc).
LABEL_SELECTIONS = ("per-phantom", "shared")
#: Settings that DIRs written before the setting existed hold implicitly.
LEGACY_SETTINGS = {"label_selection": "shared"}


def selection_seed(phantom: str, seed: int) -> int:
    """The seed that draws ``phantom``'s labelled frames for benchmark seed ``seed``: a
    32-bit draw from ``np.random.SeedSequence([seed, crc32(phantom)])``, so that phantoms with
    sweeps of the same length do not label the same frame indices."""
    state = np.random.SeedSequence([int(seed), zlib.crc32(phantom.encode())])
    return int(state.generate_state(1, np.uint32)[0])


def _plain(value: Any) -> Any:
    """Nested dataclasses / tuples → JSON-able dicts / lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


#: ``--quick``'s reductions (see :func:`quick_config`).
QUICK_FIELD_ITERATIONS = 2000
QUICK_OCCUPANCY_ITERS = 1000
QUICK_METRIC_POINTS, QUICK_METRIC_REPEATS = 50_000, 2


def quick_config(**changes: Any) -> BenchmarkConfig:
    """``--quick``: L3 (+ L2 for Table 2), one seed, 2000 field iterations (default 3000),
    1000 occupancy iterations for UltrON and ON (default 1500), metrics on 50k points × 2
    repeats (default 100k × 3). RoCoSDF keeps its ``fast`` preset (a ``ReconstructionRequest``
    carries only the preset name). ``changes`` override any field.

    Sized to take minutes on 2 idle cores (the measured stage times behind that estimate:
    docs/decisions.md#benchmark-the-quick-run-benchmarkconfigpy)."""
    on = ONConfig()
    base = BenchmarkConfig(
        phantoms=("L3",),
        seeds=1,
        quick=True,
        field_fit=FieldTrainConfig(iterations=QUICK_FIELD_ITERATIONS),
        ultron=UltronConfig(occupancy=OccupancyTrainConfig(iters=QUICK_OCCUPANCY_ITERS)),
        on=replace(on, occupancy=replace(on.occupancy, iters=QUICK_OCCUPANCY_ITERS)),
        metrics=MetricsConfig(n_points=QUICK_METRIC_POINTS, repeats=QUICK_METRIC_REPEATS),
    )
    return replace(base, **changes)


def benchmark_config(preset: str = "fast", quick: bool = False, **changes: Any) -> BenchmarkConfig:
    """The benchmark whose every stage has the settings of pipeline preset ``preset``
    (:func:`~ultron.pipeline.presets.pipeline_preset`: field fit, UltrON, ON, RoCoSDF), reduced
    as :func:`quick_config` says when ``quick`` (the fast preset only); ``changes`` override any
    field."""
    if quick and preset != "fast":
        raise argument_error(
            "preset", f"a quick benchmark (--quick) runs the fast preset only, got {preset!r}"
        )
    stages = pipeline_preset(preset)
    settings: dict[str, Any] = {"rocosdf_preset": stages.rocosdf_preset}
    if preset != "fast":  # the fast preset's stages are BenchmarkConfig's own defaults
        settings |= {"field_fit": stages.field, "ultron": stages.ultron, "on": stages.on}
    settings |= changes
    return quick_config(**settings) if quick else BenchmarkConfig(**settings)
