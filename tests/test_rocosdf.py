"""RoCoSDF baseline: SDF network, Neural-Pull losses, CSG fusion, inputs and a tiny end-to-end run."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import make_sweep
from ultron.data.dataset import ProbeGeometry, SweepDataset
from ultron.data.geometry import UnitCube
from ultron.data.labels import select_label_frames
from ultron.errors import UltronInputError
from ultron.fields.sdf import SDFNetwork, SDFNetworkConfig
from ultron.methods.rocosdf import PRESETS, RoCoSDFConfig, reconstruct_rocosdf
from ultron.methods.rocosdf_input import (
    check_views_fusable,
    cloud_normalisation,
    cloud_thickness_mm,
    view_point_clouds,
)
from ultron.timing import StageTimer
from ultron.train.neural_pull import (
    RefineConfig,
    ResampleConfig,
    ViewFitConfig,
    csg_intersection,
    farthest_point_sampling,
    fuse_and_resample,
    pull_loss,
    pull_points,
    refine_loss,
    sign_consistency_loss,
    subsample_points,
    warmup_cosine_lr,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _unit_directions(n: int, seed: int) -> torch.Tensor:
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True)


# ------------------------------------------------------------------------------ network
def test_geometric_init_is_a_sphere_of_radius_half():
    network = SDFNetwork(SDFNetworkConfig(), torch.Generator().manual_seed(0))
    directions = _unit_directions(500, 1).float()
    with torch.no_grad():
        f0 = network(torch.zeros(1, 3))
        on_sphere = network(0.5 * directions)
        inside = network(0.2 * directions)
        outside = network(0.95 * directions)
    assert f0.item() == pytest.approx(-0.5, abs=1e-6)  # all hidden activations are ReLU(0)
    assert abs(float(on_sphere.mean())) < 0.15 and float(on_sphere.abs().max()) < 0.3
    assert bool((inside < 0).all()) and bool((outside > 0).all())


def test_sdf_gradient_matches_finite_differences():
    config = SDFNetworkConfig(hidden=32, layers=4, skip_at=2)
    network = SDFNetwork(config, torch.Generator().manual_seed(3)).double()
    x = torch.tensor([[0.1, -0.2, 0.3], [0.4, 0.1, -0.05]], dtype=torch.float64)
    f, grad = network.sdf_and_gradient(x)
    assert f.shape == (2,) and grad.shape == (2, 3)
    h = 1e-6
    for axis in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = h
        with torch.no_grad():
            numeric = (network(x + step) - network(x - step)) / (2 * h)
        torch.testing.assert_close(grad[:, axis], numeric, atol=1e-6, rtol=1e-5)


def test_network_config_validation():
    with pytest.raises(UltronInputError, match="skip_at"):
        SDFNetworkConfig(layers=4, skip_at=4)
    with pytest.raises(UltronInputError, match="hidden"):
        SDFNetworkConfig(hidden=2)


# ------------------------------------------------------------------------------- losses
def test_pull_moves_queries_onto_a_plane():
    normal = torch.tensor([1.0, 2.0, -2.0], dtype=torch.float64) / 3.0
    offset = 0.2

    def plane_sdf(x: torch.Tensor) -> torch.Tensor:
        return x @ normal - offset

    queries = torch.randn(64, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grad = 5.0 * normal.expand(64, 3)  # an unnormalised gradient: the pull normalises it
    pulled = pull_points(queries, plane_sdf(queries), grad)
    torch.testing.assert_close(plane_sdf(pulled), torch.zeros(64, dtype=torch.float64))
    # q′ is the orthogonal projection of q onto the plane
    projection = queries - plane_sdf(queries)[:, None] * normal
    torch.testing.assert_close(pulled, projection)
    assert float(pull_loss(pulled, projection)) == pytest.approx(0.0, abs=1e-12)


def test_csg_intersection_of_two_spheres_is_their_lens():
    centre_a = torch.tensor([-0.15, 0.0, 0.0])
    centre_b = torch.tensor([0.15, 0.0, 0.0])

    def sphere(centre: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return (x - centre).norm(dim=-1) - 0.3

    points = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [-0.35, 0.0, 0.0], [0.35, 0.0, 0.0], [0.0, 0.0, 0.5]]
    )
    fused = csg_intersection([sphere(centre_a, points), sphere(centre_b, points)])
    assert bool((fused[:2] < 0).all())  # inside both: inside the lens
    assert bool((fused[2:4] > 0).all())  # inside only one sphere: outside the lens
    assert float(fused[4]) > 0  # inside neither


@pytest.mark.parametrize("candidates", ["grids", "box"])
def test_resampling_concentrates_near_the_fused_zero_level(candidates: str):
    def sphere(centre: float):
        return lambda x: (x - torch.tensor([centre, 0.0, 0.0])).norm(dim=-1) - 0.3

    config = ResampleConfig(
        grid_samples=5000, surface_samples=3000, grid_resolution=40, candidate_batch=20_000,
        candidates=candidates,
    )  # fmt: skip
    box = np.array([[-0.5] * 3, [0.5] * 3])
    samples = fuse_and_resample(
        [sphere(-0.1), sphere(0.1)], config, torch.Generator().manual_seed(0), candidate_bounds=box
    )
    assert samples.n_grid == 5000 and samples.n_surface == 3000
    assert samples.points.shape == (8000, 3) and samples.sdf.shape == (8000,)
    lens = torch.maximum(sphere(-0.1)(samples.points), sphere(0.1)(samples.points))
    torch.testing.assert_close(samples.sdf, lens)
    near = samples.sdf[samples.n_grid :].abs()
    assert float((near < 0.03).float().mean()) > 0.95  # σ = 0.01
    with pytest.raises(UltronInputError, match="candidate"):
        fuse_and_resample([sphere(0.0)], replace(config, candidates="box"), torch.Generator())


def test_loss_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    queries = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    targets = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    sdf = (0.1 + torch.rand(6, generator=gen, dtype=torch.float64)).requires_grad_(True)
    grad = torch.randn(6, 3, generator=gen, dtype=torch.float64).requires_grad_(True)

    def stage1(f: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        pulled = pull_points(queries, f, g)
        return pull_loss(pulled, targets) + 0.01 * sign_consistency_loss(g, pulled, targets, f)

    assert torch.autograd.gradcheck(stage1, (sdf, grad))
    target = torch.rand(6, generator=gen, dtype=torch.float64) - 2.0  # |f − t| away from its kink
    assert torch.autograd.gradcheck(lambda f: refine_loss(f, target), (sdf,))


def test_sign_consistency_is_zero_when_residual_follows_the_normal():
    grad = torch.tensor([[0.0, 0.0, 2.0]])
    pulled = torch.tensor([[0.0, 0.0, 0.3]])
    targets = torch.zeros(1, 3)
    assert float(sign_consistency_loss(grad, pulled, targets, torch.zeros(1))) == pytest.approx(
        0.0, abs=1e-6
    )
    # opposite direction: 1 − cos = 2, weight exp(−100·0.01)
    value = sign_consistency_loss(-grad, pulled, targets, torch.tensor([0.01]))
    assert float(value) == pytest.approx(2 * math.exp(-1.0), rel=1e-5)


def test_warmup_cosine_schedule():
    assert warmup_cosine_lr(0, 100, 10, 1e-3) == 0.0
    assert warmup_cosine_lr(5, 100, 10, 1e-3) == pytest.approx(5e-4)
    assert warmup_cosine_lr(10, 100, 10, 1e-3) == pytest.approx(1e-3)
    assert warmup_cosine_lr(55, 100, 10, 1e-3) == pytest.approx(5e-4)
    assert warmup_cosine_lr(100, 100, 10, 1e-3) == pytest.approx(0.0, abs=1e-12)


def test_farthest_point_sampling_and_subsampling():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [10, 0, 0], [5, 0, 0], [2, 0, 0], [8, 0, 0]])
    assert farthest_point_sampling(points, 3).tolist() == [0, 2, 3]
    cloud = np.random.default_rng(0).random((50, 3))
    assert subsample_points(cloud, 60, (5, 15)).shape == (50, 3)  # small clouds kept whole
    sub = subsample_points(cloud, 20, (5, 15))
    assert sub.shape == (20, 3)
    np.testing.assert_array_equal(sub[:5], sub[5:10])  # the 5-sample is the 15-sample's prefix


# ------------------------------------------------------------------------ inputs / config
def test_normalisation_round_trips_to_mm():
    rng = np.random.default_rng(0)
    row = rng.normal([10.0, -40.0, 3.0], [20.0, 5.0, 8.0], size=(200, 3))
    column = rng.normal([12.0, -35.0, 0.0], [4.0, 6.0, 25.0], size=(150, 3))
    norm = cloud_normalisation([row, column])
    both = np.concatenate([row, column])
    unit = norm.to_unit(torch.as_tensor(both)).numpy()
    assert unit.min() >= -0.5 - 1e-12 and unit.max() <= 0.5 + 1e-12
    assert float((unit.max(0) - unit.min(0)).max()) == pytest.approx(1.0)
    # hand-worked: centre of the union's box, scale = its largest extent
    lo, hi = both.min(0), both.max(0)
    assert norm.center_mm == pytest.approx(tuple((lo + hi) / 2))
    assert norm.half_extent_mm == pytest.approx(float((hi - lo).max()))
    back = norm.to_world(norm.to_unit(torch.as_tensor(row))).numpy()
    np.testing.assert_allclose(back, row, atol=1e-9)
    with pytest.raises(UltronInputError, match="clouds"):
        cloud_normalisation([np.zeros((0, 3))])


def test_presets_and_bad_preset_name():
    fast = RoCoSDFConfig.preset("fast")
    assert fast == RoCoSDFConfig() and fast is not PRESETS["fast"]
    paper = RoCoSDFConfig.preset("paper")
    assert paper.view_fit.network.hidden == 256 and paper.view_fit.iterations == 10_000
    assert paper.view_fit.batch_size == 5000 and paper.mesh_resolution == 256
    with pytest.raises(UltronInputError, match="preset"):
        RoCoSDFConfig.preset("slow")


def test_dataset_without_column_sweep_is_a_clear_error():
    probe = ProbeGeometry(width_mm=12.0, depth_mm=16.0, height_px=8, width_px=6)
    dataset = SweepDataset(
        probe=probe,
        sweeps=[make_sweep("row", "row", seed=1), make_sweep("tilt_p10", "tilted", seed=2)],
    )
    selection = select_label_frames(dataset, 1.0, 0)
    with pytest.raises(UltronInputError, match="column") as error:
        view_point_clouds(dataset, selection, dataset_name="phantom-A")
    assert "phantom-A" in str(error.value) and "tilt_p10 (tilted)" in str(error.value)
    # a single row view needs no column sweep; tilted sweeps join the row group
    clouds = view_point_clouds(dataset, selection, voxel_mm=None, views=("row",))
    assert set(clouds) == {"row"} and len(clouds["row"]) > 0
    with pytest.raises(UltronInputError, match="views"):
        view_point_clouds(dataset, selection, views=("row", "diagonal"))


def test_view_without_bone_is_a_clear_error(tiny_dataset: SweepDataset):
    for sweep in tiny_dataset.sweeps:
        if sweep.kind == "column":
            sweep.labels[sweep.labels == 1] = 0
    selection = select_label_frames(tiny_dataset, 1.0, 0)
    with pytest.raises(UltronInputError, match="no bone pixel"):
        view_point_clouds(tiny_dataset, selection)


def test_a_view_in_one_plane_is_refused_before_any_fit(tiny_dataset: SweepDataset):
    """One frame per view (the cause of a 400 s run: stage 2 finds almost no fused surface)."""
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 30, (200, 2)), np.zeros(200)]
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # an oblique plane
    assert cloud_thickness_mm(plane @ rotation.T) < 1e-9
    two_planes = np.r_[plane, plane + np.array([0.0, 0.0, 5.0])]
    assert cloud_thickness_mm(two_planes) == pytest.approx(5.0)
    selection = select_label_frames(tiny_dataset, 1.0, 0)
    clouds = {"row": two_planes, "column": plane @ rotation.T}
    with pytest.raises(UltronInputError, match=r"^ds: labels: .* the column view's bone points"):
        check_views_fusable(tiny_dataset, selection, clouds, 0.5, "ds")
    check_views_fusable(tiny_dataset, selection, {"row": two_planes}, 0.5)
    one_frame = SweepDataset(
        tiny_dataset.probe,
        [replace(s, images=s.images[:1], probe_to_world=s.probe_to_world[:1],
                 labels=s.labels[:1]) for s in tiny_dataset.sweeps],
    )  # fmt: skip
    with pytest.raises(UltronInputError, match="lie in one plane"):
        reconstruct_rocosdf(one_frame, select_label_frames(one_frame, 1.0, 0), TINY)


# --------------------------------------------------------------------------- end to end
TINY_NETWORK = SDFNetworkConfig(hidden=64, layers=4, skip_at=2)
TINY = RoCoSDFConfig(
    preset_name="test",
    view_fit=ViewFitConfig(
        network=TINY_NETWORK, iterations=400, batch_size=512, warmup=40, grid_queries=2000,
        discriminator_hidden=64,
    ),
    resample=ResampleConfig(grid_samples=20_000, surface_samples=10_000, grid_resolution=60, candidate_batch=50_000),
    refine=RefineConfig(network=TINY_NETWORK, iterations=400, batch_size=512, warmup=40),
    mesh_resolution=64,
)  # fmt: skip


@pytest.fixture(scope="module")
def tiny_phantom(tmp_path_factory) -> Path:
    """L3, row + column sweeps of 12 frames of 64 × 48 pixels (as in test_reconstruct.py)."""
    from ultron.phantom import SimulationConfig, simulate_dataset
    from ultron.phantom.protocols import ScanConfig

    config = SimulationConfig(
        sweeps=("row", "column"), scan=ScanConfig(frames_per_sweep=12), height_px=64, width_px=48
    )
    out = tmp_path_factory.mktemp("tiny_rocosdf") / "dataset"
    simulate_dataset(config, out=out)
    return out


def test_rocosdf_and_unsr_end_to_end(tiny_phantom: Path):
    import trimesh

    from ultron.metrics.surface import MetricsConfig, evaluate_meshes

    dataset = SweepDataset.load(tiny_phantom)
    assert {s.kind for s in dataset.sweeps} == {"row", "column"}
    reference = trimesh.load(dataset.reference)
    selection = select_label_frames(dataset, 1.0, 0)
    metrics = MetricsConfig(n_points=5000, repeats=1)
    timer = StageTimer()
    rocosdf = reconstruct_rocosdf(dataset, selection, TINY, seed=0, timer=timer)
    unsr = reconstruct_rocosdf(dataset, selection, TINY, seed=0, views=("row",))
    assert {"rocosdf_points", "rocosdf_stage1", "rocosdf_stage2", "rocosdf_stage3", "mesh"} <= set(
        timer.seconds
    )
    assert rocosdf.info["variant"] == "rocosdf" and unsr.info["variant"] == "unsr-row"
    assert "stage3" in rocosdf.info and "stage3" not in unsr.info
    # same seed → the same row field in both runs
    assert (
        unsr.info["stage1"]["row"]["final_losses"] == rocosdf.info["stage1"]["row"]["final_losses"]
    )
    for result in (rocosdf, unsr):
        assert len(result.mesh.faces) > 100
        assert result.volume.shape == result.grid.shape and result.volume.dtype == np.float32
        assert 0.0 <= float(result.volume.min()) and float(result.volume.max()) <= 1.0
        # a smoke test: the surface lies in the vertebra's neighbourhood (a surface scattered
        # over the field of view would be ≈ 15–20 mm away); quality is the benchmark's job
        assert evaluate_meshes(result.mesh, reference, metrics)["mean"]["mad"] < 5.0


def test_sdf_without_zero_level_is_no_surface():
    from ultron.mesh.extract import NoSurfaceError
    from ultron.methods.rocosdf import mesh_grid, mesh_sdf

    network = SDFNetwork(TINY_NETWORK, torch.Generator().manual_seed(0))  # ≈ ‖u‖ − 0.5
    norm = UnitCube((0.0, 0.0, 0.0), 10.0)
    far = [np.array([[3.0, 3.0, 3.0], [3.5, 3.5, 3.5]])]  # a box well outside the sphere
    grid = mesh_grid(far, norm, replace(TINY, mesh_resolution=16))
    with pytest.raises(NoSurfaceError):
        mesh_sdf(network, norm, grid, TINY)


def test_config_is_never_mutated_by_a_preset_copy():
    copy = RoCoSDFConfig.preset("fast")
    changed = replace(copy, mesh_resolution=32)
    assert PRESETS["fast"].mesh_resolution == 128 and changed.mesh_resolution == 32


def test_rocosdf_resumes_its_fits_bit_for_bit(tiny_phantom: Path, tmp_path: Path):
    from ultron.train.fit_checkpoint import FitCheckpoint

    class Killed(Exception):
        pass

    def kill_in_stage3(entry: dict) -> None:
        if entry.get("stage") == "stage3" and entry["step"] >= 300:
            raise Killed

    dataset = SweepDataset.load(tiny_phantom)
    selection = select_label_frames(dataset, 1.0, 0)
    plain = reconstruct_rocosdf(dataset, selection, TINY, seed=0)
    with pytest.raises(Killed):  # stage 1's two fits done, stage 3 saved at update 250
        reconstruct_rocosdf(dataset, selection, TINY, seed=0, progress=kill_in_stage3,
                            checkpoints=tmp_path)  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "stage1_column.pt", "stage1_row.pt", "stage3.pt",
    ]  # fmt: skip
    assert FitCheckpoint(tmp_path / "stage3.pt").matching("another fit", 400) is None
    resumed = reconstruct_rocosdf(dataset, selection, TINY, seed=0, checkpoints=tmp_path)
    assert resumed.info["resumed_from_step"] == {
        "stage1_row": 400, "stage1_column": 400, "stage3": 250,
    }  # fmt: skip
    assert "resumed_from_step" not in plain.info
    assert np.array_equal(plain.mesh.vertices, resumed.mesh.vertices)
    assert np.array_equal(plain.mesh.faces, resumed.mesh.faces)
    assert np.array_equal(plain.volume, resumed.volume)
    assert plain.info["stage2"] == resumed.info["stage2"]
    fits = [("stage1", "row"), ("stage1", "column"), ("stage3",)]
    for path in fits:  # each fit's own log, not only the mesh, is the uninterrupted one's
        a, b = plain.info, resumed.info
        for key in path:
            a, b = a[key], b[key]
        assert a["final_losses"] == b["final_losses"], path
