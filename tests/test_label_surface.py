"""Label fusion's second half: the compounded labels' own kept surface added where UltrON's kept
surface lacks it (:func:`ultron.mesh.label_fusion.add_label_surface`), on hand-built squares."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ultron.errors import UltronInputError
from ultron.mesh.label_fusion import SURFACE_GAP_MM, LabelFusionConfig, add_label_surface
from ultron.mesh.observed import SurfaceObservation


def _square(z: float, x0: float = 0.0, side: float = 2.0) -> trimesh.Trimesh:
    """A side × side square in the plane z, two triangles, from (x0, 0)."""
    vertices = np.array(
        [[x0, 0, z], [x0 + side, 0, z], [x0 + side, side, z], [x0, side, z]], dtype=float
    )
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


def _kept_all(mesh: trimesh.Trimesh, observed: np.ndarray | None = None) -> SurfaceObservation:
    """An observation that kept all of ``mesh`` (``observed``: per vertex, default all)."""
    flags = np.ones(len(mesh.vertices), bool) if observed is None else observed
    info = {"faces_extracted": len(mesh.faces), "faces_kept": len(mesh.faces)}
    return SurfaceObservation(mesh, flags, mesh, np.arange(len(mesh.vertices)), info)


def _cropped(mesh: trimesh.Trimesh, keep_face: int) -> SurfaceObservation:
    """An observation of ``mesh`` that kept only face ``keep_face`` (its vertices observed)."""
    face = mesh.faces[keep_face]
    kept = trimesh.Trimesh(mesh.vertices[face], [[0, 1, 2]], process=False)
    observed = np.isin(np.arange(len(mesh.vertices)), face)
    info = {"faces_extracted": len(mesh.faces), "faces_kept": 1}
    return SurfaceObservation(mesh, observed, kept, face.astype(np.int64), info)


def test_only_the_faces_farther_than_the_gap_are_added():
    """UltrON kept a square at z = 0; the labels' surface holds the same square, one 0.5 mm
    above it and one 5 mm above it: only the far square (2 faces, 4 mm²) is added."""
    kept = _kept_all(_square(0.0))
    labels_mesh = trimesh.util.concatenate([_square(0.0), _square(0.5), _square(5.0)])
    joined, account = add_label_surface(kept, _kept_all(labels_mesh), 1.0)
    assert account == {"label_surface_faces_added": 2, "label_surface_area_added_mm2": 4.0}
    assert len(joined.kept.faces) == 4 and len(joined.extracted.faces) == 4
    assert np.allclose(joined.kept.vertices[4:, 2], 5.0)  # the far square, appended
    assert joined.info == {"faces_extracted": 4, "faces_kept": 4}
    # every kept vertex indexes its own position in the extracted surface
    assert np.array_equal(joined.extracted.vertices[joined.kept_vertices], joined.kept.vertices)


def test_a_near_surface_adds_nothing_and_returns_the_observation_itself():
    kept = _kept_all(_square(0.0))
    joined, account = add_label_surface(kept, _kept_all(_square(0.9)), 1.0)
    assert joined is kept
    assert account == {"label_surface_faces_added": 0, "label_surface_area_added_mm2": 0.0}


def test_the_added_vertices_keep_the_labels_own_observation():
    """The labels' surface kept one of its two triangles; only that triangle is added, and its
    vertices carry the labels' observed flags (all observed), after UltrON's own (one of its
    three extracted vertices unobserved)."""
    ours = _square(0.0)
    kept = _cropped(ours, 0)
    labels = _cropped(_square(3.0, x0=10.0), 1)
    joined, account = add_label_surface(kept, labels, SURFACE_GAP_MM)
    assert account["label_surface_faces_added"] == 1
    assert len(joined.extracted.vertices) == 4 + 3
    assert list(joined.observed) == [True, True, True, False, True, True, True]
    assert joined.kept_observed.all()
    assert np.array_equal(joined.extracted.vertices[joined.kept_vertices], joined.kept.vertices)
    assert joined.cropped  # UltrON's own second triangle is still cropped


def test_beside_no_kept_surface_every_label_face_is_added():
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    kept = SurfaceObservation(empty, np.zeros(0, bool), empty, np.zeros(0, np.int64), {})
    joined, account = add_label_surface(kept, _kept_all(_square(0.0)), 1.0)
    assert account["label_surface_faces_added"] == 2 and len(joined.kept.faces) == 2


@pytest.mark.parametrize("gap", [0, -1.0, "1", None, True])
def test_add_label_surface_refuses_a_gap_that_is_not_a_positive_distance(gap):
    kept = _kept_all(_square(0.0))
    with pytest.raises(UltronInputError, match="gap_mm"):
        add_label_surface(kept, kept, gap)


def test_add_label_surface_refuses_what_is_not_an_observation():
    kept = _kept_all(_square(0.0))
    with pytest.raises(UltronInputError, match="labels"):
        add_label_surface(kept, _square(1.0), 1.0)
    with pytest.raises(UltronInputError, match="kept"):
        add_label_surface(_square(1.0), kept, 1.0)


@pytest.mark.parametrize("gap", [0.0, -0.5, float("inf"), float("nan"), "1", True])
def test_fusion_config_refuses_a_gap_that_is_not_a_positive_distance(gap):
    with pytest.raises(UltronInputError, match="surface_gap_mm"):
        LabelFusionConfig(surface_gap_mm=gap)
    assert LabelFusionConfig(surface_gap_mm=None).surface_gap_mm is None
    assert LabelFusionConfig().surface_gap_mm == SURFACE_GAP_MM == 1.0
