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
