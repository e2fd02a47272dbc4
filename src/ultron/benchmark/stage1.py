"""Stage 1 in the benchmark: each fitted field's T against the simulator's truth (issue 15).

Every field task of the plan leaves ``transmission_check.json`` in its FIELD_DIR
(:mod:`ultron.train.transmission_check`, written by the fit). Here they are read back, one row
per dataset, averaged over the datasets of the default condition (the robustness conditions'
fields are listed, not averaged), printed as a markdown table and checked against the targets
(median |T − T_true| ≤ 0.15, shadowed-vs-lit ROC AUC ≥ 0.9) on the mean.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ultron.benchmark.config import DEFAULT
from ultron.benchmark.plan import FieldJob, Plan
from ultron.errors import UltronInputError
from ultron.metrics.transmission import TARGET_RELATIONS, TARGETS, target_met
from ultron.models.field_dir import read_transmission_check

STAGE1 = "stage1"
#: The check's figures shown, in order, with their column titles.
FIGURES = {
    "median_abs_error": "median abs(T − T_true)",
    "roc_auc": "ROC AUC shadowed vs lit",
    "deep_shadow_share": "share T < 0.3 where T_true < 0.1",
    "deep_shadow_median": "median T where T_true < 0.1",
    "lit_median": "median T where T_true > 0.9",
}


def field_checks(plan: Plan, status: Mapping[str, str]) -> list[dict[str, Any]]:
    """One entry per field task that succeeded and left a check: ``{"dataset", "default",
    **figures}`` (a missing or unreadable check is left out)."""
    entries = []
    for task_id, task in plan.tasks.items():
        if not isinstance(task.job, FieldJob) or status.get(task_id) == "failed":
            continue
        try:
            check = read_transmission_check(Path(task.job.out))
        except UltronInputError:
            check = None
        if check is None:
            continue
        name = task_id.split(":", 1)[1]
        entry: dict[str, Any] = {"dataset": name, "default": task.job.condition == DEFAULT}
        entry.update({k: check.get(k) for k in FIGURES})
        entries.append(entry)
    return entries


def summarise(entries: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean and std (ddof 1; 0 for one) of each figure over the default condition's datasets."""
    rows = [e for e in entries if e["default"]]
    mean, std = {}, {}
    for key in FIGURES:
        values = [float(e[key]) for e in rows if e.get(key) is not None]
        mean[key] = float(np.mean(values)) if values else None
        std[key] = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0 if values else None
    return {"n": len(rows), "mean": mean, "std": std, "fields": list(entries)}


def _cell(value: Any, spread: Any = None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:.3f}" if spread is None else f"{value:.3f} ± {spread:.3f}"


def markdown(summary: Mapping[str, Any]) -> str:
    """The per-dataset rows and their mean as a markdown table."""
    header = "| dataset | " + " | ".join(FIGURES.values()) + " |"
    lines = [
        "**Stage 1: the fitted field's transmission T against the simulator's truth**",
        "",
        header,
        "|---|" + "---:|" * len(FIGURES),
    ]
    for entry in summary["fields"]:
        lines.append(
            f"| {entry['dataset']} | " + " | ".join(_cell(entry.get(k)) for k in FIGURES) + " |"
        )
    if summary["n"]:
        mean = [_cell(summary["mean"][k], summary["std"][k]) for k in FIGURES]
        lines.append(f"| mean ± std ({summary['n']} datasets) | " + " | ".join(mean) + " |")
    lines += [
        "",
        "over every labelled pixel of each dataset; shadowed: T_true < 0.3; the mean over the"
        " default condition's datasets (robustness datasets listed only)",
    ]
    return "\n".join(lines)


def targets(summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Issue 15's stage-1 targets on the mean over the default datasets."""
    result = []
    for key, bound in TARGETS.items():
        name = f"stage 1: {FIGURES[key]} {TARGET_RELATIONS[key]} {bound:g} (mean over datasets)"
        value = summary["mean"].get(key) if summary["n"] else None
        met = target_met(key, value)
        detail = "not measured (no ground truth)" if met is None else f"{value:.3f}"
        result.append({"name": name, "met": met, "detail": detail})
    return result


__all__ = ["FIGURES", "STAGE1", "field_checks", "markdown", "summarise", "targets"]
