"""Which parts of a surface some frame actually observed.

A point x of a surface with outward unit normal n is *observed* by frame k (probe-to-world
pose P_k, beam direction b_k = P_k's probe +y in world) when, with p = P_k⁻¹ x its probe
coordinates (lateral p_x, depth p_y, elevation p_z, mm):

* it lies in the image: |p_x| ≤ W_mm/2 and 0 ≤ p_y < D_mm;
* it lies in the frame's elevational slab: |p_z| ≤ ``slab_half_thickness_mm``;
* it faces the transducer: −n·b_k ≥ cos(``max_incidence_deg``) (the beam meets it from the
  outside at an incidence of at most that angle; a surface seen edge-on or from behind sends
  no specular echo back);
* the beam reaches it: the transmission T_k just above it — at the pixel row r = ⌊p_y/Δ⌋ of
  the nearest scanline, T being exclusive — is ≥ ``min_transmission``.

With echo support (:mod:`ultron.mesh.echo_support`, UltrON's default) some frame must also
show bone at the point: a frame for which the point lies in the image and slab and faces the
transducer, whose support map is true at the point's pixel (row ⌊p_y/Δ⌉) — not necessarily the
frame that observed it (each test errs with the tracked pose; requiring both of one frame
dropped true surface on the simulated L3, docs/real-sweeps.md).

With label support (``label_support_mm`` > 0 and the labelled surface given, UltrON's default)
a point within that distance of the labelled surface — the top edge of a band of bone labels
in a frame the method trained on (:func:`~ultron.data.labels.labelled_surface_points_mm`) — is
observed as well: the annotator saw bone there. The field's T decays with depth through real
tissue, so a deep wall the annotator labelled can fall below ``min_transmission`` (figures in
docs/real-sweeps.md). With ``label_bridges`` the labelled surface also runs between consecutive
labelled frames whose labelled cross-sections agree (:mod:`ultron.mesh.label_bridges`).

A point is observed when some frame observes it. This is the criterion the simulated labels
follow (a visible echo under an unshadowed beam), so with the simulator's true T it gives the
part of the reference that *can* be seen; with the transmission a reconstruction estimated,
it gives the part of a reconstructed surface that is backed by evidence (everything else —
walls along shadow columns, floors under them — was never observed; the paper's Fig. 1c).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import as_pose_tensor, probe_mm_to_pixel
from ultron.errors import argument_error
from ultron.mesh.evidence import nearest_distance_mm
from ultron.mesh.extract import ExtractionConfig
from ultron.mesh.occupancy_mesh import elevation_half_thickness_mm

_FRAMES_PER_CHUNK = 8

#: Defaults of the criterion: the simulated annotator's (incidence ≤ 70°, T ≥ 0.3).
DEFAULT_MAX_INCIDENCE_DEG = 70.0
DEFAULT_MIN_TRANSMISSION = 0.3
#: Distance (mm) from the labelled surface within which a point counts as observed.
DEFAULT_LABEL_SUPPORT_MM = 1.0
#: ``observation_transmission`` of the T ≡ 1 criterion (:func:`faced_observation`).
NO_TRANSMISSION = "none (T = 1)"
#: What a reconstruction keeps of its surface: only the observed part, or all of it.
SURFACES = ("observed", "all")

#: The extraction of a surface the observed crop then trims (UltrON, its ablation, label
#: compounding): every connected piece is meshed, however small. What is kept is decided by
#: what some frame observed (this module), not by a piece's size against the
#: largest one — which, for an occupancy that fills the shadow or a long bone, drops labelled
#: bone (docs/decisions.md#meshing-every-piece-then-the-observed-crop-meshobservedpy).
OBSERVED_EXTRACTION = ExtractionConfig(min_component_fraction=0.0)


@dataclass(frozen=True)
class ObservedSurfaceConfig:
    """Which part of a reconstructed surface is kept: ``observed`` (the faces whose vertices
    some frame observes, by this criterion) or ``all`` (the closed iso-surface as extracted).
    ``label_support_mm``: how close to the labelled surface a point counts as observed (0: the
    labels do not count; used only where the caller gives the labelled surface).
    ``label_bridges``: the labelled surface includes the bridges between consecutive labelled
    frames that agree to within ``label_support_mm`` (:mod:`ultron.mesh.label_bridges`)."""

    surface: str = "observed"
    max_incidence_deg: float = DEFAULT_MAX_INCIDENCE_DEG
    min_transmission: float = DEFAULT_MIN_TRANSMISSION
    label_support_mm: float = DEFAULT_LABEL_SUPPORT_MM
    label_bridges: bool = True

    def __post_init__(self) -> None:
        if self.surface not in SURFACES:
            raise argument_error("surface", f"expected one of {SURFACES}, got {self.surface!r}")
        if not (math.isfinite(self.max_incidence_deg) and 0 <= self.max_incidence_deg <= 90):
            raise argument_error("max_incidence_deg", "expected an angle in [0, 90]")
        if not (math.isfinite(self.min_transmission) and 0 <= self.min_transmission <= 1):
            raise argument_error("min_transmission", "expected a value in [0, 1]")
        support = self.label_support_mm
        if isinstance(support, bool) or not isinstance(support, int | float):
            raise argument_error("label_support_mm", f"expected a distance in mm, got {support!r}")
        if not (math.isfinite(support) and support >= 0):
            raise argument_error("label_support_mm", f"expected a finite value ≥ 0, got {support}")
        if not isinstance(self.label_bridges, bool):
            raise argument_error(
                "label_bridges", f"expected true or false, got {self.label_bridges!r}"
            )

    @property
    def extraction(self) -> ExtractionConfig:
        """The extraction that goes with :attr:`surface`: ``observed`` meshes every piece and
        lets the crop decide (:data:`OBSERVED_EXTRACTION`); ``all``, the whole iso-surface
        without a crop, drops the pieces under :class:`~ultron.mesh.extract.ExtractionConfig`'s
        share of the largest."""
        return OBSERVED_EXTRACTION if self.surface == "observed" else ExtractionConfig()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class CroppedExtraction:
    """What a method's config gains from holding an ``extraction`` (an
    :class:`~ultron.mesh.extract.ExtractionConfig` or None) and an ``observed``
    (:class:`ObservedSurfaceConfig`): :attr:`surface_extraction`."""

    extraction: ExtractionConfig | None
    observed: ObservedSurfaceConfig

    @property
    def surface_extraction(self) -> ExtractionConfig:
        """``extraction`` where given, else the one that goes with the kept surface
        (:attr:`ObservedSurfaceConfig.extraction`): a config built with ``observed.surface``
        ``all`` drops small pieces without being told twice."""
        return self.observed.extraction if self.extraction is None else self.extraction


def observed_points(
    points_mm: np.ndarray,
    normals: np.ndarray,
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    probe: ProbeGeometry,
    transmission: np.ndarray | Sequence[np.ndarray],
    slab_half_thickness_mm: float,
    max_incidence_deg: float = DEFAULT_MAX_INCIDENCE_DEG,
    min_transmission: float = DEFAULT_MIN_TRANSMISSION,
    support: np.ndarray | None = None,
) -> np.ndarray:
    """Boolean (P,) mask of the points (P, 3) with outward ``normals`` (P, 3) that some frame
    observes (module docstring). ``transmission`` is T per frame, (N, H, W) in [0, 1], in the
    order of ``probe_to_world`` (N, 4, 4); a list of per-sweep arrays is concatenated.
    ``support`` (N, H, W) bool, when given, is each frame's echo support
    (:func:`~ultron.mesh.echo_support.echo_support_maps`): a point then also needs some frame
    that supports its pixel (module docstring)."""
    poses = as_pose_tensor(probe_to_world).to(torch.float64).numpy()
    maps = _as_maps(transmission, poses.shape[0], probe)
    if support is not None:
        support = np.asarray(support)
        if support.dtype != bool or support.shape != maps.shape:
            raise argument_error(
                "support", f"expected bool {maps.shape}, got {support.dtype} {support.shape}"
            )
    points = np.asarray(points_mm, dtype=np.float64)
    normal = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise argument_error("points_mm", f"expected (P, 3), got {points.shape}")
    if normal.shape != points.shape:
        raise argument_error("normals", f"expected {points.shape}, got {normal.shape}")
    if not (math.isfinite(slab_half_thickness_mm) and slab_half_thickness_mm >= 0):
        raise argument_error("slab_half_thickness_mm", "expected a finite value ≥ 0")
    if not 0 <= max_incidence_deg <= 90:
        raise argument_error("max_incidence_deg", "expected an angle in [0, 90]")
    if not 0 <= min_transmission <= 1:
        raise argument_error("min_transmission", "expected a value in [0, 1]")
    return _observed_vertices(
        points, normal, poses, maps, probe, slab_half_thickness_mm, max_incidence_deg,
        min_transmission, support,
    )  # fmt: skip


def _observed_vertices(
    v: np.ndarray,
    n: np.ndarray,
    poses: np.ndarray,
    t_maps: np.ndarray,
    probe: ProbeGeometry,
    half_thickness_mm: float,
    max_incidence_deg: float,
    min_transmission: float,
    support: np.ndarray | None = None,
) -> np.ndarray:
    """The criterion, vectorised over points per chunk of frames (inputs validated)."""
    cos_min = math.cos(math.radians(max_incidence_deg))
    visible = np.zeros(len(v), dtype=bool)
    shown = np.zeros(len(v), dtype=bool) if support is not None else np.ones(len(v), dtype=bool)
    # Candidates by a sorted projection on the sweep's mean elevation axis ē: a vertex in a
    # frame's image slab has |(v − t)·ẑ| ≤ h and |v − t| ≤ reach, so
    # |v·ē − t·ē| ≤ h + reach·|ẑ − ē| (exactly the vertices the full test would keep).
    axis = poses[:, :3, 2].sum(axis=0)
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    along = _dot3(v, axis[None])[:, 0]
    order = np.argsort(along, kind="stable")
    along = along[order]
    reach = math.sqrt((probe.width_mm / 2) ** 2 + probe.depth_mm**2 + half_thickness_mm**2)
    for start in range(0, poses.shape[0], _FRAMES_PER_CHUNK):
        chunk = poses[start : start + _FRAMES_PER_CHUNK]
        axes, origin = chunk[:, :3, :3], chunk[:, :3, 3]
        centre = _dot3(origin, axis[None])[:, 0]
        tilt = float(np.abs(axes[:, :, 2] - axis).sum(axis=1).max())  # ≥ |ẑ − ē|
        margin = half_thickness_mm + reach * tilt + 1e-6  # (+ rounding slack)
        lo = np.searchsorted(along, centre.min() - margin, side="left")
        hi = np.searchsorted(along, centre.max() + margin, side="right")
        candidates = order[lo:hi]
        z = _dot3(v[candidates], axes[:, :, 2]) - np.einsum("fi,fi->f", origin, axes[:, :, 2])
        ci, fi = np.nonzero(np.abs(z) <= half_thickness_mm)
        vi = candidates[ci]
        keep = ~(visible[vi] & shown[vi])  # a vertex already seen (and shown) needs no more
        vi, fi = vi[keep], fi[keep]
        d = v[vi] - origin[fi]
        x = np.einsum("ki,ki->k", d, axes[fi, :, 0])
        y = np.einsum("ki,ki->k", d, axes[fi, :, 1])
        facing = -np.einsum("ki,ki->k", n[vi], axes[fi, :, 1])
        ok = (np.abs(x) <= probe.width_mm / 2) & (y >= 0) & (y <= probe.depth_mm)
        ok &= facing >= cos_min
        vi, fi, x, y = vi[ok], fi[ok], x[ok], y[ok]
        rows, cols = probe_mm_to_pixel(x, y, probe)
        row = np.clip(np.floor(rows), 0, probe.height_px - 1).astype(int)
        col = np.minimum(np.clip(np.rint(cols), 0, None), probe.width_px - 1).astype(int)
        lit = t_maps[start + fi, row, col].astype(np.float64) >= min_transmission
        visible[vi[lit]] = True
        if support is not None:
            at = np.minimum(np.clip(np.rint(rows), 0, None), probe.height_px - 1).astype(int)
            shown[vi[support[start + fi, at, col]]] = True
    return visible & shown


def _dot3(points: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(M, F) dot products of points (M, 3) with directions (F, 3), as explicit products (not
    BLAS: the same bits whatever the machine's thread count)."""
    return (
        points[:, :1] * directions[:, 0]
        + points[:, 1:2] * directions[:, 1]
        + points[:, 2:] * directions[:, 2]
    )


def observed_faces(mesh, vertex_observed: np.ndarray) -> np.ndarray:
    """Boolean (F,) mask of the faces of ``mesh`` whose three vertices are all observed."""
    mask = np.asarray(vertex_observed, dtype=bool)
    if mask.shape != (len(mesh.vertices),):
        raise argument_error("vertex_observed", f"expected ({len(mesh.vertices)},) booleans")
    if len(mesh.faces) == 0:
        return np.zeros(0, dtype=bool)
    return mask[np.asarray(mesh.faces)].all(axis=1)


def observed_submesh(mesh, vertex_observed: np.ndarray):
    """The sub-mesh of the observed faces (:func:`observed_faces`), unreferenced vertices
    dropped and the order kept; an empty mesh when none is observed."""
    return face_submesh(mesh, observed_faces(mesh, vertex_observed))[0]


def face_submesh(mesh, keep: np.ndarray) -> tuple[Any, np.ndarray]:
    """The faces ``keep`` of ``mesh`` as a mesh, unreferenced vertices dropped in order, and
    the (V',) indices of its vertices in ``mesh``."""
    import trimesh

    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)[keep]
    used = np.unique(faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    vertices = np.asarray(mesh.vertices)[used]
    return trimesh.Trimesh(vertices=vertices, faces=remap[faces], process=False), used


@dataclass(frozen=True)
class SurfaceObservation:
    """A reconstruction's surface split into observed and inferred parts.

    ``extracted`` is the whole iso-surface, ``observed`` (V,) which of its vertices some frame
    observed (module docstring), ``kept`` the mesh the method returns (the observed faces with
    ``surface="observed"``, else ``extracted``) and ``kept_vertices`` (V',) the index in
    ``extracted`` of each vertex of ``kept``. ``info`` is run.json's account: ``surface``,
    ``faces_extracted``, ``faces_kept``, ``observation_transmission`` and, when no face was
    observed and the whole iso-surface is kept, ``surface_fallback``.
    """

    extracted: Any
    observed: np.ndarray
    kept: Any
    kept_vertices: np.ndarray
    info: dict[str, Any]

    @property
    def kept_observed(self) -> np.ndarray:
        """(V',) which vertices of ``kept`` some frame observed."""
        return self.observed[self.kept_vertices]

    @property
    def cropped(self) -> bool:
        """Whether ``kept`` lacks faces of ``extracted``."""
        return len(self.kept.faces) < len(self.extracted.faces)


def observe_surface(
    mesh,
    probe_to_world: np.ndarray | torch.Tensor | Sequence[np.ndarray],
    probe: ProbeGeometry,
    transmission: np.ndarray | Sequence[np.ndarray] | None,
    slab_half_thickness_mm: float,
    config: ObservedSurfaceConfig,
    source: str,
    support: np.ndarray | None = None,
    labelled_surface_mm: np.ndarray | None = None,
) -> SurfaceObservation:
    """Which vertices of ``mesh`` some frame observed, and the part kept by ``config.surface``.
    ``support``: each frame's echo support, as in :func:`observed_points`.
    ``labelled_surface_mm`` (P, 3): the labelled surface, whose neighbourhood within
    ``config.label_support_mm`` counts as observed (module docstring); None: the labels do not
    count (``info["surface"]`` then records 0). ``info["label_supported_vertices"]`` counts the
    vertices only it observes.

    ``transmission`` is T per frame as in :func:`observed_points`, or None for T ≡ 1 (a method
    without a transmission: a vertex is then observed when some frame's beam faces it);
    ``source`` names it in ``info["observation_transmission"]``. When nothing is observed the
    whole iso-surface is kept and ``info["surface_fallback"]`` says so (a degenerate surface,
    e.g. from a barely trained network, rather than no mesh).
    """
    poses = as_pose_tensor(probe_to_world)
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    surface = config.to_dict()
    if labelled_surface_mm is None:
        surface |= {"label_support_mm": 0.0, "label_bridges": False}  # what was applied
    info: dict[str, Any] = {"surface": surface, "faces_extracted": len(mesh.faces)}
    info["observation_transmission"] = source
    info["echo_support"] = support is not None
    everything = np.arange(len(vertices), dtype=np.int64)
    if len(mesh.faces) == 0:
        observed = np.zeros(len(vertices), dtype=bool)
        return SurfaceObservation(mesh, observed, mesh, everything, info | {"faces_kept": 0})
    if transmission is None:
        shape = (poses.shape[0], *probe.image_shape)
        transmission = np.broadcast_to(np.ones((1, *probe.image_shape), np.float32), shape)
    observed = observed_points(
        vertices, np.asarray(mesh.vertex_normals), poses, probe, transmission,
        slab_half_thickness_mm, config.max_incidence_deg, config.min_transmission, support,
    )  # fmt: skip
    if labelled_surface_mm is not None and config.label_support_mm > 0:
        support_mm = config.label_support_mm
        near = nearest_distance_mm(vertices, labelled_surface_mm, support_mm) <= support_mm
        info["label_supported_vertices"] = int(np.count_nonzero(near & ~observed))
        observed = observed | near
    if config.surface == "all":
        return SurfaceObservation(
            mesh, observed, mesh, everything, info | {"faces_kept": len(mesh.faces)}
        )
    kept, used = face_submesh(mesh, observed_faces(mesh, observed))
    if len(kept.faces) == 0:
        info |= {"faces_kept": len(mesh.faces), "surface_fallback": "all"}
        return SurfaceObservation(mesh, observed, mesh, everything, info)
    return SurfaceObservation(mesh, observed, kept, used, info | {"faces_kept": len(kept.faces)})


def _as_maps(
    transmission: np.ndarray | Sequence[np.ndarray], n_frames: int, probe: ProbeGeometry
) -> np.ndarray:
    if isinstance(transmission, list | tuple):
        transmission = np.concatenate([np.asarray(t) for t in transmission], axis=0)
    maps = np.asarray(transmission)
    if maps.shape != (n_frames, *probe.image_shape):
        raise argument_error(
            "transmission",
            f"expected ({n_frames}, {probe.height_px}, {probe.width_px}), got {maps.shape}",
        )
    if not np.isfinite(maps).all():
        raise argument_error("transmission", "expected finite values")
    return maps


def faced_observation(
    mesh, dataset: SweepDataset, voxel_mm: float, observed: ObservedSurfaceConfig
) -> SurfaceObservation:
    """:func:`observe_surface` of ``mesh`` with T ≡ 1 over every frame of ``dataset``, in the
    slab UltrON's crop uses for a grid of ``voxel_mm``: the criterion of a method without a
    transmission (label compounding crops its surface with it)."""
    return observe_surface(
        mesh, dataset.all_poses(), dataset.probe, None,
        elevation_half_thickness_mm(dataset, voxel_mm), observed, NO_TRANSMISSION,
    )  # fmt: skip
