"""Observed vs inferred surface (per-vertex evidence) and Slicer-ready mesh coordinates."""

from __future__ import annotations

import json
import math
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import trimesh
from scipy.ndimage import map_coordinates
from typer.testing import CliRunner

from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry
from ultron.errors import UltronError
from ultron.mesh.evidence import (
    SURFACE_PLACES,
    SurfaceEvidence,
    nearest_distance_mm,
    surface_evidence,
    surface_places,
)
from ultron.mesh.export import (
    MESH_COORDINATES,
    load_mesh,
    load_vertex_properties,
    mesh_file_space,
    save_mesh,
)
from ultron.mesh.observed import ObservedSurfaceConfig, observe_surface
from ultron.metrics.surface import MetricsConfig
from ultron.pipeline.run import EXTRACTED_MESH, ReconstructionRequest, reconstruct

PROBE = ProbeGeometry(width_mm=20.0, depth_mm=20.0, height_px=40, width_px=20)
FAST_METRICS = MetricsConfig(n_points=3_000, repeats=1)


def _frames_looking_down(n: int = 11) -> np.ndarray:
    """Frames at y = 0 looking along world +y (the beam), swept along world z over ±5 mm."""
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = np.linspace(-5.0, 5.0, n)
    return poses


def _sphere() -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=3.0)
    sphere.apply_translation([0.0, 12.0, 0.0])
    return sphere


# ------------------------------------------------------------------------ observe_surface
def test_sphere_under_the_probe_underside_is_inferred_and_cropped() -> None:
    sphere, poses = _sphere(), _frames_looking_down()
    config = ObservedSurfaceConfig(surface="observed")
    seen = observe_surface(sphere, poses, PROBE, None, 0.6, config, "none (T = 1)")
    facing = -sphere.vertex_normals[:, 1] >= math.cos(math.radians(70))
    underside = sphere.vertex_normals[:, 1] > 0.2  # facing away from the probe
    assert not seen.observed[underside].any()
    assert seen.observed[facing & (np.abs(sphere.vertices[:, 2]) <= 5.6)].all()
    # the crop keeps observed faces only, and maps its vertices back exactly
    assert seen.cropped and 0 < len(seen.kept.faces) < len(sphere.faces)
    np.testing.assert_array_equal(seen.kept.vertices, sphere.vertices[seen.kept_vertices])
    assert seen.kept_observed.all()
    assert seen.info["faces_extracted"] == len(sphere.faces)
    assert seen.info["faces_kept"] == len(seen.kept.faces)
    assert seen.info["observation_transmission"] == "none (T = 1)"


def test_a_plate_in_front_shadows_the_whole_sphere_and_all_keeps_it() -> None:
    sphere, poses = _sphere(), _frames_looking_down()
    transmission = np.ones((len(poses), 40, 20), dtype=np.float32)
    transmission[:, 13:, :] = 0.0  # a plate at 6.5 mm depth: everything below is in shadow
    observed = observe_surface(sphere, poses, PROBE, transmission, 0.6,
                               ObservedSurfaceConfig(surface="observed"), "field")  # fmt: skip
    assert not observed.observed.any()
    # nothing observed: the whole iso-surface is kept and run.json says so
    assert observed.kept is sphere and observed.info["surface_fallback"] == "all"
    everything = observe_surface(sphere, poses, PROBE, None, 0.6,
                                 ObservedSurfaceConfig(surface="all"), "none")  # fmt: skip
    assert everything.kept is sphere and not everything.cropped
    np.testing.assert_array_equal(everything.kept_vertices, np.arange(len(sphere.vertices)))
    assert 0 < everything.observed.sum() < len(sphere.vertices)


# ------------------------------------------------------------------------ label distances
def test_nearest_distance_hand_worked() -> None:
    points = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [1.0, 1.0, 1.0]])
    targets = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(nearest_distance_mm(points, targets), [0.0, 4.0, math.sqrt(3)])
    assert np.isinf(nearest_distance_mm(points, np.zeros((0, 3)))).all()
    assert nearest_distance_mm(np.zeros((0, 3)), targets).shape == (0,)
    with pytest.raises(UltronError, match="targets_mm"):
        nearest_distance_mm(points, np.zeros((2, 2)))
    with pytest.raises(UltronError, match="points_mm"):
        nearest_distance_mm(np.array([[np.nan, 0.0, 0.0]]), targets)
    # a bound: a neighbour exactly at it counts, one beyond it is +inf
    np.testing.assert_array_equal(
        nearest_distance_mm(points, targets, within_mm=math.sqrt(3)), [0.0, np.inf, math.sqrt(3)]
    )
    np.testing.assert_array_equal(nearest_distance_mm(points, targets, 0.0), [0.0, np.inf, np.inf])
    with pytest.raises(UltronError, match="within_mm"):
        nearest_distance_mm(points, targets, within_mm=math.nan)


def test_nearest_distance_is_brute_force_on_clustered_points() -> None:
    """Clustered targets (as labelled echoes are) against scattered points: the exact minimum
    over every pair, with and without a bound at an exact pair distance."""
    rng = np.random.default_rng(5)
    centres = rng.uniform(-20, 20, (6, 3))
    targets = (centres[:, None] + rng.normal(0, 0.5, (6, 200, 3))).reshape(-1, 3)
    points = rng.uniform(-25, 25, (500, 3))
    pairwise = np.sqrt(((points[:, None] - targets[None]) ** 2).sum(-1))
    exact = pairwise.min(axis=1)
    np.testing.assert_allclose(nearest_distance_mm(points, targets), exact, rtol=1e-12)
    bound = float(np.median(exact))
    bounded = nearest_distance_mm(points, targets, within_mm=bound)
    np.testing.assert_array_equal(bounded <= bound, exact <= bound)
    np.testing.assert_allclose(bounded[exact <= bound], exact[exact <= bound], rtol=1e-12)
    assert np.isinf(bounded[exact > bound]).all()


def test_surface_evidence_summary_and_attributes() -> None:
    vertices = np.array([[0.0, 0, 0], [0, 0, 2], [0, 0, 4], [0, 0, 10]])
    evidence = surface_evidence(vertices, np.array([True, True, False, False]), vertices[:1])
    np.testing.assert_allclose(evidence.label_distance_mm, [0.0, 2.0, 4.0, 10.0])
    summary = evidence.summary()
    assert summary["vertices"] == 4 and summary["observed_share"] == 0.5
    assert summary["label_distance_mm"]["median"] == 3.0
    assert summary["label_distance_mm"]["max"] == 10.0
    assert summary["vertices_beyond_mm"] == {"2": 2, "3": 2}  # 4 and 10 mm; 2 mm is not beyond
    attributes = evidence.vertex_attributes()
    assert attributes["observed"].dtype == np.uint8 and attributes["observed"].tolist() == [
        1, 1, 0, 0
    ]  # fmt: skip
    assert attributes["label_distance_mm"].dtype == np.float32
    no_labels = surface_evidence(vertices, np.zeros(4, bool), np.zeros((0, 3))).summary()
    assert no_labels["label_distance_mm"] is None and no_labels["observed_share"] == 0.0
    assert no_labels["vertices_beyond_mm"] is None
    with pytest.raises(UltronError, match="observed"):
        surface_evidence(vertices, np.zeros(3, bool), vertices)
    with pytest.raises(UltronError, match="label_distance_mm"):
        SurfaceEvidence(np.zeros(4, bool), np.zeros(3))


# ------------------------------------------------------------------------ mesh coordinates
@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
@pytest.mark.parametrize("space", MESH_COORDINATES)
def test_mesh_files_say_their_space_and_load_back_in_world(tmp_path: Path, suffix, space):
    mesh = _sphere()
    mesh.apply_translation([10.0, 5.0, -20.0])
    path = save_mesh(mesh, tmp_path / f"m{suffix}", space)
    assert mesh_file_space(path) == space
    head = path.read_bytes()[:200]
    assert f"SPACE={space.upper()}".encode() in head  # where 3D Slicer reads it
    if space == "ras":  # x and y negated in the file
        raw = trimesh.load(path, force="mesh", process=False)
        np.testing.assert_allclose(raw.bounds[:, :2], -mesh.bounds[::-1, :2], atol=1e-4)
    loaded = load_mesh(path)
    np.testing.assert_allclose(loaded.bounds, mesh.bounds, atol=1e-4)
    assert loaded.volume > 0  # a rotation: outward normals stay outward
    np.testing.assert_allclose(loaded.volume, mesh.volume, rtol=1e-4)


def test_ply_vertex_properties_round_trip(tmp_path: Path) -> None:
    mesh = _sphere()
    flags = (mesh.vertices[:, 1] < 12).astype(np.uint8)
    path = save_mesh(mesh, tmp_path / "m.ply", "ras", {"observed": flags})
    properties = load_vertex_properties(path)
    np.testing.assert_array_equal(properties["observed"], flags)
    with pytest.raises(UltronError, match="vertex_attributes"):
        save_mesh(mesh, tmp_path / "n.ply", "lps", {"observed": flags[:-1]})
    with pytest.raises(UltronError, match="coordinates"):
        save_mesh(mesh, tmp_path / "n.ply", "xyz")


# ------------------------------------------------------------------------ end to end
def _as_slicer_ras(path: Path) -> np.ndarray:
    """The vertices of a mesh file in RAS, as 3D Slicer places them (its SPACE tag)."""
    raw = np.asarray(trimesh.load(path, force="mesh", process=False).vertices, np.float64)
    return raw if mesh_file_space(path) == "ras" else raw * [-1.0, -1.0, 1.0]


@pytest.mark.parametrize("space", MESH_COORDINATES)
def test_mesh_vertices_land_on_the_occupied_boundary_of_the_nifti(tiny_l3: Path, tmp_path, space):
    request = ReconstructionRequest(
        method="compounding", label_fraction=1.0, metrics=FAST_METRICS, mesh_coordinates=space
    )
    out = tmp_path / "out"
    reconstruct(tiny_l3, request, out, report=False)
    image = nib.load(out / "occupancy.nii.gz")
    volume = np.asarray(image.get_fdata(), dtype=np.float32)
    ras = _as_slicer_ras(out / "mesh.ply")
    ijk = (np.linalg.inv(image.affine) @ np.c_[ras, np.ones(len(ras))].T)[:3]
    assert (ijk > -0.5).all() and (ijk.T < np.array(volume.shape) - 0.5).all()
    # each vertex sits on the iso-surface (of the smoothed volume): a voxel ≥ ½ and one < ½
    # among the 3 × 3 × 3 voxels around it
    around = np.stack([np.rint(ijk) + np.array(o)[:, None] - 1
                       for o in np.ndindex(3, 3, 3)])  # fmt: skip
    values = np.stack([map_coordinates(volume, c, order=0, mode="nearest") for c in around])
    assert (values.max(axis=0) >= 0.5).all()
    assert (values.min(axis=0) < 0.5).all()
    # the wrong convention would put the mesh far off the occupied voxels
    wrong = ras * [-1.0, -1.0, 1.0]
    wrong_ijk = (np.linalg.inv(image.affine) @ np.c_[wrong, np.ones(len(wrong))].T)[:3]
    hit = map_coordinates(volume, wrong_ijk, order=1, mode="constant", cval=0.0)
    assert (hit >= 0.5).mean() < 0.5


def test_reconstruction_writes_per_vertex_evidence(tiny_l3: Path, tmp_path: Path) -> None:
    request = ReconstructionRequest(method="compounding", label_fraction=0.5, metrics=FAST_METRICS)
    reconstruct(tiny_l3, request, tmp_path / "out")
    out = tmp_path / "out"
    run = json.loads((out / "run.json").read_text())
    mesh_props = load_vertex_properties(out / "mesh.ply")
    assert mesh_props["observed"].all()  # the observed crop keeps observed vertices only
    assert (out / EXTRACTED_MESH).is_file()  # so the whole iso-surface is written beside it
    whole = load_vertex_properties(out / EXTRACTED_MESH)
    assert 0 < whole["observed"].mean() < 1
    assert run["surface_evidence"]["extracted"]["observed_share"] == pytest.approx(
        float(whole["observed"].mean())
    )
    assert np.isfinite(mesh_props["label_distance_mm"]).all()
    # the bone labels used lie on the compounded surface: most vertices within a few mm
    assert np.median(mesh_props["label_distance_mm"]) < 2.0
    assert run["mesh"]["coordinates"] == "lps"
    html = (out / "report.html").read_text()
    assert 'data-kind="evidence"' in html and "inferred" in html


def test_all_surface_writes_no_extracted_copy(tiny_l3: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "all"
    result = runner.invoke(app, ["reconstruct", str(tiny_l3), "--method", "on", "--out", str(out),
                                 "--occupancy-iters", "30", "--points", "2000",
                                 "--mesh-coordinates", "ras"])  # fmt: skip
    assert result.exit_code == 0, result.output
    # off a terminal every stage says when it starts and what it took (issue 31: no minutes of
    # silence in a log)
    for stage in ("load", "occupancy_fit", "mesh_evaluate", "mesh_extract", "metrics", "report"):
        assert f"{stage} …" in result.output and f"{stage}: " in result.output, stage
    assert not (out / EXTRACTED_MESH).exists()
    assert mesh_file_space(out / "mesh.ply") == "ras"
    flags = load_vertex_properties(out / "mesh.ply")["observed"]
    assert flags.shape == (len(load_mesh(out / "mesh.ply").vertices),)
    bad = runner.invoke(app, ["reconstruct", str(tiny_l3), "--method", "compounding", "--out",
                              str(tmp_path / "bad"), "--mesh-coordinates", "xyz"])  # fmt: skip
    assert bad.exit_code == 2
    assert "--mesh-coordinates" in bad.output and "Traceback" not in bad.output
    assert not (tmp_path / "bad").exists()


def test_surface_places_hand_worked() -> None:
    """Two frames 1 mm apart in elevation, 1 mm pixels: pixel (r, c) lies at (c − 2, r, 0)."""
    probe = ProbeGeometry(width_mm=4.0, depth_mm=5.0, height_px=5, width_px=4)
    near = np.full((5, 4), 255, dtype=np.uint8)
    near[:, 1] = [0, 255, 1, 1, 255]  # background, unsure, a band of two, unsure beneath
    far = np.ones((5, 4), dtype=np.uint8)
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 2, 3] = 1.0
    vertices = np.array([
        [-2.0, 2.0, 0.0],  # column 0 has no band
        [-1.0, 0.0, 0.0],  # background
        [-1.0, 1.2, 0.0],  # unsure, the band below it: tissue above the echo
        [-1.0, 2.0, 0.0],  # bone
        [-1.0, 3.6, 0.0],  # rounds to row 4: unsure under the band, in its shadow
        [-1.0, 1.0, 0.4],  # elevation 0.4 from the near frame, 0.6 from the far one
        [-1.0, 1.0, 0.8],  # 0.2 from the far frame: its bone label
        [-1.0, 1.0, -0.6],  # outside both slabs
        [3.0, 1.0, 0.0],  # outside the image laterally
    ])  # fmt: skip
    places = surface_places(vertices, poses, probe, np.stack([near, far]), 0.5)
    names = [SURFACE_PLACES[i] for i in places]
    assert names == [
        "no_band", "background_label", "above_band", "bone_label", "below_band",
        "above_band", "bone_label", "between_frames", "between_frames",
    ]  # fmt: skip
    # a rotated, translated frame gives the same answers for the same probe points
    turn = np.array([[0.0, -1, 0, 5], [1, 0, 0, -3], [0, 0, 1, 2], [0, 0, 0, 1]])
    moved = vertices @ turn[:3, :3].T + turn[:3, 3]
    assert np.array_equal(
        surface_places(moved, turn @ poses, probe, np.stack([near, far]), 0.5), places
    )


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"vertices_mm": np.zeros((3, 2))}, "vertices_mm"),
        ({"vertices_mm": np.full((3, 3), np.nan)}, "vertices_mm"),
        ({"probe_to_world": np.eye(4)}, "probe_to_world"),
        ({"probe_to_world": np.full((1, 4, 4), np.inf)}, "probe_to_world"),
        ({"labels": np.zeros((1, 5, 4), dtype=np.int32)}, "labels"),
        ({"labels": np.full((1, 5, 4), 7, dtype=np.uint8)}, "labels"),
        ({"slab_half_thickness_mm": -1.0}, "slab_half_thickness_mm"),
    ],
)
def test_surface_places_rejects_bad_input(change: dict, name: str) -> None:
    probe = ProbeGeometry(width_mm=4.0, depth_mm=5.0, height_px=5, width_px=4)
    args = {
        "vertices_mm": np.tile([0.0, 1.0, 0.0], (3, 1)),
        "probe_to_world": np.eye(4)[None],
        "probe": probe,
        "labels": np.zeros((1, 5, 4), dtype=np.uint8),
        "slab_half_thickness_mm": 0.5,
    }
    with pytest.raises(UltronError, match=name):
        surface_places(**{**args, **change})
