"""Warnings for lengths that cannot be millimetres: poses in metres, a reference mesh in other
units or far from the scanned region."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from conftest import make_pose, rotation_z
from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.units import box_mismatch, path_warnings, units_warnings

PROBE = ProbeGeometry(40.0, 30.0, 16, 12)


def _dataset(origins_mm: np.ndarray, degrees: np.ndarray | None = None) -> SweepDataset:
    n = len(origins_mm)
    degrees = np.zeros(n) if degrees is None else degrees
    poses = np.stack(
        [make_pose(rotation_z(d), o) for d, o in zip(degrees, origins_mm, strict=True)]
    )
    images = np.zeros((n, 16, 12), np.uint8)
    return SweepDataset(PROBE, [Sweep("row", "row", images, poses)])


def test_a_path_recorded_in_metres_is_flagged_and_one_in_millimetres_is_not() -> None:
    path_mm = np.stack([np.linspace(0, 50, 20), np.zeros(20), np.zeros(20)], axis=1)
    assert path_warnings(_dataset(path_mm)) == []
    (line,) = path_warnings(_dataset(path_mm / 1000))
    assert "sweep row" in line and "0.05 mm" in line and "metres" in line
    # a tilt about the transducer face moves its origin little but more than 0.4 mm
    tilt = np.stack([np.zeros(20), np.linspace(0, 1.5, 20), np.zeros(20)], axis=1)
    assert path_warnings(_dataset(tilt, np.linspace(-20, 20, 20))) == []
    assert path_warnings(_dataset(path_mm[:5] / 1000)) == []  # too few frames to judge


def test_boxes_that_cannot_be_one_object_in_one_unit_are_flagged() -> None:
    box = np.array([[0.0, 0.0, 0.0], [40.0, 30.0, 60.0]])
    assert box_mismatch(box, box + 5.0, "a", "b") is None
    scaled = box_mismatch(box / 1000, box, "the reference", "the scanned region")
    assert scaled is not None and "1000×" in scaled and "millimetres" in scaled
    far = box_mismatch(box + 5000.0, box, "the reference", "the scanned region")
    assert far is not None and "lies 8.59e+03 mm away" in far  # |(4960, 4970, 4940)|


def test_a_reference_in_metres_is_flagged_against_the_scanned_region() -> None:
    path_mm = np.stack([np.linspace(0, 50, 20), np.zeros(20), np.zeros(20)], axis=1)
    dataset = _dataset(path_mm)
    bone = trimesh.creation.box(extents=(30.0, 10.0, 10.0))
    bone.apply_translation((25.0, 10.0, 0.0))
    assert units_warnings(dataset, bone.vertices) == []
    (line,) = units_warnings(dataset, bone.vertices / 1000)
    assert line.startswith("the reference is")


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_evaluate_warns_when_mesh_and_reference_differ_in_units(tmp_path: Path, scale: float):
    box = trimesh.creation.box(extents=(30.0, 10.0, 10.0))
    box.export(tmp_path / "mesh.ply")
    box.apply_scale(scale)
    box.export(tmp_path / "reference.ply")
    args = ["evaluate", str(tmp_path / "mesh.ply"), str(tmp_path / "reference.ply")]
    result = CliRunner().invoke(app, [*args, "--points", "2000", "--repeats", "1"])
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == (1 if scale != 1.0 else 0), warnings
