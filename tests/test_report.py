"""HTML reports: a tiny simulated run → run report and benchmark report; figure input checks."""

from __future__ import annotations

import base64
import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.mesh.export import load_mesh, save_mesh
from ultron.pipeline.record import RunRecord
from ultron.report import write_benchmark_report, write_run_report
from ultron.report.figures import (
    frames_figure,
    label_masks_figure,
    loss_curves_figure,
    mesh_distance_figure,
)
from ultron.report.html import PNG_SIGNATURE, image_html, markdown_table_html, table_html
from ultron.report.sections import final_loss_rows, metrics_html, run_loss_curves

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source",
        "track", "wbr"}  # fmt: skip


class _Checker(HTMLParser):
    """Records the doctype, <img> sources, <figure> attributes; checks that tags balance."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.doctype = ""
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.images: list[str] = []
        self.figures: list[dict[str, str]] = []
        self.tags: set[str] = set()

    def handle_decl(self, decl: str) -> None:
        self.doctype = decl

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        attributes = {k: v or "" for k, v in attrs}
        if tag == "img":
            self.images.append(attributes.get("src", ""))
        if tag == "figure":
            self.figures.append(attributes)
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()


def check_html(text: str) -> _Checker:
    """Parse ``text``; assert valid structure and that it is self-contained."""
    checker = _Checker()
    checker.feed(text)
    checker.close()
    assert checker.doctype.lower() == "doctype html"
    assert not checker.errors, checker.errors
    assert not checker.stack, f"unclosed tags: {checker.stack}"
    assert {"html", "head", "meta", "title", "body"} <= checker.tags
    assert re.search(r'<html lang="[a-z]+">', text) and '<meta charset="utf-8">' in text
    assert not re.search(r'(src|href)\s*=\s*"(https?:)?//', text)
    assert "<script" not in text and "<link" not in text
    for src in checker.images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == PNG_SIGNATURE
    return checker


def kinds(checker: _Checker) -> list[str]:
    return [f.get("data-kind", "") for f in checker.figures]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> dict[str, Path]:
    """A tiny L3 dataset (row + column sweeps, 12 frames of 64 × 48), a 4-step field and a
    compounding run whose run.json names them (dataset_dir, field_dir)."""
    from ultron.metrics.surface import MetricsConfig
    from ultron.phantom import SimulationConfig, simulate_dataset
    from ultron.phantom.protocols import ScanConfig
    from ultron.pipeline.run import ReconstructionRequest, reconstruct
    from ultron.train.field_fit import FieldTrainConfig, fit_field

    root = tmp_path_factory.mktemp("report")
    config = SimulationConfig(
        sweeps=("row", "column"), scan=ScanConfig(frames_per_sweep=12), height_px=64, width_px=48
    )
    simulate_dataset(config, out=root / "dataset")
    dataset = SweepDataset.load(root / "dataset")
    fit_field(
        dataset,
        FieldTrainConfig(iterations=4, check_every=1000, checkpoint_every=1000, log_every=1),
        root / "field",
    )
    request = ReconstructionRequest(
        method="compounding", label_fraction=0.5, metrics=MetricsConfig(n_points=2000, repeats=1)
    )
    reconstruct(root / "dataset", request, root / "run")
    run = json.loads((root / "run" / "run.json").read_text())
    run.setdefault("dataset_dir", str(root / "dataset"))
    run["field_dir"] = str(root / "field")
    (root / "run" / "run.json").write_text(json.dumps(run))
    return {"root": root, "dataset": root / "dataset", "field": root / "field", "run": root / "run"}


def test_run_report_is_valid_self_contained_html(tiny_run):
    path = write_run_report(tiny_run["run"])
    assert path == tiny_run["run"] / "report.html"
    assert not list(tiny_run["run"].glob(".*.tmp"))
    text = path.read_text(encoding="utf-8")
    checker = check_html(text)
    # one image per section: mesh vs reference, observed vs inferred surface, frames with
    # θ / T maps, label masks, losses
    assert sorted(kinds(checker)) == ["evidence", "frames", "labels", "losses", "mesh"]
    assert len(checker.images) == 5
    assert "surface_extracted.ply" in text and "label_distance_mm" in text
    metrics = json.loads((tiny_run["run"] / "metrics.json").read_text())
    assert f"{metrics['mean']['mad']:.3f}" in text and ">MAD<" in text
    # the simulated dataset's visible reference: the visible figures are measured and shown
    assert metrics["mean"]["cd_visible"] is not None and ">CD vis.<" in text
    assert f"{metrics['mean']['cd_visible']:.3f}" in text and "one-sided" in text
    assert "compounding" in text and "Timings" in text and "peak memory" in text
    assert "acoustic field" in text  # the field's train log is a loss curve


def test_run_report_without_dataset_dir_skips_dataset_sections(tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    for name in ("mesh.ply", "metrics.json"):
        shutil.copy(tiny_run["run"] / name, run_dir / name)
    run = json.loads((tiny_run["run"] / "run.json").read_text())
    run.pop("dataset_dir")
    run.pop("field_dir")
    (run_dir / "run.json").write_text(json.dumps(run))
    text = write_run_report(run_dir).read_text(encoding="utf-8")
    checker = check_html(text)
    # mesh.ply alone: the evidence figure shows it (its vertex properties)
    assert kinds(checker) == ["mesh", "evidence"]
    assert "no dataset_dir" in text and "No training logs" in text

    dataset = SweepDataset.load(tiny_run["dataset"])  # given explicitly: B-mode frames only
    checker = check_html(write_run_report(run_dir, dataset=dataset).read_text(encoding="utf-8"))
    assert sorted(kinds(checker)) == ["evidence", "frames", "labels", "mesh"]

    # a mesh written without the evidence (an older ultron): the section says so
    save_mesh(load_mesh(run_dir / "mesh.ply"), run_dir / "mesh.ply")
    text = write_run_report(run_dir).read_text(encoding="utf-8")
    assert kinds(check_html(text)) == ["mesh"] and "no per-vertex evidence" in text


def test_run_report_rejects_bad_input(tmp_path):
    with pytest.raises(UltronInputError, match="run_dir"):
        write_run_report(tmp_path / "missing")
    with pytest.raises(UltronInputError, match=r"run.json"):
        write_run_report(tmp_path)
    (tmp_path / "run.json").write_text("{}")
    with pytest.raises(UltronInputError, match="dataset"):
        write_run_report(tmp_path, dataset="not a dataset")


def _bench_cell(cell_id: str, row: str, run_dir: str, status: str = "ok") -> dict:
    error = None if status == "ok" else "boom"
    return {
        **{"id": cell_id, "table": "table1", "row": row, "phantom": "L3", "seed": 0},
        **{"run_dir": run_dir, "status": status, "error": error},
    }


def test_benchmark_report_has_one_mesh_per_method(tiny_run, tmp_path):
    bench = tmp_path / "bench"
    for name, method in (("comp", "compounding"), ("ultron-a", "ultron"), ("ultron-b", "ultron")):
        skip = shutil.ignore_patterns("*.stl", "*.obj", "*.nii.gz", "report.html")
        shutil.copytree(tiny_run["run"], bench / "runs" / name, ignore=skip)
        run = json.loads((bench / "runs" / name / "run.json").read_text())
        run["method"] = method
        run["occupancy_log"] = [{"step": s, "loss": 1.0 / (s + 1)} for s in range(0, 100, 10)]
        if method != "ultron":
            run.pop("field_dir")
        (bench / "runs" / name / "run.json").write_text(json.dumps(run))
    markdown = "| method | CD |\n|---|---:|\n| UltrON | 1.00 ± 0.10 |\n| Compounding <x> | 2.00 |"
    benchmark = {
        "config": {"phantoms": ["L3"]},
        "markdown": {"table1": markdown},
        "targets": [{"name": "UltrON beats compounding", "met": True, "detail": "1.0 < 2.0"}],
        "cells": [
            _bench_cell("a", "Compounding", "runs/comp"),
            _bench_cell("b", "UltrON", "runs/missing", status="failed"),
            _bench_cell("c", "UltrON", "runs/ultron-a"),
            _bench_cell("d", "UltrON", "runs/ultron-b"),
        ],
    }
    (bench / "benchmark.json").write_text(json.dumps(benchmark))
    text = write_benchmark_report(bench).read_text(encoding="utf-8")
    checker = check_html(text)
    meshes = [f for f in checker.figures if f.get("data-kind") == "mesh"]
    assert sorted(f["data-method"] for f in meshes) == ["Compounding", "UltrON"]
    assert {f["data-method"]: f["data-cell"] for f in meshes}["UltrON"] == "c"
    assert sorted(kinds(checker)) == ["frames", "labels", "losses", "mesh", "mesh"]
    assert "<th>CD</th>" in text and "Compounding &lt;x&gt;" in text and "|---" not in text
    assert "UltrON beats compounding" in text and "boom" in text


def test_figures_reject_bad_input(tiny_run):
    import trimesh

    dataset = SweepDataset.load(tiny_run["dataset"])
    box = trimesh.creation.box()
    with pytest.raises(UltronInputError, match=r"mesh.*empty"):
        mesh_distance_figure(trimesh.Trimesh(), box, "t")
    with pytest.raises(UltronInputError, match=r"reference.*empty"):
        mesh_distance_figure(box, trimesh.Trimesh(), "t")
    with pytest.raises(UltronInputError, match="n_points"):
        mesh_distance_figure(box, None, "t", n_points=0)
    with pytest.raises(UltronInputError, match="no sweep 'nope'"):
        frames_figure(dataset, None, "nope", [0])
    with pytest.raises(UltronInputError, match=r"frame_indices.*out of range"):
        frames_figure(dataset, None, "row", [99])
    with pytest.raises(UltronInputError, match="frame_indices"):
        frames_figure(dataset, None, "row", [])
    with pytest.raises(UltronInputError, match="no sweep 'tilt'"):
        label_masks_figure(dataset, {"tilt": [0]})
    with pytest.raises(UltronInputError, match="max_frames"):
        label_masks_figure(dataset, {"row": [0]}, max_frames=0)
    with pytest.raises(UltronInputError, match="curves"):
        loss_curves_figure({})
    with pytest.raises(UltronInputError, match=r"'occupancy'.*loss"):
        loss_curves_figure({"occupancy": [{"step": 0}]})
    with pytest.raises(UltronInputError, match="png_bytes"):
        image_html(b"GIF89a", "alt", "caption")
    with pytest.raises(UltronInputError, match="markdown"):
        markdown_table_html("no table here")


def test_figures_make_pngs(tiny_run):
    import trimesh

    dataset = SweepDataset.load(tiny_run["dataset"])
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    shifted = box.copy()
    shifted.apply_translation((1.0, 0.0, 0.0))
    for png in (
        mesh_distance_figure(shifted, box, "box", n_points=2000),
        mesh_distance_figure(box, None, "box alone", n_points=2000),
        frames_figure(dataset, None, "column", [3, 8]),
        label_masks_figure(dataset, {"row": [1, 5], "column": np.array([2])}, max_frames=2),
        loss_curves_figure({"a": [{"step": 0, "loss": -1.0}, {"step": 1, "loss": float("nan")}]}),
    ):
        assert png[:8] == PNG_SIGNATURE


def test_stage_logs_and_tables():
    run = {
        "occupancy_log": [{"step": 0, "loss": 0.5}],
        "stage1": {"row": {"final_losses": {"loss": 0.02}, "history": [{"step": 1, "loss": 0.1}]}},
        "stage3": {"final_losses": {"loss": 0.1, "zero": 0.05}},
    }
    curves = run_loss_curves(run, None)
    assert list(curves) == ["occupancy", "stage1/row/history"]
    assert final_loss_rows(run) == [
        ("stage1/row", "loss", "0.0200"), ("stage3", "loss", "0.1000"), ("stage3", "zero", "0.0500")
    ]  # fmt: skip
    ultron = {"occupancy_label_loss": 0.0205, "field_dir": "/f/b"}
    assert final_loss_rows(ultron) == [("occupancy", "label loss", "0.02050")]
    candidates = [{"field_dir": "/f/a", "occupancy_label_loss": 0.03},
                  {"field_dir": "/f/b", "occupancy_label_loss": 0.0205}]  # fmt: skip
    assert final_loss_rows({**ultron, "field_candidates": candidates}, prefix="x: ") == [
        ("x: occupancy", "label loss, field /f/a", "0.03000"),
        ("x: occupancy", "label loss, field /f/b (kept)", "0.02050"),
    ]
    table = table_html(["a", "b"], [["<i>", 1.5]])
    assert "&lt;i&gt;" in table and '<td class="num">1.5</td>' in table
    with pytest.raises(UltronInputError, match="rows"):
        table_html(["a", "b"], [["only one"]])
    html = markdown_table_html("Caption\n| a | b \\| c |\n|:--|--:|\n| 1 | x |")
    assert "<p>Caption</p>" in html and "<th>b | c</th>" in html and "<td>x</td>" in html


def test_metrics_html_shows_unmeasured_as_na():
    metrics = {
        "mean": {"cd_visible": None, "cd": 1.25, "hd": float("inf")},
        "std": {"cd_visible": None, "cd": 0.5, "hd": float("nan")},
        "config": {"repeats": 2, "n_points": 100},
    }
    text = metrics_html(metrics)
    assert "<td>cd_visible</td><td>n/a</td>" in text
    assert "1.250 ± 0.500" in text and "inf" in text and "None" not in text


def _panel_pixels(png: bytes) -> np.ndarray:
    """The decoded RGB pixels (H, W', 3) left of the colour bar (the figure's left 86 %)."""
    import io

    from matplotlib import image

    rgb = image.imread(io.BytesIO(png), format="png")[..., :3]
    return rgb[:, : int(rgb.shape[1] * 0.86)]


def _share_near(pixels: np.ndarray, colour: np.ndarray, tolerance: float = 0.06) -> float:
    return float((np.abs(pixels - colour).max(axis=-1) < tolerance).mean())


def test_distance_figure_reads_the_shift():
    """A box shifted 1 mm, coloured on a 0–2 mm scale: its panels show the colour of 1 mm
    (viridis at 0.5) and none of 1.5 or 2 mm; the unshifted box shows only the colour of 0 mm.
    The figure is not blank."""
    import trimesh
    from matplotlib import colormaps

    viridis = colormaps["viridis"]
    at = {mm: np.asarray(viridis(mm / 2.0)[:3]) for mm in (0.0, 1.0, 1.5, 2.0)}
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    shifted = box.copy()
    shifted.apply_translation((1.0, 0.0, 0.0))
    moved = _panel_pixels(mesh_distance_figure(shifted, box, "box", n_points=4000, clip_mm=2.0))
    same = _panel_pixels(mesh_distance_figure(box, box, "box", n_points=4000, clip_mm=2.0))
    # measured shares of the panels' pixels: shifted 0.21 % at 0 mm, 0.094 % at 1 mm, none
    # beyond; unshifted 0.41 % at 0 mm and nothing else
    for pixels in (moved, same):
        assert (np.abs(pixels - 1.0).max(axis=-1) > 0.05).mean() > 0.05  # not blank
        assert _share_near(pixels, at[1.5]) == 0.0 and _share_near(pixels, at[2.0]) == 0.0
    assert _share_near(moved, at[1.0]) > 0.0005
    assert _share_near(same, at[1.0]) == 0.0 and _share_near(same, at[0.0]) > 0.002


def test_points_are_drawn_nearest_first():
    """Hand-worked raster: on a 20 mm view of 300 cells a point at x = z = 0 covers cells
    149–150 on both axes (⌊10 / (20 / 300) − 0.5⌋ = 149, 2 × 2 cells). Of two points there,
    the one nearer along the view's direction (+y: the smaller y) shows; a point at (8, 8)
    covers 269–270; every other cell is transparent (alpha 0, or NaN for values)."""
    from ultron.report.figures import RASTER_SIDE, VIEWS, _draw_points
    from ultron.report.plotting import new_figure

    assert RASTER_SIDE == 300  # the cells below are worked for 300
    _, direction, h, v = VIEWS[0]
    points = np.array([[0.0, 5.0, 0.0], [0.0, -5.0, 0.0], [8.0, 0.0, 8.0]])
    limits = ((-10.0, 10.0), (-10.0, 10.0))
    ax = new_figure(3.0, 3.0).add_subplot()
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    image = np.asarray(_draw_points(ax, points, direction, h, v, limits, c=rgb).get_array())
    assert image.shape == (300, 300, 4)
    np.testing.assert_array_equal(image[149:151, 149:151], np.tile([0.0, 0.0, 1.0, 1.0], (2, 2, 1)))
    np.testing.assert_array_equal(image[269:271, 269:271], np.tile([0.0, 1.0, 0.0, 1.0], (2, 2, 1)))
    assert (image[..., 3] > 0).sum() == 8
    drawn = _draw_points(ax, points, direction, h, v, limits, c=np.array([1.0, 2.0, 3.0]),
                         cmap="viridis", vmin=0.0, vmax=3.0)  # fmt: skip
    values = np.ma.filled(drawn.get_array(), np.nan)
    np.testing.assert_array_equal(values[149:151, 149:151], 2.0)
    np.testing.assert_array_equal(values[269:271, 269:271], 3.0)
    assert np.isfinite(values).sum() == 8


def test_a_runs_record_round_trips(tiny_run):
    written = json.loads((tiny_run["run"] / "run.json").read_text(encoding="utf-8"))
    record = RunRecord.read(tiny_run["run"])
    assert written["schema"] == "ultron-run/1" and record.command == "reconstruct"
    assert record.method == "compounding" and record.mesh.vertices > 0
    assert record.device["device"] == "cpu" and record.total_s > 0
    assert record.to_dict() == written


def test_place_grid_puts_margins_and_gaps_in_inches():
    """A 10 × 5 in figure, 2 × 3 panels: margins (1, 0.5, 0.8, 0.4) in and gaps (0.6, 0.7) in
    give panels (10 − 1 − 0.5 − 2·0.6)/3 = 2.4333 in wide and (5 − 0.8 − 0.4 − 0.7)/2 = 1.55 in
    tall, at the hand-worked positions; with the grid ending at 80 % of the width, the right
    margin counts from 8 in."""
    from ultron.report.plotting import new_figure, place_grid

    fig = new_figure(10, 5)
    axes = [fig.add_subplot(2, 3, k + 1) for k in range(6)]
    place_grid(fig, 2, 3, (1.0, 0.5, 0.8, 0.4), (0.6, 0.7))
    boxes = np.array([ax.get_position().bounds for ax in axes]) * [10, 5, 10, 5]  # inches
    width, height = 7.3 / 3, 1.55
    np.testing.assert_allclose(boxes[:, 2], width, atol=1e-9)
    np.testing.assert_allclose(boxes[:, 3], height, atol=1e-9)
    np.testing.assert_allclose(boxes[:3, 0], [1.0, 1.6 + width, 2.2 + 2 * width], atol=1e-9)
    np.testing.assert_allclose(boxes[[0, 3], 1], [0.8 + 0.7 + height, 0.8], atol=1e-9)
    place_grid(fig, 2, 3, (1.0, 0.5, 0.8, 0.4), (0.6, 0.7), right_fraction=0.8)
    right = max(ax.get_position().x1 for ax in axes) * 10
    assert right == pytest.approx(8.0 - 0.5, abs=1e-9)


def test_frames_are_reduced_by_whole_blocks_for_their_panel():
    from ultron.report.plotting import display_factor, reduced_frame

    assert display_factor(820, 216.0) == 3 and display_factor(100, 216.0) == 1
    with pytest.raises(UltronInputError, match="panel_px"):
        display_factor(820, 0.0)
    image = np.arange(7 * 8, dtype=np.uint8).reshape(7, 8)
    labels = np.zeros((7, 8), np.uint8)
    labels[4, 1] = 1  # the centre of block (1, 0) for k = 3
    mean, centre, extent = reduced_frame(image, labels, 3, (-4.0, 4.0, 7.0, 0.0))
    assert mean.shape == (2, 2) and centre.shape == (2, 2)
    assert mean[0, 0] == pytest.approx(image[:3, :3].mean()) and mean.dtype == np.float32
    assert mean[1, 1] == pytest.approx(image[3:6, 3:6].mean())
    np.testing.assert_array_equal(centre, [[0, 0], [1, 0]])
    # 6 of 8 columns and 6 of 7 rows drawn: the extent covers exactly those pixels
    assert extent == pytest.approx((-4.0, 2.0, 6.0, 0.0))
    same, _, full = reduced_frame(image, None, 1, (-4.0, 4.0, 7.0, 0.0))
    np.testing.assert_array_equal(same, image)
    assert full == (-4.0, 4.0, 7.0, 0.0)
