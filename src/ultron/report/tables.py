"""Metric tables for the terminal (rich) and for markdown."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ultron.metrics.surface import METRIC_NAMES

LABELS = {
    "cd": "CD",
    "hd": "HD",
    "mad": "MAD",
    "rmse": "RMSE",
    "hd95": "HD95",
    "completeness": "Comp.",
    "completeness_hd95": "Comp. HD95",
    "fscore_1mm": "F@1mm",
    "fscore_2mm": "F@2mm",
}


def format_mean_std(mean: float, std: float) -> str:
    """'1.23 ± 0.04' (or 'inf' / 'nan')."""
    if math.isnan(mean) or math.isinf(mean):
        return str(mean)
    if math.isnan(std) or std == 0:
        return f"{mean:.3f}"
    return f"{mean:.3f} ± {std:.3f}"


def metrics_table(
    results: Mapping[str, Mapping], title: str = "", names: Sequence[str] = METRIC_NAMES
):
    """A rich Table with one row per entry of ``results`` (each an ``evaluate_meshes`` result)."""
    from rich.table import Table

    table = Table(title=title or None)
    table.add_column("method")
    for name in names:
        table.add_column(LABELS.get(name, name), justify="right")
    for row, result in results.items():
        mean, std = result["mean"], result["std"]
        table.add_row(row, *(format_mean_std(mean[n], std[n]) for n in names))
    return table


def metrics_markdown(results: Mapping[str, Mapping], names: Sequence[str] = METRIC_NAMES) -> str:
    """The same table as GitHub markdown."""
    header = "| method | " + " | ".join(LABELS.get(n, n) for n in names) + " |"
    rule = "|---|" + "---:|" * len(names)
    rows = [
        f"| {row} | " + " | ".join(format_mean_std(r["mean"][n], r["std"][n]) for n in names) + " |"
        for row, r in results.items()
    ]
    return "\n".join([header, rule, *rows])
