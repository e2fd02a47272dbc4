"""Report sections shared by the run and benchmark reports: reading run outputs, and HTML
fragments for the summary, metrics, meshes, frames, label masks and loss curves.

A section whose input is missing or unreadable becomes a note saying why (the rest of the
report is still written); programming errors are not hidden.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ultron.data.auto_label_dataset import auto_label_records
from ultron.data.dataset import SweepDataset
from ultron.errors import UltronError, UltronInputError, argument_error
from ultron.mesh.export import load_mesh, load_vertex_properties
from ultron.report.evidence_figure import surface_evidence_figure
from ultron.report.figures import (
    frames_figure,
    label_masks_figure,
    loss_curves_figure,
    mesh_distance_figure,
)
from ultron.report.html import image_html, paragraph_html, table_html
from ultron.report.tables import LABELS, NOT_AVAILABLE, format_mean_std

STAGE_KEYS = ("stage1", "stage2", "stage3")


def existing_dir(value: Any, name: str) -> Path:
    """``value`` as the path of an existing directory; errors name the argument ``name``."""
    if not isinstance(value, str | Path):
        raise argument_error(name, f"expected a path, got {type(value).__name__}")
    root = Path(value)
    if not root.is_dir():
        raise UltronInputError(root, name, "is not a directory")
    return root


def read_json_file(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``; a missing or malformed file is an :class:`UltronInputError`."""
    if not path.is_file():
        raise UltronInputError(path, path.name, "file is missing")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UltronInputError(path, path.name, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise UltronInputError(path, path.name, "expected a JSON object")
    return data


def read_train_log(field_dir: Path) -> list[dict[str, Any]]:
    """The entries of ``field_dir/train_log.jsonl`` (one JSON object per line)."""
    path = field_dir / "train_log.jsonl"
    if not path.is_file():
        raise UltronInputError(path, "train_log.jsonl", "file is missing")
    entries = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            raise UltronInputError(path, f"line {number}", "not valid JSON") from None
        if isinstance(entry, dict):
            entries.append(entry)
    return entries


def resolve_dir(value: Any, base: Path) -> Path | None:
    """A directory named in a run.json (absolute, or relative to ``base``), or ``None``."""
    if not isinstance(value, str) or not value:
        return None
    path = Path(value)
    if not path.is_absolute() and not path.is_dir():
        path = base / path
    return path


def guarded(build: Callable[[], str], what: str) -> str:
    """``build()``, or a note naming ``what`` could not be shown when its input is bad."""
    try:
        return build()
    except (UltronError, OSError) as exc:
        return paragraph_html(f"{what} not available: {exc}", note=True)


def _number(value: Any, digits: int = 3) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def summary_html(run: Mapping[str, Any], run_dir: Path) -> str:
    """Method, label fraction, seed, label counts, mesh size, peak memory, inputs, timings."""
    selection = run.get("selection") if isinstance(run.get("selection"), dict) else {}
    mesh = run.get("mesh") if isinstance(run.get("mesh"), dict) else {}
    rows: list[tuple[str, str]] = [("run directory", str(run_dir))]
    fields = [
        ("method", run.get("method")),
        ("variant / preset", " / ".join(str(run[k]) for k in ("variant", "preset") if k in run)),
        ("label fraction", run.get("label_fraction", selection.get("fraction"))),
        ("seed", run.get("seed", selection.get("seed"))),
        ("labelled frames used", run.get("n_label_frames")),
        ("labelled pixels", run.get("n_labelled_pixels")),
        ("bone pixels", run.get("n_bone_pixels")),
        ("mesh vertices", mesh.get("vertices")),
        ("mesh faces", mesh.get("faces")),
        ("mesh area (mm²)", mesh.get("area_mm2")),
        ("peak memory (MiB)", run.get("peak_rss_mb")),
        ("dataset", run.get("dataset_dir")),
        ("acoustic field", run.get("field_dir")),
        ("field from cache", run.get("field_cached")),
    ]
    rows.extend((name, _number(value, 2)) for name, value in fields if value not in (None, ""))
    parts = [table_html(["item", "value"], rows)]
    timings = run.get("timings_s")
    if isinstance(timings, dict) and timings:
        total = timings.get("total") or sum(v for v in timings.values() if isinstance(v, float))
        timing_rows = [
            (stage, f"{seconds:.2f}", f"{100 * seconds / total:.1f} %" if total else "")
            for stage, seconds in timings.items()
            if isinstance(seconds, int | float)
        ]
        parts.append("<h3>Timings</h3>" + table_html(["stage", "seconds", "share"], timing_rows))
    versions = run.get("versions")
    if isinstance(versions, dict) and versions:
        parts.append(
            "<h3>Versions</h3>" + table_html(["package", "version"], list(versions.items()))
        )
    return "\n".join(parts)


def metrics_html(metrics: Mapping[str, Any]) -> str:
    """The metrics.json table: metric, mean ± std over the sampling repeats ("n/a": not
    measured, e.g. the visible-reference figures without a visible reference)."""
    mean, std = metrics.get("mean"), metrics.get("std", {})
    if not isinstance(mean, dict) or not mean:
        raise UltronInputError("metrics.json", "mean", "missing or empty")
    std = std if isinstance(std, dict) else {}
    rows = []
    for name, value in mean.items():
        spread = std.get(name)
        try:
            text = format_mean_std(
                None if value is None else float(value),
                None if spread is None else float(spread),
            )
        except (TypeError, ValueError):
            text = NOT_AVAILABLE if value is None else str(value)
        rows.append((LABELS.get(name, name), name, text))
    config = metrics.get("config")
    note = ""
    if isinstance(config, dict):
        note = paragraph_html(
            "Distances in mm (F-scores are shares); mean ± std over "
            f"{config.get('repeats', '?')} repeats of {config.get('n_points', '?')} points per "
            "surface. HD and HD95 are one-sided (reconstruction → reference); HD sym. and HD95 "
            "sym. take the larger of both directions. The 'vis.' figures measure completeness "
            "against the visible part of the reference (what some frame could image); n/a "
            "without one."
        )
    return table_html(["metric", "key", "mean ± std"], rows) + note


def mesh_figure_html(
    mesh_path: Path, reference: Path | None, title: str, attrs: Mapping[str, Any] | None = None
) -> str:
    """The mesh-vs-reference figure of ``mesh_path`` (``reference`` may be ``None``)."""
    mesh = load_mesh(mesh_path)
    ref = load_mesh(reference) if reference is not None else None
    png = mesh_distance_figure(mesh, ref, title)
    caption = (
        f"{title}: reconstruction coloured by point-to-surface distance to the reference "
        "(colour clipped at 10 mm), reference in grey; orthographic views of 20,000 surface "
        "samples per mesh."
        if ref is not None
        else f"{title}: reconstruction (no reference surface available)."
    )
    return image_html(png, f"{title}: reconstructed surface", caption, attrs)


def evidence_html(run_dir: Path, title: str) -> str:
    """The observed-vs-inferred figure of the run's whole extracted surface
    (``surface_extracted.ply`` when the observed crop dropped faces, else ``mesh.ply``), from
    the evidence in its PLY vertex properties; a note for a mesh written without them."""
    extracted = run_dir / "surface_extracted.ply"
    path = extracted if extracted.is_file() else run_dir / "mesh.ply"
    if not path.is_file():
        return note("No mesh.ply in the run directory.")
    properties = load_vertex_properties(path)
    if not {"observed", "label_distance_mm"} <= properties.keys():
        return note(f"{path.name} has no per-vertex evidence (written by an older ultron).")
    mesh = load_mesh(path)
    png = surface_evidence_figure(
        mesh.vertices, properties["observed"], properties["label_distance_mm"], title
    )
    kept = (
        "mesh.ply keeps only the observed faces (--surface observed); the figure shows the "
        "whole extracted iso-surface (surface_extracted.ply)."
        if path == extracted
        else "The figure shows mesh.ply."
    )
    caption = (
        f"{title}: vertices observed by some frame (in its image and elevational slab, facing "
        "the probe, T ≥ 0.3 above them; T ≡ 1 for methods without a transmission; for UltrON "
        "also showing bone there: an echo or a shadow's onset, run.json's echo_support) in blue, "
        "inferred ones in orange; right, each vertex's distance to the nearest labelled bone "
        f"pixel the method used (colour clipped at the 95th percentile). {kept} Both are PLY "
        "vertex properties: observed (0/1) and label_distance_mm."
    )
    return image_html(png, f"{title}: observed and inferred surface", caption,
                      {"data-kind": "evidence"})  # fmt: skip


def example_frames(dataset: SweepDataset, count: int = 2) -> tuple[str, list[int]]:
    """The first sweep's name and ``count`` evenly spaced interior frame indices."""
    sweep = dataset.sweeps[0]
    n = sweep.n_frames
    picks = sorted({min(n - 1, (k + 1) * n // (count + 1)) for k in range(count)})
    return sweep.name, picks


def frames_html(dataset: SweepDataset, fitted, attrs: Mapping[str, Any] | None = None) -> str:
    """Example frames of the first sweep (with rendered B-mode, θ and T when ``fitted``)."""
    sweep_name, picks = example_frames(dataset)
    png = frames_figure(dataset, fitted, sweep_name, picks)
    if fitted is None:
        caption = f"Recorded B-mode of sweep {sweep_name!r}, frames {picks} (no acoustic field)."
    else:
        caption = (
            f"Sweep {sweep_name!r}, frames {picks}: recorded B-mode, the field's rendered "
            "B-mode, its θ maps (colour range: 1st–99th percentile) and transmission T."
        )
    return image_html(png, "example frames", caption, {"data-kind": "frames", **(attrs or {})})


def masks_html(
    dataset: SweepDataset, selection: Any, attrs: Mapping[str, Any] | None = None
) -> str:
    """The labelled frames used (run.json ``selection``), masks overlaid."""
    if not isinstance(selection, dict) or not isinstance(selection.get("frames"), dict):
        raise UltronInputError("run.json", "selection", "missing (no label selection recorded)")
    png = label_masks_figure(dataset, selection["frames"])
    used = sum(len(v) for v in selection["frames"].values())
    caption = (
        f"{used} labelled frames used (fraction {selection.get('fraction')}, seed "
        f"{selection.get('seed')}); up to 8 shown, frames with bone first. Red: bone, "
        "blue: ignored (255), untinted: background."
    ) + _auto_label_note(dataset)
    return image_html(png, "label masks", caption, {"data-kind": "labels", **(attrs or {})})


def _auto_label_note(dataset: SweepDataset) -> str:
    """`` Labels of sweep(s) …: automatic (ultron label --auto, …).`` or ``""``."""
    records = auto_label_records(dataset)
    if not records:
        return ""
    methods = sorted({str(r.get("method", "?")) for r in records.values()})
    return (
        f" Labels of sweep(s) {', '.join(sorted(records))}: automatic (ultron label --auto,"
        f" {', '.join(methods)}), not drawn by a person."
    )


def _find_curves(node: Any, path: str, out: dict[str, list[dict]]) -> None:
    """Lists of {"step", "loss"} dicts anywhere under ``node``, keyed by their path."""
    if isinstance(node, dict):
        for key, value in node.items():
            _find_curves(value, f"{path}/{key}" if path else str(key), out)
    elif isinstance(node, list) and node and all(isinstance(e, dict) for e in node):
        if all("step" in e and "loss" in e for e in node):
            out[path] = list(node)


def run_loss_curves(
    run: Mapping[str, Any], field_dir: Path | None, prefix: str = ""
) -> dict[str, list[dict]]:
    """Loss curves of a run: ``occupancy_log``, the field's train log, RoCoSDF stage logs."""
    curves: dict[str, list[dict]] = {}
    if isinstance(run.get("occupancy_log"), list) and run["occupancy_log"]:
        curves[f"{prefix}occupancy"] = run["occupancy_log"]
    for stage in STAGE_KEYS:
        found: dict[str, list[dict]] = {}
        _find_curves(run.get(stage), stage, found)
        curves.update({f"{prefix}{name}": entries for name, entries in found.items()})
    if field_dir is not None and (field_dir / "train_log.jsonl").is_file():
        log = [e for e in read_train_log(field_dir) if "step" in e and "loss" in e]
        if log:
            curves[f"{prefix}acoustic field"] = log
    return curves


def final_loss_rows(run: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str, str]]:
    """(stage, loss, value) of every ``final_losses`` dict under the stage logs (RoCoSDF), and
    UltrON's label loss (``occupancy_label_loss``; per candidate field when there were several,
    ``field_candidates``)."""
    rows: list[tuple[str, str, str]] = []
    for candidate in run.get("field_candidates") or []:
        kept = " (kept)" if candidate.get("field_dir") == run.get("field_dir") else ""
        name = f"label loss, field {candidate.get('field_dir')}{kept}"
        rows.append((prefix + "occupancy", name, _number(candidate.get("occupancy_label_loss"), 5)))
    if "occupancy_label_loss" in run and not run.get("field_candidates"):
        rows.append((prefix + "occupancy", "label loss", _number(run["occupancy_label_loss"], 5)))

    def visit(node: Any, path: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "final_losses" and isinstance(value, dict):
                    rows.extend((prefix + path, k, _number(v, 4)) for k, v in value.items())
                else:
                    visit(value, f"{path}/{key}")

    for stage in STAGE_KEYS:
        visit(run.get(stage), stage)
    return rows


def losses_html(curves: dict[str, list[dict]], final_rows: list[tuple[str, str, str]]) -> str:
    """The loss-curve figure and a table of final stage losses (either may be empty)."""
    parts = []
    if curves:
        png = loss_curves_figure(curves)
        caption = "Training loss against step: " + ", ".join(curves) + "."
        parts.append(image_html(png, "loss curves", caption, {"data-kind": "losses"}))
    if final_rows:
        parts.append("<h3>Final stage losses</h3>")
        parts.append(table_html(["stage", "loss", "value"], final_rows))
    if not parts:
        parts.append(paragraph_html("No training logs recorded for this run.", note=True))
    return "\n".join(parts)


def note(text: str) -> str:
    """A remark paragraph (escaped)."""
    return paragraph_html(text, note=True)
