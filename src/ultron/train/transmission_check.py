"""A transmission source checked against the simulator's truth (diagnostic, simulated data only).

:func:`transmission_check` renders T of every frame of every annotated sweep from a source of
:mod:`ultron.train.visibility` (the fitted field by default) and compares it, at the labelled
pixels, with ``<sweep>/transmission.npy`` (:mod:`ultron.metrics.transmission`: median
|T − T_true|, the share of deep-shadow pixels the estimate switches off, the shadowed-vs-lit
ROC AUC). :func:`ultron.train.fit_field` writes the field's check to FIELD_DIR's
``transmission_check.json`` when the dataset has the truth; the benchmark prints them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ultron.data.dataset import SweepDataset
from ultron.metrics.transmission import TARGETS, labelled_transmission_diagnostics
from ultron.train.visibility import VisibilityConfig, frame_transmission

#: The check's file format (``transmission_check.json``'s ``format``).
CHECK_FORMAT = "ultron-transmission-check/1"


def has_truth(dataset: SweepDataset) -> bool:
    """Every annotated sweep carries its true transmission (and there is one)."""
    annotated = [s for s in dataset.sweeps if s.labels is not None]
    return bool(annotated) and all(s.true_transmission is not None for s in annotated)


def transmission_check(
    dataset: SweepDataset, fitted=None, source: VisibilityConfig | None = None
) -> dict[str, Any] | None:
    """The diagnostics of ``source`` (default: the field's T, which needs ``fitted``) over
    every labelled pixel of ``dataset``, as a JSON-ready record with the targets' verdicts;
    None when the dataset has no true transmission (:func:`has_truth`)."""
    if not has_truth(dataset):
        return None
    config = source or VisibilityConfig("field")
    estimates, truths, labels = {}, {}, {}
    for sweep in dataset.sweeps:
        if sweep.labels is None:
            continue
        estimates[sweep.name] = frame_transmission(config, dataset, sweep.name, fitted=fitted)
        truths[sweep.name] = np.asarray(sweep.true_transmission, dtype=np.float32)
        labels[sweep.name] = sweep.labels
    diagnostics = labelled_transmission_diagnostics(estimates, truths, labels)
    return {
        "format": CHECK_FORMAT,
        "source": config.source,
        "pixels": "every labelled pixel (label 0 or 1) of every annotated sweep",
        **diagnostics.to_dict(),
        "targets": dict(TARGETS),
        "met": diagnostics.meets_targets(),
    }


__all__ = ["CHECK_FORMAT", "has_truth", "transmission_check"]
