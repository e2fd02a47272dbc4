"""``write_benchmark_report``: a benchmark directory → a self-contained ``report.html``.

Reads ``bench_dir/benchmark.json``::

    {"config": {...},
     "markdown": {"table1": "<markdown table>", ...},          # any subset
     "targets": [{"name": str, "met": bool | null, "detail": str}],
     "cells": [{"id", "table", "row", "phantom", "seed", "run_dir" (relative to bench_dir),
                "status": "ok" | "failed", "error"}]}

and writes the tables, the targets, the cells' status, ONE mesh-vs-reference figure per
distinct row (method) from its first successful cell (``<figure data-kind="mesh"
data-method="ROW">``), example frames with θ / T maps of the first cell that used an acoustic
field, the label masks of one cell (one whose method read the field first), and the cells' loss curves in one figure.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronError, UltronInputError
from ultron.methods.catalog import FIELD_RUN_METHODS
from ultron.models.fitted import load_field
from ultron.pipeline.record import RunRecord
from ultron.report.html import (
    Section,
    build_html,
    esc,
    markdown_table_html,
    pre_json_html,
    table_html,
    write_html,
)
from ultron.report.sections import (
    existing_dir,
    final_loss_rows,
    frames_html,
    guarded,
    losses_html,
    masks_html,
    mesh_figure_html,
    note,
    read_json_file,
    read_train_log,
    resolve_dir,
    run_loss_curves,
)

BENCHMARK_JSON = "benchmark.json"
REPORT_NAME = "report.html"
TABLE_ORDER = ("table1", "table1_per_phantom", "table2", "robustness")
MAX_CURVES = 6


@dataclass
class Cell:
    """One benchmark cell as read from benchmark.json, with its run directory resolved."""

    id: str
    row: str
    status: str
    run_dir: Path
    entry: dict[str, Any]


def read_benchmark(bench_dir: Path) -> tuple[dict[str, Any], list[Cell]]:
    """benchmark.json and its cells; malformed entries raise :class:`UltronInputError`."""
    path = bench_dir / BENCHMARK_JSON
    data = read_json_file(path)
    for key, kind in (("config", dict), ("markdown", dict), ("targets", list), ("cells", list)):
        if key in data and data[key] is not None and not isinstance(data[key], kind):
            raise UltronInputError(path, key, f"expected a JSON {kind.__name__}")
    cells = []
    for i, entry in enumerate(data.get("cells") or []):
        if not isinstance(entry, dict):
            raise UltronInputError(path, f"cells[{i}]", "expected an object")
        for key in ("row", "run_dir"):
            if not isinstance(entry.get(key), str) or not entry[key]:
                raise UltronInputError(path, f"cells[{i}].{key}", "expected a non-empty string")
        run_dir = Path(entry["run_dir"])
        cells.append(
            Cell(
                id=str(entry.get("id", f"cell {i}")),
                row=entry["row"],
                status=str(entry.get("status", "unknown")),
                run_dir=run_dir if run_dir.is_absolute() else bench_dir / run_dir,
                entry=entry,
            )
        )
    return data, cells


class _Loader:
    """Caches run.json files, datasets and fields shared by many cells."""

    def __init__(self) -> None:
        self.runs: dict[Path, RunRecord] = {}
        self.datasets: dict[Path, SweepDataset] = {}
        self.fields: dict[Path, Any] = {}

    def run(self, cell: Cell) -> RunRecord:
        if cell.run_dir not in self.runs:
            self.runs[cell.run_dir] = RunRecord.read(cell.run_dir)
        return self.runs[cell.run_dir]

    def dataset(self, cell: Cell) -> SweepDataset:
        path = resolve_dir(self.run(cell).dataset_dir, cell.run_dir)
        if path is None:
            raise UltronInputError(cell.run_dir / "run.json", "dataset_dir", "is missing")
        if path not in self.datasets:
            self.datasets[path] = SweepDataset.load(path)
        return self.datasets[path]

    def field_dir(self, cell: Cell) -> Path | None:
        path = resolve_dir(self.run(cell).field_dir, cell.run_dir)
        return path if path is not None and path.is_dir() else None

    def fitted(self, field_dir: Path):

        if field_dir not in self.fields:
            self.fields[field_dir] = load_field(field_dir)
        return self.fields[field_dir]


def _ok_cells(cells: list[Cell], loader: _Loader) -> list[Cell]:
    """Successful cells whose run directory holds a readable run.json, in file order."""
    found = []
    for cell in cells:
        if cell.status != "ok" or not (cell.run_dir / "run.json").is_file():
            continue
        try:
            loader.run(cell)
        except UltronError:
            continue
        found.append(cell)
    return found


def _rows(cells: list[Cell]) -> list[str]:
    return list(dict.fromkeys(cell.row for cell in cells))


def _tables_html(markdown: dict[str, Any]) -> str:
    keys = [k for k in TABLE_ORDER if k in markdown] + [k for k in markdown if k not in TABLE_ORDER]
    if not keys:
        return note("benchmark.json holds no markdown tables.")
    parts = []
    for key in keys:
        value = markdown[key]
        parts.append(f"<h3>{esc(key)}</h3>")
        parts.append(guarded(lambda value=value: markdown_table_html(str(value)), f"table {key!r}"))
    return "\n".join(parts)


def _targets_html(targets: list[Any]) -> str:
    if not targets:
        return note("benchmark.json lists no targets.")
    rows = []
    for target in targets:
        target = target if isinstance(target, dict) else {"name": str(target)}
        met = target.get("met")
        verdict = "met" if met is True else "not met" if met is False else "not measured"
        rows.append((target.get("name", "?"), verdict, target.get("detail", "")))
    return table_html(["target", "verdict", "detail"], rows)


def _cells_html(cells: list[Cell]) -> str:
    if not cells:
        return note("benchmark.json lists no cells.")
    keys = ("id", "table", "row", "phantom", "seed", "status", "error")
    return table_html(list(keys), [[c.entry.get(k, "") for k in keys] for c in cells])


def _meshes_html(rows: list[str], ok: list[Cell], loader: _Loader) -> str:
    parts = []
    for row in rows:
        cell = next((c for c in ok if c.row == row and (c.run_dir / "mesh.ply").is_file()), None)
        if cell is None:
            parts.append(note(f"{row}: no successful cell with a mesh."))
            continue

        def figure(cell: Cell = cell, row: str = row) -> str:
            try:
                reference = loader.dataset(cell).reference
                remark = "" if reference else note(f"{row}: the dataset has no reference.")
            except UltronError as exc:
                reference, remark = None, note(f"{row}: reference unknown ({exc}).")
            attrs = {"data-kind": "mesh", "data-method": row, "data-cell": cell.id}
            title = f"{row} (cell {cell.id})"
            return remark + mesh_figure_html(cell.run_dir / "mesh.ply", reference, title, attrs)

        parts.append(guarded(figure, f"{row} mesh"))
    return "\n".join(parts)


def _frames_html(ok: list[Cell], loader: _Loader) -> tuple[str, Path | None]:
    cell = next((c for c in ok if loader.field_dir(c) is not None), None)
    if cell is None:
        return note("No successful cell used an acoustic field."), None
    field_dir = loader.field_dir(cell)

    def figure() -> str:
        attrs = {"data-method": cell.row, "data-cell": cell.id}
        return frames_html(loader.dataset(cell), loader.fitted(field_dir), attrs)

    return guarded(figure, f"frames of cell {cell.id}"), field_dir


def _masks_html(ok: list[Cell], loader: _Loader) -> str:
    with_selection = [c for c in ok if isinstance(loader.run(c).details.get("selection"), dict)]
    on_field = (c for c in with_selection if loader.run(c).method in FIELD_RUN_METHODS)
    cell = next(on_field, None) or next(iter(with_selection), None)
    if cell is None:
        return note("No successful cell with a recorded label selection.")
    attrs = {"data-method": cell.row, "data-cell": cell.id}
    return guarded(
        lambda: masks_html(loader.dataset(cell), loader.run(cell).details["selection"], attrs),
        f"label masks of cell {cell.id}",
    )


def _losses_html(rows: list[str], ok: list[Cell], loader: _Loader, field_dir: Path | None) -> str:
    curves: dict[str, list[dict]] = {}
    finals: list[tuple[str, str, str]] = []
    for row in rows:
        cell = next((c for c in ok if c.row == row), None)
        if cell is None:
            continue
        run = loader.run(cell).to_dict()
        curves.update(run_loss_curves(run, None, prefix=f"{row}: "))
        finals.extend(final_loss_rows(run, prefix=f"{row}: "))
    curves = dict(list(curves.items())[: MAX_CURVES - 1 if field_dir else MAX_CURVES])
    if field_dir is not None and (field_dir / "train_log.jsonl").is_file():
        log = [e for e in read_train_log(field_dir) if "step" in e and "loss" in e]
        if log:
            curves["acoustic field"] = log
    return losses_html(curves, finals)


def build_benchmark_report(bench_dir: str | Path) -> str:
    """The HTML text of :func:`write_benchmark_report` (nothing is written)."""
    root = existing_dir(bench_dir, "bench_dir")
    data, cells = read_benchmark(root)
    loader = _Loader()
    ok = _ok_cells(cells, loader)
    rows = _rows(cells)
    failed = sum(1 for c in cells if c.status != "ok")
    overview = (
        f"<p>{len(cells)} cells ({len(cells) - failed} ok, {failed} not ok), {len(rows)} "
        f"methods.</p><details><summary>configuration</summary>"
        f"{pre_json_html(data.get('config') or {})}</details>"
    )
    frames, field_dir = _frames_html(ok, loader)
    sections = [
        Section("Overview", overview),
        Section("Tables", _tables_html(data.get("markdown") or {})),
        Section("Targets", _targets_html(data.get("targets") or [])),
        Section("Cells", _cells_html(cells)),
        Section("Reconstructions vs reference (one per method)", _meshes_html(rows, ok, loader)),
        Section("Example frames and field maps", frames),
        Section("Label masks (UltrON)", _masks_html(ok, loader)),
        Section(
            "Loss curves", guarded(lambda: _losses_html(rows, ok, loader, field_dir), "Losses")
        ),
    ]
    return build_html(f"ultron benchmark report: {root.name}", sections)


def write_benchmark_report(bench_dir: str | Path) -> Path:
    """Write ``bench_dir/report.html`` from ``bench_dir/benchmark.json``; returns its path."""
    text = build_benchmark_report(bench_dir)
    return write_html(Path(bench_dir) / REPORT_NAME, text)
