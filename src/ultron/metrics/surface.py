"""Surface distance metrics between a reconstructed mesh and a reference mesh (METHOD.md §5).

Both surfaces are sampled uniformly by area (``n_points`` each, seeded) and every sample's
exact point-to-surface distance to the other mesh is computed (:mod:`ultron.metrics.distance`:
the exact minimum of the point-to-triangle distances over all triangles of positive area,
libigl's AABB tree), once per repeat in each direction, then reduced. A triangle without area
(coincident or collinear corners: a segment or a point, which marching cubes leaves where the
surface passes through a grid node) is not surface: no sample lies on it, and no distance ends
on it.

* accuracy, reconstruction → reference distances d_acc: MAD = mean d_acc,
  RMSE = sqrt(mean d_acc²), HD = max d_acc, HD95 = 95th percentile of d_acc. HD and HD95 are
  therefore ONE-SIDED (how far the reconstruction strays from the reference, not how much of
  the reference it misses);
* completeness, reference → reconstruction distances d_comp: mean, HD95 (``completeness``,
  ``completeness_hd95``);
* symmetric Hausdorff distances ``hd_sym`` = max(max d_acc, max d_comp) and
  ``hd95_sym`` = max(HD95 of d_acc, HD95 of d_comp);
* Chamfer distance CD = (mean d_acc + mean d_comp) / 2;
* F-score at τ: precision P = share of d_acc < τ, recall R = share of d_comp < τ,
  F = 2PR / (P + R) (0 when P + R = 0), for τ = 1 mm and 2 mm;
* with a visible reference (the part of the reference some frame could image, e.g. a
  simulated dataset's ``reference_visible.ply``), d_vis from its samples to the
  reconstruction: ``completeness_visible`` = mean d_vis, ``completeness_visible_hd95`` and
  ``cd_visible`` = (mean d_acc + mean d_vis) / 2 (accuracy stays against the whole reference).
  ``fscore_visible_1mm`` / ``2mm`` are the F-scores with recall against the visible reference
  (share of d_vis < τ). Without a visible reference these five are None (shown as "n/a",
  never 0).
* **crop** (``crop_mm``, needs a visible reference): for a real sweep whose images show more
  than the reference holds (the tibia and soft tissue beside a CT fibula), the reconstruction's
  faces whose centroid lies farther than ``crop_mm`` from the visible reference are dropped
  before sampling; every figure is then of the kept part, and ``"crop"`` reports the area kept
  and the area left outside (mm²) so that what was dropped stays visible.

The paper's table samples points on the reconstruction and measures to the CAD model, so its
MAD, RMSE and HD correspond to ultron's accuracy figures (``mad``, ``rmse``, ``hd``), and its
CD to ``cd``.

Empty reconstruction (no triangles): accuracy figures are NaN (there is nothing to measure
from), completeness, CD, the symmetric HDs and the visible figures are +inf (nothing reaches
the reference), F-scores are 0. An empty reference (or visible reference) is an input error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ultron.arguments import check_count, check_seed
from ultron.errors import UltronInputError, argument_error
from ultron.memory import check_fits_in_memory
from ultron.metrics.distance import MeshDistanceIndex, build_distance_index, mesh_distances

#: Every metric, in display order (the visible-reference figures first).
METRIC_NAMES = (
    "cd_visible",
    "completeness_visible",
    "cd",
    "hd95",
    "hd",
    "mad",
    "rmse",
    "completeness",
    "completeness_hd95",
    "completeness_visible_hd95",
    "hd_sym",
    "hd95_sym",
    "fscore_1mm",
    "fscore_2mm",
    "fscore_visible_1mm",
    "fscore_visible_2mm",
)
#: The metrics that need a visible reference (None without one).
VISIBLE_METRIC_NAMES = (
    "cd_visible",
    "completeness_visible",
    "completeness_visible_hd95",
    "fscore_visible_1mm",
    "fscore_visible_2mm",
)


#: Bytes per sampled point while both surfaces are scored: points and normals (float64), the
#: distances both ways, a surface's nearest-triangle query and the visible crop's; rounded up.
POINT_BYTES = 512


@dataclass(frozen=True)
class MetricsConfig:
    """Sampling settings (module doc).

    Attributes:
        n_points: Points sampled per surface.
        repeats: Repeats with different seeds (seed … seed + repeats − 1).
        seed: First sampling seed.
        crop_mm: Keep only the mesh's faces within this distance (mm) of the visible
            reference before measuring (a real sweep images more than its reference holds,
            e.g. the tibia beside a CT fibula); the area left outside is reported (default:
            no crop).
    """

    n_points: int = 100_000
    repeats: int = 3
    seed: int = 0
    crop_mm: float | None = None

    def __post_init__(self) -> None:
        check_count("n_points", self.n_points)
        check_count("repeats", self.repeats)
        check_seed("seed", self.seed)
        crop = self.crop_mm
        if crop is not None and not (isinstance(crop, int | float) and 0 < crop < math.inf):
            raise argument_error("crop_mm", f"expected a positive distance in mm, got {crop!r}")


def distance_metrics(
    acc_mm: np.ndarray, comp_mm: np.ndarray, comp_visible_mm: np.ndarray | None = None
) -> dict[str, float | None]:
    """Reduce accuracy (recon → ref), completeness (ref → recon) and, optionally, visible
    completeness (visible ref → recon) distances to :data:`METRIC_NAMES` (module doc)."""
    if comp_mm.size == 0:
        raise argument_error("comp_mm", "reference distances are empty")
    if comp_visible_mm is not None and comp_visible_mm.size == 0:
        raise argument_error("comp_visible_mm", "visible-reference distances are empty")
    if acc_mm.size == 0:
        nan, inf = float("nan"), math.inf
        result = {
            "cd": inf, "hd": nan, "mad": nan, "rmse": nan, "hd95": nan,
            "completeness": inf, "completeness_hd95": inf, "hd_sym": inf, "hd95_sym": inf,
            "fscore_1mm": 0.0, "fscore_2mm": 0.0,
        }  # fmt: skip
        result |= dict.fromkeys(VISIBLE_METRIC_NAMES, None if comp_visible_mm is None else inf)
        if comp_visible_mm is not None:
            result |= {"fscore_visible_1mm": 0.0, "fscore_visible_2mm": 0.0}
        return {name: result[name] for name in METRIC_NAMES}
    hd95, comp_hd95 = float(np.percentile(acc_mm, 95)), float(np.percentile(comp_mm, 95))
    result: dict[str, float | None] = {
        "cd": float((acc_mm.mean() + comp_mm.mean()) / 2),
        "hd": float(acc_mm.max()),
        "mad": float(acc_mm.mean()),
        "rmse": float(np.sqrt(np.mean(acc_mm**2))),
        "hd95": hd95,
        "completeness": float(comp_mm.mean()),
        "completeness_hd95": comp_hd95,
        "hd_sym": float(max(acc_mm.max(), comp_mm.max())),
        "hd95_sym": max(hd95, comp_hd95),
    }
    result.update(dict.fromkeys(VISIBLE_METRIC_NAMES))
    if comp_visible_mm is not None:
        result["completeness_visible"] = float(comp_visible_mm.mean())
        result["completeness_visible_hd95"] = float(np.percentile(comp_visible_mm, 95))
        result["cd_visible"] = float((acc_mm.mean() + comp_visible_mm.mean()) / 2)
    for tau in (1, 2):
        result[f"fscore_{tau}mm"] = _fscore(acc_mm, comp_mm, tau)
        if comp_visible_mm is not None:
            result[f"fscore_visible_{tau}mm"] = _fscore(acc_mm, comp_visible_mm, tau)
    return {name: result[name] for name in METRIC_NAMES}


def _fscore(acc_mm: np.ndarray, comp_mm: np.ndarray, tau: float) -> float:
    """F = 2PR / (P + R), P = share of ``acc_mm`` < τ, R = share of ``comp_mm`` < τ (0 when
    P + R = 0)."""
    precision = float((acc_mm < tau).mean())
    recall = float((comp_mm < tau).mean())
    total = precision + recall
    return 0.0 if total == 0 else 2 * precision * recall / total


def sample_surface(mesh, n_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_points`` points uniformly distributed by area on ``mesh`` (seeded), float64 (n, 3),
    and the index of the face each lies on."""
    import trimesh

    points, faces = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(faces, dtype=np.int64)


def distance_index(mesh) -> MeshDistanceIndex:
    """The exact-distance search structure of the triangles of positive area of a trimesh
    mesh that has some (module doc), reusable."""
    triangles = np.asarray(mesh.triangles, dtype=np.float64)
    return build_distance_index(triangles[np.asarray(mesh.area_faces) > 0])


def point_to_surface_distances(
    points: np.ndarray, target_mesh, index: MeshDistanceIndex | None = None
) -> np.ndarray:
    """Exact distance (mm) from each of ``points`` (n, 3) to the surface of ``target_mesh``:
    min over its triangles T of min_{q ∈ T} |p − q| (:mod:`ultron.metrics.distance`).
    ``index`` (from :func:`distance_index` of the same mesh) saves rebuilding the search."""
    if index is None:
        if target_mesh is None or len(target_mesh.faces) == 0 or target_mesh.area <= 0:
            raise argument_error("target_mesh", "mesh is empty (no triangle of positive area)")
        index = distance_index(target_mesh)
    return mesh_distances(points, index)


def crop_near(mesh, index: MeshDistanceIndex, max_mm: float):
    """The faces of ``mesh`` whose centroid lies within ``max_mm`` of the surface indexed by
    ``index`` (a new mesh, unreferenced vertices removed; empty when none is)."""
    import trimesh

    if len(mesh.faces) == 0:
        return mesh
    centroids = np.asarray(mesh.triangles_center, dtype=np.float64)
    keep = mesh_distances(centroids, index) <= max_mm
    cropped = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    cropped.remove_unreferenced_vertices()
    return cropped


def _crop_reconstruction(reconstruction, reference_visible, crop_mm: float):
    """The reconstruction cropped to ``crop_mm`` of the visible reference and the crop's
    record (areas in mm²)."""
    empty = reconstruction is None or len(reconstruction.faces) == 0
    total = 0.0 if empty else float(reconstruction.area)
    if not empty:
        reconstruction = crop_near(reconstruction, distance_index(reference_visible), crop_mm)
    kept = 0.0 if empty or len(reconstruction.faces) == 0 else float(reconstruction.area)
    record = {
        "crop_mm": crop_mm,
        "area_mm2": total,
        "area_kept_mm2": kept,
        "area_outside_mm2": total - kept,
    }
    return reconstruction, record


def _check_reference(mesh, name: str) -> None:
    if mesh is None or len(mesh.faces) == 0 or mesh.area <= 0:
        raise UltronInputError(name, "mesh", f"{name} mesh is empty (no triangles)")


def evaluate_meshes(
    reconstruction, reference, config: MetricsConfig | None = None, reference_visible=None
) -> dict:
    """Metrics of ``reconstruction`` against ``reference`` (trimesh meshes in mm), and its
    visible part ``reference_visible`` when given (module doc).

    Returns ``{"mean": {...}, "std": {...}, "repeats": [{...}, ...], "config": {...},
    "crop": {...} | None}`` where each inner dict of figures maps every name of
    :data:`METRIC_NAMES` to a float (None: not measured, the visible figures without a
    visible reference).
    """
    config = config or MetricsConfig()
    check_fits_in_memory(
        float(config.n_points) * POINT_BYTES, "argument", "n_points (--points)",
        f"{config.n_points} points per surface",
    )  # fmt: skip
    _check_reference(reference, "reference")
    if reference_visible is not None:
        _check_reference(reference_visible, "reference_visible")
    crop = None
    if config.crop_mm is not None:
        if reference_visible is None:
            raise argument_error(
                "reference_visible", "the crop (crop_mm) needs a visible reference"
            )
        reconstruction, crop = _crop_reconstruction(
            reconstruction, reference_visible, config.crop_mm
        )
    empty = reconstruction is None or len(reconstruction.faces) == 0 or reconstruction.area <= 0
    ref_index = None if empty else distance_index(reference)
    rec_index = None if empty else distance_index(reconstruction)
    runs = []
    for k in range(config.repeats):
        seed = config.seed + k
        ref_points, _ = sample_surface(reference, config.n_points, seed=2 * seed + 1)
        vis_points = None
        if reference_visible is not None:
            vis_points, _ = sample_surface(reference_visible, config.n_points, seed=2 * seed + 1)
        if empty:
            acc, comp = np.zeros(0), np.full(config.n_points, np.inf)
            comp_vis = None if vis_points is None else np.full(config.n_points, np.inf)
        else:
            rec_points, _ = sample_surface(reconstruction, config.n_points, seed=2 * seed)
            acc = mesh_distances(rec_points, ref_index)
            comp = mesh_distances(ref_points, rec_index)
            comp_vis = None if vis_points is None else mesh_distances(vis_points, rec_index)
        runs.append(distance_metrics(acc, comp, comp_vis))
    mean = {name: _reduce(np.mean, [r[name] for r in runs]) for name in METRIC_NAMES}
    std = {name: _reduce(np.std, [r[name] for r in runs]) for name in METRIC_NAMES}
    return {
        "mean": mean,
        "std": std,
        "repeats": runs,
        "config": {
            "n_points": config.n_points,
            "repeats": config.repeats,
            "seed": config.seed,
            "crop_mm": config.crop_mm,
        },
        "crop": crop,
    }


def _reduce(fn, values: list[float | None]) -> float | None:
    if any(v is None for v in values):
        return None
    array = np.asarray(values, dtype=np.float64)
    if np.isnan(array).all():
        return float("nan")
    if np.isinf(array).any():
        return math.inf if fn is np.mean else float("nan")
    return float(fn(array))
