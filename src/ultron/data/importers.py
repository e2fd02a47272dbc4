"""Importers from other sweep layouts into ``ultron-sweeps/1``.

Ultra-NeRF layout (Wysocki et al., MIDL 2023)::

    SRC/images/0.png, 1.png, ...   8-bit grey frames, row 0 at the transducer face
      or SRC/images.npy            uint8 (N, H, W)
    SRC/poses.npy                  float (N, 4, 4) probe-to-world, translation in mm

Ultra-NeRF's geometry is ultron's (METHOD.md §1), so frames and poses are taken unchanged
except for one repair: published pose files carry rotation blocks that are only approximately
orthonormal (the shared ``l2`` sample deviates by up to 1e-2, a shear of ≈ 0.6°), while
``ultron-sweeps/1`` requires 1e-3. Rotation blocks that deviate by at most
``orthonormalize_tolerance`` are replaced by the nearest rotation (polar decomposition via
SVD), the translation kept; larger deviations are refused as non-rigid.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.validation import (
    ROTATION_TOLERANCE,
    input_file,
    load_npy,
    pose_errors,
    validate_images,
    validate_positive,
)
from ultron.errors import UltronInputError, argument_error
from ultron.outputs import check_dataset_out

#: Largest rotation-block deviation the importer repairs (above it a pose is refused).
DEFAULT_ORTHONORMALIZE_TOLERANCE = 0.05
#: Tolerances must lie in [0, 1): a block deviating by 1 or more (e.g. a uniform scale ≥ √2)
#: is no perturbed rotation, and "repairing" it would hide a wrong pose file.
MAX_ORTHONORMALIZE_TOLERANCE = 1.0


@dataclass(frozen=True)
class ImportReport:
    """What an import did: frames read and how much the poses were repaired.

    Every rotation block is projected to the nearest rotation; ``n_poses_beyond_tolerance``
    counts those that would have failed the format's 1e-3 rigidity check without it.
    """

    n_frames: int
    image_shape: tuple[int, int]
    max_rotation_deviation: float
    n_poses_beyond_tolerance: int


def nearest_rotation(matrices: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (Frobenius norm) of each (..., 3, 3) matrix M = U·Σ·Vᵀ:
    R = U·diag(1, 1, s)·Vᵀ, s = sign det(U·Vᵀ) = ±1 exactly (U's last column flipped where M
    reflects)."""
    u, _, vt = np.linalg.svd(matrices)
    u[..., :, 2] *= np.where(np.linalg.det(u) * np.linalg.det(vt) < 0, -1.0, 1.0)[..., None]
    return u @ vt


def check_orthonormalize_tolerance(tolerance: float) -> None:
    """``tolerance`` must lie in [0, :data:`MAX_ORTHONORMALIZE_TOLERANCE`): NaN, which fails
    every comparison, would "repair" any pose."""
    if isinstance(tolerance, bool) or not (
        isinstance(tolerance, int | float) and 0 <= tolerance < MAX_ORTHONORMALIZE_TOLERANCE
    ):
        raise argument_error(
            "orthonormalize_tolerance",
            f"expected a value in [0, {MAX_ORTHONORMALIZE_TOLERANCE:g}), got {tolerance!r}",
        )


def orthonormalize_poses(
    poses: np.ndarray, tolerance: float, where: str | Path
) -> tuple[np.ndarray, np.ndarray]:
    """Replace each pose's rotation block by its nearest rotation; refuse deviations > ``tolerance``.

    Returns the repaired float64 poses and the per-pose deviation max|R Rᵀ − I| before repair.
    """
    check_orthonormalize_tolerance(tolerance)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise UltronInputError(where, "poses", f"expected shape (N, 4, 4), got {poses.shape}")
    if not np.isfinite(poses).all():
        bad = int(np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))[0])
        raise UltronInputError(where, "poses", f"pose {bad} contains NaN or inf")
    ortho, det = pose_errors(poses)
    bad_mask = (ortho > tolerance) | (det > tolerance)
    if bad_mask.any():
        bad = int(np.flatnonzero(bad_mask)[0])
        raise UltronInputError(
            where,
            "poses",
            f"pose {bad} is not rigid: rotation deviates from orthonormal by {ortho[bad]:.2e}"
            f" (det error {det[bad]:.2e}), more than the repairable {tolerance:g}",
        )
    repaired = poses.copy()
    repaired[:, :3, :3] = nearest_rotation(poses[:, :3, :3])
    repaired[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    return repaired, ortho


def numbered_frames(folder: Path) -> list[Path]:
    """The frames ``0.png, 1.png, …, (N−1).png`` of ``folder`` in numeric order.

    Frame i is paired with pose i, so the numbering must be exactly 0 … N − 1: a gap (say
    ``3.png`` renamed ``30.png``) would pair every later frame with the wrong pose, and two
    names of one number (``3.png``, ``03.png``) are ambiguous; both are errors naming the first
    missing index or the clashing files.
    """
    by_index = png_numbers(folder)
    missing = next((i for i in range(len(by_index)) if i not in by_index), None)
    if missing is not None:
        raise UltronInputError(
            folder / f"{missing}.png", "images", f"frame {missing} is missing: {len(by_index)}"
            f" frames must be numbered 0 … {len(by_index) - 1} (found up to"
            f" {max(by_index)}.png), or frames and poses would be paired wrongly",
        )  # fmt: skip
    return [by_index[i] for i in range(len(by_index))]


def png_numbers(folder: Path) -> dict[int, Path]:
    """The ``.png`` files of ``folder`` by the frame number their name gives (``0010.png`` →
    10), in numeric order; a name that is not a number, or two names of one number, is an
    error naming them."""
    files = list(folder.glob("*.png"))
    if not files:
        raise UltronInputError(folder, "images", "no .png frames found")
    non_numeric = sorted(f.name for f in files if not (f.stem.isascii() and f.stem.isdigit()))
    if non_numeric:
        raise UltronInputError(
            folder, "images", f"frame names must be 0.png, 1.png, …; found {non_numeric[:3]}"
        )
    by_index: dict[int, Path] = {}
    for file in sorted(files, key=lambda f: (int(f.stem), f.name)):
        index = int(file.stem)
        if index in by_index:
            raise UltronInputError(
                folder,
                "images",
                f"{by_index[index].name} and {file.name} both number frame {index}",
            )
        by_index[index] = file
    return by_index


#: The largest frame a PNG may declare (pixels): far beyond any B-mode image, far below a
#: decompression bomb.
MAX_FRAME_PIXELS = 2**25


def _read_png(file: Path) -> tuple[np.ndarray, str]:
    """One PNG's pixels and mode; a palette image reads as its colours, never its indices."""
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(file) as img:
                width, height = img.size
                if width * height > MAX_FRAME_PIXELS:
                    raise UltronInputError(
                        file, "image", f"declares {width} × {height} pixels (more than"
                        f" {MAX_FRAME_PIXELS}): not a B-mode frame",
                    )  # fmt: skip
                mode = img.mode
                if mode in ("P", "PA"):
                    img = img.convert("RGBA")
                return np.asarray(img), mode
    except (OSError, Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise UltronInputError(file, "image", f"not a readable PNG ({exc})") from None


def read_png_frames(folder: Path) -> np.ndarray:
    """Read ``0.png, 1.png, …`` (:func:`numbered_frames`) as uint8 (N, H, W) grey frames."""
    return read_png_files(numbered_frames(folder))


def read_png_files(files: list[Path]) -> np.ndarray:
    """Read ``files`` as uint8 (N, H, W) grey frames of one size; a colour or non-8-bit PNG,
    or one of another size, is an error naming it."""
    frames = []
    for file in files:
        input_file(file, "image")
        array, mode = _read_png(file)
        if array.ndim == 3 and array.shape[2] in (3, 4):
            rgb = array[..., :3]
            if not (rgb == rgb[..., :1]).all():
                raise UltronInputError(
                    file, "image", f"colour PNG (mode {mode}); expected grey B-mode"
                )
            array = rgb[..., 0]
        if array.dtype != np.uint8 or array.ndim != 2:
            raise UltronInputError(
                file, "image", f"expected 8-bit grey, got mode {mode} shape {array.shape}"
            )
        if frames and array.shape != frames[0].shape:
            raise UltronInputError(
                file, "image", f"size {array.shape} differs from {files[0].name} {frames[0].shape}"
            )
        frames.append(array)
    return np.stack(frames)


def read_ultranerf(
    src: str | Path,
    width_mm: float,
    depth_mm: float,
    name: str = "sweep",
    kind: str = "other",
    orthonormalize_tolerance: float = DEFAULT_ORTHONORMALIZE_TOLERANCE,
) -> tuple[Sweep, ProbeGeometry, ImportReport]:
    """Read one Ultra-NeRF sweep folder as a :class:`Sweep` and its :class:`ProbeGeometry`."""
    src = Path(src)
    validate_positive(width_mm, "argument", "width_mm")
    validate_positive(depth_mm, "argument", "depth_mm")
    check_orthonormalize_tolerance(orthonormalize_tolerance)
    if not src.is_dir():
        raise UltronInputError(src, "SRC", "not a directory")
    has_npy = input_file(src / "images.npy", "images", required=False) is not None
    if has_npy and (src / "images").is_dir() and any((src / "images").glob("*.png")):
        raise UltronInputError(
            src, "images", "holds both images.npy and images/*.png: which are the frames is"
            " ambiguous; move one of them away",
        )  # fmt: skip
    if has_npy:
        images_path = src / "images.npy"
        images = load_npy(images_path, "images")
    elif (src / "images").is_dir():
        images_path = src / "images"
        images = read_png_frames(images_path)
    else:
        raise UltronInputError(src, "images", "expected images/0.png… or images.npy")
    validate_images(images, images_path)
    poses_path = src / "poses.npy"
    poses = load_npy(poses_path, "poses")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise UltronInputError(poses_path, "poses", f"expected shape (N, 4, 4), got {poses.shape}")
    if poses.shape[0] != images.shape[0]:
        raise UltronInputError(
            poses_path,
            "poses",
            f"has {poses.shape[0]} poses but {images.shape[0]} frames (N mismatch)",
        )
    if not np.issubdtype(poses.dtype, np.floating):
        raise UltronInputError(
            poses_path, "poses", f"expected a floating-point dtype, got {poses.dtype}"
        )
    if not (np.abs(poses[:, 3, :] - np.array([0, 0, 0, 1])) <= 1e-6).all():
        raise UltronInputError(poses_path, "poses", "last row of some pose is not [0, 0, 0, 1]")
    repaired, deviation = orthonormalize_poses(poses, orthonormalize_tolerance, poses_path)
    sweep = Sweep(name=name, kind=kind, images=images, probe_to_world=repaired)
    probe = ProbeGeometry(
        float(width_mm), float(depth_mm), int(images.shape[1]), int(images.shape[2])
    )
    report = ImportReport(
        n_frames=int(images.shape[0]),
        image_shape=(int(images.shape[1]), int(images.shape[2])),
        max_rotation_deviation=float(deviation.max()),
        n_poses_beyond_tolerance=int((deviation > ROTATION_TOLERANCE).sum()),
    )
    return sweep, probe, report


def _frames(probe: ProbeGeometry) -> str:
    """``probe``'s frames in words: pixels, and the mm they span."""
    return (
        f"{probe.height_px} × {probe.width_px} pixels over {probe.depth_mm:.3f} mm deep ×"
        f" {probe.width_mm:.3f} mm wide"
    )


def add_sweep_to_dataset(
    out: str | Path,
    sweep: Sweep,
    probe: ProbeGeometry,
    replace: bool = False,
    tolerance_mm: float = 1e-9,
    sweep_metadata: dict[str, Any] | None = None,
) -> SweepDataset:
    """Add ``sweep`` to the dataset at ``out`` (created if absent) and save it atomically.

    An existing dataset must have the same probe geometry; a sweep of the same name is an error
    unless ``replace`` is true, in which case it is replaced in place. ``sweep_metadata`` (the
    import's provenance) is kept in ``dataset.json``'s metadata under ``"imports"`` → sweep
    name; a replaced sweep's earlier entry is dropped.
    """
    out = check_dataset_out(out, "out")  # new, empty or a dataset: not a folder of other files
    if (out / "dataset.json").exists():
        dataset = SweepDataset.load(out)
        same = (
            abs(dataset.probe.width_mm - probe.width_mm) <= tolerance_mm
            and abs(dataset.probe.depth_mm - probe.depth_mm) <= tolerance_mm
            and dataset.probe.image_shape == probe.image_shape
        )
        if not same:
            raise UltronInputError(
                out / "dataset.json", "probe", f"the dataset's frames are {_frames(dataset.probe)},"
                f" the new sweep's {_frames(probe)}: a dataset has one probe geometry (an"
                " import-plus sweep added without --downsample takes the dataset's factor)",
            )  # fmt: skip
        names = [s.name for s in dataset.sweeps]
        if sweep.name in names and not replace:
            raise argument_error(
                "sweep_name",
                f"dataset {out} already has a sweep named {sweep.name!r} (replace it with --replace)",
            )
        sweeps = [s for s in dataset.sweeps if s.name != sweep.name]
        if sweep.name in names:
            sweeps.insert(names.index(sweep.name), sweep)
        else:
            sweeps.append(sweep)
        dataset = SweepDataset(
            dataset.probe,
            sweeps,
            dataset.reference,
            _with_import(dataset.metadata, sweep.name, sweep_metadata),
            reference_visible_path=dataset.reference_visible_path,
        )
        dataset.save(out, only_sweeps=[sweep.name])
        return dataset
    metadata = _with_import({}, sweep.name, sweep_metadata)
    dataset = SweepDataset(probe=probe, sweeps=[sweep], metadata=metadata)
    dataset.save(out)
    return dataset


def _with_import(
    metadata: dict[str, Any], name: str, entry: dict[str, Any] | None
) -> dict[str, Any]:
    """``metadata`` with ``imports[name]`` set to ``entry`` (removed when None)."""
    imports = metadata.get("imports")
    if not isinstance(imports, dict):
        if entry is None:
            return metadata
        imports = {}
    imports = {key: value for key, value in imports.items() if key != name}
    if entry is not None:
        imports[name] = entry
    updated = {key: value for key, value in metadata.items() if key != "imports"}
    if imports:
        updated["imports"] = imports
    return updated
