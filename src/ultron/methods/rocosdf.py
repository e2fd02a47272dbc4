"""RoCoSDF (Chen et al., MICCAI 2024) and its first stage alone, UNSR-Row / UNSR-Col.

Follows ROCOSDF.md (a reading of ``chenhbo/RoCoSDF``); the losses and stages are in
:mod:`ultron.train.neural_pull`, the network in :mod:`ultron.fields.sdf`.

Input and normalisation: :mod:`ultron.methods.rocosdf_input` (each view's bone points in world
mm, the check that a view is not one plane, and ONE normalisation for all views).

Stages (``views`` = ("row", "column")): 1. one SDF per view (Neural-Pull + SCC + adversarial
term); 2. f_csg = max(f_row, f_col) resampled on grids and near its zero level; 3. a fresh SDF
regressing f_csg. With a single view (``unsr-row`` / ``unsr-col``) only stage 1 runs and its
SDF is meshed directly.

Mesh: marching cubes (PyMCubes) of −f at level 0 on a grid (``paper``: 256³ over the
normalised cube [−1, 1]³ as the code does; ``fast``: 128 samples along the longest side of the
data's bounding box grown by 0.05 normalised units on every side — the code's
``object_bbox`` margin — at the same spacing along the other sides), no smoothing, vertices
mapped to world mm; components smaller than 5% of the largest one's area are dropped. The
stored ``volume`` is a [0, 1] inside indicator sigmoid(−f/h) (h = one voxel in normalised
units): ≥ 0.5 exactly where f ≤ 0, so thresholding it at 0.5 reproduces the mesh's inside,
and it keeps the sub-voxel position of the zero level. The released outputs are thin closed
shells around the labelled band, not solids.

Presets (:data:`PRESETS`; ``RoCoSDFConfig.preset(name)`` returns a copy):

* ``paper``: the code's settings — 8 × 256, batch 5000, 10k iterations per stage with 1k
  warm-up, 200k + 150k stage-2 samples (two-cube grid candidates), 256³ over [−1, 1]³. Slow on
  a CPU (step times in docs/decisions.md#rocosdf-presets-methodsrocosdfpy).
* ``fast`` (default): 6 × 128 (skip at 4), batch 2048, 2000 iterations per stage with 200
  warm-up, 100k + 75k stage-2 samples (candidates in the data's box), 128 samples along the
  data box's longest side. Chosen by measurement on simulated L3: more iterations, the paper's
  larger network or batch did not make it more accurate, and it takes minutes on 2 cores
  (figures in docs/decisions.md#rocosdf-presets-methodsrocosdfpy).
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import UnitCube
from ultron.data.labels import FrameSelection
from ultron.device import module_device
from ultron.errors import UltronInputError, argument_error
from ultron.fields.sdf import SDFNetwork, SDFNetworkConfig
from ultron.mesh.extract import NoSurfaceError, mesh_on_grid
from ultron.mesh.grid import GridSpec, evaluate_on_grid
from ultron.mesh.marching import marching_cubes
from ultron.methods.rocosdf_input import (
    VIEW_KINDS,
    VIEWS,
    check_views,
    check_views_fusable,
    cloud_normalisation,
    view_point_clouds,
)
from ultron.methods.ultron_method import Reconstruction, TrainedModel
from ultron.timing import StageTimer
from ultron.train.fit_checkpoint import FitCheckpoint, checkpoint_in, resumed_steps
from ultron.train.neural_pull import (
    Progress,
    RefineConfig,
    ResampleConfig,
    ViewFitConfig,
    fit_refined_sdf,
    fit_view_sdf,
    fuse_and_resample,
)

METHOD_NAMES = MappingProxyType(
    {("row", "column"): "rocosdf", ("row",): "unsr-row", ("column",): "unsr-col"}
)
MESH_BOXES = ("data", "cube")


def _fast_view_fit() -> ViewFitConfig:
    return ViewFitConfig(
        network=SDFNetworkConfig(hidden=128, layers=6, skip_at=4),
        iterations=2000,
        batch_size=2048,
        warmup=200,
    )


def _fast_refine() -> RefineConfig:
    return RefineConfig(
        network=SDFNetworkConfig(hidden=128, layers=6, skip_at=4),
        iterations=2000,
        batch_size=2048,
        warmup=200,
    )


def _fast_resample() -> ResampleConfig:
    return ResampleConfig(
        grid_samples=100_000, surface_samples=75_000, grid_resolution=120, candidates="box"
    )


@dataclass(frozen=True)
class RoCoSDFConfig:
    """Settings of a RoCoSDF / UNSR run; the defaults are the ``fast`` preset."""

    preset_name: str = "fast"
    view_fit: ViewFitConfig = field(default_factory=_fast_view_fit)
    resample: ResampleConfig = field(default_factory=_fast_resample)
    refine: RefineConfig = field(default_factory=_fast_refine)
    voxel_mm: float | None = 0.5
    mesh_resolution: int = 128
    mesh_box: str = "data"
    mesh_margin: float = 0.05
    min_component_fraction: float = 0.05
    chunk_points: int = 65_536

    def __post_init__(self) -> None:
        if self.voxel_mm is not None and not (np.isfinite(self.voxel_mm) and self.voxel_mm > 0):
            raise argument_error("voxel_mm", f"expected None or > 0, got {self.voxel_mm}")
        if (
            isinstance(self.mesh_resolution, bool)
            or not isinstance(self.mesh_resolution, int)
            or self.mesh_resolution < 8
        ):
            raise argument_error(
                "mesh_resolution", f"expected an integer ≥ 8, got {self.mesh_resolution!r}"
            )
        if self.mesh_box not in MESH_BOXES:
            raise argument_error("mesh_box", f"expected one of {MESH_BOXES}, got {self.mesh_box!r}")
        if not self.mesh_margin >= 0:
            raise argument_error("mesh_margin", f"expected ≥ 0, got {self.mesh_margin}")
        if not 0 <= self.min_component_fraction <= 1:
            raise argument_error(
                "min_component_fraction", f"expected in [0, 1], got {self.min_component_fraction}"
            )
        if self.chunk_points < 1:
            raise argument_error("chunk_points", f"expected ≥ 1, got {self.chunk_points}")

    @classmethod
    def preset(cls, name: str) -> RoCoSDFConfig:
        """A new config equal to ``PRESETS[name]`` (``paper`` or ``fast``)."""
        if name not in PRESETS:
            raise argument_error("preset", f"expected one of {tuple(PRESETS)}, got {name!r}")
        return replace(PRESETS[name])

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


PRESETS: MappingProxyType[str, RoCoSDFConfig] = MappingProxyType(
    {
        "paper": RoCoSDFConfig(
            preset_name="paper",
            view_fit=ViewFitConfig(),
            resample=ResampleConfig(),
            refine=RefineConfig(),
            mesh_resolution=256,
            mesh_box="cube",
        ),
        "fast": RoCoSDFConfig(),
    }
)
#: The names of :data:`PRESETS`, in order.
ROCOSDF_PRESETS: tuple[str, ...] = tuple(PRESETS)


# ------------------------------------------------------------------- normalised units
def _to_unit(normalisation: UnitCube, points_mm: np.ndarray) -> np.ndarray:
    """mm (..., 3) → normalised (..., 3), float64 NumPy."""
    return normalisation.to_unit(torch.as_tensor(points_mm), torch.float64).numpy()


def _to_mm(normalisation: UnitCube, points_unit: np.ndarray) -> np.ndarray:
    """Normalised (..., 3) → mm (..., 3), float64 NumPy."""
    return normalisation.to_world(torch.as_tensor(points_unit), torch.float64).numpy()


# ---------------------------------------------------------------------------------- meshing
def _stage_generator(seed: int, label: str) -> torch.Generator:
    """An independent generator per stage, so ``unsr-row`` reproduces RoCoSDF's row field."""
    state = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(label.encode())])
    return torch.Generator().manual_seed(int(state.generate_state(1, np.uint64)[0] >> 1))


def data_box_unit(clouds_unit: Iterable[np.ndarray], margin: float) -> np.ndarray:
    """The clouds' union bounding box (2, 3) in normalised units, grown by ``margin``."""
    points = np.concatenate([np.asarray(c).reshape(-1, 3) for c in clouds_unit])
    return np.stack([points.min(0) - margin, points.max(0) + margin])


def mesh_grid(
    clouds_unit: Iterable[np.ndarray], normalisation: UnitCube, config: RoCoSDFConfig
) -> GridSpec:
    """The meshing grid in world mm (see module doc: ``data`` box or normalised ``cube``)."""
    scale = normalisation.half_extent_mm
    if config.mesh_box == "cube":
        bounds_unit = np.array([[-1.0] * 3, [1.0] * 3])
        voxel_mm = 2.0 * scale / (config.mesh_resolution - 1)
        return GridSpec.from_bounds(_to_mm(normalisation, bounds_unit), voxel_mm, pad_voxels=0)
    bounds_unit = data_box_unit(clouds_unit, config.mesh_margin)
    bounds_mm = _to_mm(normalisation, bounds_unit)
    voxel_mm = float((bounds_mm[1] - bounds_mm[0]).max()) / (config.mesh_resolution - 1)
    return GridSpec.from_bounds(bounds_mm, voxel_mm, pad_voxels=0)


def mesh_sdf(
    network: SDFNetwork, normalisation: UnitCube, grid: GridSpec, config: RoCoSDFConfig
) -> tuple[Any, np.ndarray]:
    """Marching cubes of −f at 0 on ``grid``; returns (mesh in world mm, inside volume).

    Raises :class:`NoSurfaceError` when f does not change sign on the grid.
    """

    def fn(points_mm: torch.Tensor) -> torch.Tensor:
        unit = normalisation.to_unit(points_mm, torch.float32)
        return network(unit.to(module_device(network))).cpu()

    sdf = evaluate_on_grid(fn, grid, config.chunk_points)
    n_inside = int((sdf < 0).sum())
    if n_inside == 0 or n_inside == sdf.size:
        where = "no voxel" if n_inside == 0 else "every voxel"
        raise NoSurfaceError(f"no surface: the SDF is negative at {where} of the meshing grid")
    vertices, faces = marching_cubes(-sdf.astype(np.float64))
    mesh = mesh_on_grid(vertices, faces, grid, config.min_component_fraction)
    voxel_unit = grid.voxel_mm / normalisation.half_extent_mm
    volume = (1.0 / (1.0 + np.exp(np.clip(sdf / voxel_unit, -60, 60)))).astype(np.float32)
    return mesh, volume


# ----------------------------------------------------------------------------- reconstruct
def _input_clouds(
    dataset: SweepDataset,
    selection: FrameSelection,
    config: RoCoSDFConfig,
    views: tuple[str, ...],
    dataset_name: str | None,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(the ``views``' bone clouds in mm, checked to be fusable for RoCoSDF, and the clouds
    that set the normalisation: UNSR on one view normalises like RoCoSDF when it can)."""
    clouds_mm = view_point_clouds(dataset, selection, config.voxel_mm, views, dataset_name)
    if len(views) > 1:
        check_views_fusable(dataset, selection, clouds_mm, config.voxel_mm, dataset_name)
    frame_clouds = dict(clouds_mm)
    for other in VIEWS:
        if other not in frame_clouds:
            with contextlib.suppress(UltronInputError):
                frame_clouds |= view_point_clouds(dataset, selection, config.voxel_mm, (other,))
    return clouds_mm, frame_clouds


def _fit_views(
    clouds_unit: dict[str, np.ndarray],
    views: tuple[str, ...],
    config: RoCoSDFConfig,
    seed: int,
    progress: Progress | None,
    device: torch.device | str,
    checkpoints: dict[str, FitCheckpoint | None],
) -> tuple[dict[str, SDFNetwork], dict[str, Any]]:
    """Stage 1: each view's SDF network and its fit's log, by view (each fit's checkpoint
    ``checkpoints["stage1_<view>"]``)."""
    fits, logs = {}, {}
    for view in views:
        fit = fit_view_sdf(
            clouds_unit[view], config.view_fit, _stage_generator(seed, f"stage1_{view}"), progress,
            name=view, device=device, checkpoint=checkpoints[f"stage1_{view}"],
        )  # fmt: skip
        fits[view], logs[view] = fit.network, fit.log
    return fits, logs


def _fuse_and_refine(
    fits: list[SDFNetwork],
    frame_unit: list[np.ndarray],
    config: RoCoSDFConfig,
    seed: int,
    progress: Progress | None,
    stage: Callable[[str], contextlib.AbstractContextManager[Any]],
    info: dict[str, Any],
    device: torch.device | str,
    checkpoint: FitCheckpoint | None = None,
) -> SDFNetwork:
    """Stages 2 and 3: the views' SDFs fused (CSG intersection) and resampled, then one
    network regressing the fused SDF; their accounts go into ``info``."""
    with stage("rocosdf_stage2"):
        samples = fuse_and_resample(
            fits,
            config.resample,
            _stage_generator(seed, "stage2"),
            candidate_bounds=data_box_unit(frame_unit, config.mesh_margin),
            device=device,
        )
    info["stage2"] = {k: getattr(samples, k) for k in ("n_grid", "n_surface", "rounds")}
    with stage("rocosdf_stage3"):
        refined = fit_refined_sdf(
            samples, config.refine, _stage_generator(seed, "stage3"), progress, device, checkpoint
        )
    info["stage3"] = refined.log
    return refined.network


def reconstruct_rocosdf(
    dataset: SweepDataset,
    selection: FrameSelection,
    config: RoCoSDFConfig | None = None,
    seed: int = 0,
    views: Sequence[str] = VIEWS,
    progress: Progress | None = None,
    timer: StageTimer | None = None,
    dataset_name: str | None = None,
    device: torch.device | str = "cpu",
    checkpoints: Path | None = None,
) -> Reconstruction:
    """RoCoSDF (``views`` = ("row", "column")) or UNSR on one view (("row",) → ``unsr-row``,
    ("column",) → ``unsr-col``) from the selected frames' bone labels (module doc).

    Each stage draws from its own generator seeded by (``seed``, stage name), so UNSR-Row's
    field is RoCoSDF's stage-1 row field. ``progress`` receives per-stage dicts every 100
    steps; ``timer`` records ``rocosdf_points``, ``rocosdf_stage1/2/3`` and ``mesh``. Raises
    :class:`UltronInputError` for missing sweeps or bone labels and :class:`NoSurfaceError`
    when the final SDF has no zero level on the meshing grid. The networks train on
    ``device``; every draw comes from the stages' CPU generators. With ``checkpoints`` (a
    directory) each SDF fit keeps a checkpoint there (``stage1_<view>.pt``, ``stage3.pt``) and
    resumes it (:mod:`ultron.train.fit_checkpoint`; info ``resumed_from_step``).
    """
    config = config or RoCoSDFConfig()
    views = check_views(views)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise argument_error("seed", f"expected an integer, got {seed!r}")

    def stage(name: str):
        return timer.stage(name) if timer is not None else contextlib.nullcontext()

    with stage("rocosdf_points"):
        clouds_mm, frame_clouds = _input_clouds(dataset, selection, config, views, dataset_name)
        normalisation = cloud_normalisation(frame_clouds.values())
        clouds_unit = {v: _to_unit(normalisation, p) for v, p in clouds_mm.items()}
        frame_unit = [_to_unit(normalisation, p) for p in frame_clouds.values()]
    saved = {name: checkpoint_in(checkpoints, name)
             for name in (*(f"stage1_{v}" for v in views), "stage3")}  # fmt: skip
    with stage("rocosdf_stage1"):
        fits, stage1 = _fit_views(clouds_unit, views, config, seed, progress, device, saved)
    info: dict[str, Any] = {
        "variant": METHOD_NAMES[views],
        "preset": config.preset_name,
        "rocosdf_config": config.to_dict(),
        "views": list(views),
        "view_kinds": {v: list(VIEW_KINDS[v]) for v in views},
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "n_points": {v: len(p) for v, p in clouds_mm.items()},
        "normalisation": normalisation.to_dict() | {"views": list(frame_clouds)},
        "stage1": stage1,
    }
    if len(views) == 1:
        network = fits[views[0]]
    else:
        fused = [fits[v] for v in views]
        network = _fuse_and_refine(fused, frame_unit, config, seed, progress, stage, info, device,
                                   saved["stage3"])  # fmt: skip
    info |= resumed_steps(saved)
    with stage("mesh"):
        grid = mesh_grid(frame_unit, normalisation, config)
        mesh, volume = mesh_sdf(network, normalisation, grid, config)
    info["grid"] = grid.to_dict()
    info["volume"] = "sigmoid(-f / voxel): inside indicator, 0.5 on the zero level"
    model = {"input": "normalised_mm", "normalisation": info["normalisation"]}
    return Reconstruction(
        mesh=mesh,
        volume=volume,
        grid=grid,
        info=info,
        model=TrainedModel(network, model),
        selection=selection,
    )
