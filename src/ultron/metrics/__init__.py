"""Surface metrics: accuracy (MAD, RMSE, HD, HD95), completeness, Chamfer distance, F-score."""

from ultron.metrics.surface import (
    METRIC_NAMES,
    MetricsConfig,
    distance_metrics,
    evaluate_meshes,
    point_to_surface_distances,
    sample_surface,
)

__all__ = [
    "METRIC_NAMES",
    "MetricsConfig",
    "distance_metrics",
    "evaluate_meshes",
    "point_to_surface_distances",
    "sample_surface",
]
