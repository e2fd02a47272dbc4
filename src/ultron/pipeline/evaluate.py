"""``evaluate``: surface metrics of a mesh file against a reference mesh file.

The metrics themselves are :func:`ultron.metrics.surface.evaluate_meshes`; this module runs them
on files in the order that refuses bad input before any work (the output name, the crop's
reference, then the meshes), warns when the two meshes do not share a region (a mesh in other
units or another frame), and writes the result atomically.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ultron import atomic
from ultron.data.units import box_mismatch
from ultron.errors import UltronInputError, argument_error
from ultron.mesh.export import load_mesh
from ultron.metrics.surface import MetricsConfig, evaluate_meshes
from ultron.outputs import check_output_file, is_inside


@dataclass(frozen=True)
class EvaluatedMesh:
    """What :func:`evaluate_files` measured (``result``: the metrics' JSON document, with the
    three paths) and where it wrote it."""

    result: dict[str, Any]
    out: Path

    def crop_line(self) -> str | None:
        """The line saying what the crop kept (None without a crop)."""
        crop = self.result["crop"]
        if crop is None:
            return None
        return (
            f"cropped to {crop['crop_mm']:g} mm of the visible reference: kept"
            f" {crop['area_kept_mm2']:.0f} of {crop['area_mm2']:.0f} mm²"
            f" ({crop['area_outside_mm2']:.0f} mm² outside, not measured)"
        )


def default_metrics_path(mesh: str | Path) -> Path:
    """Where ``evaluate`` writes by default: MESH with ``.metrics.json``."""
    mesh = Path(mesh)
    return mesh.with_name(mesh.stem + ".metrics.json")


def _check_replaces_only_metrics(target: Path) -> None:
    """Refuse an existing ``target`` that is not an earlier ``evaluate`` result (a JSON object
    naming its ``mesh`` and ``reference``): a dataset's, a field's or a run's file, or any
    other, which the metrics would replace."""
    if not target.exists():
        return
    try:
        earlier = json.loads(target.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        earlier = None
    if not (isinstance(earlier, dict) and {"mesh", "reference"} <= earlier.keys()):
        raise UltronInputError(
            target, "--out", "exists and is not an earlier evaluate result: the metrics would"
            " replace it; write them to another file (default: MESH with .metrics.json)",
        )  # fmt: skip


def evaluate_files(
    mesh: str | Path,
    reference: str | Path,
    config: MetricsConfig,
    reference_visible: str | Path | None = None,
    out: str | Path | None = None,
    warn: Callable[[str], None] | None = None,
) -> EvaluatedMesh:
    """Measure the mesh file ``mesh`` against ``reference`` (and, when given, the visible part
    ``reference_visible``, which ``config.crop_mm`` needs) and write the result as JSON to
    ``out`` (default :func:`default_metrics_path`). ``warn`` receives a line when the two
    meshes' bounding boxes do not overlap as one region. Errors name the file or argument."""
    if config.crop_mm is not None and reference_visible is None:
        raise argument_error("--crop-mm", "needs --reference-visible (the surface to crop to)")
    target = check_output_file(out or default_metrics_path(mesh), "--out")
    inputs = {"MESH": mesh, "REFERENCE": reference, "--reference-visible": reference_visible}
    for name, given in inputs.items():
        if given is not None and Path(given).exists() and is_inside(target, given):
            raise UltronInputError(
                target, "--out", f"is {name}, an input: the metrics would replace it; write them"
                " to another file (default: MESH with .metrics.json)",
            )  # fmt: skip
    _check_replaces_only_metrics(target)
    mesh, reference = Path(mesh), Path(reference)
    recon = load_mesh(mesh, allow_empty=True)
    ref = load_mesh(reference)
    visible = None if reference_visible is None else load_mesh(reference_visible)
    if len(recon.vertices) and warn is not None:
        mismatch = box_mismatch(recon.bounds, ref.bounds, f"the mesh {mesh}", "the reference")
        if mismatch is not None:
            warn(mismatch)
    result = evaluate_meshes(recon, ref, config, reference_visible=visible)
    result["mesh"], result["reference"] = str(mesh), str(reference)
    result["reference_visible"] = None if reference_visible is None else str(reference_visible)
    atomic.write_json(target, result)
    return EvaluatedMesh(result, target)
