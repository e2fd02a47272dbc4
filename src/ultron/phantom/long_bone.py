"""A digital long bone (a femur-like shaft with condyle-like ends) for long-sweep tests.

Real recordings of a long bone are long: 1000+ frames over 40 cm in several passes. This
phantom gives the simulator such a bone in the world frame of every phantom (``shapes.py``:
+x lateral, +y posterior → anterior, the beam's direction; the bone's long axis is +z, so the
``row`` sweep — transverse images moved along z — runs along the whole bone):

* the **shaft**: a tube of radius ``shaft_radius_mm`` whose centre line is the arc
  y(z) = ``bow_mm`` · (1 − (z / (L/2))²), x = 0, over |z| ≤ L/2 (L = ``shaft_length_mm``):
  bowed anteriorly (away from the probe) by ``bow_mm`` at mid-shaft, as the femur is;
  built of ``shaft_segments`` rounded boxes (near-circular section, corner radius
  ``shaft_radius_mm`` − 0.1 mm) along chords of the arc, each extended by the radius beyond
  both ends so that neighbours overlap at the knots, smoothly joined;
* the **distal end** (z = −L/2): two condyles, ellipsoids of semi-axes ``condyle_radii_mm``
  centred ``condyle_spread_mm`` either side of the mid-line and ``condyle_radii_mm[2]`` / 2
  beyond the shaft's end;
* the **proximal end** (z = +L/2): one head, an ellipsoid of semi-axes ``head_radii_mm``
  centred ``head_radii_mm[2]`` / 2 beyond the shaft's end.

Everything is smoothly united (blend ``blend_mm``); SDF values are negative inside bone. The
default (``femur``: 400 mm shaft of 13 mm radius, 10 mm bow, condyles 16 × 18 × 22 mm, head
20 × 18 × 22 mm) is ≈ 44 cm long and 62 mm wide at the condyles, within adult femoral
morphometry (shaft diameter ≈ 25–30 mm, bicondylar width ≈ 75–85 mm, length 40–50 cm).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, fields

import numpy as np

from ultron.errors import argument_error
from ultron.phantom.primitives import Ellipsoid, Primitive, SegmentBox


@dataclass(frozen=True)
class LongBoneShape:
    """Dimensions of a long bone, mm (module docstring)."""

    shaft_length_mm: float = 400.0
    shaft_radius_mm: float = 13.0
    bow_mm: float = 10.0
    shaft_segments: int = 12
    condyle_radii_mm: tuple[float, float, float] = (16.0, 18.0, 22.0)
    condyle_spread_mm: float = 15.0
    head_radii_mm: tuple[float, float, float] = (20.0, 18.0, 22.0)
    blend_mm: float = 2.5

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if len(values) not in (1, 3) or not all(
                isinstance(v, int | float) and math.isfinite(v) for v in values
            ):
                raise argument_error(f.name, f"expected finite number(s), got {value!r}")
            if f.name.endswith("_mm") and f.name != "bow_mm" and min(values) <= 0:
                raise argument_error(f.name, f"expected positive length(s), got {value!r}")
        if isinstance(self.shaft_segments, bool) or not isinstance(self.shaft_segments, int):
            raise argument_error(
                "shaft_segments", f"expected an integer, got {self.shaft_segments!r}"
            )
        if self.shaft_segments < 1:
            raise argument_error("shaft_segments", f"expected ≥ 1, got {self.shaft_segments}")
        if self.shaft_radius_mm <= 0.2:
            raise argument_error(
                "shaft_radius_mm", f"expected > 0.2 mm, got {self.shaft_radius_mm}"
            )

    def centre_line(self, z_mm: np.ndarray) -> np.ndarray:
        """Points (…, 3) of the shaft's centre line at ``z_mm`` (module docstring)."""
        z = np.asarray(z_mm, dtype=np.float64)
        half = self.shaft_length_mm / 2
        y = self.bow_mm * (1.0 - (z / half) ** 2)
        return np.stack([np.zeros_like(z), y, z], axis=-1)

    def primitives(self) -> tuple[Primitive, ...]:
        """The shaft's segments, the two condyles and the head, in the world frame."""
        half = self.shaft_length_mm / 2
        r = self.shaft_radius_mm
        knots = self.centre_line(np.linspace(-half, half, self.shaft_segments + 1))
        parts: list[Primitive] = []
        for a, b in itertools.pairwise(knots):
            step = (b - a) / np.linalg.norm(b - a) * r
            parts.append(
                SegmentBox(tuple(a - step), tuple(b + step), (1.0, 0.0, 0.0), r, r, r - 0.1)
            )
        end_y = float(self.centre_line(np.array(-half))[1])
        cz = self.condyle_radii_mm[2] / 2
        for side in (-1.0, 1.0):
            centre = (side * self.condyle_spread_mm, end_y, -half - cz)
            parts.append(Ellipsoid(centre, tuple(self.condyle_radii_mm)))
        head = (0.0, end_y, half + self.head_radii_mm[2] / 2)
        parts.append(Ellipsoid(head, tuple(self.head_radii_mm)))
        return tuple(parts)

    def length_mm(self) -> float:
        """End-to-end length along z: the shaft plus the ends' overhang."""
        return self.shaft_length_mm + 1.5 * self.condyle_radii_mm[2] + 1.5 * self.head_radii_mm[2]
