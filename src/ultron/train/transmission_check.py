"""A transmission source checked against the simulator's truth (diagnostic, simulated data only).

:func:`transmission_check` ray-casts the fitted field's T through every frame of every
annotated sweep (the ``field`` source of :mod:`ultron.train.visibility`) and compares it, at the
labelled pixels, with ``<sweep>/transmission.npy`` (:mod:`ultron.metrics.transmission`: median
|T − T_true|, the share of deep-shadow pixels the estimate switches off, the shadowed-vs-lit
ROC AUC). :func:`record_transmission_check` writes it to FIELD_DIR's
``transmission_check.json`` when the dataset has the truth (:func:`ultron.train.fit_field` at
the end of every fit; the benchmark for fields fitted before the check existed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ultron.data.dataset import SweepDataset
from ultron.metrics.transmission import TARGETS, labelled_transmission_diagnostics
from ultron.models.field_dir import write_transmission_check
from ultron.models.fitted import FittedField
from ultron.train.visibility import VisibilityConfig, frame_transmission

#: The check's file format (``transmission_check.json``'s ``format``).
CHECK_FORMAT = "ultron-transmission-check/1"


def has_truth(dataset: SweepDataset) -> bool:
    """Every annotated sweep carries its true transmission (and there is one)."""
    annotated = [s for s in dataset.sweeps if s.labels is not None]
    return bool(annotated) and all(s.true_transmission is not None for s in annotated)


def transmission_check(dataset: SweepDataset, fitted: FittedField) -> dict[str, Any] | None:
    """The diagnostics of ``fitted``'s T over every labelled pixel of ``dataset``, as a
    JSON-ready record with the targets' verdicts; None when the dataset has no true
    transmission (:func:`has_truth`)."""
    if not has_truth(dataset):
        return None
    config = VisibilityConfig("field")
    annotated = [sweep for sweep in dataset.sweeps if sweep.labels is not None]
    estimates = {
        s.name: frame_transmission(config, dataset, s.name, fitted=fitted) for s in annotated
    }
    diagnostics = labelled_transmission_diagnostics(
        estimates,
        {s.name: s.true_transmission for s in annotated},
        {s.name: s.labels for s in annotated},
    )
    return {
        "format": CHECK_FORMAT,
        "source": config.source,
        "pixels": "every labelled pixel (label 0 or 1) of every annotated sweep",
        **diagnostics.to_dict(),
        "targets": dict(TARGETS),
        "met": diagnostics.meets_targets(),
    }


def record_transmission_check(dataset: SweepDataset, fitted: FittedField, out: Path) -> None:
    """Write FIELD_DIR ``out``'s ``transmission_check.json`` when ``dataset`` has the truth."""
    check = transmission_check(dataset, fitted)
    if check is not None:
        write_transmission_check(out, check)


__all__ = ["CHECK_FORMAT", "has_truth", "record_transmission_check", "transmission_check"]
