"""Surface metrics against hand-worked cases."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from ultron.cli.main import app
from ultron.errors import UltronInputError
from ultron.metrics import MetricsConfig, distance_metrics, evaluate_meshes

FAST = MetricsConfig(n_points=20_000, repeats=2, seed=0)


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=10.0)


def test_hand_worked_reduction():
    acc = np.array([0.0, 1.0, 2.0, 3.0])
    comp = np.array([1.0, 1.0])
    result = distance_metrics(acc, comp)
    assert result["mad"] == pytest.approx(1.5)
    assert result["rmse"] == pytest.approx(math.sqrt((0 + 1 + 4 + 9) / 4))
    assert result["hd"] == 3.0
    assert result["completeness"] == 1.0
    assert result["cd"] == pytest.approx((1.5 + 1.0) / 2)
    # F@2mm: precision 2/4 (0 and 1 are < 2), recall 2/2 → F = 2·0.5·1/1.5
    assert result["fscore_2mm"] == pytest.approx(2 * 0.5 * 1.0 / 1.5)
    # F@1mm: precision 1/4, recall 0 (1.0 is not < 1)
    assert result["fscore_1mm"] == pytest.approx(0.0)


def test_mesh_against_itself_is_near_zero(sphere):
    result = evaluate_meshes(sphere, sphere, FAST)
    assert result["mean"]["cd"] < 0.01
    assert result["mean"]["mad"] < 0.01
    assert result["mean"]["fscore_1mm"] == 1.0


def test_one_mm_normal_offset_gives_one_mm(sphere):
    # an icosphere's vertices lie on the sphere: push them 1 mm along the normal
    offset = trimesh.Trimesh(sphere.vertices * (11.0 / 10.0), sphere.faces)
    result = evaluate_meshes(offset, sphere, FAST)["mean"]
    # faces sit slightly inside the circumscribed sphere, so allow the chord sagitta (< 0.05 mm)
    assert result["mad"] == pytest.approx(1.0, abs=0.05)
    assert result["completeness"] == pytest.approx(1.0, abs=0.05)
    assert result["cd"] == pytest.approx(1.0, abs=0.05)
    assert result["hd"] == pytest.approx(1.0, abs=0.1)


def test_translation_of_a_plane_patch_gives_exact_distance():
    plane = trimesh.Trimesh(
        vertices=[[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]], faces=[[0, 1, 2], [0, 2, 3]]
    )
    shifted = plane.copy()
    shifted.apply_translation([0, 0, 1.0])
    result = evaluate_meshes(shifted, plane, FAST)["mean"]
    assert result["mad"] == pytest.approx(1.0, abs=1e-5)
    assert result["rmse"] == pytest.approx(1.0, abs=1e-5)
    assert result["fscore_2mm"] == 1.0


def test_empty_reconstruction_gives_documented_inf_nan(sphere):
    result = evaluate_meshes(trimesh.Trimesh(), sphere, FAST)["mean"]
    assert math.isinf(result["cd"]) and math.isinf(result["completeness"])
    assert math.isnan(result["mad"]) and math.isnan(result["hd"])
    assert result["fscore_1mm"] == 0.0


def test_empty_reference_is_an_error(sphere):
    with pytest.raises(UltronInputError, match="empty"):
        evaluate_meshes(sphere, trimesh.Trimesh(), FAST)


def test_repeats_give_mean_and_std(sphere):
    shrunk = trimesh.Trimesh(sphere.vertices * 0.95, sphere.faces)
    result = evaluate_meshes(shrunk, sphere, MetricsConfig(n_points=5_000, repeats=3, seed=4))
    assert len(result["repeats"]) == 3
    values = [r["cd"] for r in result["repeats"]]
    assert result["mean"]["cd"] == pytest.approx(np.mean(values))
    assert result["std"]["cd"] == pytest.approx(np.std(values))
    assert result["std"]["cd"] > 0  # different seeds, different samples
    # same seed → same numbers
    again = evaluate_meshes(shrunk, sphere, MetricsConfig(n_points=5_000, repeats=3, seed=4))
    assert again["mean"] == result["mean"]


def test_bad_config():
    with pytest.raises(UltronInputError, match="n_points"):
        MetricsConfig(n_points=0)


def test_evaluate_cli(tmp_path: Path, sphere):
    sphere.export(tmp_path / "ref.ply")
    trimesh.Trimesh(sphere.vertices * 1.1, sphere.faces).export(tmp_path / "rec.stl")
    result = CliRunner().invoke(
        app,
        [
            "evaluate",
            str(tmp_path / "rec.stl"),
            str(tmp_path / "ref.ply"),
            "--points",
            "5000",
            "--repeats",
            "2",
        ],
        terminal_width=200,
    )
    assert result.exit_code == 0, result.output
    assert "CD" in result.output
    import json

    data = json.loads((tmp_path / "rec.metrics.json").read_text())
    assert data["mean"]["mad"] == pytest.approx(1.0, abs=0.05)
    missing = CliRunner().invoke(
        app, ["evaluate", str(tmp_path / "nope.ply"), str(tmp_path / "ref.ply")]
    )
    assert missing.exit_code == 2 and "nope.ply" in missing.stderr


# ----------------------------------------------------------------- exact point-to-surface
def _brute_force(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """min over ALL triangles of trimesh's closest-point distance (an independent kernel)."""
    from trimesh.triangles import closest_point

    triangles = np.asarray(mesh.triangles)
    out = np.empty(len(points))
    for i, p in enumerate(points):
        nearest = closest_point(triangles, np.repeat(p[None], len(triangles), axis=0))
        out[i] = np.linalg.norm(nearest - p, axis=1).min()
    return out


def _sphere_and_big_triangle() -> trimesh.Trimesh:
    """A fine sphere (r 5 mm) and one large triangle 60 mm away: both search paths."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    big = trimesh.Trimesh(
        [[60.0, -40.0, -40.0], [60.0, 80.0, -40.0], [60.0, -40.0, 80.0]], [[0, 1, 2]]
    )
    return trimesh.util.concatenate([sphere, big])


def test_point_above_a_large_triangle_gets_exactly_its_height():
    from ultron.metrics import point_to_surface_distances

    mesh = _sphere_and_big_triangle()
    # above the big triangle's centroid, 7 mm off its plane x = 60: far from every vertex
    points = np.array([[67.0, 0.0, 0.0], [53.0, 0.0, 0.0], [60.0, 10.0, 10.0]])
    np.testing.assert_allclose(
        point_to_surface_distances(points, mesh), [7.0, 7.0, 0.0], atol=1e-12
    )
    # a two-triangle square: a point over the middle of one triangle, far from its corners
    square = trimesh.Trimesh(
        [[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]], [[0, 1, 2], [0, 2, 3]]
    )
    assert point_to_surface_distances(np.array([[70.0, 30.0, 3.5]]), square)[0] == 3.5


def test_exact_distances_match_brute_force():
    from ultron.metrics import point_to_surface_distances

    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    sphere.vertices += rng.normal(scale=0.5, size=sphere.vertices.shape)  # irregular triangles
    for mesh in (sphere, _sphere_and_big_triangle()):
        on = trimesh.sample.sample_surface(mesh, 300, seed=1)[0]
        points = np.concatenate(
            [
                on + rng.normal(scale=0.3, size=on.shape),  # near the surface
                rng.uniform(-30, 90, size=(300, 3)),  # anywhere, up to ~100 mm away
                np.asarray(mesh.vertices[:50]),  # on vertices
            ]
        )
        got = point_to_surface_distances(points, mesh)
        np.testing.assert_allclose(got, _brute_force(points, mesh), rtol=0, atol=1e-9)


def test_exact_distances_fast_enough():
    """100k points 0.4 mm off a 328k-face sphere: seconds, not minutes (≈ 1 s of CPU; see
    benchmarks/distances.py for the L3 reference)."""
    import time

    from ultron.metrics import point_to_surface_distances

    mesh = trimesh.creation.icosphere(subdivisions=7, radius=20.0)  # 327,680 faces
    points = trimesh.sample.sample_surface(mesh, 100_000, seed=0)[0] * 1.02
    start = time.process_time()
    distances = point_to_surface_distances(points, mesh)
    assert time.process_time() - start < 60
    assert np.all(np.abs(distances - 0.4) < 0.01)


# -------------------------------------------------------- one-sided / symmetric / visible
def test_symmetric_hausdorff_and_visible_reduction():
    acc = np.array([0.0, 1.0, 2.0, 3.0])
    comp = np.array([1.0, 5.0])
    result = distance_metrics(acc, comp)
    assert result["hd"] == 3.0 and result["hd_sym"] == 5.0  # HD is one-sided
    assert result["hd95_sym"] == max(np.percentile(acc, 95), np.percentile(comp, 95))
    assert result["cd_visible"] is None and result["completeness_visible"] is None
    visible = distance_metrics(acc, comp, np.array([1.0, 1.0, 2.0]))
    assert visible["completeness_visible"] == pytest.approx(4 / 3)
    assert visible["cd_visible"] == pytest.approx((1.5 + 4 / 3) / 2)
    assert visible["cd"] == result["cd"]  # accuracy still against the whole reference


def _plate_over_sphere() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """A 40 × 40 × 2 mm plate over x < 0 (top face at z = 10) and a sphere (r 6 mm) centred at
    the origin: the plate shadows the sphere's −x half."""
    plate = trimesh.creation.box(extents=(40.0, 40.0, 2.0))
    plate.apply_translation((-20.0, 0.0, 9.0))
    plate = plate.subdivide().subdivide().subdivide().subdivide()
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=6.0)
    return plate, sphere


def _looking_down(probe) -> tuple[np.ndarray, np.ndarray]:
    """Frames 20 mm above the origin looking down (beam −z), swept along y every 0.5 mm; the
    true T is 1 above the plate's top (z = 10) and, below it, 0.01 under the plate (x < 0)."""
    poses = []
    for y in np.arange(-25.0, 25.01, 0.5):
        pose = np.eye(4)
        pose[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # x̂ = x, ŷ = −z, ẑ = y
        pose[:3, 3] = (0.0, y, 20.0)
        poses.append(pose)
    poses = np.stack(poses)
    rows = np.arange(probe.height_px) * probe.axial_spacing_mm  # depth below z = 20
    cols = (np.arange(probe.width_px) - probe.width_px / 2) * probe.lateral_spacing_mm
    shadow = (rows[:, None] > 10.0) & (cols[None, :] < 0.0)
    t_map = np.where(shadow, 0.01, 1.0).astype(np.float16)
    return poses, np.repeat(t_map[None], len(poses), axis=0)


def test_visibility_of_a_plate_over_a_sphere():
    from ultron.data.dataset import ProbeGeometry
    from ultron.mesh.observed import observed_points, observed_submesh

    probe = ProbeGeometry(width_mm=80.0, depth_mm=40.0, height_px=160, width_px=160)
    plate, sphere = _plate_over_sphere()
    reference = trimesh.util.concatenate([plate, sphere])
    poses, t_maps = _looking_down(probe)
    visible = observed_points(
        reference.vertices, reference.vertex_normals, poses, probe, t_maps, 0.5
    )
    v = np.asarray(reference.vertices)
    on_sphere = np.arange(len(v)) >= len(plate.vertices)
    facing_up = np.asarray(reference.vertex_normals)[:, 2] > np.cos(np.radians(70))
    assert not visible[on_sphere & (v[:, 2] < 0)].any()  # the sphere's underside: never
    assert not visible[on_sphere & (v[:, 0] < -0.5)].any()  # its top under the plate: shadowed
    assert visible[on_sphere & facing_up & (v[:, 0] > 0.5)].all()  # its lit top: all
    assert visible[~on_sphere & (v[:, 2] > 9.99)].all()  # the plate's top face
    assert not visible[~on_sphere & (v[:, 2] < 8.01)].any()  # not its bottom face

    visible_mesh = observed_submesh(reference, visible)
    assert 0 < len(visible_mesh.faces) < len(reference.faces)
    # a reconstruction of what was seen: perfect on the visible part, nothing elsewhere
    result = evaluate_meshes(visible_mesh, reference, FAST, reference_visible=visible_mesh)["mean"]
    assert result["completeness_visible"] < 0.01 and result["cd_visible"] < 0.01
    assert result["completeness"] > 1.0  # the unseen sphere and plate bottom count here
    assert result["mad"] < 0.01


def test_visible_metrics_are_none_and_na_without_a_visible_reference(sphere):
    from ultron.report.tables import metrics_markdown

    result = evaluate_meshes(sphere, sphere, FAST)
    for name in ("cd_visible", "completeness_visible", "completeness_visible_hd95"):
        assert result["mean"][name] is None and result["std"][name] is None
    assert result["mean"]["hd_sym"] < 0.1
    markdown = metrics_markdown({"self": result})
    assert markdown.splitlines()[0].startswith("| method | CD vis. | Comp. vis. | CD | HD95 |")
    assert markdown.splitlines()[2].startswith("| self | n/a | n/a | 0.000")  # never 0
    empty = evaluate_meshes(trimesh.Trimesh(), sphere, FAST, reference_visible=sphere)["mean"]
    assert math.isinf(empty["cd_visible"]) and math.isinf(empty["hd_sym"])


def test_evaluate_cli_with_visible_reference(tmp_path: Path, sphere):
    import json

    sphere.export(tmp_path / "ref.ply")
    half = sphere.submesh([np.flatnonzero(sphere.triangles_center[:, 2] > 0)], append=True)
    half.export(tmp_path / "visible.ply")
    half.export(tmp_path / "rec.ply")
    args = ["evaluate", str(tmp_path / "rec.ply"), str(tmp_path / "ref.ply"), "--points", "5000",
            "--repeats", "1"]  # fmt: skip
    runner = CliRunner()
    result = runner.invoke(app, [*args, "--reference-visible", str(tmp_path / "visible.ply")])
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "rec.metrics.json").read_text())
    assert data["mean"]["completeness_visible"] < 0.01 < data["mean"]["completeness"]
    assert data["reference_visible"] == str(tmp_path / "visible.ply")
    plain = runner.invoke(app, args, terminal_width=250)
    assert plain.exit_code == 0 and "n/a" in plain.output
    text = (tmp_path / "rec.metrics.json").read_text()
    assert '"cd_visible": null' in text
    missing = runner.invoke(app, [*args, "--reference-visible", str(tmp_path / "nope.ply")])
    assert missing.exit_code == 2 and "nope.ply" in missing.stderr


# --------------------------------------------------------------------- crop to the visible
def _square(x0: float, size: float, z: float) -> trimesh.Trimesh:
    """An axis-aligned square [x0, x0 + size] × [0, size] at height z, two triangles."""
    corners = [[x0, 0, z], [x0 + size, 0, z], [x0 + size, size, z], [x0, size, z]]
    return trimesh.Trimesh(corners, [[0, 1, 2], [0, 2, 3]])


def test_crop_drops_faces_far_from_the_visible_reference_and_reports_their_area():
    reference = _square(0.0, 20.0, 0.0)
    visible = _square(0.0, 10.0, 0.0)
    near = _square(0.0, 10.0, 0.5)  # 0.5 mm above the visible part: kept
    far = _square(40.0, 10.0, 0.0)  # 30 mm beside it (a tibia): dropped, 100 mm²
    recon = trimesh.util.concatenate([near, far])
    config = MetricsConfig(n_points=4_000, repeats=1, crop_mm=5.0)
    result = evaluate_meshes(recon, reference, config, reference_visible=visible)
    crop = result["crop"]
    assert crop["area_mm2"] == pytest.approx(200.0)
    assert crop["area_kept_mm2"] == pytest.approx(100.0)
    assert crop["area_outside_mm2"] == pytest.approx(100.0)
    mean = result["mean"]
    assert mean["mad"] == pytest.approx(0.5, abs=1e-6)  # the far square no longer counts
    assert mean["hd"] == pytest.approx(0.5, abs=1e-6)
    assert mean["fscore_visible_1mm"] == 1.0  # every visible point within 0.5 mm
    uncropped = evaluate_meshes(recon, reference, MetricsConfig(n_points=4_000, repeats=1),
                                reference_visible=visible)  # fmt: skip
    assert uncropped["crop"] is None and uncropped["mean"]["hd"] > 20.0


def test_visible_fscore_uses_the_visible_reference():
    acc = np.array([0.5, 0.5, 3.0, 3.0])  # precision at 1 mm: 1/2
    comp = np.array([5.0, 5.0])  # the whole reference: nothing within 1 mm
    comp_visible = np.array([0.2, 0.2, 0.2, 3.0])  # recall 3/4
    result = distance_metrics(acc, comp, comp_visible)
    assert result["fscore_1mm"] == 0.0
    assert result["fscore_visible_1mm"] == pytest.approx(2 * 0.5 * 0.75 / 1.25)
    assert distance_metrics(acc, comp)["fscore_visible_1mm"] is None


def test_crop_needs_a_visible_reference_and_a_positive_distance(sphere, tmp_path: Path):
    with pytest.raises(UltronInputError, match="reference_visible"):
        evaluate_meshes(sphere, sphere, MetricsConfig(n_points=100, repeats=1, crop_mm=5.0))
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(UltronInputError, match="crop_mm"):
            MetricsConfig(crop_mm=bad)
    sphere.export(tmp_path / "ref.ply")
    cli = CliRunner().invoke(
        app, ["evaluate", str(tmp_path / "ref.ply"), str(tmp_path / "ref.ply"), "--crop-mm", "5"]
    )
    assert cli.exit_code == 2 and "--crop-mm" in cli.stderr and "Traceback" not in cli.output


def test_crop_of_everything_gives_the_empty_figures(sphere):
    far = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    far.apply_translation([100.0, 0, 0])
    config = MetricsConfig(n_points=1_000, repeats=1, crop_mm=5.0)
    result = evaluate_meshes(far, sphere, config, reference_visible=sphere)
    assert result["crop"]["area_kept_mm2"] == 0.0
    assert math.isinf(result["mean"]["cd_visible"]) and result["mean"]["fscore_visible_1mm"] == 0.0


def test_evaluate_files_writes_beside_the_mesh_and_names_a_crop_without_its_surface(
    sphere, tmp_path: Path
) -> None:
    from ultron.errors import UltronError
    from ultron.pipeline.evaluate import evaluate_files

    shifted = sphere.copy()
    shifted.apply_translation([0.5, 0.0, 0.0])
    mesh, reference = tmp_path / "recon.ply", tmp_path / "ref.ply"
    shifted.export(mesh)
    sphere.export(reference)
    config = MetricsConfig(n_points=5_000, repeats=1, seed=0)
    with pytest.raises(UltronError, match="--crop-mm"):
        evaluate_files(mesh, reference, MetricsConfig(n_points=100, repeats=1, crop_mm=5.0))
    warnings: list[str] = []
    done = evaluate_files(mesh, reference, config, warn=warnings.append)
    assert done.out == tmp_path / "recon.metrics.json" and done.out.is_file()
    assert done.result["mesh"] == str(mesh) and done.result["reference_visible"] is None
    assert done.crop_line() is None and warnings == []  # the boxes overlap
    # a 0.5 mm shift: every reconstructed point lies within 0.5 mm of the reference
    assert 0.1 < done.result["mean"]["mad"] < 0.5
    far = shifted.copy()
    far.apply_translation([1000.0, 0.0, 0.0])
    far.export(mesh)
    evaluate_files(mesh, reference, config, out=tmp_path / "far.json", warn=warnings.append)
    assert len(warnings) == 1 and str(mesh) in warnings[0]
