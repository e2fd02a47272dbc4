"""Shared fixtures: tiny datasets built by hand and the path of the shared sample data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.parallel import torch_threads

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Under pytest-xdist (the README's test command runs ``-n auto``) the cores are shared out
#: between the workers: torch gets this worker's share of threads, not every core.
if workers := int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0")):
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))
SHARED = Path(os.environ.get("ULTRON_SHARED", REPO_ROOT.parent / "shared"))
L2_SAMPLE = SHARED / "data" / "ultranerf-synthetic-l2"


@pytest.fixture(scope="session", autouse=True)
def private_field_cache(tmp_path_factory):
    """Fields the tests fit into the cache go to this session's temporary directory: never the
    user's ``~/.cache/ultron``, never another xdist worker's."""
    patch = pytest.MonkeyPatch()
    patch.setenv("ULTRON_CACHE", str(tmp_path_factory.mktemp("field-cache")))
    yield
    patch.undo()


@pytest.fixture
def one_thread():
    """Torch on one thread for the test (tiny workloads run faster and steadier on a shared
    CPU)."""
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def grid():
    """The meshing tests' grid: 0.35 mm voxels over a box of 19 × 19 × 18 mm about the
    origin, off-centre so that no axis is symmetric."""
    from ultron.mesh.grid import GridSpec

    return GridSpec.from_bounds(np.array([[-9.0, -11.0, -7.0], [10.0, 8.0, 11.0]]), 0.35)


def rotation_z(degrees: float) -> np.ndarray:
    angle = np.deg2rad(degrees)
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_pose(rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    pose = np.eye(4)
    if rotation is not None:
        pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def make_sweep(
    name: str = "row",
    kind: str = "row",
    n: int = 3,
    h: int = 8,
    w: int = 6,
    labels: bool = True,
    seed: int = 0,
) -> Sweep:
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, size=(n, h, w), dtype=np.uint8)
    poses = np.stack([make_pose(rotation_z(5.0 * i), (1.0 * i, 2.0, -0.5 * i)) for i in range(n)])
    label_array = None
    if labels:
        label_array = rng.choice(np.array([0, 1, 255], dtype=np.uint8), size=(n, h, w))
        label_array[-1] = 255  # last frame not annotated
    return Sweep(name=name, kind=kind, images=images, probe_to_world=poses, labels=label_array)


def build_tiny_dataset() -> SweepDataset:
    """Two sweeps of 8 × 6 frames from a 12 mm × 16 mm probe."""
    probe = ProbeGeometry(width_mm=12.0, depth_mm=16.0, height_px=8, width_px=6)
    return SweepDataset(
        probe=probe,
        sweeps=[make_sweep("row", "row", seed=1), make_sweep("column", "column", n=4, seed=2)],
        metadata={"origin": "test"},
    )


@pytest.fixture
def tiny_dataset() -> SweepDataset:
    """Two sweeps of 8 × 6 frames from a 12 mm × 16 mm probe (:func:`build_tiny_dataset`)."""
    return build_tiny_dataset()


@pytest.fixture
def tiny_dataset_dir(tmp_path: Path, tiny_dataset: SweepDataset) -> Path:
    path = tmp_path / "tiny"
    tiny_dataset.save(path)
    return path


@pytest.fixture
def l2_sample() -> Path:
    if not (L2_SAMPLE / "poses.npy").is_file():
        pytest.skip(f"shared sample data not found at {L2_SAMPLE}")
    return L2_SAMPLE


@pytest.fixture(scope="module")
def one_torch_thread():
    """A module's tests on one torch thread (the simulator's own setting)."""
    with torch_threads(1):
        yield


@pytest.fixture(scope="session")
def tiny_l3(tmp_path_factory) -> Path:
    """A simulated L3 dataset directory: row + column sweeps of 12 frames of 64 × 48 pixels
    (shared by the session's tests; never write into it)."""
    from ultron.phantom import SimulationConfig, simulate_dataset
    from ultron.phantom.protocols import ScanConfig

    config = SimulationConfig(
        sweeps=("row", "column"), scan=ScanConfig(frames_per_sweep=12), height_px=64, width_px=48
    )
    out = tmp_path_factory.mktemp("tiny_l3") / "dataset"
    simulate_dataset(config, out=out)
    return out


def tiny_ultron_run(iters: int, field_iters: int, n_points: int):
    """UltrON on half of :func:`tiny_l3`'s labels, learnt in ``iters`` steps (rate 1e-3,
    balanced classes: enough to find the bone on so few pixels), metrics on ``n_points``, and
    the field fit of ``field_iters`` steps it reads: (request, field config)."""
    from ultron.methods.ultron_method import UltronConfig
    from ultron.metrics.surface import MetricsConfig
    from ultron.pipeline.run import ReconstructionRequest
    from ultron.train.field_fit import FieldTrainConfig
    from ultron.train.occupancy import OccupancyTrainConfig

    occupancy = OccupancyTrainConfig(iters=iters, batch_size=1024, lr=1e-3, positive_weight=None)
    request = ReconstructionRequest(
        method="ultron",
        label_fraction=0.5,
        method_config=UltronConfig(occupancy=occupancy),
        metrics=MetricsConfig(n_points=n_points, repeats=1),
    )
    fields = FieldTrainConfig(iterations=field_iters, check_every=1000, checkpoint_every=1000)
    return request, fields


#: A small occupancy network for fits of a few hundred steps in the tests.
SMALL_OCCUPANCY = {"width": 32, "depth": 4, "skip_at": 2, "n_frequencies": 2}


def random_occupancy_data(n: int, seed: int = 0, front: bool = False):
    """Stage 2's data on n random 3-D inputs in [−1, 1), T uniform, bone where x > 0.3 and,
    with ``front``, a random half of the pixels marked in front of the bone (drawn last)."""
    from ultron.train.occupancy import OccupancyTrainingData

    generator = torch.Generator().manual_seed(seed)
    inputs = torch.rand(n, 3, generator=generator) * 2 - 1
    transmission = torch.rand(n, generator=generator)
    labels = (inputs[:, 0] > 0.3).to(torch.uint8)
    in_front = torch.rand(n, generator=generator) > 0.5 if front else None
    return OccupancyTrainingData(inputs, transmission, labels, in_front=in_front)


def assert_refused(invoke, cases) -> None:
    """Each ``(args, needle)`` of ``cases`` run through ``invoke`` (a CLI runner call) exits 2
    with ``needle`` on stderr and no traceback."""
    for args, needle in cases:
        result = invoke(*args)
        assert result.exit_code == 2, (args, result.output)
        assert needle in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.output + result.stderr
