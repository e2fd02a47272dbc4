"""A real recording's scale: the long-bone phantom, and a 1040-frame sweep over 47 cm whose
meshing stays within its field of view's tiles (issue 17, item 6)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.errors import UltronInputError
from ultron.mesh.extract import extract_surface_tiles
from ultron.mesh.occupancy_mesh import (
    MeshingConfig,
    elevation_half_thickness_mm,
    mesh_occupancy,
    scan_grid,
)
from ultron.mesh.tiles import evaluate_tiles, field_of_view_tiles
from ultron.phantom import (
    PHANTOMS,
    ScanConfig,
    SimulationConfig,
    get_phantom,
    plan_sweep,
    sweep_spec,
)
from ultron.phantom.long_bone import LongBoneShape
from ultron.pipeline.resources import check_meshing_grid, meshing_memory
from ultron.timing import StageTimer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The two legs of one recording: a pass along each femur, 300 mm apart.
LEGS_MM = (-150.0, 150.0)
FRAMES_PER_PASS = 520


def test_femur_phantom_geometry():
    femur = get_phantom("femur")
    shape = femur.shape
    assert isinstance(shape, LongBoneShape)
    assert set(PHANTOMS) == {"L2", "L3", "L3b", "L4"}  # the vertebra benchmark is unchanged
    assert shape.length_mm() >= 400
    z = np.linspace(-190.0, 190.0, 9)
    axis = torch.from_numpy(shape.centre_line(z))
    top = axis - torch.tensor([0.0, shape.shaft_radius_mm, 0.0], dtype=torch.float64)
    assert (femur.sdf(axis) < -shape.shaft_radius_mm + 0.5).all()  # deep inside the shaft
    assert femur.sdf(top).abs().max() < 1.5  # its posterior surface (blends add ≤ k/4)
    assert femur.sdf(axis - torch.tensor([0.0, 20.0, 0.0], dtype=torch.float64)).min() > 5
    bow = shape.centre_line(np.array([0.0, 200.0]))[:, 1]
    assert bow[0] - bow[1] == pytest.approx(shape.bow_mm)  # mid-shaft lies deeper
    half = shape.shaft_length_mm / 2
    ends = torch.tensor([[15.0, 0.0, -half - 11.0], [-15.0, 0.0, -half - 11.0],
                         [0.0, 0.0, half + 11.0], [0.0, 0.0, half + 40.0]], dtype=torch.float64)  # fmt: skip
    assert (femur.sdf(ends[:3]) < -10).all()  # two condyles, one head
    assert femur.sdf(ends[3:]) > 5
    assert SimulationConfig(phantom="femur").phantom == "femur"


def test_long_bone_shape_is_validated():
    with pytest.raises(UltronInputError, match="shaft_radius_mm"):
        LongBoneShape(shaft_radius_mm=-1.0)
    with pytest.raises(UltronInputError, match="shaft_segments"):
        LongBoneShape(shaft_segments=0)
    with pytest.raises(UltronInputError, match="condyle_radii_mm"):
        LongBoneShape(condyle_radii_mm=(1.0, float("nan"), 2.0))


def two_legs() -> SweepDataset:
    """1040 frames of 8 × 6 px: a row pass over each of two femurs, 47 cm long."""
    femur = get_phantom("femur")
    probe = ProbeGeometry(width_mm=38.0, depth_mm=70.0, height_px=8, width_px=6)
    box = femur.primitive_box_mm
    sweeps = []
    for name, x in zip(("left", "right"), LEGS_MM, strict=True):
        leg = box + np.array([x, 0.0, 0.0])
        scan = ScanConfig(frames_per_sweep=FRAMES_PER_PASS)
        poses = plan_sweep(sweep_spec("row"), leg, -30.0, scan)
        images = np.zeros((len(poses), 8, 6), dtype=np.uint8)
        sweeps.append(Sweep(name=name, kind="row", images=images, probe_to_world=poses))
    return SweepDataset(probe=probe, sweeps=sweeps)


def two_femurs(points: torch.Tensor) -> torch.Tensor:
    """Occupancy of two straight 26 mm shafts along z, 25 mm deep (a rational function)."""
    x, y, z = (points[:, i].double() for i in range(3))
    r2 = torch.minimum((x - LEGS_MM[0]) ** 2, (x - LEGS_MM[1]) ** 2) + (y - 5.0) ** 2
    along = (z.abs() < 230).double()
    return (169.0 / (169.0 + r2 * r2 / 169.0) * along).float()


def test_a_long_sweep_is_meshed_in_its_field_of_view_tiles():
    dataset = two_legs()
    assert sum(s.n_frames for s in dataset.sweeps) >= 1000
    config = MeshingConfig(voxel_mm=1.5)
    grid = scan_grid(dataset, config.voxel_mm)
    extent = np.asarray(grid.shape) * grid.voxel_mm
    assert extent[2] >= 400 and extent[0] > 200  # 47 cm long, both legs in one box
    coarse = grid.coarsened(2)
    half = elevation_half_thickness_mm(dataset, grid.voxel_mm)
    mask = field_of_view_tiles(coarse, dataset.all_poses(), dataset.probe, half, 16)
    fov_voxels = 8 * sum(int(m.sum()) for m in mask.values())  # at the fine voxel
    evaluated = evaluate_tiles(two_femurs, grid, 0.5, 2, mask, 32, max_volume_voxels=10**5)
    stats = evaluated.stats
    # only the legs' tiles are evaluated and kept: the box between them is never touched
    assert stats["voxels_evaluated"] < 0.4 * grid.n_voxels
    assert stats["points_evaluated"] < fov_voxels < 0.3 * grid.n_voxels
    kept = sum(b.size for b in evaluated.tiles.mixed.values())
    assert kept <= stats["voxels_evaluated"]
    # the occupancy volume is pooled to its budget
    assert stats["volume_voxels"] <= 10**5 and stats["volume_factor"] == 4
    assert evaluated.volume.grid.voxel_mm == pytest.approx(4 * grid.voxel_mm)
    mesh = extract_surface_tiles(evaluated.tiles, grid)
    parts = mesh.split(only_watertight=False)
    assert len(parts) == 2
    assert all(np.ptp(p.vertices[:, 2]) > 400 for p in parts)


def test_mesh_occupancy_of_a_long_sweep():
    dataset = two_legs()
    mesh, volume, grid = mesh_occupancy(
        two_femurs, dataset, MeshingConfig(voxel_mm=1.5), StageTimer()
    )
    assert volume.shape == grid.shape == scan_grid(dataset, 1.5).shape  # under the budget
    assert len(mesh.split(only_watertight=False)) == 2


def test_the_guard_counts_the_tiles_not_the_box():
    dataset = two_legs()
    memory = meshing_memory(dataset, 0.5)
    dense = scan_grid(dataset, 0.5).n_voxels * 64  # the earlier estimate: 64 B per voxel
    assert memory.fov_voxels < 0.5 * memory.grid_voxels
    assert memory.total < dense / 2
    gib = memory.total / 1024**3
    check_meshing_grid(dataset, "long", 0.5, max_memory_gib=1.01 * gib)  # fits now
    with pytest.raises(UltronInputError, match="field of view's tiles"):
        check_meshing_grid(dataset, "long", 0.5, max_memory_gib=0.9 * gib)


# ------------------------------------------------------------- the voxel from the region
def test_meshing_voxel_grows_with_the_region_only_beyond_the_budget():
    from ultron.data.dataset import ProbeGeometry
    from ultron.mesh.grid import MAX_REGION_VOXELS, meshing_voxel_mm

    probe = ProbeGeometry(width_mm=40.0, depth_mm=30.0, height_px=100, width_px=80)  # 0.3 mm
    assert meshing_voxel_mm(probe, None) == pytest.approx(0.3)
    assert meshing_voxel_mm(probe, 0.7, region_mm3=1e12) == 0.7  # given: kept
    small = 0.5 * MAX_REGION_VOXELS * 0.3**3  # half the budget at the pixel spacing
    assert meshing_voxel_mm(probe, None, small) == pytest.approx(0.3)
    # 1000 × the budget at the pixel spacing: the voxel grows by 10 (the cube root)
    big = 1000 * MAX_REGION_VOXELS * 0.3**3
    assert meshing_voxel_mm(probe, None, big) == pytest.approx(3.0)
    # a larger budget never takes the voxel below the pixel spacing
    assert meshing_voxel_mm(probe, None, big, max_voxels=8000 * MAX_REGION_VOXELS) == 0.3


def test_field_of_view_volume_of_a_straight_sweep_is_its_swept_box():
    from ultron.data.dataset import ProbeGeometry
    from ultron.mesh.grid import field_of_view_volume_mm3

    probe = ProbeGeometry(width_mm=40.0, depth_mm=30.0, height_px=61, width_px=81)  # 0.5 mm
    poses = np.tile(np.eye(4), (101, 1, 1))
    poses[:, 2, 3] = np.linspace(0.0, 100.0, 101)  # 1 mm steps along the elevation
    volume = field_of_view_volume_mm3(poses, probe, 0.5, voxel_mm=1.0)
    # the slabs sweep the image rectangle (pixel centre to centre: 40 × 30 mm) over 101 mm:
    # 121 200 mm³, to within a voxel layer on each face
    assert volume == pytest.approx(40.0 * 30.0 * 101.0, rel=0.1)
