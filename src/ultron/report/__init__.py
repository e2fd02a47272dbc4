"""Reporting: metric tables, figures (PNG, offscreen) and self-contained HTML reports.

* :mod:`ultron.report.tables` — metric tables for the terminal and markdown;
* :mod:`ultron.report.figures` — mesh-vs-reference, frames / θ / T, label masks, loss curves;
* :mod:`ultron.report.html` — a tiny HTML5 builder (sections, inline PNG figures, tables);
* :mod:`ultron.report.run_report` — ``write_run_report(run_dir)`` → ``run_dir/report.html``;
* :mod:`ultron.report.bench_report` — ``write_benchmark_report(bench_dir)``.

The report writers are importable from here; they are loaded on first use (they pull in torch
and matplotlib).
"""

from __future__ import annotations

from typing import Any

__all__ = ["write_benchmark_report", "write_run_report"]


def __getattr__(name: str) -> Any:
    if name == "write_run_report":
        from ultron.report.run_report import write_run_report

        return write_run_report
    if name == "write_benchmark_report":
        from ultron.report.bench_report import write_benchmark_report

        return write_benchmark_report
    raise AttributeError(f"module 'ultron.report' has no attribute {name!r}")
