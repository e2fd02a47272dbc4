"""What ``ultron benchmark`` runs: the task graph of its cells.

Layout of the output directory ``DIR`` (every path below is relative to it):

* ``data/<P>-s<S>/dataset`` — phantom ``P`` simulated with seed ``S``; ``data/<P>-s<S>/field``
  — its acoustic field (one per dataset, shared by every method that needs one). The robustness
  conditions get their own datasets and fields: ``data/L3-annot-s<S>`` and ``data/L3-pose-s<S>``.
* ``data/<P>-s<S>/dataset-auto`` — the same dataset with every sweep's labels replaced by
  ``ultron label --auto``'s (the "auto labels" rows: what a user without annotations gets).
  Its images and poses are the dataset's, so its UltrON cells use the dataset's field.
* ``runs/<dataset>/<row-slug>`` — one ``reconstruct`` (or ``finetune``) output per cell.

A run directory is shared by every table row that needs the same run (Table 2's "full training"
is Table 1's UltrON (10%) cell of L2; the robustness "default" rows are Table 1's L3 cells), so
it is computed once. Tasks form a graph: ``simulate`` → ``field`` → the cells that need a field
(UltrON, UltrON w/o loss); RoCoSDF, ON and compounding need only the simulated dataset; the
fine-tuning cells need L2's field and the L3 UltrON (10%) cell of the same seed.

The settings, the rows and which frames a cell labels: :mod:`ultron.benchmark.config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ultron.benchmark.config import (
    ANNOTATION,
    CONDITION_TAGS,
    DEFAULT,
    POSE,
    ROBUSTNESS,
    ROBUSTNESS_METHODS,
    ROBUSTNESS_PHANTOM,
    SOURCE_PHANTOM,
    TABLE1,
    TABLE1_ROWS,
    TABLE2,
    TABLE2_ROWS,
    TARGET_PHANTOM,
    ULTRON_10,
    BenchmarkConfig,
    Row,
    robustness_row,
    selection_seed,
)
from ultron.data.auto_labels import AutoLabelConfig
from ultron.errors import argument_error
from ultron.methods.registry import get_method
from ultron.methods.request import ReconstructionRequest
from ultron.methods.ultron_method import UltronConfig
from ultron.metrics.surface import MetricsConfig
from ultron.phantom.dataset import SimulationConfig
from ultron.train.field_fit import FieldTrainConfig


# ---------------------------------------------------------------------------------- tasks
@dataclass(frozen=True)
class DatasetSpec:
    """One simulated dataset: phantom, seed and robustness condition."""

    phantom: str
    seed: int
    condition: str = DEFAULT

    @property
    def name(self) -> str:
        tag = CONDITION_TAGS[self.condition]
        return f"{self.phantom}-{tag}-s{self.seed}" if tag else f"{self.phantom}-s{self.seed}"

    def dataset_dir(self, out: Path) -> Path:
        return out / "data" / self.name / "dataset"

    def field_dir(self, out: Path) -> Path:
        return out / "data" / self.name / "field"

    def auto_dataset_dir(self, out: Path) -> Path:
        return out / "data" / self.name / "dataset-auto"


@dataclass(frozen=True)
class SimulateJob:
    config: SimulationConfig
    out: str


@dataclass(frozen=True)
class FieldJob:
    dataset_dir: str
    config: FieldTrainConfig
    out: str
    device: str = "cpu"
    condition: str = DEFAULT  # the dataset's robustness condition (the Stage 1 table's mean)


@dataclass(frozen=True)
class AutoLabelJob:
    """A copy of ``dataset_dir`` at ``out`` with every sweep auto-labelled (``config``)."""

    dataset_dir: str
    config: AutoLabelConfig
    out: str


@dataclass(frozen=True)
class ReconstructJob:
    dataset_dir: str
    request: ReconstructionRequest
    out: str
    field_dir: str | None
    #: The field was fitted on another copy of the same images and poses (auto labels).
    allow_other_field: bool = False
    #: Write the run's report.html (:attr:`BenchmarkConfig.cell_reports`).
    report: bool = True


@dataclass(frozen=True)
class FinetuneJob:
    model_dir: str
    dataset_dir: str
    field_dir: str
    label_fraction: float
    iters: int
    seed: int
    out: str
    meshing: UltronConfig
    metrics: MetricsConfig
    device: str = "cpu"
    report: bool = True


@dataclass(frozen=True)
class Task:
    """A node of the task graph: ``job`` runs after every task in ``deps`` succeeded."""

    id: str
    deps: tuple[str, ...]
    job: SimulateJob | FieldJob | AutoLabelJob | ReconstructJob | FinetuneJob

    @property
    def is_cell(self) -> bool:
        return isinstance(self.job, ReconstructJob | FinetuneJob)


@dataclass(frozen=True)
class CellEntry:
    """A table cell: (table, row, phantom, seed) → the task whose run directory holds it.
    ``primary`` is False where the run is another table's cell reused (runtime counted once)."""

    table: str
    row: str
    phantom: str
    seed: int
    task_id: str
    run_dir: str  # relative to DIR
    primary: bool

    @property
    def id(self) -> str:
        return f"{self.table}/{self.row}/{self.phantom}-s{self.seed}"


@dataclass
class Plan:
    """Tasks in a runnable order, the cells of each table, notes for the user."""

    tasks: dict[str, Task] = field(default_factory=dict)
    cells: list[CellEntry] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    tables: list[str] = field(default_factory=list)


def plan_benchmark(config: BenchmarkConfig, out: str | Path) -> Plan:
    """The task graph and cells of ``config`` with outputs under ``out``."""
    planner = _Planner(config, Path(out))
    return planner.build()


class _Planner:
    def __init__(self, config: BenchmarkConfig, out: Path) -> None:
        self.config, self.out, self.plan = config, out, Plan()

    def build(self) -> Plan:
        config, plan = self.config, self.plan
        seeds = range(config.seeds)
        plan.tables.append(TABLE1)
        for phantom in config.phantoms:
            for seed in seeds:
                for row in TABLE1_ROWS:
                    self.cell(TABLE1, row.name, DatasetSpec(phantom, seed), row)
        if config.generalisation:
            plan.tables.append(TABLE2)
            missing = [p for p in (SOURCE_PHANTOM, TARGET_PHANTOM) if p not in config.phantoms]
            if missing:
                plan.notes.append(
                    f"Table 2 (train on {SOURCE_PHANTOM}, apply to {TARGET_PHANTOM}) needs"
                    f" {' and '.join(missing)}, not in --phantoms: simulated for Table 2 only"
                )
            for seed in seeds:
                self.table2(seed)
        else:
            plan.notes.append("Table 2 skipped (--no-generalisation)")
        if config.robustness:
            plan.tables.append(ROBUSTNESS)
            for seed in seeds:
                for condition in (DEFAULT, ANNOTATION, POSE):
                    spec = DatasetSpec(ROBUSTNESS_PHANTOM, seed, condition)
                    for row in ROBUSTNESS_METHODS:
                        self.cell(ROBUSTNESS, robustness_row(row, condition), spec, row)
        return plan

    def table2(self, seed: int) -> None:
        source, target = DatasetSpec(SOURCE_PHANTOM, seed), DatasetSpec(TARGET_PHANTOM, seed)
        model = self.run(source, ULTRON_10)
        self.register(TABLE2, f"source model: {ULTRON_10.name} on {SOURCE_PHANTOM}", source, model)
        for row in TABLE2_ROWS:
            self.cell(TABLE2, row.name, target, row, model_task=model)

    def dataset(self, spec: DatasetSpec) -> tuple[str, str]:
        """Ids of the dataset's simulate and field tasks (added on first use)."""
        sim_id, field_id = f"simulate:{spec.name}", f"field:{spec.name}"
        if sim_id not in self.plan.tasks:
            config = self.config
            simulation = config.simulation.replace(phantom=spec.phantom, seed=spec.seed)
            if spec.condition == ANNOTATION:
                simulation = simulation.replace(annotation=config.robust_annotation)
            elif spec.condition == POSE:
                simulation = simulation.replace(tracking=config.robust_tracking)
            dataset_dir = str(spec.dataset_dir(self.out))
            self.plan.tasks[sim_id] = Task(sim_id, (), SimulateJob(simulation, dataset_dir))
            job = FieldJob(
                dataset_dir,
                replace(config.field_fit, seed=spec.seed),
                str(spec.field_dir(self.out)),
                config.device,
                spec.condition,
            )
            self.plan.tasks[field_id] = Task(field_id, (sim_id,), job)
        return sim_id, field_id

    def auto_labelled(self, spec: DatasetSpec, sim_id: str) -> str:
        """Id of the task writing the dataset's auto-labelled copy (added on first use)."""
        task_id = f"autolabel:{spec.name}"
        if task_id not in self.plan.tasks:
            dataset_dir, out = spec.dataset_dir(self.out), spec.auto_dataset_dir(self.out)
            job = AutoLabelJob(str(dataset_dir), self.config.auto_labels, str(out))
            self.plan.tasks[task_id] = Task(task_id, (sim_id,), job)
        return task_id

    def run(self, spec: DatasetSpec, row: Row, model_task: str | None = None) -> str:
        """Id of the task computing ``row`` on ``spec`` (added on first use)."""
        task_id = f"run:{spec.name}/{row.slug}"
        if task_id in self.plan.tasks:
            return task_id
        sim_id, field_id = self.dataset(spec)
        config, out = self.config, str(self.out / "runs" / spec.name / row.slug)
        dataset_dir, field_dir = str(spec.dataset_dir(self.out)), str(spec.field_dir(self.out))
        seed = spec.seed  # a share of the frames: drawn per phantom (module doc)
        if row.label_fraction < 1 and config.label_selection == "per-phantom":
            seed = selection_seed(spec.phantom, spec.seed)
        if row.finetune_iters is not None:
            if model_task is None:
                raise argument_error("model_task", "a fine-tuning row needs its model's task")
            model_dir = self.plan.tasks[model_task].job.out
            job: Any = FinetuneJob(
                model_dir, dataset_dir, field_dir, row.label_fraction, row.finetune_iters,
                seed, out, config.ultron, config.metrics, config.device, config.cell_reports,
            )  # fmt: skip
            deps: tuple[str, ...] = (field_id, model_task)
        else:
            request = ReconstructionRequest(
                method=row.method,
                label_fraction=row.label_fraction,
                seed=seed,
                method_config=get_method(row.method).config_of(config),
                metrics=config.metrics,
                device=config.device,
            )
            needs_field = get_method(row.method).needs_field
            data_id = sim_id
            if row.labels == "auto":
                data_id = self.auto_labelled(spec, sim_id)
                dataset_dir = self.plan.tasks[data_id].job.out
            job = ReconstructJob(
                dataset_dir, request, out, field_dir if needs_field else None,
                allow_other_field=needs_field and row.labels == "auto",
                report=config.cell_reports,
            )  # fmt: skip
            deps = (field_id, data_id) if needs_field else (data_id,)
        self.plan.tasks[task_id] = Task(task_id, deps, job)
        return task_id

    def cell(
        self, table: str, row_name: str, spec: DatasetSpec, row: Row, model_task: str | None = None
    ) -> None:
        self.register(table, row_name, spec, self.run(spec, row, model_task))

    def register(self, table: str, row_name: str, spec: DatasetSpec, task_id: str) -> None:
        primary = not any(c.task_id == task_id for c in self.plan.cells)
        run_dir = Path(self.plan.tasks[task_id].job.out).relative_to(self.out).as_posix()
        self.plan.cells.append(
            CellEntry(table, row_name, spec.phantom, spec.seed, task_id, run_dir, primary)
        )
