"""B-mode simulator, annotation simulator, scan protocols and ``simulate_dataset``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import frame_pixels_world
from ultron.errors import UltronInputError
from ultron.phantom import (
    AnnotationConfig,
    BModeConfig,
    ScanConfig,
    SimulationConfig,
    TrackingNoise,
    get_phantom,
    perturb_poses,
    plan_sweep,
    scatterer_field,
    simulate_dataset,
    simulate_frames,
    sweep_spec,
)
from ultron.phantom.tissue import CORTICAL_BONE, GEL_PULP

EXACT_LABELS = AnnotationConfig(jitter_mm=0.0, error_rate=0.0)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """Row and column sweeps of L3, 7 frames each, exact labels, default tracking noise."""
    config = SimulationConfig(
        sweeps=("row", "column"), scan=ScanConfig(frames_per_sweep=7), annotation=EXACT_LABELS
    )
    out = tmp_path_factory.mktemp("sim")
    return config, simulate_dataset(config, out=out), out


def first_bone_depth(phantom, pose, probe, step_mm=0.02):
    """Depth (mm) of the first gel→bone crossing of every scanline by fine marching of the
    analytic SDF, NaN where none; and the cosine of the incidence angle there."""
    depths = torch.arange(0.0, probe.depth_mm, step_mm, dtype=torch.float64)
    cols = torch.arange(probe.width_px, dtype=torch.float64)
    x = (cols - probe.width_px / 2) * probe.lateral_spacing_mm
    local = torch.stack(
        [x[:, None].expand(-1, depths.numel()), depths[None].expand(x.numel(), -1)], -1
    )
    rot, t = torch.as_tensor(pose[:3, :3]), torch.as_tensor(pose[:3, 3])
    world = local[..., 0, None] * rot[:, 0] + local[..., 1, None] * rot[:, 1] + t
    d = phantom.sdf(world)
    inside = d < 0
    has = inside.any(dim=1)
    first = inside.float().argmax(dim=1)
    depth = torch.where(has, depths[first], torch.nan)
    hit = world[torch.arange(x.numel()), first].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(phantom.sdf(hit).sum(), hit)
    cos = (grad / grad.norm(dim=-1, keepdim=True) @ rot[:, 1]).abs()
    return depth.numpy(), torch.where(has, cos, torch.nan).numpy()


def test_dataset_layout(small):
    _config, _data, out = small
    loaded = SweepDataset.load(out)
    assert [s.name for s in loaded.sweeps] == ["row", "column"]
    assert [s.kind for s in loaded.sweeps] == ["row", "column"]
    assert loaded.probe.image_shape == (128, 96)
    assert loaded.probe.width_mm == 38.0
    assert loaded.metadata["phantom"] == "L3"
    assert loaded.reference is not None and loaded.reference.name == "reference.ply"
    assert (out / "phantom.json").is_file()
    for sweep in loaded.sweeps:
        assert sweep.images.dtype == np.uint8 and sweep.labels is not None
        assert sweep.true_probe_to_world is not None
        moved = np.linalg.norm(sweep.probe_to_world[:, :3, 3] - sweep.true_probe_to_world[:, :3, 3])
        assert moved > 0


def test_brightest_echo_on_reference_surface(small):
    _config, data, _ = small
    phantom = get_phantom("L3")
    sweep = data.sweep("row")
    probe = data.probe
    checked = 0
    for frame in (2, 3, 4):
        depth, cos = first_bone_depth(phantom, sweep.true_probe_to_world[frame], probe)
        good = np.flatnonzero(np.isfinite(depth) & (cos > 0.8))
        brightest = sweep.images[frame].argmax(axis=0) * probe.axial_spacing_mm
        errors = np.abs(brightest[good] - depth[good])
        assert np.all(errors <= 1.0), (frame, errors.max())
        checked += good.size
    assert checked >= 20


def test_shadow_is_dark_below_bone(small):
    _config, data, _ = small
    phantom = get_phantom("L3")
    sweep = data.sweep("row")
    probe = data.probe
    step = probe.axial_spacing_mm
    shadow, gel = [], []
    for frame in range(sweep.n_frames):
        depth, _ = first_bone_depth(phantom, sweep.true_probe_to_world[frame], probe)
        image = sweep.images[frame].astype(float)
        for col in np.flatnonzero(np.isfinite(depth) & (depth > 15) & (depth < 55)):
            r = int(depth[col] / step)
            shadow.append(image[r + int(4 / step) : r + int(12 / step), col].mean())
            gel.append(image[r - int(12 / step) : r - int(4 / step), col].mean())
    assert len(shadow) > 50
    assert np.mean(shadow) < 0.35 * np.mean(gel)


def test_labels_only_on_visible_bone(small):
    config, data, _ = small
    phantom = get_phantom("L3")
    probe = data.probe
    step = probe.axial_spacing_mm
    for sweep in data.sweeps:
        points = frame_pixels_world(torch.as_tensor(sweep.true_probe_to_world), probe)
        sdf = phantom.sdf(points).numpy()
        labels = sweep.labels
        bone = labels == 1
        assert bone.sum() > 100
        # on bone (within the grid interpolation error) ...
        assert sdf[bone].max() < 0.05
        # ... only the first bone met by the beam (exactly one gel→bone entry above) ...
        entries = np.cumsum((sdf[:, :-1] >= 0) & (sdf[:, 1:] < 0), axis=1)
        entries = np.concatenate([np.zeros_like(entries[:, :1]), entries], axis=1)
        assert entries[bone].max() == 1
        # ... and only a band under its surface: most bone is in shadow and labelled 0.
        inside = sdf < -0.5
        assert (labels[inside] == 0).mean() > 0.6
        first = np.where(entries >= 1, 1, 0).argmax(axis=1)  # (N, W) first bone row
        rows = np.arange(probe.height_px)[None, :, None]
        below_band = rows * step > first[:, None, :] * step + config.annotation.band_mm + step
        assert not (bone & below_band).any()


def test_true_transmission_is_one_above_bone_and_dark_in_its_shadow(small):
    _config, _data, out = small
    phantom = get_phantom("L3")
    loaded = SweepDataset.load(out)
    probe = loaded.probe
    step = probe.axial_spacing_mm
    for sweep in loaded.sweeps:
        t = np.load(out / sweep.name / "transmission.npy")
        assert t.dtype == np.float16 and t.shape == sweep.images.shape
        assert t.min() >= 0 and t.max() <= 1 and (t[:, 0] == 1).all()
        np.testing.assert_array_equal(sweep.true_transmission, t)
    sweep = loaded.sweep("row")
    t = sweep.true_transmission.astype(np.float64)
    shadow, lit = [], []
    for frame in range(sweep.n_frames):
        pose = sweep.true_probe_to_world[frame]
        depth, _ = first_bone_depth(phantom, pose, probe)
        for col in np.flatnonzero(np.isfinite(depth) & (depth > 15) & (depth < 55)):
            # a shadow column: the beam stays in bone for 2 mm past the surface
            x = (col - probe.width_px / 2) * probe.lateral_spacing_mm
            below = depth[col] + np.array([0.5, 1.0, 1.5, 2.0])
            world = pose[:3, 3] + x * pose[:3, 0] + below[:, None] * pose[:3, 1]
            r = int(depth[col] / step)
            lit.append(t[frame, : r - 2, col].min())
            if (phantom.sdf(torch.as_tensor(world)) < 0).all():
                shadow.append(t[frame, r + int(4 / step) :, col].max())
    assert len(shadow) > 50
    assert max(shadow) < 0.1
    # gel only above the bone, compensated by the TGC (but where the beam grazes bone within
    # half a pixel: the simulator's partial-volume occupancy attenuates there)
    assert np.median(lit) == 1.0 and np.mean(np.array(lit) > 0.99) > 0.95


def test_visible_reference_is_a_subset_seen_from_the_probe(small):
    config, data, out = small
    import json

    import trimesh

    loaded = SweepDataset.load(out)
    assert loaded.reference_visible_path == out / "reference_visible.ply"
    assert data.reference_visible_path is not None
    assert json.loads((out / "dataset.json").read_text())["reference_visible"] == (
        "reference_visible.ply"
    )
    reference = trimesh.load(loaded.reference, process=False)
    visible = trimesh.load(loaded.reference_visible_path, process=False)
    assert 0 < len(visible.faces) < 0.5 * len(reference.faces)
    # a sub-mesh of the reference: its vertices are reference vertices
    known = {tuple(v) for v in np.asarray(reference.vertices)}
    assert all(tuple(v) in known for v in np.asarray(visible.vertices))
    # faces the probe (beam +y): outward normals point back at it
    assert (visible.face_normals[:, 1] < 0).mean() > 0.95
    criterion = json.loads((out / "phantom.json").read_text())["reference_visible"]
    assert criterion["max_incidence_deg"] == 70.0 and criterion["min_transmission"] == 0.3
    slabs = criterion["slab_half_thickness_mm"]
    assert set(slabs) == {"row", "column"}
    assert min(slabs.values()) >= config.bmode.elevation_span_mm
    assert criterion["faces_visible"] == len(visible.faces)


def test_labels_follow_visibility_threshold(small):
    _config, data, _ = small
    phantom = get_phantom("L3")
    probe = data.probe
    sweep = data.sweep("row")
    true = torch.as_tensor(sweep.true_probe_to_world)
    volume = phantom.sdf_volume()
    field = scatterer_field(
        np.array([[-40.0, -80.0, -30.0], [40.0, 0.0, 30.0]]), 0.5, GEL_PULP, CORTICAL_BONE, 0
    )
    frames = simulate_frames(true[:3], probe, volume, field, BModeConfig(), torch.Generator())
    from ultron.phantom import annotate

    def count(min_echo_db):
        cfg = AnnotationConfig(jitter_mm=0.0, error_rate=0.0, min_echo_db=min_echo_db)
        return int((annotate(frames.interfaces, probe, cfg, torch.Generator()) == 1).sum())

    assert count(1.0) == 0  # no echo is brighter than a normal, unattenuated one
    assert 0 < count(-10.0) < count(-18.0) <= count(-100.0)


def test_gel_brightness_flat_with_tgc_and_decays_without():
    """Pure gel (probe far from the bone), depth-invariant PSF (no focal gain): with full TGC
    the mean level is flat with depth; without TGC it falls by the round-trip attenuation
    2·0.5 dB/cm/MHz·5 MHz = 0.5 dB/mm, i.e. 0.5·255/50 = 2.55 grey levels per mm on a 50 dB
    display."""
    phantom = get_phantom("L3")
    config = SimulationConfig()
    probe = config.probe()
    pose = np.eye(4)
    pose[:3, 3] = (200.0, -75.0, 0.0)  # far lateral: gel only
    poses = torch.as_tensor(np.stack([pose] * 4))
    poses[:, 2, 3] = torch.tensor([0.0, 3.0, 6.0, 9.0], dtype=torch.float64)
    box = np.array([[175.0, -80.0, -5.0], [225.0, 0.0, 15.0]])
    field = scatterer_field(box, 0.5, GEL_PULP, CORTICAL_BONE, 3)
    volume = phantom.sdf_volume()
    step = probe.axial_spacing_mm
    depth = np.arange(probe.height_px) * step

    def mean_profile(tgc):
        bmode = BModeConfig(
            tgc_compensation=tgc, lateral_rayleigh_mm=1e9, elevation_rayleigh_mm=1e9
        )
        frames = simulate_frames(poses, probe, volume, field, bmode, torch.Generator())
        return frames.images.double().mean(dim=(0, 2)).numpy()

    flat = mean_profile(1.0)
    top, bottom = flat[(depth > 5) & (depth < 25)], flat[(depth > 45) & (depth < 65)]
    assert abs(top.mean() - bottom.mean()) < 3.0
    decay = mean_profile(0.0)
    fit = (depth > 3) & (depth < 30)
    slope = np.polyfit(depth[fit], decay[fit], 1)[0]
    assert slope == pytest.approx(-2.55, rel=0.2)


def test_scatterers_are_world_anchored():
    box_a = np.array([[-10.0, -10.0, -10.0], [10.0, 10.0, 10.0]])
    box_b = np.array([[-4.0, -30.0, -2.0], [30.0, 5.0, 25.0]])
    a = scatterer_field(box_a, 0.5, GEL_PULP, CORTICAL_BONE, 7)
    b = scatterer_field(box_b, 0.5, GEL_PULP, CORTICAL_BONE, 7)
    other = scatterer_field(box_a, 0.5, GEL_PULP, CORTICAL_BONE, 8)
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand((500, 3), generator=gen, dtype=torch.float64) * 6 - 1  # in both boxes
    torch.testing.assert_close(a.sample(pts)[0], b.sample(pts)[0])
    assert not torch.allclose(a.sample(pts)[0], other.sample(pts)[0])
    gel = a.values[:2]
    assert gel.pow(2).sum(0).mean().item() == pytest.approx(
        GEL_PULP.scatterer_amplitude**2 * GEL_PULP.scatterer_density_per_mm3 * 0.125, rel=0.1
    )


def test_sweep_geometry():
    phantom = get_phantom("L3")
    bounds = phantom.bounds_mm
    scan = ScanConfig(frames_per_sweep=5)
    row = plan_sweep(sweep_spec("row"), bounds, phantom.surface_y_mm, scan)
    column = plan_sweep(sweep_spec("column"), bounds, phantom.surface_y_mm, scan)
    tilt = plan_sweep(sweep_spec("tilt_p10"), bounds, phantom.surface_y_mm, scan)
    np.testing.assert_allclose(row[:, :3, 1], np.tile([0.0, 1.0, 0.0], (5, 1)))  # beam = +y
    np.testing.assert_allclose(column[:, :3, 0], np.tile([0.0, 0.0, 1.0], (5, 1)))
    np.testing.assert_allclose(np.diff(row[:, 2, 3]), (bounds[1, 2] - bounds[0, 2] + 8) / 4)
    assert np.allclose(row[:, 1, 3], phantom.surface_y_mm)
    beam = tilt[0, :3, 1]
    assert math.degrees(math.acos(beam[1])) == pytest.approx(10.0)
    # the tilted centre scanline crosses the bone mid-line 40 mm deep
    crossing = tilt[0, :3, 3] + 40.0 / beam[1] * beam
    assert crossing[0] == pytest.approx(bounds[:, 0].mean().item(), abs=1e-9)
    assert sweep_spec("tilt_m15").tilt_deg == -15.0 and sweep_spec("tilt_m15").kind == "tilted"


def test_tracking_noise_statistics():
    poses = np.tile(np.eye(4), (4000, 1, 1))
    noisy = perturb_poses(poses, TrackingNoise(1.0, 2.0, 0.0), torch.Generator().manual_seed(0))
    assert noisy[:, :3, 3].std(axis=0) == pytest.approx([1.0, 1.0, 1.0], rel=0.1)
    angles = np.degrees(
        np.arccos(np.clip((np.trace(noisy[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    )
    # |ω| for ω ~ N(0, σ²I₃) has RMS σ√3
    assert np.sqrt((angles**2).mean()) == pytest.approx(2.0 * math.sqrt(3), rel=0.1)
    gram = noisy[:, :3, :3] @ noisy[:, :3, :3].transpose(0, 2, 1)
    assert np.abs(gram - np.eye(3)).max() < 1e-12
    exact = perturb_poses(poses[:3], TrackingNoise(0.0, 0.0), torch.Generator())
    np.testing.assert_array_equal(exact, poses[:3])


def test_same_seed_same_bytes_other_seed_other_images(tmp_path):
    config = SimulationConfig(
        sweeps=("tilt_m10",), scan=ScanConfig(frames_per_sweep=3), voxel_mm=0.6
    )
    simulate_dataset(config, out=tmp_path / "a")
    simulate_dataset(config, out=tmp_path / "b")
    simulate_dataset(config.replace(seed=1), out=tmp_path / "c")
    files = sorted(
        p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()
    )
    assert {str(f) for f in files} >= {
        "dataset.json",
        "phantom.json",
        "reference.ply",
        "tilt_m10/images.npy",
        "tilt_m10/labels.npy",
        "tilt_m10/poses.npy",
        "tilt_m10/true_poses.npy",
        "tilt_m10/transmission.npy",
        "reference_visible.ply",
    }
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    a = np.load(tmp_path / "a" / "tilt_m10" / "images.npy")
    c = np.load(tmp_path / "c" / "tilt_m10" / "images.npy")
    assert (a != c).mean() > 0.5


def test_annotation_noise_options(tmp_path):
    config = SimulationConfig(sweeps=("row",), scan=ScanConfig(frames_per_sweep=10))
    runs = iter(range(10))

    def run(cfg):
        return simulate_dataset(cfg, out=tmp_path / str(next(runs))).sweeps[0]

    base = run(config.replace(annotation=EXACT_LABELS)).labels
    missing = run(
        config.replace(annotation=AnnotationConfig(jitter_mm=0, error_rate=0, missing_fraction=0.3))
    )
    assert len(missing.labelled_frames) == 7
    assert ((missing.labels == 255).all(axis=(1, 2))).sum() == 3
    jitter = run(config.replace(annotation=AnnotationConfig(jitter_mm=0.5, error_rate=0.0))).labels
    changed = (jitter != base).mean()
    assert 0 < changed < 0.02
    coarse = run(config.replace(annotation=AnnotationConfig(jitter_mm=0.0, error_rate=1.0))).labels
    # every frame shifted/thickened: most of the exact band is no longer where it was
    assert ((coarse == 1) & (base == 1)).sum() < 0.8 * (base == 1).sum()


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"phantom": "L9"}, "phantom"),
        ({"scan": "frames"}, None),
        ({"sweeps": ("row", "diagonal")}, "sweeps"),
        ({"sweeps": ()}, "sweeps"),
        ({"seed": -1}, "seed"),
        ({"voxel_mm": 0.0}, "voxel_mm"),
    ],
)
def test_bad_config_is_a_clear_error(changes, match):
    if changes.get("scan") == "frames":
        with pytest.raises(UltronInputError, match="frames_per_sweep"):
            ScanConfig(frames_per_sweep=0)
        return
    with pytest.raises(UltronInputError, match=match):
        SimulationConfig(**changes)


def test_bad_noise_is_a_clear_error():
    with pytest.raises(UltronInputError, match="translation_mm"):
        TrackingNoise(translation_mm=-0.1)
    with pytest.raises(UltronInputError, match="rotation_deg"):
        TrackingNoise(rotation_deg=-1.0)
    with pytest.raises(UltronInputError, match="jitter_mm"):
        AnnotationConfig(jitter_mm=-1.0)
    with pytest.raises(UltronInputError, match="missing_fraction"):
        AnnotationConfig(missing_fraction=1.5)


def test_cli_simulate(tmp_path):
    from typer.testing import CliRunner

    from ultron.cli.main import app

    runner = CliRunner()
    out = tmp_path / "ds"
    result = runner.invoke(
        app,
        [
            "simulate", "--out", str(out), "--phantom", "L3", "--frames", "2",
            "--sweeps", "row,tilt_p10", "--voxel-mm", "0.6", "--preview",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    data = SweepDataset.load(out)
    assert [s.name for s in data.sweeps] == ["row", "tilt_p10"]
    assert (out / "preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for args, name in (
        (["--phantom", "L9"], "phantom"),
        (["--frames", "0"], "--frames"),
        (["--pose-noise-mm", "-1"], "--pose-noise-mm"),
        (["--label-noise-mm", "-0.5"], "--label-noise-mm"),
    ):
        bad = runner.invoke(app, ["simulate", "--out", str(tmp_path / "bad"), *args])
        assert bad.exit_code == 2
        assert name in bad.output and "Traceback" not in bad.output


def test_config_round_trips_through_phantom_json(small):
    config, _, out = small
    import json

    stored = json.loads((out / "phantom.json").read_text())
    assert SimulationConfig.from_dict(stored["config"]) == config
    assert stored["phantom"]["name"] == "L3"
    assert stored["derived"]["reflection_gel_bone"] == pytest.approx(config.bmode.reflection)
    with pytest.raises(UltronInputError, match=r"config\.scan.*unknown"):
        SimulationConfig.from_dict({"scan": {"frames": 3}})


def test_preview_draws_pixels_where_the_geometry_puts_them(tiny_dataset: SweepDataset) -> None:
    """Hand-worked: 6 × 8 pixels of 2 mm; pixel (r, c) is at ((c − 3)·2, 2r) mm, so the image's
    edges lie half a pixel (1 mm) outside the first and last centres."""
    from ultron.phantom.preview import frame_extent_mm, pixel_centres_mm, preview_png

    x_mm, depth_mm = pixel_centres_mm(tiny_dataset.probe)
    np.testing.assert_array_equal(x_mm, [-6.0, -4.0, -2.0, 0.0, 2.0, 4.0])
    np.testing.assert_array_equal(depth_mm, 2.0 * np.arange(8))
    assert frame_extent_mm(tiny_dataset.probe) == (-7.0, 5.0, 15.0, -1.0)
    png = preview_png(tiny_dataset, frames_per_sweep=2)
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(UltronInputError, match="frames_per_sweep"):
        preview_png(tiny_dataset, frames_per_sweep=0)


def test_simulate_to_writes_the_dataset_and_its_preview(tmp_path):
    from ultron.pipeline.simulate import simulate_to

    config = SimulationConfig(sweeps=("row",), scan=ScanConfig(frames_per_sweep=3), voxel_mm=0.6)
    config = config.replace(height_px=32, width_px=24)
    result = simulate_to(config, tmp_path / "sim", preview=True)
    assert result.out == tmp_path / "sim" and result.seconds > 0
    assert SweepDataset.load(tmp_path / "sim").n_frames == result.dataset.n_frames == 3
    assert result.preview == tmp_path / "sim" / "preview.png"
    assert result.preview.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert simulate_to(config, tmp_path / "plain").preview is None
    assert not (tmp_path / "plain" / "preview.png").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(UltronInputError, match=r"file: --out: exists and is not a directory"):
        simulate_to(config, tmp_path / "file")
