"""``run_benchmark``: plan, run (resumably, in parallel), aggregate, write DIR/benchmark.json.

Outputs (atomic): ``DIR/benchmark.json`` (schema below), ``DIR/tables.md`` (the markdown tables
and targets) and ``DIR/report.html`` (:mod:`ultron.report.bench_report`)::

    {"config": {...every setting, "settings": the result-shaping ones...},
     "markdown": {"table1": "...", "table1_per_phantom": "...", "table2": "...",
                  "robustness": "...", "stage1": "..."},                  # those that ran
     "tables": {"table1": [{"row", "n", "mean": {metric: float}, "std": {...},
                            "paper": {metric: float} | null}], ...},
     "targets": [{"name": str, "met": bool | null, "detail": str}],
     "cells": [{"id", "table", "row", "phantom", "seed", "run_dir" (relative to DIR),
                "status": "ok" | "failed", "error": str | null, "runtime_s": float}],
     "stage1": {"n", "mean": {figure: float}, "std": {...},           # each field's T vs
                "fields": [{"dataset", "default", figure: float}]}}   # the true T (stage1.py)

Non-finite figures (an empty reconstruction's CD, a row without cells) are written as null. A
run reused by another table (Table 2's "full training", the robustness "default" rows) appears
once per table; only its first entry carries its runtime, the others 0. Re-running into the same
DIR resumes: finished datasets, fields and cells are skipped, failed ones are retried; a DIR
made with other result-shaping settings is refused.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ultron import atomic
from ultron.benchmark import stage1
from ultron.benchmark.config import LEGACY_SETTINGS, TABLE1, BenchmarkConfig
from ultron.benchmark.plan import Plan, Task, plan_benchmark
from ultron.benchmark.ray_executor import check_executor
from ultron.benchmark.runner import Outcome, default_threads, run_tasks
from ultron.benchmark.tables import (
    TARGETS,
    aggregate,
    cell_figures,
    cell_targets,
    json_safe,
    markdown_table,
    per_phantom_markdown,
    table1_phantoms,
)
from ultron.device import resolve_device
from ultron.errors import UltronInputError, argument_error
from ultron.outputs import check_not_inside_output, ultron_output_kind
from ultron.report.bench_report import write_benchmark_report

BENCHMARK_JSON = "benchmark.json"
TABLES_MD = "tables.md"
#: The key of ``markdown``'s per-phantom Table 1 (CD vis. per phantom, mean over seeds).
PER_PHANTOM = "table1_per_phantom"

Log = Callable[[str], None]


@dataclass
class BenchmarkResult:
    """The written ``benchmark.json`` payload and what this call did."""

    out: Path
    payload: dict[str, Any]
    executed: list[str] = field(default_factory=list)  # task ids run now
    skipped: list[str] = field(default_factory=list)  # task ids already done
    failed: list[str] = field(default_factory=list)  # task ids that failed (cells and others)
    notes: list[str] = field(default_factory=list)

    @property
    def failed_cells(self) -> list[dict[str, Any]]:
        return [c for c in self.payload["cells"] if c["status"] == "failed"]

    @property
    def markdown(self) -> str:
        return tables_markdown(self.payload)


def check_out_dir(out: Path, config: BenchmarkConfig) -> None:
    """``out`` must be a directory (or absent) whose earlier results used the same settings."""
    if out.exists() and not out.is_dir():
        raise argument_error("out", f"{out} exists and is not a directory")
    kind = ultron_output_kind(out) or ("dataset" if (out / "dataset.json").exists() else None)
    if kind is not None:
        raise UltronInputError(
            out, "--out", f"is an ultron {kind}'s directory, whose files the benchmark's"
            " reports would mix with or replace: give another directory",
        )  # fmt: skip
    check_not_inside_output(out, "--out")
    previous = out / BENCHMARK_JSON
    if not previous.is_file():
        return
    try:
        saved = json.loads(previous.read_text(encoding="utf-8"))["config"]["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        return  # unreadable or older: the per-task checks still guard datasets and fields
    current = json.loads(json.dumps(config.settings(), default=str))
    saved = {**LEGACY_SETTINGS, **saved}
    differing = sorted(k for k in current if k in saved and saved[k] != current[k])
    if differing:
        raise UltronInputError(
            previous,
            "config",
            f"{out} holds results made with other settings ({', '.join(differing)});"
            " use another --out directory",
        )


def run_benchmark(
    config: BenchmarkConfig,
    out: str | Path,
    log: Log | None = None,
    report_html: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> BenchmarkResult:
    """Run the benchmark of ``config`` into ``out`` (see the module doc); the executor
    (:func:`~ultron.benchmark.runner.run_tasks`) does not change a cell's outputs.

    Args:
        config: Every setting of the benchmark.
        out: Output directory (resumed if it exists).
        log: Told each line of progress.
        report_html: Write DIR/report.html.
        executor: local (this machine, config.jobs at a time) or ray (each task a Ray task of
            config.threads CPUs; needs Ray: pip install ray).
        address: With the ray executor: the Ray cluster to join (auto, ray://host:10001);
            default: start a local one.
    """
    check_executor(executor, address)
    if not isinstance(config, BenchmarkConfig):
        raise argument_error("config", f"expected a BenchmarkConfig, got {type(config).__name__}")
    out = Path(out)
    say = log or (lambda line: None)
    check_out_dir(out, config)
    plan = plan_benchmark(config, out)
    for note in plan.notes:
        say(f"note: {note}")
    threads = config.threads or default_threads(config.jobs)
    tasks = list(plan.tasks.values())
    cells = sum(task.is_cell for task in tasks)
    say(
        f"{len(tasks)} tasks ({cells} runs) into {out}; "
        + (f"{config.jobs} job(s)" if executor == "local" else "Ray tasks")
        + f" × {threads} torch thread(s)"
    )
    gpus = 1.0 if resolve_device(config.device, "device").type == "cuda" else 0.0
    outcomes = run_tasks(
        tasks, config.jobs, threads, _reporter(say), executor=executor, address=address,
        gpus=gpus,
    )  # fmt: skip
    payload = build_payload(config, plan, outcomes, out, threads)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_json(out / BENCHMARK_JSON, payload)
    atomic.write_text(out / TABLES_MD, tables_markdown(payload) + "\n")
    result = BenchmarkResult(
        out=out,
        payload=payload,
        executed=[k for k, v in outcomes.items() if v["status"] == "ok"],
        skipped=[k for k, v in outcomes.items() if v["status"] == "skipped"],
        failed=[k for k, v in outcomes.items() if v["status"] == "failed"],
        notes=list(plan.notes),
    )
    if report_html:
        result.notes.append(write_report(out))
    return result


def _reporter(say: Log) -> Callable[[Task, Outcome, int, int], None]:
    def report(task: Task, outcome: Outcome, done: int, total: int) -> None:
        status = outcome["status"]
        line = f"[{done}/{total}] {task.id}: {status}"
        if status == "ok":
            line += f" in {outcome['runtime_s']:.1f} s"
        if outcome.get("cd_visible") is not None:
            line += f", CD vis. {outcome['cd_visible']:.3f} mm"
        if outcome.get("cd") is not None:
            line += f", CD {outcome['cd']:.3f} mm"
        if status == "failed":
            line += f": {outcome['error']}"
        say(line)

    return report


def build_payload(
    config: BenchmarkConfig,
    plan: Plan,
    outcomes: dict[str, Outcome],
    out: Path,
    threads: int,
) -> dict[str, Any]:
    """The ``benchmark.json`` content (module doc) of a finished run."""
    status = {task_id: outcome["status"] for task_id, outcome in outcomes.items()}
    tables = {name: aggregate(name, plan.cells, status, out) for name in plan.tables}
    targets = [t for name in plan.tables for t in TARGETS[name](tables[name])]
    figures = {}
    if TABLE1 in plan.tables:  # every cell's metrics.json read once, for both uses below
        figures = cell_figures(plan.cells, status, out)
        targets += cell_targets(figures)
    markdown = {}
    for name, rows in tables.items():
        markdown[name] = markdown_table(name, rows)
        if name == TABLE1 and (
            per_phantom := per_phantom_markdown(figures, table1_phantoms(plan.cells))
        ):
            markdown[PER_PHANTOM] = per_phantom
    stage1_summary = stage1.summarise(stage1.field_checks(plan, status))
    if stage1_summary["fields"]:  # simulated datasets carry the true T
        markdown[stage1.STAGE1] = stage1.markdown(stage1_summary)
        targets += stage1.targets(stage1_summary)
    cells = []
    for cell in plan.cells:
        outcome = outcomes[cell.task_id]
        failed = outcome["status"] == "failed"
        cells.append(
            {
                "id": cell.id,
                "table": cell.table,
                "row": cell.row,
                "phantom": cell.phantom,
                "seed": cell.seed,
                "run_dir": cell.run_dir,
                "status": "failed" if failed else "ok",
                "error": outcome["error"] if failed else None,
                "runtime_s": float(outcome["runtime_s"]) if cell.primary else 0.0,
            }
        )
    annotation, tracking = config.robust_annotation, config.robust_tracking
    settings = {
        **config.to_dict(),
        "out": str(out),
        "threads_per_job": threads,
        "tables": list(plan.tables),
        "notes": list(plan.notes),
        "robustness_conditions": {
            "annotation errors": "annotation: jitter_mm, error_rate, error_shift_mm as in"
            f" robust_annotation ({annotation.jitter_mm} mm, {annotation.error_rate},"
            f" {annotation.error_shift_mm} mm)",
            "pose misalignment": "tracking: translation_mm, rotation_deg per axis as in"
            f" robust_tracking ({tracking.translation_mm} mm, {tracking.rotation_deg} deg)",
        },
        "aggregation": "mean ± std (ddof 1) over phantoms × seeds of each cell's metric means",
        "settings": config.settings(),
    }
    return json_safe(
        {"config": settings, "markdown": markdown, "tables": tables, "targets": targets,
         "cells": cells, "stage1": stage1_summary}
    )  # fmt: skip


def targets_markdown(targets: list[dict[str, Any]]) -> str:
    """One line per target: met / MISSED / not measured, with its figures."""
    lines = ["**Targets**", ""]
    for target in targets:
        verdict = {True: "met", False: "MISSED", None: "n/a"}[target["met"]]
        lines.append(f"- {verdict}: {target['name']} — {target['detail']}")
    return "\n".join(lines)


def tables_markdown(payload: dict[str, Any]) -> str:
    """The tables and the targets of a ``benchmark.json`` payload as one markdown text."""
    failed = [c for c in payload["cells"] if c["status"] == "failed"]
    parts = list(payload["markdown"].values())
    parts.append(targets_markdown(payload["targets"]))
    if failed:
        lines = [f"**Failed cells ({len(failed)})**", ""]
        lines += [f"- {c['id']} ({c['run_dir']}): {c['error']}" for c in failed]
        parts.append("\n".join(lines))
    return "\n\n".join(parts)


def write_report(out: Path) -> str:
    """DIR/report.html via :func:`ultron.report.bench_report.write_benchmark_report`; returns a
    note saying what happened (the tables are already written: a report failure is reported,
    not raised)."""
    try:
        write_benchmark_report(out)
    except Exception as exc:  # the tables are written; a report failure must not hide them
        return f"report.html not written: {type(exc).__name__}: {exc}"
    return f"report written: {out / 'report.html'}"
