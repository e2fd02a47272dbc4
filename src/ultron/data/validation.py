"""Validation of the arrays of an ``ultron-sweeps/1`` dataset.

Every check raises :class:`~ultron.errors.UltronInputError` naming the file (or argument), the
field and what was expected, so a user can fix the input without reading a traceback.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from ultron.errors import UltronInputError

#: Maximum allowed deviation of a pose's rotation block from orthonormality (|R Rᵀ − I|∞)
#: and of its determinant from +1.
ROTATION_TOLERANCE = 1e-3

#: The largest translation (mm, per axis) a pose may have: far beyond any tracker, far below
#: where float arithmetic overflows (a pose of 1e300 mm).
MAX_TRANSLATION_MM = 1e9

#: Label values: 0 background, 1 target (bone), 255 not annotated.
LABEL_BACKGROUND = 0
LABEL_TARGET = 1
LABEL_UNANNOTATED = 255
VALID_LABEL_VALUES = (LABEL_BACKGROUND, LABEL_TARGET, LABEL_UNANNOTATED)
#: Label values checked at once by :func:`validate_labels` (bounds its working memory).
_CHECK_VALUES = 1 << 24


def input_file(path: Path, field: str, required: bool = True) -> Path | None:
    """``path`` as an input file, symlinks followed: a regular file, or — when not
    ``required`` — absent (None). A dangling symlink or a symlink loop is always an error naming
    the file (never "absent"), as are a missing required file and a non-file."""
    try:
        os.stat(path)  # follows symlinks
    except FileNotFoundError:
        if os.path.islink(path):
            target = os.readlink(path)
            raise UltronInputError(path, field, f"dangling symlink (to {target!r})") from None
        if required:
            raise UltronInputError(path, field, "file is missing") from None
        return None
    except OSError as exc:
        problem = "symlink loop" if exc.errno == errno.ELOOP else f"cannot be read ({exc.strerror})"
        raise UltronInputError(path, field, problem) from None
    if not os.path.isfile(path):
        raise UltronInputError(path, field, "not a regular file")
    return path


def contained_path(folder: Path, name: object, where: Path, field: str) -> Path:
    """``folder / name`` for a path that the file ``where`` records in ``field``, refused in
    one line (naming ``where`` and ``field``) unless it stays inside ``folder``: a non-empty
    relative name without ``..`` whose target, symlinks followed, lies in ``folder`` (symlinks
    followed too). A dataset or recording can so never make ultron read outside itself; a
    file elsewhere is passed on the command line instead."""
    if not isinstance(name, str) or not name.strip():
        raise UltronInputError(where, field, f"expected a file name, got {name!r}")
    relative = Path(name)
    if relative.is_absolute() or ".." in relative.parts or name.startswith("~"):
        raise UltronInputError(
            where, field, f"{name!r} points outside {folder}: only names inside it are read"
        )
    target = folder / relative
    try:
        inside = target.resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):  # a symlink loop: input_file names it
        return target
    if not inside:
        raise UltronInputError(
            where, field, f"{name!r} is a symlink out of {folder}: only files inside it are read"
        )
    return target


def _check_npy_size(path: Path, field: str) -> None:
    """Refuse a ``.npy`` whose header declares more data than the file holds (before anything
    is allocated: a forged header can declare 10¹⁸ elements in a few bytes)."""
    try:
        with path.open("rb") as handle:
            version = np.lib.format.read_magic(handle)
            if version == (1, 0):
                shape, _order, dtype = np.lib.format.read_array_header_1_0(handle)
            else:
                shape, _order, dtype = np.lib.format.read_array_header_2_0(handle)
            offset = handle.tell()
    except (ValueError, EOFError, OSError, SyntaxError, TypeError):
        return  # np.load names what is wrong
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize if not dtype.hasobject else 0
    held = path.stat().st_size - offset
    if declared > held:
        raise UltronInputError(
            path, field, f"the header declares {shape} {dtype} ({declared} bytes) but the file"
            f" holds {held}: truncated or forged",
        )  # fmt: skip


#: The first bytes of every ``.npy`` file (NumPy's format, any version).
NPY_MAGIC = b"\x93NUMPY"


def load_npy(path: Path, field: str, mmap: bool = False) -> np.ndarray:
    """Load a ``.npy`` file without pickles, turning every failure into a clear error;
    ``mmap``: memory-mapped read-only (frames are read as they are indexed)."""
    input_file(path, field)
    _check_npy_size(path, field)
    with open(path, "rb") as handle:  # else NumPy reads it as a pickle and says to trust it
        if handle.read(len(NPY_MAGIC)) != NPY_MAGIC:
            raise UltronInputError(
                path, field, "not a readable .npy array (it does not start with NumPy's header)"
            )
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise UltronInputError(
            path, field, f"not a readable .npy array (truncated or not .npy format: {exc})"
        ) from None


def validate_images(images: np.ndarray, where: str | Path, field: str = "images") -> None:
    """Images must be a non-empty uint8 array of shape (N, H, W)."""
    if not isinstance(images, np.ndarray):
        raise UltronInputError(where, field, f"expected a numpy array, got {type(images).__name__}")
    if images.dtype != np.uint8:
        raise UltronInputError(where, field, f"expected dtype uint8, got {images.dtype}")
    if images.ndim != 3:
        raise UltronInputError(where, field, f"expected shape (N, H, W), got {images.shape}")
    if min(images.shape) < 1:
        raise UltronInputError(
            where, field, f"expected a non-empty (N, H, W) array, got {images.shape}"
        )


def pose_errors(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose orthonormality error max|R Rᵀ − I| and determinant error |det R − 1|."""
    rot = poses[..., :3, :3].astype(np.float64)
    gram = rot @ np.swapaxes(rot, -1, -2)
    ortho = np.abs(gram - np.eye(3)).max(axis=(-1, -2))
    det = np.abs(np.linalg.det(rot) - 1.0)
    return ortho, det


def validate_poses(
    poses: np.ndarray,
    where: str | Path,
    field: str = "poses",
    tolerance: float = ROTATION_TOLERANCE,
) -> None:
    """Poses must be finite rigid probe-to-world transforms of shape (N, 4, 4).

    The rotation block must satisfy max|R Rᵀ − I| ≤ ``tolerance`` and |det R − 1| ≤ ``tolerance``
    and the last row must be exactly (0, 0, 0, 1).
    """
    if not isinstance(poses, np.ndarray):
        raise UltronInputError(where, field, f"expected a numpy array, got {type(poses).__name__}")
    if not np.issubdtype(poses.dtype, np.floating):
        raise UltronInputError(where, field, f"expected a floating-point dtype, got {poses.dtype}")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] < 1:
        raise UltronInputError(where, field, f"expected shape (N, 4, 4), got {poses.shape}")
    finite = np.isfinite(poses).all(axis=(1, 2))
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise UltronInputError(where, field, f"pose {bad} contains NaN or inf")
    far = np.abs(poses[:, :3, 3]).max(axis=1) > MAX_TRANSLATION_MM
    if far.any():
        bad = int(np.flatnonzero(far)[0])
        raise UltronInputError(
            where, field, f"pose {bad} translates by {np.abs(poses[bad, :3, 3]).max():.3g} mm,"
            f" beyond {MAX_TRANSLATION_MM:.0e} mm (1000 km): not a tracked probe in millimetres",
        )  # fmt: skip
    last_row_ok = (poses[:, 3, :] == np.array([0.0, 0.0, 0.0, 1.0])).all(axis=1)
    if not last_row_ok.all():
        bad = int(np.flatnonzero(~last_row_ok)[0])
        raise UltronInputError(
            where, field, f"pose {bad} last row is {poses[bad, 3].tolist()}, expected [0, 0, 0, 1]"
        )
    ortho, det = pose_errors(poses)
    bad_mask = (ortho > tolerance) | (det > tolerance)
    if bad_mask.any():
        bad = int(np.flatnonzero(bad_mask)[0])
        raise UltronInputError(
            where,
            field,
            f"pose {bad} is not rigid: rotation block deviates from orthonormal by {ortho[bad]:.2e}"
            f" and det is {1.0 + float(np.linalg.det(poses[bad, :3, :3]) - 1.0):.6f}"
            f" (expected orthonormal with det +1 within {tolerance:g})",
        )


def validate_labels(labels: np.ndarray, where: str | Path, field: str = "labels") -> None:
    """Labels must be uint8 (N, H, W) holding only 0 (background), 1 (target), 255 (unannotated)."""
    if not isinstance(labels, np.ndarray):
        raise UltronInputError(where, field, f"expected a numpy array, got {type(labels).__name__}")
    if labels.dtype != np.uint8:
        raise UltronInputError(where, field, f"expected dtype uint8, got {labels.dtype}")
    if labels.ndim != 3:
        raise UltronInputError(where, field, f"expected shape (N, H, W), got {labels.shape}")
    # 0, 1, 255 + 1 wrap to 1, 2, 0: one comparison, frames at a time (no full-size temporaries;
    # np.unique sorted every value: 3.4 s per check of a 770 MB recording's labels)
    step = max(1, _CHECK_VALUES // max(1, labels[:1].size))
    if any((labels[k : k + step] + np.uint8(1) > 2).any() for k in range(0, len(labels), step)):
        present = np.unique(labels)
        invalid = np.setdiff1d(present, np.array(VALID_LABEL_VALUES, dtype=np.uint8))
        raise UltronInputError(
            where,
            field,
            f"invalid label values {invalid[:8].tolist()}; expected only 0 (background),"
            " 1 (target) and 255 (not annotated)",
        )


def validate_transmission(
    transmission: np.ndarray,
    where: str | Path,
    field: str = "transmission",
    image_shape: tuple[int, ...] | None = None,
) -> None:
    """A true transmission map (``<sweep>/transmission.npy``): float16 (N, H, W), finite, every
    value in [0, 1], and of the sweep's ``image_shape`` when given."""
    if not isinstance(transmission, np.ndarray):
        raise UltronInputError(
            where, field, f"expected a numpy array, got {type(transmission).__name__}"
        )
    if transmission.dtype != np.float16:
        raise UltronInputError(where, field, f"expected dtype float16, got {transmission.dtype}")
    if transmission.ndim != 3 or min(transmission.shape) < 1:
        raise UltronInputError(
            where, field, f"expected a non-empty (N, H, W) array, got {transmission.shape}"
        )
    finite = np.isfinite(transmission)
    if not finite.all():
        frame = int(np.flatnonzero(~finite.all(axis=(1, 2)))[0])
        raise UltronInputError(where, field, f"frame {frame} contains NaN or inf")
    low, high = float(transmission.min()), float(transmission.max())
    if low < 0.0 or high > 1.0:
        raise UltronInputError(
            where, field, f"values span [{low:g}, {high:g}], expected transmissions in [0, 1]"
        )
    if image_shape is not None and tuple(transmission.shape) != tuple(image_shape):
        raise UltronInputError(
            where,
            field,
            f"shape {transmission.shape} differs from the sweep's images {tuple(image_shape)}",
        )


def validate_mesh_file(path: Path, field: str) -> None:
    """A mesh file that exists, can be opened and is not empty (a PLY must start with ``ply``);
    its triangles are read only where it is used."""
    input_file(path, field)
    try:
        with path.open("rb") as handle:
            head = handle.read(3)
    except OSError as exc:
        raise UltronInputError(path, field, f"mesh file cannot be read ({exc})") from None
    if not head:
        raise UltronInputError(path, field, "mesh file is empty")
    if path.suffix.lower() == ".ply" and head != b"ply":
        raise UltronInputError(path, field, "not a readable PLY mesh (no 'ply' header)")


def validate_positive(value: object, where: str | Path, field: str) -> float:
    """A finite, strictly positive number (bools are rejected)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise UltronInputError(where, field, f"expected a positive number, got {value!r}")
    number = float(value)
    if not np.isfinite(number) or number <= 0:
        raise UltronInputError(where, field, f"expected a positive number, got {value!r}")
    return number


#: The widest or deepest image a probe may have, mm: far beyond any probe, far below where
#: float arithmetic on the scanned region overflows (a width of 1e308).
MAX_PROBE_EXTENT_MM = 1e4


def validate_probe_extent(value: object, where: str | Path, field: str) -> float:
    """A probe's image width or depth, mm: a positive number up to :data:`MAX_PROBE_EXTENT_MM`."""
    extent = validate_positive(value, where, field)
    if extent > MAX_PROBE_EXTENT_MM:
        raise UltronInputError(
            where, field, f"{extent:g} mm; expected at most {MAX_PROBE_EXTENT_MM:g} mm (are the"
            " lengths in mm?)",
        )  # fmt: skip
    return extent
