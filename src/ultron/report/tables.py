"""Metric tables for the terminal (rich) and for markdown."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ultron.metrics.surface import METRIC_NAMES

LABELS = {
    "cd_visible": "CD vis.",
    "completeness_visible": "Comp. vis.",
    "completeness_visible_hd95": "Comp. vis. HD95",
    "hd_sym": "HD sym.",
    "hd95_sym": "HD95 sym.",
    "cd": "CD",
    "hd": "HD",
    "mad": "MAD",
    "rmse": "RMSE",
    "hd95": "HD95",
    "completeness": "Comp.",
    "completeness_hd95": "Comp. HD95",
    "fscore_1mm": "F@1mm",
    "fscore_2mm": "F@2mm",
    "fscore_visible_1mm": "F@1mm vis.",
    "fscore_visible_2mm": "F@2mm vis.",
}


#: How a metric that was not measured (None, e.g. no visible reference) is shown.
NOT_AVAILABLE = "n/a"


def format_mean_std(mean: float | None, std: float | None) -> str:
    """'1.23 ± 0.04' (or 'inf' / 'nan'; 'n/a' when ``mean`` is None: not measured)."""
    if mean is None:
        return NOT_AVAILABLE
    if math.isnan(mean) or math.isinf(mean):
        return str(mean)
    if std is None or math.isnan(std) or std == 0:
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
        table.add_row(row, *(format_mean_std(mean.get(n), std.get(n)) for n in names))
    return table


def metrics_column_table(result: Mapping, title: str = "", names: Sequence[str] = METRIC_NAMES):
    """A rich Table of one ``evaluate_meshes`` result, one metric per row (metric, key,
    mean ± std): readable in a narrow terminal."""
    from rich.table import Table

    table = Table(title=title or None)
    for column, justify in (("metric", "left"), ("key", "left"), ("mean ± std", "right")):
        table.add_column(column, justify=justify)
    mean, std = result["mean"], result["std"]
    for name in names:
        table.add_row(LABELS.get(name, name), name, format_mean_std(mean.get(name), std.get(name)))
    return table


def metrics_markdown(results: Mapping[str, Mapping], names: Sequence[str] = METRIC_NAMES) -> str:
    """The same table as GitHub markdown."""
    header = "| method | " + " | ".join(LABELS.get(n, n) for n in names) + " |"
    rule = "|---|" + "---:|" * len(names)
    rows = [
        f"| {row} | "
        + " | ".join(format_mean_std(r["mean"].get(n), r["std"].get(n)) for n in names)
        + " |"
        for row, r in results.items()
    ]
    return "\n".join([header, rule, *rows])
