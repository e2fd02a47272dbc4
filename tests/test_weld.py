"""Meshes as written: coincident vertices merged, faces without area dropped; and the metrics'
surface, which is the triangles of positive area."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ultron.errors import UltronInputError
from ultron.mesh.evidence import SurfaceEvidence
from ultron.mesh.export import load_mesh
from ultron.mesh.extract import weld_coincident
from ultron.metrics.surface import MetricsConfig, evaluate_meshes, point_to_surface_distances
from ultron.pipeline.evaluate import evaluate_files
from ultron.pipeline.run import EXTRACTED_MESH, ReconstructionRequest, reconstruct


def _mesh_with_copies() -> trimesh.Trimesh:
    """Vertices 3 and 4 copy 1 and 2; 6 is used only by a face without area. Faces: a
    triangle (0, 1, 2); a sliver between copies (1, 3, 4); a segment (0, 4, 4); three
    collinear corners (0, 5, 1); a triangle through a copy (0, 4, 5); a point and a corner
    (6, 6, 2)."""
    vertices = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 0, 0], [1, 1, 0], [0.5, 0, 0], [5, 5, 5]],
        dtype=np.float64,
    )
    faces = np.array([[0, 1, 2], [1, 3, 4], [0, 4, 4], [0, 5, 1], [0, 4, 5], [6, 6, 2]])
    return trimesh.Trimesh(vertices, faces, process=False)


def test_weld_merges_copies_and_drops_the_faces_without_area():
    mesh = _mesh_with_copies()
    welded, new_index = weld_coincident(mesh)
    # merged in the order of their first copy; 6 is dropped, no face with area uses it
    np.testing.assert_array_equal(new_index, [0, 1, 2, 1, 2, 3, -1])
    np.testing.assert_array_equal(welded.vertices, mesh.vertices[[0, 1, 2, 5]])
    # faces 0 and 4 keep their order and winding, 1 (a sliver), 2 (a segment), 3 (collinear)
    # and 5 (a point and a corner) go
    np.testing.assert_array_equal(welded.faces, [[0, 1, 2], [0, 2, 3]])
    assert welded.area == mesh.area  # every face with area kept, to the bit
    again, identity = weld_coincident(welded)  # idempotent
    np.testing.assert_array_equal(again.faces, welded.faces)
    np.testing.assert_array_equal(identity, np.arange(len(welded.vertices)))


def test_merged_evidence_is_observed_where_any_copy_is():
    evidence = SurfaceEvidence(
        np.array([False, True, False, False, True, False, True]),
        np.array([0.5, 1.0, 2.0, 1.0, 2.0, 0.25, 9.0]),
    )
    merged = evidence.merged(np.array([0, 1, 2, 1, 2, 3, -1]), 4)
    np.testing.assert_array_equal(merged.observed, [False, True, True, False])
    np.testing.assert_array_equal(merged.label_distance_mm, [0.5, 1.0, 2.0, 0.25])
    with pytest.raises(UltronInputError, match="new_index"):
        evidence.merged(np.zeros(3, dtype=np.int64), 4)


def test_a_segment_is_not_surface_for_the_distances():
    """A reference point beside a zero-area face is as far from the mesh as without that face:
    the face is a segment from (1, 0, 0) to (1, 0, 3) in the plane x = 1."""
    square = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 1, 2]], process=False)
    with_segment = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 0, 3], [1, 0, 3]],
        [[0, 1, 2], [1, 3, 4]],
        process=False,
    )
    point = np.array([[1.0, 0.0, 2.0]])  # on the segment, 2 mm above the triangle's corner
    np.testing.assert_allclose(point_to_surface_distances(point, with_segment), [2.0])
    np.testing.assert_allclose(point_to_surface_distances(point, square), [2.0])
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(UltronInputError, match="positive area"):
        point_to_surface_distances(point, flat)


def test_metrics_do_not_change_when_a_mesh_is_welded():
    reference = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    mesh = _mesh_with_copies()
    mesh = trimesh.Trimesh(mesh.vertices * 8.0 - [4.0, 4.0, 9.0], mesh.faces, process=False)
    config = MetricsConfig(n_points=2000, repeats=2)
    whole = evaluate_meshes(mesh, reference, config, reference_visible=reference)
    welded = evaluate_meshes(weld_coincident(mesh)[0], reference, config, reference)
    assert whole["mean"] == welded["mean"]


def test_a_run_writes_welded_meshes_and_describes_them(tiny_l3: Path, tmp_path: Path):
    request = ReconstructionRequest(
        method="compounding", label_fraction=0.5, metrics=MetricsConfig(n_points=3000, repeats=1)
    )
    out = tmp_path / "out"
    reconstruct(tiny_l3, request, out, report=False)
    run = json.loads((out / "run.json").read_text())
    for name in ("mesh.ply", "mesh.obj", EXTRACTED_MESH):  # STL holds no shared vertices
        mesh = load_mesh(out / name)
        assert len(np.unique(mesh.vertices, axis=0)) == len(mesh.vertices), name
        assert (mesh.area_faces > 0).all(), name
    written = load_mesh(out / "mesh.ply")
    assert len(load_mesh(out / "mesh.stl").faces) == len(written.faces)
    assert run["mesh"]["vertices"] == len(written.vertices)
    assert run["mesh"]["faces"] == len(written.faces)
    assert run["surface_evidence"]["mesh"]["vertices"] == len(written.vertices)
    # the run's metrics are those of the file it wrote (whose PLY coordinates are float32)
    metrics = json.loads((out / "metrics.json").read_text())
    again = evaluate_files(out / "mesh.ply", tiny_l3 / "reference.ply", MetricsConfig(3000, 1),
                           tiny_l3 / "reference_visible.ply", out=tmp_path / "again.json")  # fmt: skip
    assert again.result["mean"] == pytest.approx(metrics["mean"], rel=1e-5)


def test_equal_rows_are_numpys_unique_rows():
    from ultron.mesh.extract import _equal_rows

    points = np.random.default_rng(1).integers(0, 4, size=(5000, 3)).astype(np.float64)
    first, inverse = _equal_rows(points)
    _, numpy_first, numpy_inverse = np.unique(
        points, axis=0, return_index=True, return_inverse=True
    )
    np.testing.assert_array_equal(first, numpy_first)
    np.testing.assert_array_equal(inverse, numpy_inverse.reshape(-1))
