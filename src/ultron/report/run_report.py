"""``write_run_report``: one reconstruction run directory → a self-contained ``report.html``.

Reads ``run.json`` (required), ``mesh.ply`` and ``metrics.json`` (when present), the dataset
named by run.json's ``dataset_dir`` and the acoustic field named by its ``field_dir`` (unless
given), and writes ``run_dir/report.html`` (atomically) with: a summary (method, label
fraction, seed, timings, peak memory), the metrics table, the mesh-vs-reference figure,
the observed-vs-inferred surface (:mod:`ultron.mesh.evidence`), example frames (with the field's rendered B-mode, θ and T maps when a field is available), the
label masks used, and the loss curves.
"""

from __future__ import annotations

import time
from pathlib import Path

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError, argument_error
from ultron.methods.catalog import FIELD_RUN_METHODS
from ultron.models.fitted import load_field
from ultron.pipeline.record import RunRecord
from ultron.report.html import Section, build_html, write_html
from ultron.report.sections import (
    evidence_html,
    existing_dir,
    final_loss_rows,
    frames_html,
    guarded,
    losses_html,
    masks_html,
    mesh_figure_html,
    metrics_html,
    note,
    read_json_file,
    resolve_dir,
    run_loss_curves,
    summary_html,
)

REPORT_NAME = "report.html"


def _load_dataset(run: RunRecord, root: Path) -> tuple[SweepDataset | None, str]:
    """The run's dataset from run.json ``dataset_dir`` and, when absent, why."""
    dataset_dir = resolve_dir(run.dataset_dir, root)
    if dataset_dir is None:
        return None, "run.json records no dataset_dir and no dataset was given"
    try:
        return SweepDataset.load(dataset_dir), ""
    except (UltronInputError, OSError) as exc:
        return None, f"the dataset could not be loaded: {exc}"


def _load_fitted(run: RunRecord, root: Path):
    """The acoustic field named by run.json ``field_dir`` (or ``None``) and a remark."""
    field_dir = resolve_dir(run.field_dir, root)
    if field_dir is None:
        if run.method in FIELD_RUN_METHODS:
            return None, "run.json records no field_dir: the field's maps are not shown"
        return None, ""
    try:
        return load_field(field_dir), ""
    except (UltronInputError, OSError) as exc:
        return None, f"the acoustic field could not be loaded: {exc}"


def _or_unknown(value: object) -> str:
    return "?" if value is None else str(value)


def build_run_report(
    run_dir: str | Path,
    dataset: SweepDataset | None = None,
    fitted=None,
    shown_as: str | Path | None = None,
) -> str:
    """The HTML text of :func:`write_run_report` (nothing is written)."""
    root = existing_dir(run_dir, "run_dir")
    shown = Path(shown_as) if shown_as is not None else root
    if dataset is not None and not isinstance(dataset, SweepDataset):
        raise argument_error("dataset", f"expected a SweepDataset, got {type(dataset).__name__}")
    if fitted is not None and not hasattr(fitted, "render_maps"):
        raise argument_error("fitted", f"expected a FittedField, got {type(fitted).__name__}")
    start = time.perf_counter()
    record = RunRecord.read(root)
    run, method = record.to_dict(), record.method
    dataset_note = ""
    if dataset is None:
        dataset, dataset_note = _load_dataset(record, root)
    field_note = ""
    if fitted is None:
        fitted, field_note = _load_fitted(record, root)
    field_dir = resolve_dir(record.field_dir, root)

    sections = [Section("Summary", summary_html(run, shown))]

    metrics_path = root / "metrics.json"
    if metrics_path.is_file():
        body = guarded(lambda: metrics_html(read_json_file(metrics_path)), "Metrics")
    else:
        body = note("No metrics.json: the dataset has no reference surface.")
    sections.append(Section("Metrics", body))

    reference = dataset.reference if dataset is not None else None
    mesh_path = root / "mesh.ply"
    if mesh_path.is_file():
        body = guarded(
            lambda: mesh_figure_html(
                mesh_path, reference, method, {"data-kind": "mesh", "data-method": method}
            ),
            "Mesh figure",
        )
        if dataset is None:
            body = note(f"Reference unknown: {dataset_note}.") + body
    else:
        body = note("No mesh.ply in the run directory.")
    sections.append(Section("Reconstruction vs reference", body))
    body = guarded(lambda: evidence_html(root, method), "Observed vs inferred figure")
    sections.append(Section("Observed vs inferred surface", body))

    if dataset is None:
        skipped = note(f"Skipped: {dataset_note}.")
        sections.append(Section("Example frames", skipped))
        sections.append(Section("Label masks used", skipped))
    else:
        body = guarded(lambda: frames_html(dataset, fitted), "Example frames")
        if field_note:
            body = note(field_note) + body
        sections.append(Section("Example frames", body))
        sections.append(
            Section("Label masks used", guarded(lambda: masks_html(dataset, run.get("selection")),
                                                "Label masks"))
        )  # fmt: skip

    def losses() -> str:
        return losses_html(run_loss_curves(run, field_dir), final_loss_rows(run))

    sections.append(Section("Loss curves", guarded(losses, "Loss curves")))
    subtitle = (
        f"Run directory {shown.name}: method {method}, label fraction "
        f"{_or_unknown(record.label_fraction)}, seed {_or_unknown(record.seed)}. Report built in "
        f"{time.perf_counter() - start:.1f} s."
    )
    return build_html(f"ultron run report: {method}", sections, subtitle)


def write_run_report(
    run_dir: str | Path,
    dataset: SweepDataset | None = None,
    fitted=None,
    shown_as: str | Path | None = None,
) -> Path:
    """Write ``run_dir/report.html`` for a reconstruction run and return its path.

    ``dataset`` (default: loaded from run.json's ``dataset_dir``) provides the reference
    surface, frames and labels; ``fitted`` (default: loaded from run.json's ``field_dir``) the
    rendered B-mode, θ and T maps. Sections whose input is unavailable say so instead.
    ``shown_as`` is the directory the report names (default ``run_dir``): the run's own, when
    the report is written into its staging copy (:func:`ultron.pipeline.run.write_outputs`).
    """
    root = existing_dir(run_dir, "run_dir")
    text = build_run_report(root, dataset, fitted, shown_as)
    return write_html(root / REPORT_NAME, text)
