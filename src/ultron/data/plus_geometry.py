"""The geometry of a PLUS frame's image plane.

PLUS's affine ImageToProbe (the pixel scale and, from a calibration fit, usually a small
shear) is factored into a rigid pose and two pixel spacings (:func:`fit_image_plane`): the
least-squares fit over the frame's pixels, exact wherever ImageToProbe is a scaled rotation.
Where it is not (a shear moves the rigid map's pixels by more than
:data:`RESAMPLE_RESIDUAL_MM` from PLUS's, as on the shared spine phantom:
docs/decisions.md#plus-import-resampling-to-a-rigid-map-dataplus_geometrypy), the frames are
resampled onto the rigid map's pixel grid (:func:`resample_to_rigid`): each new pixel takes
the grey level PLUS's own calibration puts at its position (bilinear). Frames can also be
area-downsampled (:func:`downsample_frames`). :mod:`ultron.data.plus_import` builds sweeps
with these.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultron.errors import UltronInputError
from ultron.parallel import thread_map

#: Largest angle (degrees) between the calibration's image axes and a right angle that is
#: factored into a rigid pose; beyond it the matrix is refused as far from a scaled rotation.
MAX_SHEAR_DEG = 10.0
#: A rigid fit that moves a pixel by more than this (mm) from PLUS's calibration has its frames
#: resampled onto the rigid grid (:func:`resample_to_rigid`); below it they are used as they are.
RESAMPLE_RESIDUAL_MM = 0.01
#: Frames resampled per chunk when downsampling (bounds the float64 working memory).
_CHUNK_FRAMES = 16


@dataclass(frozen=True)
class ImagePlaneFit:
    """Image → probe as a rigid pose and pixel spacings.

    ``rotation`` columns are the probe-frame directions of image x (columns), image y (rows)
    and their cross product; ``origin_mm`` is the fitted probe point of pixel (0, 0):
    pixel (i, j) ↦ origin + i·s_x·r₁ + j·s_y·r₂. ``shear_deg`` is the angle between the
    calibration's image axes minus 90°; ``residual_max_mm`` / ``residual_rms_mm`` the largest
    (at a corner) and RMS distance over the frame's pixels between this map and the
    calibration's own.
    """

    rotation: np.ndarray
    origin_mm: np.ndarray
    spacing_mm: tuple[float, float]
    shear_deg: float
    residual_max_mm: float
    residual_rms_mm: float

    def image_to_probe(self) -> np.ndarray:
        """The fitted calibration as PLUS writes one: pixel (i, j, 0, 1) → probe (4 × 4)."""
        matrix = np.eye(4)
        matrix[:3, 0] = self.spacing_mm[0] * self.rotation[:, 0]
        matrix[:3, 1] = self.spacing_mm[1] * self.rotation[:, 1]
        matrix[:3, 2] = self.rotation[:, 2]
        matrix[:3, 3] = self.origin_mm
        return matrix

    def dataset_probe_to_probe(self, width_px: int) -> np.ndarray:
        """The rigid map from ultron's probe frame of a ``width_px``-column frame (x lateral
        from the centre column, y along the beam) to PLUS's probe frame (4 × 4)."""
        pose = np.eye(4)
        pose[:3, :3] = self.rotation
        pose[:3, 3] = self.origin_mm + (width_px / 2) * self.spacing_mm[0] * self.rotation[:, 0]
        return pose


def _fit_angle(a: float, b: float, shear: float) -> float:
    """Rotation α of r₁ away from image x (towards image y) that minimises the weighted
    residual a²·sin²α + b²·sin²(shear − α): tan 2α = b² sin 2δ / (a² + b² cos 2δ)."""
    return 0.5 * math.atan2(b * b * math.sin(2 * shear), a * a + b * b * math.cos(2 * shear))


def fit_image_plane(
    matrix: np.ndarray, width_px: int, height_px: int, where: str | Path, field_name: str
) -> ImagePlaneFit:
    """Factor the calibration ``matrix`` (pixel → probe, 4 × 4) of a ``height_px`` ×
    ``width_px`` frame into a rigid pose and pixel spacings.

    Only its first two columns (the image axes a_x, a_y) and translation act on pixels. The fit
    minimises the mean squared displacement of the frame's pixels: with the residual zero at
    the centre pixel, it is |u|²·var_c + |v|²·var_r (u = a_x − s_x r₁, v = a_y − s_y r₂; var
    the variance of the column / row index over the frame), a Procrustes problem with one free
    angle in the image plane (:func:`_fit_angle`); the optimal spacings are s_x = a_x·r₁,
    s_y = a_y·r₂. An exact scaled rotation is reproduced exactly.
    """
    ax, ay, t = (np.asarray(matrix[:3, k], dtype=np.float64) for k in (0, 1, 3))
    nx, ny = float(np.linalg.norm(ax)), float(np.linalg.norm(ay))
    normal = np.cross(ax, ay)
    if not (nx > 0 and ny > 0 and np.linalg.norm(normal) > 1e-9 * nx * ny):
        raise UltronInputError(
            where, field_name, "image axes are zero or parallel (not a calibration)"
        )
    e1, n = ax / nx, normal / np.linalg.norm(normal)
    e2 = np.cross(n, e1)
    shear = math.atan2(float(ay @ e2), float(ay @ e1)) - math.pi / 2
    var_c, var_r = (width_px**2 - 1) / 12, (height_px**2 - 1) / 12
    alpha = _fit_angle(nx * math.sqrt(var_c), ny * math.sqrt(var_r), shear)
    r1 = math.cos(alpha) * e1 + math.sin(alpha) * e2
    r2 = np.cross(n, r1)
    sx, sy = float(ax @ r1), float(ay @ r2)
    u, v = ax - sx * r1, ay - sy * r2
    centre_c, centre_r = (width_px - 1) / 2, (height_px - 1) / 2
    corners = [(dc, dr) for dc in (-centre_c, centre_c) for dr in (-centre_r, centre_r)]
    residual_max = max(float(np.linalg.norm(dc * u + dr * v)) for dc, dr in corners)
    residual_rms = math.sqrt(float(u @ u) * var_c + float(v @ v) * var_r)
    if abs(math.degrees(shear)) > MAX_SHEAR_DEG or min(sx, sy) <= 0:
        raise UltronInputError(
            where,
            field_name,
            f"far from a scaled rotation: its image axes are {abs(math.degrees(shear)):.2f}°"
            f" from perpendicular (at most {MAX_SHEAR_DEG:g}° is factored into a rigid pose);"
            f" a rigid pose would move pixels by up to {residual_max:.3g} mm",
        )
    return ImagePlaneFit(
        rotation=np.stack([r1, r2, n], axis=1),
        origin_mm=t + centre_c * u + centre_r * v,
        spacing_mm=(sx, sy),
        shear_deg=math.degrees(shear),
        residual_max_mm=residual_max,
        residual_rms_mm=residual_rms,
    )


def rigid_to_image_pixels(calibration: np.ndarray, fit: ImagePlaneFit) -> np.ndarray:
    """The affine map (3 × 3, homogeneous) from a pixel (i', j') of the rigid fit's grid to the
    pixel (i, j) of the original frame that PLUS's ``calibration`` places at the same probe
    point: a_x·i + a_y·j + t = o + i'·s_x·r₁ + j'·s_y·r₂, solved in the image plane (both maps
    span it) with the pseudo-inverse of [a_x a_y]."""
    inverse = np.linalg.pinv(np.asarray(calibration, dtype=np.float64)[:3, :2])  # (2, 3)
    linear = inverse @ np.stack(
        [fit.spacing_mm[0] * fit.rotation[:, 0], fit.spacing_mm[1] * fit.rotation[:, 1]], axis=1
    )
    offset = inverse @ (fit.origin_mm - np.asarray(calibration, dtype=np.float64)[:3, 3])
    matrix = np.eye(3)
    matrix[:2, :2], matrix[:2, 2] = linear, offset
    return matrix


def resample_to_rigid(
    frames: np.ndarray,
    calibration: np.ndarray,
    fit: ImagePlaneFit,
    advance: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """uint8 (N, H, W) frames resampled onto the rigid fit's pixel grid (module doc): new pixel
    (row j', column i') is the original frame bilinearly interpolated at the pixel
    (:func:`rigid_to_image_pixels`) PLUS's ``calibration`` puts at the same probe point; 0
    (PLUS's background) where that lies outside the frame. Frames are resampled on
    :func:`~ultron.parallel.thread_map`'s threads (ndimage releases the GIL), a run of
    :data:`RESAMPLE_RUN` frames at a time; ``advance``, when given, is told (frames done, N)
    before the first run and after each."""
    from scipy import ndimage

    pixels = rigid_to_image_pixels(calibration, fit)
    # ndimage works in (row, column) = (j, i) order: swap both sides of the map
    swap = np.array([[0, 1, 0], [1, 0, 0], [0, 0, 1]], dtype=np.float64)
    rows_cols = swap @ pixels @ swap
    out = np.empty_like(frames)

    def resample(k: int) -> None:
        values = ndimage.affine_transform(
            frames[k].astype(np.float32), rows_cols[:2, :2], rows_cols[:2, 2],
            order=1, mode="constant", cval=0.0,
        )  # fmt: skip
        out[k] = np.clip(np.rint(values), 0, 255).astype(np.uint8)

    n = len(frames)
    if advance is not None:
        advance(0, n)
    for start in range(0, n, RESAMPLE_RUN):
        thread_map(resample, range(start, min(start + RESAMPLE_RUN, n)))
        if advance is not None:
            advance(min(start + RESAMPLE_RUN, n), n)
    return out


#: Frames :func:`resample_to_rigid` resamples between two progress reports.
RESAMPLE_RUN = 64


#: Largest displacement (mm, at a frame corner) between one frame's calibration and the
#: recording's common one that :func:`factor_image_to_world` accepts as one calibration (a
#: tracker's rounding moves a pixel by 1e-4 mm; a changed depth or zoom by millimetres).
CALIBRATION_SPREAD_MM = 0.05


@dataclass(frozen=True)
class TrackedCalibration:
    """Per-frame Image → world transforms factored into a rigid image-plane pose per frame and
    one calibration (:func:`factor_image_to_world`)."""

    #: (K, 4, 4) rigid: the image plane's own frame (x along image columns, y in the plane
    #: towards the rows, z their normal; origin at pixel (0, 0)) → world.
    plane_to_world: np.ndarray
    #: pixel (i, j, 0, 1) → the plane's frame, mm: [[s_x, a, 0, 0], [0, s_y, 0, 0], …].
    image_to_plane: np.ndarray
    #: Largest distance (mm) by which a frame's own calibration moves a frame corner from
    #: ``image_to_plane``'s placement.
    spread_mm: float


def factor_image_to_world(
    image_to_world: np.ndarray, width_px: int, height_px: int, where: str | Path, field_name: str
) -> TrackedCalibration:
    """Factor per-frame Image → world transforms A_k (PLUS's ``ImageToReference``: tracking
    with the calibration, and so the pixel scale, already in it) as A_k = P_k · C.

    Only the image axes a_x, a_y (A_k's first two columns) and its translation t act on pixels.
    Per frame, the image plane's frame is q₁ = a_x/|a_x|, q₃ = a_x × a_y/|a_x × a_y|, q₂ =
    q₃ × q₁ (a rotation), P_k = [q₁ q₂ q₃ | t]; in it the axes are C_k's columns (|a_x|, 0, 0)
    and (a_y·q₁, a_y·q₂, 0), so P_k·C_k·[i, j, 0, 1]ᵀ = A_k·[i, j, 0, 1]ᵀ exactly. A tracked
    probe's frames differ only in P_k, so C = mean C_k is their common calibration; a frame
    whose C_k moves a corner of the ``height_px`` × ``width_px`` frame by more than
    :data:`CALIBRATION_SPREAD_MM` from C's placement (the depth or zoom changed during the
    recording) is an error naming ``field_name``, as are zero or parallel image axes."""
    matrices = np.asarray(image_to_world, dtype=np.float64)
    ax, ay, t = matrices[:, :3, 0], matrices[:, :3, 1], matrices[:, :3, 3]
    nx = np.linalg.norm(ax, axis=1)
    normal = np.cross(ax, ay)
    nn = np.linalg.norm(normal, axis=1)
    if not (np.all(nx > 0) and np.all(nn > 1e-9 * nx * np.linalg.norm(ay, axis=1))):
        raise UltronInputError(
            where, field_name, "image axes are zero or parallel in some frame (not a calibration)"
        )
    q1, q3 = ax / nx[:, None], normal / nn[:, None]
    q2 = np.cross(q3, q1)
    plane = np.tile(np.eye(4), (len(matrices), 1, 1))
    plane[:, :3, :3] = np.stack([q1, q2, q3], axis=2)
    plane[:, :3, 3] = t
    own = np.zeros((len(matrices), 2, 2))  # each frame's C_k restricted to the image plane
    own[:, 0, 0] = nx
    own[:, 0, 1], own[:, 1, 1] = np.einsum("ki,ki->k", ay, q1), np.einsum("ki,ki->k", ay, q2)
    common = own.mean(axis=0)
    corners = np.array([(i, j) for i in (0, width_px - 1) for j in (0, height_px - 1)])
    spread = float(np.linalg.norm(np.einsum("kab,cb->kca", own - common, corners), axis=2).max())
    if spread > CALIBRATION_SPREAD_MM:
        worst = int(np.argmax(np.abs(own - common).reshape(len(own), -1).max(axis=1)))
        raise UltronInputError(
            where,
            field_name,
            f"the image's scale or shear changes across frames (a frame corner moves by up to"
            f" {spread:.3g} mm from the recording's mean calibration, at most"
            f" {CALIBRATION_SPREAD_MM:g}; e.g. {own[worst, 0, 0]:.5f} × {own[worst, 1, 1]:.5f}"
            f" mm per pixel against {common[0, 0]:.5f} × {common[1, 1]:.5f}): the depth or zoom"
            " changed during the recording, and a sweep has one calibration",
        )  # fmt: skip
    calibration = np.eye(4)
    calibration[:2, :2] = common
    return TrackedCalibration(plane, calibration, spread)


# --------------------------------------------------------------------------- downsampling
def downsampled_shape(height: int, width: int, factor: float) -> tuple[int, int]:
    """(H', W') of frames downsampled by ``factor`` ≥ 1 (rounded, at least 1)."""
    return max(1, round(height / factor)), max(1, round(width / factor))


def _box_resample(values: np.ndarray, new_len: int) -> np.ndarray:
    """Area-resample the last axis of ``values`` (length L) to ``new_len`` ≤ L samples at
    positions k·L/new_len (the format's pixel positions of the new grid): each is the mean of
    the pixel-constant signal over a window of L/new_len pixels centred there, edges extended."""
    length = values.shape[-1]
    if new_len == length:
        return values
    step = length / new_len
    cumulative = np.concatenate(
        [np.zeros((*values.shape[:-1], 1)), np.cumsum(values, axis=-1)], axis=-1
    )

    def integral(x: np.ndarray) -> np.ndarray:  # ∫ from −0.5 to x of the signal
        inside = np.clip(x, -0.5, length - 0.5)
        k = np.clip(np.floor(inside + 0.5).astype(np.int64), 0, length - 1)
        value = cumulative[..., k] + (inside + 0.5 - k) * values[..., k]
        below = np.minimum(x + 0.5, 0.0) * values[..., :1]
        above = np.maximum(x - (length - 0.5), 0.0) * values[..., -1:]
        return value + below + above

    centres = np.arange(new_len) * step
    return (integral(centres + step / 2) - integral(centres - step / 2)) / step


def downsample_frames(frames: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Anti-aliased (area-averaging) downsampling of uint8 (N, H, W) frames to (N, H', W'):
    new pixel (r', c') is the mean over a (H/H') × (W/W') pixel window centred on old position
    (r'·H/H', c'·W/W'), where the format places it, so the field of view (width and depth in
    mm) is unchanged and the spacings grow by W/W' and H/H'."""
    n, height, width = frames.shape
    if (height, width) == tuple(shape):
        return frames
    out = np.empty((n, *shape), dtype=np.uint8)
    for start in range(0, n, _CHUNK_FRAMES):
        chunk = frames[start : start + _CHUNK_FRAMES].astype(np.float64)
        chunk = _box_resample(chunk, shape[1])
        chunk = np.swapaxes(_box_resample(np.swapaxes(chunk, 1, 2), shape[0]), 1, 2)
        out[start : start + _CHUNK_FRAMES] = np.clip(np.rint(chunk), 0, 255).astype(np.uint8)
    return out


# --------------------------------------------------------------------------- tracking
