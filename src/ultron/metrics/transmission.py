"""How well an estimated transmission T matches the simulator's true one (issue 15's stage-1
diagnostics; ground truth exists for simulated datasets only, ``<sweep>/transmission.npy``).

Three figures, over the labelled pixels (every pixel whose label is 0 or 1):

* ``median_abs_error`` = median |T − T_true|: the estimate's overall agreement (lit and shadow);
* ``deep_shadow_share`` = share of the pixels in deep shadow (T_true < ``deep_shadow_t``, 0.1)
  whose estimate is below ``low_t`` (0.3): does the estimate switch the shadow off, which is
  what the attenuation-compensated loss needs;
* ``roc_auc``: the area under the ROC curve of −T as a score separating shadowed pixels
  (T_true < ``shadow_t``, 0.3, the labels' own visibility criterion) from lit ones — the
  probability that a random shadowed pixel has a lower estimate than a random lit one (ties
  count one half), Mann–Whitney's U / (n_shadow · n_lit).

Issue 15's targets: median |T − T_true| ≤ 0.15, ROC AUC ≥ 0.9 (:data:`TARGETS`). Medians of the
estimate in deep shadow and in lit tissue (T_true > 0.9) are reported beside them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ultron.data.validation import LABEL_UNANNOTATED
from ultron.errors import argument_error

#: Issue 15's stage-1 targets: the largest median error and the smallest ROC AUC.
TARGETS = {"median_abs_error": 0.15, "roc_auc": 0.9}
#: How each target's figure must compare with its bound.
TARGET_RELATIONS = {"median_abs_error": "≤", "roc_auc": "≥"}
#: A pixel whose true T exceeds this counts as lit in ``lit_median``.
LIT_T = 0.9


@dataclass(frozen=True)
class TransmissionDiagnostics:
    """The figures of :func:`transmission_diagnostics` (NaN where a class is empty)."""

    n_pixels: int
    n_shadowed: int
    n_deep_shadow: int
    median_abs_error: float
    deep_shadow_share: float
    deep_shadow_median: float
    lit_median: float
    roc_auc: float
    shadow_t: float
    deep_shadow_t: float
    low_t: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: NaN becomes ``None``."""
        return {
            k: (None if isinstance(v, float) and math.isnan(v) else v)
            for k, v in asdict(self).items()
        }

    def meets_targets(self) -> dict[str, bool | None]:
        """Per target of :data:`TARGETS`: met, missed, or ``None`` when not measurable."""
        return {name: target_met(name, getattr(self, name)) for name in TARGETS}


def target_met(name: str, value: float | None) -> bool | None:
    """Whether ``value`` of figure ``name`` meets its target (:data:`TARGETS`,
    :data:`TARGET_RELATIONS`); ``None`` for a figure that was not measured (None or NaN)."""
    if name not in TARGETS:
        raise argument_error("name", f"expected one of {sorted(TARGETS)}, got {name!r}")
    if value is None or math.isnan(value):
        return None
    bound = TARGETS[name]
    return value <= bound if TARGET_RELATIONS[name] == "≤" else value >= bound


def roc_auc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for the boolean classes ``positive``: the
    probability that a random positive scores higher than a random negative, ties counting
    one half (Mann–Whitney U / (n₊ n₋), from average ranks). NaN when a class is empty."""
    scores = np.asarray(scores, dtype=np.float64).ravel()
    positive = np.asarray(positive).ravel()
    if positive.dtype != bool or positive.shape != scores.shape:
        raise argument_error("positive", "expected a boolean array of the scores' shape")
    n_pos = int(positive.sum())
    n_neg = positive.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return math.nan
    from scipy.stats import rankdata  # scipy.stats takes ~1 s to import: only when used

    ranks = rankdata(scores)
    u = ranks[positive].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def _median(values: np.ndarray) -> float:
    return float(np.median(values)) if values.size else math.nan


def transmission_diagnostics(
    estimate: np.ndarray,
    truth: np.ndarray,
    *,
    shadow_t: float = 0.3,
    deep_shadow_t: float = 0.1,
    low_t: float = 0.3,
) -> TransmissionDiagnostics:
    """Compare an estimated transmission with the true one at the same pixels (any equal
    shapes; NaN estimates — e.g. the ``labels`` source on unannotated scanlines — and NaN
    truths are left out). Values must lie in [0, 1]."""
    est = np.asarray(estimate, dtype=np.float64).ravel()
    true = np.asarray(truth, dtype=np.float64).ravel()
    if np.shape(estimate) != np.shape(truth):
        raise argument_error(
            "estimate", f"shape {np.shape(estimate)} differs from truth {np.shape(truth)}"
        )
    for name, value in (("shadow_t", shadow_t), ("deep_shadow_t", deep_shadow_t), ("low_t", low_t)):
        if not (isinstance(value, int | float) and 0 < value < 1):
            raise argument_error(name, f"expected a value in (0, 1), got {value!r}")
    keep = np.isfinite(est) & np.isfinite(true)
    est, true = est[keep], true[keep]
    for name, values in (("estimate", est), ("truth", true)):
        if values.size and (values.min() < 0 or values.max() > 1):
            raise argument_error(name, "expected transmissions in [0, 1]")
    shadowed = true < shadow_t
    deep = true < deep_shadow_t
    return TransmissionDiagnostics(
        n_pixels=int(est.size),
        n_shadowed=int(shadowed.sum()),
        n_deep_shadow=int(deep.sum()),
        median_abs_error=_median(np.abs(est - true)),
        deep_shadow_share=float((est[deep] < low_t).mean()) if deep.any() else math.nan,
        deep_shadow_median=_median(est[deep]),
        lit_median=_median(est[true > LIT_T]),
        roc_auc=roc_auc(-est, shadowed),
        shadow_t=float(shadow_t),
        deep_shadow_t=float(deep_shadow_t),
        low_t=float(low_t),
    )


def labelled_transmission_diagnostics(
    estimates: Mapping[str, np.ndarray],
    truths: Mapping[str, np.ndarray],
    labels: Mapping[str, np.ndarray],
    **thresholds: float,
) -> TransmissionDiagnostics:
    """:func:`transmission_diagnostics` pooled over sweeps, at their labelled pixels (label 0 or
    1; 255 = not annotated is left out). The three mappings are keyed by sweep name; every
    sweep of ``estimates`` needs a truth and labels of the same (N, H, W) shape."""
    est_parts, true_parts = [], []
    for name, estimate in estimates.items():
        if name not in truths or name not in labels:
            raise argument_error("truths", f"no true transmission or labels for sweep {name!r}")
        shapes = {np.shape(estimate), np.shape(truths[name]), np.shape(labels[name])}
        if len(shapes) != 1:
            raise argument_error("estimates", f"sweep {name!r}: shapes differ: {sorted(shapes)}")
        annotated = np.asarray(labels[name]) != LABEL_UNANNOTATED
        est_parts.append(np.asarray(estimate, dtype=np.float64)[annotated])
        true_parts.append(np.asarray(truths[name], dtype=np.float64)[annotated])
    if not est_parts:
        raise argument_error("estimates", "expected at least one sweep")
    return transmission_diagnostics(
        np.concatenate(est_parts), np.concatenate(true_parts), **thresholds
    )


__all__ = [
    "LIT_T",
    "TARGETS",
    "TARGET_RELATIONS",
    "TransmissionDiagnostics",
    "labelled_transmission_diagnostics",
    "roc_auc",
    "target_met",
    "transmission_diagnostics",
]
