"""Scan protocols (robot-held sweeps over the phantom) and tracking error.

Sweeps (world frame of ``shapes.py``: x lateral, y posterior→anterior, z caudal→cranial; the
probe face lies on the gel surface ``y = surface_y_mm`` and the beam, probe +y, points along
world +y):

* ``row``: transverse images (probe +x = world +x), the probe moved cranio-caudally (world z)
  over the bone's z extent plus a margin;
* ``column``: sagittal images (probe +x = world +z, elevation probe +z = world −x), the probe
  moved left–right (world x) over the bone's x extent plus a margin;
* ``tilt_p<deg>`` / ``tilt_m<deg>`` (default ``tilt_p10``, ``tilt_m10``): the row sweep with the
  probe rotated by ±deg about its elevation axis, so the beam is steered within the transverse
  plane (the paper's "±10° from the standard row scan position"). The probe rotates about the
  centre of its face, shifted laterally so the centre scanline still crosses the bone's
  mid-line at ``tilt_pivot_depth_mm``. (The tilted face is not flush with the flat gel
  surface; the simulator treats all space outside the bone as gel, as if the gel followed the
  probe — in practice ultrasound gel fills the wedge.)

Frames are spread evenly over the sweep range, or spaced ``step_mm`` apart about its centre.
Tracking error (``TrackingNoise``): stored pose = true pose · ΔT, ΔT a rigid motion in the probe
frame whose translation (mm) and rotation vector (deg) have independent Gaussian components;
``sweep_bias_share`` of the variance is one draw per sweep (calibration / registration bias),
the rest is per-frame jitter. Defaults (0.3 mm, 0.2° per axis) reflect a robot arm of ≈ 0.1 mm
repeatability whose probe calibration leaves errors of a few tenths of a mm and degree.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ultron.arguments import check_count
from ultron.errors import argument_error

DEFAULT_SWEEPS = ("row", "column", "tilt_p10", "tilt_m10")
_TILT = re.compile(r"^tilt_([pm])(\d+(?:\.\d+)?)$")


@dataclass(frozen=True)
class ScanConfig:
    """Sweep sampling.

    Attributes:
        frames_per_sweep: Frames per sweep.
        step_mm: Probe step between frames, mm (default: spread over the bone extent).
        margin_mm: Distance the sweep runs beyond the bone's extent at each end, mm.
        tilt_pivot_depth_mm: Depth below the probe about which a tilted sweep turns, mm.
    """

    frames_per_sweep: int = 60
    step_mm: float | None = None  # None: spread the frames over the bone extent + margin
    margin_mm: float = 4.0
    tilt_pivot_depth_mm: float = 40.0

    def __post_init__(self) -> None:
        check_count("frames_per_sweep", self.frames_per_sweep)
        if self.step_mm is not None and not (math.isfinite(self.step_mm) and self.step_mm > 0):
            raise argument_error("step_mm", f"expected a positive step or None, got {self.step_mm}")
        if not (math.isfinite(self.margin_mm) and self.margin_mm >= 0):
            raise argument_error("margin_mm", f"expected ≥ 0, got {self.margin_mm}")
        if not (math.isfinite(self.tilt_pivot_depth_mm) and self.tilt_pivot_depth_mm >= 0):
            raise argument_error(
                "tilt_pivot_depth_mm", f"expected ≥ 0, got {self.tilt_pivot_depth_mm}"
            )


@dataclass(frozen=True)
class SweepSpec:
    """A named sweep: dataset kind, image orientation (``row`` or ``column``), in-plane tilt."""

    name: str
    kind: str
    orientation: str
    tilt_deg: float


def sweep_spec(name: str) -> SweepSpec:
    """Parse a sweep name: ``row``, ``column``, ``tilt_p<deg>`` or ``tilt_m<deg>``."""
    if name == "row":
        return SweepSpec("row", "row", "row", 0.0)
    if name == "column":
        return SweepSpec("column", "column", "column", 0.0)
    match = _TILT.match(name) if isinstance(name, str) else None
    if match:
        angle = float(match.group(2)) * (1.0 if match.group(1) == "p" else -1.0)
        if not 0 < abs(angle) < 60:
            raise argument_error("sweeps", f"tilt of {name!r} must be in (0, 60) degrees")
        return SweepSpec(name, "tilted", "row", angle)
    raise argument_error(
        "sweeps",
        f"unknown sweep {name!r}; expected row, column, tilt_p<deg> or tilt_m<deg> (e.g. tilt_p10)",
    )


def _positions(lo: float, hi: float, scan: ScanConfig) -> np.ndarray:
    n = scan.frames_per_sweep
    if scan.step_mm is None:
        if n == 1:
            return np.array([(lo + hi) / 2])
        return np.linspace(lo - scan.margin_mm, hi + scan.margin_mm, n)
    return (lo + hi) / 2 + scan.step_mm * (np.arange(n) - (n - 1) / 2)


def plan_sweep(
    spec: SweepSpec, bounds_mm: torch.Tensor | np.ndarray, surface_y_mm: float, scan: ScanConfig
) -> np.ndarray:
    """True probe-to-world poses (N, 4, 4) float64 of one sweep over a bone box (2, 3)."""
    box = np.asarray(bounds_mm, dtype=np.float64)
    if box.shape != (2, 3):
        raise argument_error("bounds_mm", f"expected a (2, 3) box, got shape {box.shape}")
    mid = box.mean(axis=0)
    if spec.orientation == "row":
        t = math.radians(spec.tilt_deg)
        rotation = np.array(
            [[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]]
        )
        z = _positions(box[0, 2], box[1, 2], scan)
        x_face = mid[0] + scan.tilt_pivot_depth_mm * math.tan(t)
        centres = np.stack([np.full_like(z, x_face), np.full_like(z, surface_y_mm), z], axis=1)
    elif spec.orientation == "column":
        rotation = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
        x = _positions(box[0, 0], box[1, 0], scan)
        centres = np.stack([x, np.full_like(x, surface_y_mm), np.full_like(x, mid[2])], axis=1)
    else:
        raise argument_error("orientation", f"expected row or column, got {spec.orientation!r}")
    poses = np.tile(np.eye(4), (centres.shape[0], 1, 1))
    poses[:, :3, :3] = rotation
    poses[:, :3, 3] = centres
    return poses


@dataclass(frozen=True)
class TrackingNoise:
    """Tracking error of stored poses.

    Attributes:
        translation_mm: Tracking error σ per axis, mm (0: exact poses).
        rotation_deg: Tracking error σ per axis, degrees.
        sweep_bias_share: Share of the error's variance that is one offset for a whole sweep
            (the rest drawn per frame).
    """

    translation_mm: float = 0.3
    rotation_deg: float = 0.2
    sweep_bias_share: float = 0.5

    def __post_init__(self) -> None:
        for name in ("translation_mm", "rotation_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise argument_error(name, f"expected a noise level ≥ 0, got {value}")
        if not 0.0 <= self.sweep_bias_share <= 1.0:
            raise argument_error(
                "sweep_bias_share", f"expected a number in [0, 1], got {self.sweep_bias_share}"
            )

    @property
    def enabled(self) -> bool:
        return self.translation_mm > 0 or self.rotation_deg > 0


def perturb_poses(
    true_probe_to_world: np.ndarray, noise: TrackingNoise, generator: torch.Generator
) -> np.ndarray:
    """Stored (tracked) poses of one sweep: true · ΔT with ΔT drawn as in ``TrackingNoise``."""
    poses = np.asarray(true_probe_to_world, dtype=np.float64)
    n = poses.shape[0]

    def draw(sigma: float) -> np.ndarray:
        bias = torch.randn(3, generator=generator, dtype=torch.float64).numpy()
        jitter = torch.randn((n, 3), generator=generator, dtype=torch.float64).numpy()
        share = noise.sweep_bias_share
        return sigma * (math.sqrt(share) * bias[None] + math.sqrt(1.0 - share) * jitter)

    translation = draw(noise.translation_mm)
    rotvec = np.radians(draw(noise.rotation_deg))
    delta = np.tile(np.eye(4), (n, 1, 1))
    delta[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    delta[:, :3, 3] = translation
    return poses @ delta
