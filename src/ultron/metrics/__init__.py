"""Surface metrics: accuracy (MAD, RMSE, HD, HD95; one-sided), completeness (also of the
visible reference), Chamfer distances, symmetric Hausdorff distances, F-score; exact
point-to-mesh distances; an estimated transmission against the true one (stage-1 diagnostics)."""

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
from ultron.metrics.transmission import (
    TransmissionDiagnostics,
    labelled_transmission_diagnostics,
    transmission_diagnostics,
)

__all__ = [
    "METRIC_NAMES",
    "VISIBLE_METRIC_NAMES",
    "MeshDistanceIndex",
    "MetricsConfig",
    "TransmissionDiagnostics",
    "build_distance_index",
    "distance_index",
    "distance_metrics",
    "evaluate_meshes",
    "labelled_transmission_diagnostics",
    "mesh_distances",
    "point_to_surface_distances",
    "sample_surface",
    "transmission_diagnostics",
]
