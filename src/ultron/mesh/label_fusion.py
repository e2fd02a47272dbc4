"""Label fusion: UltrON's occupancy and the compounded labels it trained on, meshed as one.

The meshed occupancy is

    F(x) = max(f(x), C(x)),

f the trained occupancy network and C the labels of the frames f trained on, compounded as
``--method compounding`` does (:func:`~ultron.mesh.compounding.compound_labels`) and read
trilinearly (0 outside C's grid). The annotated bone is bone whatever f made of it; f decides
everywhere else. Its 0.5 level is the union of the two solids, so the surface keeps every
labelled bone f lost and the bone f found beyond the labels.

The compounded labels' own surface, cropped as label compounding crops it, can lie inside f's
bone where f extends past the labels: max(f, C) then has no surface there, and the observed crop
may drop f's surface beyond it for want of evidence, leaving a hole where the labels show bone.
So the kept surface also takes every face of the labels' kept surface whose centroid lies more
than :attr:`LabelFusionConfig.surface_gap_mm` from it (:func:`add_label_surface`): the surface
is then no longer one closed level set, but each of its faces is backed by f and the crop or by
the labels themselves.

When it applies (:attr:`LabelFusionConfig.min_frame_share`): C between two labelled frames is
the hole filling's interpolation across their gap. With nearly every frame labelled the gap is
one step of the sweep and C is the labels themselves; with sparse frames (10 % of them lie
about ten steps apart) the fill adds surface off the bone where the cross-sections differ.
Not a law: with an annotator's labels on every frame of a rounded bone (a condyle) the labels'
own slabs added surface off the bone too. Measured on
tuning data, both ways: docs/decisions.md#label-fusion-when-nearly-every-frame-is-labelled-meshlabel_fusionpy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy import ndimage

from ultron.arguments import check_range
from ultron.data.dataset import SweepDataset
from ultron.data.labels import FrameSelection
from ultron.errors import argument_error
from ultron.mesh.compounding import CompoundedVolume, CompoundingConfig
from ultron.mesh.observed import SurfaceObservation, face_submesh
from ultron.metrics.surface import point_to_surface_distances

#: The share of a dataset's frames a run must label for the default fusion to apply: nearly
#: every frame, which admits a few unannotated ones (the benchmark leaves 5 % unannotated).
DENSE_FRAME_SHARE = 0.9
#: How far (mm) a face of the labels' kept surface must lie from the fused kept surface to be
#: added to it: the distance within which UltrON's crop already counts the labelled surface
#: as observed (:data:`~ultron.mesh.observed.DEFAULT_LABEL_SUPPORT_MM`), so a face nearer than
#: that has its counterpart in the kept surface.
SURFACE_GAP_MM = 1.0


@dataclass(frozen=True)
class LabelFusionConfig:
    """When and how UltrON meshes max(f, C) (module doc): ``min_frame_share``, fuse only when
    the run's labelled frames are at least this share of the dataset's frames (0: at every
    label fraction); ``volume``, how C is compounded; ``surface_gap_mm``, add the faces of the
    labels' own kept surface farther than this from the kept surface (None: do not)."""

    min_frame_share: float = DENSE_FRAME_SHARE
    volume: CompoundingConfig = field(default_factory=CompoundingConfig)
    surface_gap_mm: float | None = SURFACE_GAP_MM

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_frame_share <= 1.0:
            raise argument_error(
                "min_frame_share", f"expected a share in [0, 1], got {self.min_frame_share}"
            )
        if self.surface_gap_mm is not None:
            _check_gap("surface_gap_mm", self.surface_gap_mm)
        if not isinstance(self.volume, CompoundingConfig):
            raise argument_error(
                "volume", f"expected a CompoundingConfig, got {type(self.volume).__name__}"
            )

    def applies(self, dataset: SweepDataset, selection: FrameSelection) -> bool:
        """Whether ``selection``'s frames are at least :attr:`min_frame_share` of
        ``dataset``'s frames (every sweep's, labelled or not; :func:`labelled_frame_share`)."""
        return labelled_frame_share(dataset, selection) >= self.min_frame_share


def _check_gap(name: str, value: object) -> None:
    """Refuse ``value`` unless it is a finite distance > 0 (mm), with an error naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise argument_error(name, f"expected a positive distance (mm), got {value!r}")
    check_range(name, value, 0, low_open=True)


def labelled_frame_share(dataset: SweepDataset, selection: FrameSelection) -> float:
    """The share of ``dataset``'s frames that ``selection`` labels (0 for an empty dataset)."""
    return selection.n_frames / dataset.n_frames if dataset.n_frames else 0.0


def fuse_with_labels(
    occupancy_fn: Callable[[torch.Tensor], torch.Tensor], compounded: CompoundedVolume
) -> Callable[[torch.Tensor], torch.Tensor]:
    """An occupancy function (points (M, 3) world mm → (M,) in [0, 1] on the CPU) fused with
    the compounded labels: x ↦ max(f(x), C(x)), C the ``compounded`` volume read trilinearly
    on its grid (0 outside it). The annotated bone is bone whatever f made of it; f decides
    everywhere else, so its 0.5 level is the union of both surfaces' solids."""
    if not isinstance(compounded, CompoundedVolume):
        raise argument_error(
            "compounded", f"expected a CompoundedVolume, got {type(compounded).__name__}"
        )
    volume = np.ascontiguousarray(compounded.volume, dtype=np.float32)
    origin_mm = np.asarray(compounded.grid.origin_mm, dtype=np.float64)
    voxel_mm = compounded.grid.voxel_mm

    def fused(points_mm: torch.Tensor) -> torch.Tensor:
        occupancy = occupancy_fn(points_mm)
        index = (points_mm.detach().cpu().double().numpy() - origin_mm) / voxel_mm
        labelled = ndimage.map_coordinates(volume, index.T, order=1, mode="constant", cval=0.0)
        return torch.maximum(occupancy, torch.from_numpy(labelled).to(occupancy.dtype))

    return fused


def add_label_surface(
    kept: SurfaceObservation, labels: SurfaceObservation, gap_mm: float
) -> tuple[SurfaceObservation, dict[str, float]]:
    """``kept`` with the faces of ``labels.kept`` whose centroid lies more than ``gap_mm`` from
    ``kept.kept`` appended (module doc), and an account: ``label_surface_faces_added`` and
    their area ``label_surface_area_added_mm2``. The appended faces join both the extracted and
    the kept surface, their vertices observed as ``labels`` found them, so that a surface's
    evidence covers every face it returns."""
    import trimesh

    for name, value in (("kept", kept), ("labels", labels)):
        if not isinstance(value, SurfaceObservation):
            raise argument_error(name, f"expected a SurfaceObservation, got {type(value)}")
    _check_gap("gap_mm", gap_mm)
    added = np.ones(len(labels.kept.faces), dtype=bool)  # all of them beside no surface
    if len(labels.kept.faces) and len(kept.kept.faces):
        centroids = np.asarray(labels.kept.triangles_center, dtype=np.float64)
        added = point_to_surface_distances(centroids, kept.kept) > gap_mm
    account = {
        "label_surface_faces_added": int(np.count_nonzero(added)),
        "label_surface_area_added_mm2": float(np.asarray(labels.kept.area_faces)[added].sum()),
    }
    if not added.any():
        return kept, account
    extra, used = face_submesh(labels.kept, added)
    n_extracted = len(kept.extracted.vertices)
    info = dict(kept.info)
    for key in ("faces_extracted", "faces_kept"):
        if key in info:
            info[key] += len(extra.faces)
    joined = SurfaceObservation(
        extracted=trimesh.util.concatenate([kept.extracted, extra]),
        observed=np.concatenate([kept.observed, labels.kept_observed[used]]),
        kept=trimesh.util.concatenate([kept.kept, extra]),
        kept_vertices=np.concatenate(
            [kept.kept_vertices, n_extracted + np.arange(len(extra.vertices))]
        ),
        info=info,
    )
    return joined, account
