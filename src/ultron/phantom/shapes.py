"""Digital lumbar vertebrae as smooth signed distance functions (SDFs) in world millimetres.

World frame of every phantom (and of the simulated datasets):

* origin at the centre of the vertebral body;
* **+x** lateral (patient's left–right), **+y** posterior → anterior, **+z** caudal → cranial;
* the phantom is embedded in a gelatin block whose scanned (posterior) surface is the plane
  ``y = surface_y_mm`` (posterior of the spinous process tip), and the probe sits on that
  surface looking anteriorly: the beam (probe +y) goes along world +y into the phantom, so the
  posterior elements (spinous process, laminae, articular and transverse processes) face the
  probe as when scanning a patient's back.

A vertebra is the smooth union (polynomial smooth minimum, blend radius ``blend_mm``) of
primitives: the vertebral body (an elliptic cylinder with a concave waist and rounded end-plate
rims), two pedicles, two laminae, the spinous process with a broadened tip, two transverse
processes and the superior and inferior articular processes. SDF values are negative inside
bone. The primitive SDFs are exact for boxes and close bounds for the ellipse/ellipsoid terms;
the smooth union keeps the zero level set smooth (a bound, not an exact distance, near blends).

Dimensions are level-dependent and within published lumbar morphometry (Panjabi et al. 1992,
Spine 17:299; Zhou et al. 2000, Eur Spine J 9:242): an L3 body ≈ 45 mm wide, 30 mm deep,
25 mm high; spinous process ≈ 30 mm long; transverse processes ≈ 80 mm tip to tip.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from ultron.device import map_chunks
from ultron.errors import argument_error
from ultron.phantom.long_bone import LongBoneShape
from ultron.phantom.primitives import Ellipsoid, Primitive, SegmentBox, VertebralBody, union_sdf
from ultron.phantom.volume import SdfVolume

if TYPE_CHECKING:
    import trimesh

#: Grid spacing of the SDF volume and the reference mesh, mm, and the gel margin around the bone.
DEFAULT_VOXEL_MM = 0.3
DEFAULT_MARGIN_MM = 3.0

# ---------------------------------------------------------------------------- vertebra


class _Landmarks(NamedTuple):
    """Derived positions of a vertebra's neural arch (mm, radians), shared by its primitives."""

    wall_y: float
    ped_x: float
    ped_back_y: float
    lam_mid_y: float
    lam_z: float
    lam_up: tuple[float, float, float]
    sweep: float
    tp_y: float


@dataclass(frozen=True)
class VertebraShape:
    """Level-dependent dimensions of a lumbar vertebra, mm and degrees (see module docstring)."""

    body_width_mm: float
    body_depth_mm: float
    body_height_mm: float
    body_waist: float
    body_rim_radius_mm: float
    canal_width_mm: float  # interpedicular distance
    canal_depth_mm: float  # posterior body wall to the laminae at the midline
    pedicle_width_mm: float
    pedicle_height_mm: float
    pedicle_length_mm: float  # posterior extent beyond the body wall
    pedicle_z_mm: float  # pedicles sit on the cranial half of the body
    lamina_thickness_mm: float
    lamina_height_mm: float
    lamina_incline_deg: float  # cranial edge anterior of the caudal edge
    spinous_length_mm: float
    spinous_height_mm: float
    spinous_thickness_mm: float
    spinous_droop_deg: float  # caudal inclination of the spinous process
    spinous_tip_mm: float  # thickness of the broadened tip
    transverse_length_mm: float  # from the pedicle centre line to the tip, each side
    transverse_height_mm: float
    transverse_thickness_mm: float
    transverse_sweep_deg: float  # posterior sweep of the transverse processes
    articular_height_mm: float
    articular_width_mm: float
    articular_thickness_mm: float
    blend_mm: float

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value):
                raise argument_error(f.name, f"expected a finite number, got {value}")
            if f.name.endswith("_mm") and value <= 0:
                raise argument_error(f.name, f"expected a positive length, got {value}")

    def primitives(self) -> tuple[Primitive, ...]:
        """The primitives of this vertebra in the world frame (origin at the body centre)."""
        s = self
        at = s._landmarks()
        droop = math.radians(s.spinous_droop_deg)
        sp_dir = np.array([0.0, -math.cos(droop), -math.sin(droop)])
        sp_start = np.array([0.0, at.lam_mid_y + 1.0, at.lam_z])
        sp_end = sp_start + s.spinous_length_mm * sp_dir
        tip_center = sp_end - 0.45 * s.spinous_tip_mm * sp_dir
        parts: list[Primitive] = [
            VertebralBody(
                s.body_width_mm,
                s.body_depth_mm,
                s.body_height_mm,
                s.body_waist,
                s.body_rim_radius_mm,
            ),
            Ellipsoid(
                tuple(tip_center),
                (s.spinous_tip_mm / 2, s.spinous_tip_mm / 2, 0.42 * s.spinous_height_mm),
            ),
            SegmentBox(
                tuple(sp_start),
                tuple(sp_end),
                (0.0, 0.0, 1.0),
                s.spinous_height_mm / 2,
                s.spinous_thickness_mm / 2,
                min(2.5, s.spinous_thickness_mm / 2 - 0.1),
            ),
        ]
        for side in (-1.0, 1.0):
            parts += s._arch_side(side, at)
        return tuple(parts)

    def _landmarks(self) -> _Landmarks:
        s = self
        wall_y = -s.body_depth_mm / 2
        ped_back_y = wall_y - s.pedicle_length_mm
        incline = math.radians(s.lamina_incline_deg)
        return _Landmarks(
            wall_y=wall_y,
            ped_x=s.canal_width_mm / 2 + s.pedicle_width_mm / 2,
            ped_back_y=ped_back_y,
            lam_mid_y=wall_y - s.canal_depth_mm - s.lamina_thickness_mm / 2,
            lam_z=s.pedicle_z_mm - 4.0,
            lam_up=(0.0, math.sin(incline), math.cos(incline)),
            sweep=math.radians(s.transverse_sweep_deg),
            tp_y=ped_back_y + 2.0,
        )

    def _arch_side(self, side: float, at: _Landmarks) -> list[Primitive]:
        """One side (x sign ``side``) of the neural arch: pedicle, lamina, transverse process,
        superior and inferior articular processes."""
        s, ped_x, ped_back_y, lam_mid_y, lam_z = (
            self,
            at.ped_x,
            at.ped_back_y,
            at.lam_mid_y,
            at.lam_z,
        )
        return [
            SegmentBox(  # pedicle
                (side * ped_x, at.wall_y + 5.0, s.pedicle_z_mm),
                (side * ped_x, ped_back_y, s.pedicle_z_mm),
                (0.0, 0.0, 1.0),
                s.pedicle_height_mm / 2,
                s.pedicle_width_mm / 2,
                3.0,
            ),
            SegmentBox(  # lamina
                (side * (ped_x + 1.0), ped_back_y + 1.0, lam_z),
                (0.0, lam_mid_y, lam_z),
                at.lam_up,
                s.lamina_height_mm / 2,
                s.lamina_thickness_mm / 2,
                min(2.5, s.lamina_thickness_mm / 2 - 0.1),
            ),
            SegmentBox(  # transverse process
                (side * ped_x, at.tp_y, s.pedicle_z_mm),
                (
                    side * (ped_x + s.transverse_length_mm),
                    at.tp_y - s.transverse_length_mm * math.sin(at.sweep),
                    s.pedicle_z_mm + 1.0,
                ),
                (0.0, 0.0, 1.0),
                s.transverse_height_mm / 2,
                s.transverse_thickness_mm / 2,
                min(2.0, s.transverse_thickness_mm / 2 - 0.1),
            ),
            SegmentBox(  # superior articular process (facet faces posteromedially)
                (side * (ped_x + 1.0), ped_back_y - 1.0, s.pedicle_z_mm + 2.0),
                (
                    side * (ped_x + 2.5),
                    ped_back_y - 4.0,
                    s.pedicle_z_mm + 2.0 + s.articular_height_mm,
                ),
                (1.0, -0.4 * side, 0.0),
                s.articular_thickness_mm / 2,
                s.articular_width_mm / 2,
                min(2.0, s.articular_thickness_mm / 2 - 0.1),
            ),
            SegmentBox(  # inferior articular process (facet faces anterolaterally)
                (side * (ped_x - 5.0), lam_mid_y + 1.0, lam_z - s.lamina_height_mm / 2 + 3),
                (
                    side * (ped_x - 3.5),
                    lam_mid_y,
                    lam_z - s.lamina_height_mm / 2 + 3 - s.articular_height_mm,
                ),
                (1.0, 0.4 * side, 0.0),
                s.articular_thickness_mm / 2,
                s.articular_width_mm / 2,
                min(2.0, s.articular_thickness_mm / 2 - 0.1),
            ),
        ]


# ---------------------------------------------------------------------------- phantoms


@dataclass(frozen=True)
class Phantom:
    """A digital bone phantom — a vertebra (:class:`VertebraShape`) or a long bone
    (:class:`~ultron.phantom.long_bone.LongBoneShape`): SDF in world mm (negative inside
    bone), bounds, reference mesh.

    ``gel_cover_mm`` is the gelatin between the most posterior bone point and the block's
    scanned surface, so the probe face lies in the plane ``y = surface_y_mm``.
    """

    name: str
    shape: VertebraShape | LongBoneShape
    description: str
    gel_cover_mm: float = 10.0

    def sdf(self, points_mm: torch.Tensor) -> torch.Tensor:
        """Signed distance (mm) at world points (..., 3); negative inside bone.

        Evaluated in the input's floating dtype (float32 inputs stay float32), in chunks.
        """
        points = torch.as_tensor(points_mm)
        if points.ndim == 0 or points.shape[-1] != 3:
            raise argument_error("points_mm", f"expected shape (..., 3), got {tuple(points.shape)}")
        if not torch.is_floating_point(points):
            points = points.to(torch.float64)
        flat = points.reshape(-1, 3)
        parts = self._primitives
        result = map_chunks(
            lambda p: union_sdf(parts, p, self.shape.blend_mm),
            flat,
            1 << 19,
            empty=flat.new_zeros(0),
            gradients=True,  # the SDF's gradient gives surface normals
        )
        return result.reshape(points.shape[:-1])

    @functools.cached_property
    def _primitives(self) -> tuple[Primitive, ...]:
        return self.shape.primitives()

    @functools.cached_property
    def primitive_box_mm(self) -> np.ndarray:
        """A box sure to contain the bone: the primitives' boxes grown by the blend radius."""
        boxes = np.stack([p.bounds() for p in self._primitives])
        pad = self.shape.blend_mm
        return np.stack([boxes[:, 0].min(axis=0) - pad, boxes[:, 1].max(axis=0) + pad])

    @functools.cached_property
    def _default_volume(self) -> SdfVolume:  # at 0.3 mm, margin 3 mm
        return SdfVolume.from_phantom(self, DEFAULT_VOXEL_MM, DEFAULT_MARGIN_MM)

    @functools.cached_property
    def _bounds(self) -> np.ndarray:
        """Bone bounding box: the inside extent of the 0.3 mm SDF grid ± half a voxel."""
        volume = self._default_volume
        inside = (volume.values < 0).nonzero()
        if inside.numel() == 0:
            raise argument_error("phantom", f"phantom {self.name!r} has no bone voxel")
        index = inside.flip(-1).to(torch.float64)
        origin = np.asarray(volume.origin_mm)
        lo = origin + volume.voxel_mm * index.min(dim=0).values.numpy()
        hi = origin + volume.voxel_mm * index.max(dim=0).values.numpy()
        return np.stack([lo - volume.voxel_mm / 2, hi + volume.voxel_mm / 2])

    @property
    def bounds_mm(self) -> torch.Tensor:
        """(2, 3) [min, max] box of the bone in world mm (float64)."""
        return torch.as_tensor(self._bounds.copy())

    @property
    def surface_y_mm(self) -> float:
        """World y of the gelatin block's scanned surface (where the probe face sits)."""
        return float(self._bounds[0, 1] - self.gel_cover_mm)

    def sdf_volume(
        self, voxel_mm: float = DEFAULT_VOXEL_MM, margin_mm: float = DEFAULT_MARGIN_MM
    ) -> SdfVolume:
        """The SDF sampled on a regular grid (an :class:`~ultron.phantom.volume.SdfVolume`) over
        the bone grown by ``margin_mm``; the default grid is computed once per phantom."""
        if voxel_mm == DEFAULT_VOXEL_MM and margin_mm == DEFAULT_MARGIN_MM:
            return self._default_volume
        return SdfVolume.from_phantom(self, voxel_mm, margin_mm)

    def reference_mesh(self, voxel_mm: float = DEFAULT_VOXEL_MM) -> trimesh.Trimesh:
        """Watertight marching-cubes mesh of the zero level set at ``voxel_mm``, world mm."""
        return self.sdf_volume(voxel_mm).mesh()

    def to_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "description": self.description,
            "gel_cover_mm": self.gel_cover_mm,
            "surface_y_mm": self.surface_y_mm,
            "bounds_mm": self._bounds.tolist(),
            "shape": {f.name: getattr(self.shape, f.name) for f in fields(self.shape)},
        }


_L3 = VertebraShape(
    body_width_mm=45.0,
    body_depth_mm=30.0,
    body_height_mm=25.0,
    body_waist=0.05,
    body_rim_radius_mm=2.5,
    canal_width_mm=23.0,
    canal_depth_mm=17.0,
    pedicle_width_mm=9.0,
    pedicle_height_mm=14.0,
    pedicle_length_mm=9.0,
    pedicle_z_mm=3.0,
    lamina_thickness_mm=6.0,
    lamina_height_mm=20.0,
    lamina_incline_deg=25.0,
    spinous_length_mm=30.0,
    spinous_height_mm=20.0,
    spinous_thickness_mm=6.0,
    spinous_droop_deg=12.0,
    spinous_tip_mm=8.0,
    transverse_length_mm=24.0,
    transverse_height_mm=10.0,
    transverse_thickness_mm=5.0,
    transverse_sweep_deg=12.0,
    articular_height_mm=12.0,
    articular_width_mm=11.0,
    articular_thickness_mm=5.0,
    blend_mm=2.5,
)

_L2 = VertebraShape(
    **{
        **{f.name: getattr(_L3, f.name) for f in fields(_L3)},
        "body_width_mm": 42.0,
        "body_depth_mm": 28.0,
        "body_height_mm": 24.0,
        "canal_width_mm": 22.0,
        "pedicle_width_mm": 8.0,
        "pedicle_height_mm": 15.0,
        "spinous_length_mm": 29.0,
        "spinous_height_mm": 19.0,
        "transverse_length_mm": 20.0,
        "transverse_sweep_deg": 10.0,
    }
)

_L4 = VertebraShape(
    **{
        **{f.name: getattr(_L3, f.name) for f in fields(_L3)},
        "body_width_mm": 48.0,
        "body_depth_mm": 32.0,
        "body_height_mm": 26.0,
        "canal_depth_mm": 18.0,
        "pedicle_width_mm": 11.0,
        "pedicle_height_mm": 13.0,
        "spinous_length_mm": 27.0,
        "spinous_height_mm": 19.0,
        "spinous_droop_deg": 8.0,
        "transverse_length_mm": 21.0,
        "transverse_sweep_deg": 16.0,
        "articular_width_mm": 12.0,
    }
)

# A second print of L3: sub-millimetre to millimetre differences (print tolerance, support
# removal), as with the paper's two L3 phantoms.
_L3B = VertebraShape(
    **{
        **{f.name: getattr(_L3, f.name) for f in fields(_L3)},
        "body_width_mm": 45.6,
        "body_depth_mm": 29.7,
        "body_height_mm": 25.4,
        "lamina_thickness_mm": 6.3,
        "spinous_length_mm": 30.7,
        "spinous_droop_deg": 13.5,
        "spinous_tip_mm": 8.6,
        "transverse_length_mm": 24.6,
        "articular_height_mm": 12.5,
        "blend_mm": 2.7,
    }
)

#: Available phantoms by name. Phantoms are immutable; build new ones instead of mutating.
PHANTOMS: Mapping[str, Phantom] = MappingProxyType(
    {
        "L2": Phantom("L2", _L2, "second lumbar vertebra"),
        "L3": Phantom("L3", _L3, "third lumbar vertebra"),
        "L3b": Phantom("L3b", _L3B, "third lumbar vertebra, second print (small differences)"),
        "L4": Phantom("L4", _L4, "fourth lumbar vertebra"),
    }
)


#: Long-bone phantoms (:mod:`ultron.phantom.long_bone`), for long sweeps; not part of the
#: vertebra benchmark's ``PHANTOMS``.
LONG_BONES: Mapping[str, Phantom] = MappingProxyType(
    {"femur": Phantom("femur", LongBoneShape(), "femur-like long bone, 44 cm (long sweeps)")}
)


#: The end of a long bone (the benchmark's non-vertebra bone, ``ultron benchmark``'s
#: ``condyle``): two condyles (14 × 16 × 18 mm semi-axes, 14 mm either side of the mid-line)
#: on a 50 mm straight shaft of 12 mm radius closed by a rounded cap — 95 mm long, 56 mm wide at
#: the condyles, in the size range of an adult distal femur's bicondylar width (≈ 75–85 mm)
#: scaled to the probe's 38 mm field of view. Its surfaces are convex and smooth where a
#: vertebra's are ridged and concave: a different bone for the benchmark to generalise to.
CONDYLE = Phantom(
    "condyle",
    LongBoneShape(
        shaft_length_mm=50.0,
        shaft_radius_mm=12.0,
        bow_mm=0.0,
        shaft_segments=2,
        condyle_radii_mm=(14.0, 16.0, 18.0),
        condyle_spread_mm=14.0,
        head_radii_mm=(12.0, 12.0, 12.0),
    ),
    "end of a long bone: two condyles on a 5 cm shaft, 9.5 cm (non-vertebra benchmark bone)",
)
#: Other bones of the benchmark (not vertebrae, short enough for the default sweeps).
OTHER_BONES: Mapping[str, Phantom] = MappingProxyType({"condyle": CONDYLE})
#: What ``ultron benchmark`` runs by default: the vertebrae and the other bones.
BENCHMARK_PHANTOMS = (*PHANTOMS, *OTHER_BONES)


def get_phantom(name: str) -> Phantom:
    """The phantom called ``name`` (one of ``PHANTOMS``, ``OTHER_BONES`` or ``LONG_BONES``); a
    clear error otherwise."""
    known = {**PHANTOMS, **OTHER_BONES, **LONG_BONES}
    if name not in known:
        raise argument_error("phantom", f"unknown phantom {name!r}; expected one of {list(known)}")
    return known[name]
