"""Resource guards: the grids a run will allocate, sized from the dataset and the options
before anything is allocated.

One outlier pose (a frame at +1e6 mm) or a tiny probe (0.5 mm wide: 5 µm pixels) makes the
meshing grid over "everything the probe saw" at the finer pixel spacing ask for petabytes, and
the acoustic field's finest planes for millions of nodes per side. :func:`check_run_resources`
refuses such a run at once with a one-line error saying which input made it so:

1. outlier poses (:func:`ultron.data.outliers.check_pose_outliers`), named by frame;
2. the meshing grid (:func:`ultron.methods.ultron_method.scan_grid`'s rule: the field of
   view's bounding box, padded by 2 voxels, at ``voxel_mm`` or the finer pixel spacing) at
   :data:`MESH_BYTES_PER_VOXEL` bytes per voxel — the coarse-to-fine evaluation's float32
   volumes, the masks, marching cubes and the constrained smoothing's arrays; ≈ 0.4 GB for the
   demo's 6 M voxels, whose meshing stage measured 0.77 GB peak RSS including the process —
   against the memory limit;
3. for a field that will be fitted, the grid backend's planes (finest cell = pixel spacing at
   the fit resolution; at most ``fields.grid.MAX_RESOLUTION`` nodes per side) at
   :data:`FIELD_BYTES_PER_VALUE` bytes per plane value (weight, gradient, Adam's two moments).

The memory limit is ``--max-memory`` (GiB) where given, else this machine's memory (physical
memory, or the cgroup's limit where lower).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.outliers import check_pose_outliers
from ultron.errors import UltronInputError

if TYPE_CHECKING:
    from ultron.train.field_config import FieldTrainConfig

#: Peak bytes per voxel of the meshing grid (module doc).
MESH_BYTES_PER_VOXEL = 64
#: Bytes per value of the field's planes while fitting: float32 weight, gradient, Adam m and v.
FIELD_BYTES_PER_VALUE = 16
_GIB = 1024**3


def machine_memory_bytes() -> int | None:
    """Physical memory, or the cgroup's memory limit where lower; None if unknown."""
    limits = []
    try:
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text(encoding="ascii").strip()
        except OSError:
            continue
        if text.isdigit() and int(text) > 0:
            limits.append(int(text))
    return min(limits) if limits else None


def memory_limit(max_memory_gib: float | None = None) -> tuple[float, str]:
    """The memory a run may plan for, bytes (inf if unknown), and how to name it."""
    if max_memory_gib is not None:
        return max_memory_gib * _GIB, f"--max-memory {max_memory_gib:g} GiB"
    machine = machine_memory_bytes()
    if machine is None:
        return math.inf, "this machine's memory"
    return float(machine), f"this machine's memory ({machine / _GIB:.1f} GiB)"


def _size(n_bytes: float) -> str:
    for unit, scale in (("PiB", 1024**5), ("TiB", 1024**4), ("GiB", _GIB), ("MiB", 1024**2)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes:.0f} B"


def describe_probe(probe: ProbeGeometry) -> str:
    """``38 mm wide / 96 columns = 0.396 mm, 70 mm deep / 128 rows = 0.547 mm``."""
    return (
        f"{probe.width_mm:g} mm wide / {probe.width_px} columns = {probe.lateral_spacing_mm:.3g}"
        f" mm, {probe.depth_mm:g} mm deep / {probe.height_px} rows ="
        f" {probe.axial_spacing_mm:.3g} mm"
    )


def meshing_grid_shape(
    dataset: SweepDataset, voxel_mm: float | None
) -> tuple[tuple[int, int, int], float, tuple[float, float, float]]:
    """The shape ``scan_grid(dataset, voxel_mm)`` will have, computed with Python integers
    (no overflow, nothing allocated), its voxel and the scanned extent in mm."""
    from ultron.data.geometry import field_of_view_bounds_mm
    from ultron.mesh.grid import grid_shape, meshing_voxel_mm

    voxel = meshing_voxel_mm(dataset.probe, voxel_mm)
    bounds = field_of_view_bounds_mm(dataset.all_poses(), dataset.probe).numpy()
    extent = tuple(float(e) for e in bounds[1] - bounds[0])
    return grid_shape(bounds, voxel), voxel, extent  # type: ignore[return-value]


def check_meshing_grid(
    dataset: SweepDataset, root: str | Path, voxel_mm: float | None, max_memory_gib: float | None
) -> None:
    """Refuse a meshing grid (module doc, 2) larger than the memory limit."""
    probe = dataset.probe
    sides, voxel, extent = meshing_grid_shape(dataset, voxel_mm)
    n_voxels = math.prod(sides)
    needed = float(n_voxels) * MESH_BYTES_PER_VOXEL
    limit, limit_name = memory_limit(max_memory_gib)
    if needed <= limit:
        return
    if voxel_mm is None:
        where, field = Path(root) / "dataset.json", "probe"
        cause = f"its voxel is the probe's finer pixel spacing ({describe_probe(probe)})"
    else:
        where, field, cause = "argument", "voxel_mm", f"its voxel is {voxel_mm:g} mm"
    raise UltronInputError(
        where, field, f"the meshing grid would have {float(n_voxels):.3g} voxels"
        f" ({' × '.join(map(str, sides))} of {voxel:.3g} mm over the"
        f" {' × '.join(f'{e:.4g}' for e in extent)} mm the probe saw), ≈ {_size(needed)},"
        f" more than {limit_name}; {cause}",
    )  # fmt: skip


def check_field_grid(
    dataset: SweepDataset,
    root: str | Path,
    config: FieldTrainConfig,
    max_memory_gib: float | None,
) -> None:
    """Refuse a field fit of ``config`` whose grid planes (module doc, 3) exceed the backend's
    largest side or the memory limit."""
    from ultron.data.geometry import UnitCube, field_of_view_bounds_mm
    from ultron.train.frames import resampled_probe

    if config.field.backend != "grid":
        return
    probe = resampled_probe(dataset.probe, config.fit_shape)
    cube = UnitCube.from_bounds(field_of_view_bounds_mm(dataset.all_poses(), probe))
    pixel = min(probe.axial_spacing_mm, probe.lateral_spacing_mm)
    where = Path(root) / "dataset.json"
    cause = (
        f"the finest cell is the probe's finer pixel spacing at the fit resolution"
        f" ({describe_probe(probe)}); fit a field at a coarser --fit-shape with"
        " `ultron fit-field` and pass it with --field"
    )
    try:
        grid = config.field.grid.resolved(cube.half_extent_mm, pixel)
    except UltronInputError as exc:
        raise UltronInputError(where, "probe", f"acoustic field: {exc.problem}; {cause}") from None
    grid_config = config.field.grid
    channels = [grid_config.features] + [grid_config.coarse_features] * (len(grid.resolutions) - 1)
    values = sum(3 * c * r * r for c, r in zip(channels, grid.resolutions, strict=True))
    needed = float(values) * FIELD_BYTES_PER_VALUE
    limit, limit_name = memory_limit(max_memory_gib)
    if needed > limit:
        raise UltronInputError(
            where, "probe", f"acoustic field: planes of {list(grid.resolutions)} nodes per side"
            f" need ≈ {_size(needed)} to fit, more than {limit_name}; {cause}",
        )  # fmt: skip


def check_run_resources(
    dataset: SweepDataset,
    root: str | Path,
    voxel_mm: float | None = None,
    mesh: bool = True,
    field_config: FieldTrainConfig | None = None,
    max_memory_gib: float | None = None,
) -> None:
    """Before any work: no outlier pose, the meshing grid (when ``mesh``: every method but
    RoCoSDF/UNSR, whose grid has a fixed resolution) and a field to fit (``field_config``,
    when one may be fitted) within the memory limit. ``root`` is the dataset
    directory, named in the errors."""
    check_pose_outliers(dataset, root)
    if mesh:
        check_meshing_grid(dataset, root, voxel_mm, max_memory_gib)
    if field_config is not None:
        check_field_grid(dataset, root, field_config, max_memory_gib)
