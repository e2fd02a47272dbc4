"""The paper's published figures (mean, std in mm), copied from its Tables 1 and 2.

Source: ``ultron-paper.tex``, Table 1 (``tab:results``) and Table 2 (``tab:generalization``).
The paper reports CD, HD, MAD and RMSE only; it has no compounding rows, no "full training"
row in Table 2 (its text calls fine-tuning "comparable to the full training") and no numbers
for the robustness study (a figure only). Rows absent here have no paper figures.
"""

from __future__ import annotations

from types import MappingProxyType

PAPER_METRICS = ("cd", "hd", "mad", "rmse")


def _row(*values: tuple[float, float]) -> MappingProxyType[str, tuple[float, float]]:
    return MappingProxyType(dict(zip(PAPER_METRICS, values, strict=True)))


#: Table 1: method (supervision) → metric → (mean, std), mm.
TABLE1 = MappingProxyType(
    {
        "RoCoSDF (100%)": _row((2.98, 0.03), (9.79, 0.02), (2.53, 0.02), (3.67, 0.03)),
        "ON (100%)": _row((2.91, 0.03), (9.23, 0.02), (2.60, 0.03), (3.70, 0.03)),
        "UltrON w/o loss (10%)": _row((3.25, 0.12), (9.30, 0.06), (2.82, 0.12), (3.98, 0.15)),
        "UltrON (10%)": _row((2.22, 0.02), (7.98, 0.04), (1.67, 0.02), (2.69, 0.03)),
        "UltrON (5%)": _row((2.36, 0.03), (8.04, 0.05), (1.85, 0.03), (2.88, 0.03)),
    }
)

#: Table 2 (trained on L3, applied to L2): supervision + iterations → metric → (mean, std), mm.
TABLE2 = MappingProxyType(
    {
        "w/o fine-tuning": _row((3.44, 0.02), (13.23, 0.07), (1.79, 0.02), (2.67, 0.03)),
        "1% + 100 iter": _row((2.44, 0.02), (7.91, 0.04), (2.00, 0.02), (2.94, 0.03)),
    }
)

PAPER = MappingProxyType({"table1": TABLE1, "table2": TABLE2})


def paper_figures(table: str, row: str) -> MappingProxyType[str, tuple[float, float]] | None:
    """The paper's (mean, std) per metric of ``row`` in ``table``, or None."""
    return PAPER.get(table, {}).get(row)


def paper_means(table: str, row: str) -> dict[str, float] | None:
    """The paper's mean per metric of ``row`` in ``table``, or None."""
    figures = paper_figures(table, row)
    return None if figures is None else {m: mean for m, (mean, _) in figures.items()}
