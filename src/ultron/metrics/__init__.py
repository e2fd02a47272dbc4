"""Surface metrics: accuracy (MAD, RMSE, HD, HD95; one-sided), completeness (also of the
visible reference), Chamfer distances, symmetric Hausdorff distances, F-score; exact
point-to-mesh distances."""

from ultron.metrics.distance import (
    MeshDistanceIndex,
    build_distance_index,
    mesh_distances,
)
from ultron.metrics.surface import (
    METRIC_NAMES,
    VISIBLE_METRIC_NAMES,
    MetricsConfig,
    distance_index,
    distance_metrics,
    evaluate_meshes,
    point_to_surface_distances,
    sample_surface,
)

__all__ = [
    "METRIC_NAMES",
    "VISIBLE_METRIC_NAMES",
    "MeshDistanceIndex",
    "MetricsConfig",
    "build_distance_index",
    "distance_index",
    "distance_metrics",
    "evaluate_meshes",
    "mesh_distances",
    "point_to_surface_distances",
    "sample_surface",
]
