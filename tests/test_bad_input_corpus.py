"""The bad-input corpus of the commands: outputs, references, importer numbering and
resources. Every case exits 2 with one ``error:`` line on stderr naming the file or option, no
traceback, and writes nothing (the directory tree, an earlier run included, is unchanged).

Broken datasets (``ultron info``) are in ``test_bad_input.py`` and out-of-range numbers in
``test_cli_numeric.py``; ``python benchmarks/bad_input_corpus.py`` runs all three corpora and
prints their size and the number of tracebacks.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ultron.cli.main import app

runner = CliRunner()

#: A PLY header with no body: passes the header check, fails when the mesh is read.
TRUNCATED_PLY = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"


def _run_dir(path: Path, command: str, method: str = "compounding") -> Path:
    """A directory that looks like an earlier run of ``command``."""
    path.mkdir(parents=True)
    run = {"command": command, "method": method}
    (path / "run.json").write_text(json.dumps(run))
    (path / "mesh.ply").write_text("old mesh\n")
    return path


def _foreign_dir(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("mine\n")
    return path


def _field_like(path: Path) -> Path:
    """A directory holding an ultron field.json (what makes it a fitted field's directory)."""
    path.mkdir(parents=True)
    (path / "field.json").write_text('{"format": "ultron-field/1"}')
    return path


def _run_like(path: Path) -> Path:
    """A directory holding a run.json (what makes it an ultron run's directory)."""
    path.mkdir(parents=True)
    (path / "run.json").write_text('{"command": "reconstruct"}')
    return path


def _file(path: Path) -> Path:
    path.write_text("a file\n")
    return path


def _edit_dataset(data: Path, change: Callable[[dict], None]) -> None:
    meta = json.loads((data / "dataset.json").read_text())
    change(meta)
    (data / "dataset.json").write_text(json.dumps(meta))


def _move_pose(data: Path, frame: int, offset_mm: float) -> None:
    poses = np.load(data / "row" / "poses.npy")
    poses[frame, 0, 3] += offset_mm
    np.save(data / "row" / "poses.npy", poses)


def _tiny_probe(data: Path) -> None:
    """A 1 µm wide probe: 0.17 µm pixels."""
    _edit_dataset(data, lambda m: m["probe"].update(width_mm=1e-3))


def _two_pixel_frames(path: Path) -> Path:
    """A dataset of frames 2 pixels deep, without labels, at ``path``."""
    from conftest import make_sweep
    from ultron.data.dataset import ProbeGeometry, SweepDataset

    probe = ProbeGeometry(width_mm=12.0, depth_mm=2.0, height_px=2, width_px=6)
    SweepDataset(probe, [make_sweep(h=2, labels=False)]).save(path)
    return path


def _point_cloud(path: Path) -> None:
    """``path``: a PLY of three vertices and no faces, and ``r.ply`` beside it a triangle."""
    vertices = "0 0 0\n1 0 0\n0 1 0\n"
    head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    head += "property float z\n"
    path.write_text(head + "end_header\n" + vertices)
    face = "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    (path.parent / "r.ply").write_text(head + face + vertices + "3 0 1 2\n")


def _detached_sequence(tmp: Path, data_file: str) -> list[str]:
    """import-plus arguments for tmp/rec/rec.igs.mha whose payload is ``data_file``."""
    from plus_synthetic import mha_header, recording, write_config

    folder = tmp / "rec"
    folder.mkdir()
    header = "".join(f"{k} = {v}\n" for k, v in mha_header(recording(n=3, height=12, width=16)))
    (folder / "rec.igs.mha").write_text(header + f"ElementDataFile = {data_file}\n")
    config = write_config(folder / "config.xml", np.diag([0.3, 0.25, 1.0, 1.0]))
    return ["import-plus", str(folder / "rec.igs.mha"), "--config", str(config),
            "--out", str(tmp / "ds")]  # fmt: skip


def _bad_reference(data: Path) -> None:
    (data / "reference.ply").write_text(TRUNCATED_PLY)
    _edit_dataset(data, lambda m: m.update(reference="reference.ply"))


def _ultranerf(tmp: Path, names: list[str]) -> Path:
    """An Ultra-NeRF folder with PNG frames of these names and as many poses."""
    from PIL import Image

    src = tmp / "un"
    (src / "images").mkdir(parents=True)
    for name in names:
        Image.fromarray(np.zeros((6, 4), np.uint8)).save(src / "images" / name)
    np.save(src / "poses.npy", np.tile(np.eye(4), (len(names), 1, 1)))
    return src


def _after(_done: object, args: list[str]) -> list[str]:
    """``args``, once the mutation evaluated before them (as the first argument) is done."""
    return args


def _import(src: Path, out: Path) -> list[str]:
    return ["import-ultranerf", str(src), "--width-mm", "8", "--depth-mm", "12", "--out", str(out)]


def _recon(data: Path, out: Path, *more: str) -> list[str]:
    return ["reconstruct", str(data), "--method", "compounding", "--out", str(out), *more]


def _finetune(model: Path, data: Path, out: Path) -> list[str]:
    return ["finetune", str(model), str(data), "--out", str(out)]


def _render(tmp: Path, out: Path, *more: str) -> list[str]:
    return ["render", str(tmp / "field"), "--poses", str(tmp / "p.npy"), "--out", str(out), *more]


def _field_parent(tmp: Path) -> Path:
    """``tmp``, holding ``field``: a directory with an ultron field.json."""
    _field_like(tmp / "field")
    return tmp


def _imported_simulation(data: Path) -> None:
    """``data`` recorded as a simulation whose sweep ``row`` was imported into it."""
    imports = {"row": {"source": "ultranerf"}}
    _edit_dataset(
        data, lambda m: m.update(metadata={"generator": "ultron simulate", "imports": imports})
    )


def _copy_tree(src: Path, dst: Path) -> Path:
    """``src``'s files copied into the existing folder ``dst``."""
    import shutil

    shutil.copytree(src, dst, dirs_exist_ok=True)
    return dst


def _evaluate(tmp: Path, *more: str) -> list[str]:
    return ["evaluate", str(tmp / "m.ply"), str(tmp / "r.ply"), *more]


def _outlier_poses_file(tmp: Path, data: Path) -> None:
    """tmp/p.npy: the dataset's 7 poses, frame 2 moved 1e6 mm."""
    poses = np.concatenate([np.load(data / s / "poses.npy") for s in ("row", "column")])
    poses[2, 0, 3] += 1e6
    np.save(tmp / "p.npy", poses)


def _fitted_field(tmp: Path, data: Path, iters: int) -> list[str]:
    """``fit-field`` arguments into tmp/f, after a fit of ``iters`` steps there."""
    args = ["fit-field", str(data), "--out", str(tmp / "f"), "--fit-shape", "8x8"]
    assert runner.invoke(app, [*args, "--iters", str(iters)]).exit_code == 0
    return args


def _rocosdf_one_frame(tmp: Path, data: Path) -> list[str]:
    """RoCoSDF on tmp/one: the dataset with its sweeps cut to their first (labelled) frame."""
    from dataclasses import replace

    from ultron.data.dataset import SweepDataset

    dataset = SweepDataset.load(data)
    sweeps = [
        replace(s, images=s.images[:1], probe_to_world=s.probe_to_world[:1], labels=s.labels[:1])
        for s in dataset.sweeps
    ]
    replace(dataset, sweeps=sweeps).save(tmp / "one")
    return ["reconstruct", str(tmp / "one"), "--method", "rocosdf", "--label-fraction", "1",
            "--out", str(tmp / "out")]  # fmt: skip


def _labels_all(tmp: Path, data: Path, value: int) -> Path:
    """tmp/relabelled: the dataset with every label set to ``value`` (0: no bone; 255: unsure)."""
    from dataclasses import replace

    import numpy as np

    from ultron.data.dataset import SweepDataset

    dataset = SweepDataset.load(data)
    sweeps = [replace(s, labels=np.full_like(s.labels, value)) for s in dataset.sweeps]
    replace(dataset, sweeps=sweeps).save(tmp / "relabelled")
    return tmp / "relabelled"


def _dangling_poses(tmp: Path, _data: Path) -> list[str]:
    src = _ultranerf(tmp, ["0.png", "1.png"])
    (src / "poses.npy").unlink()
    (src / "poses.npy").symlink_to(src / "gone.npy")
    return _import(src, tmp / "ds")


def _looping_images(tmp: Path, _data: Path) -> list[str]:
    src = _ultranerf(tmp, ["0.png"])
    (src / "images.npy").symlink_to(src / "images.npy")
    return _import(src, tmp / "ds")


#: case → (build the case in (tmp, dataset) and return the CLI arguments, hints the one error
#: line must contain). Each case's mutations happen before the snapshot.
CASES: dict[str, tuple[Callable[[Path, Path], list[str]], tuple[str, ...]]] = {
    # 1. an output directory is owned by one run
    "reconstruct_into_foreign_dir": (
        lambda t, d: _recon(d, _foreign_dir(t / "out")),
        ("out", "--out", "holds no run.json"),
    ),
    "reconstruct_into_finetune_run": (
        lambda t, d: _recon(d, _run_dir(t / "out", "finetune", "ultron-finetune")),
        ("out", "--out", "earlier finetune run"),
    ),
    "finetune_into_reconstruct_run": (
        lambda t, d: _finetune(
            _run_dir(t / "model", "reconstruct"), d, _run_dir(t / "out", "reconstruct")
        ),
        ("out", "--out", "earlier reconstruct run"),
    ),
    "reconstruct_out_holds_its_field": (
        lambda t, d: _recon(
            d, _run_dir(t / "out", "reconstruct"), "--field", str(_foreign_dir(t / "out" / "field"))
        ),
        ("out", "--out", "holds the input"),
    ),
    "fit_field_out_is_the_dataset": (
        lambda t, d: ["fit-field", str(d), "--out", str(d)],
        ("--out", "holds the dataset"),
    ),
    "fit_field_into_reconstruct_run": (
        lambda t, d: ["fit-field", str(d), "--out", str(_run_dir(t / "out", "reconstruct"))],
        ("out", "--out", "ultron run"),
    ),
    "fit_field_into_foreign_dir": (
        lambda t, d: ["fit-field", str(d), "--out", str(_foreign_dir(t / "out"))],
        ("out", "--out", "no field of an earlier fit"),
    ),
    "reconstruct_out_inside_its_field": (
        lambda t, d: _recon(d, t / "field" / "run", "--field", str(_field_like(t / "field"))),
        ("run", "--out", "lies inside the input"),
    ),
    "reconstruct_out_inside_another_field": (
        lambda t, d: _recon(d, _field_like(t / "field") / "sub" / "run"),
        ("run", "--out", "lies inside", "an ultron field (field.json)"),
    ),
    "fit_field_out_inside_a_run": (
        lambda t, d: ["fit-field", str(d), "--out", str(_run_like(t / "run") / "field")],
        ("field", "--out", "lies inside", "an ultron run (run.json)"),
    ),
    "compound_out_inside_a_run": (
        lambda t, d: ["compound", str(d), "--out", str(_run_like(t / "run") / "occ.nii.gz")],
        ("occ.nii.gz", "--out", "lies inside", "an ultron run (run.json)"),
    ),
    "render_out_inside_a_field": (
        lambda t, d: _render(_field_parent(t), t / "field" / "frames.npy"),
        ("frames.npy", "--out", "lies inside", "an ultron field (field.json)"),
    ),
    "evaluate_out_onto_a_dataset_file": (
        lambda t, d: _after(
            _point_cloud(t / "m.ply"), _evaluate(t, "--out", str(d / "dataset.json"))
        ),
        ("dataset.json", "--out", "not an earlier evaluate result"),
    ),
    "render_out_onto_a_sweep_file": (
        lambda t, d: _render(t, d / "row" / "images.npy"),
        ("images.npy", "--out", "is a file of the dataset"),
    ),
    "render_out_onto_its_poses": (
        lambda t, d: _after(_outlier_poses_file(t, d), _render(t, t / "p.npy")),
        ("p.npy", "--out", "is the --poses file"),
    ),
    "import_from_the_sweep_folder_it_writes": (
        lambda t, d: _after(
            (d / "un").mkdir(),
            _import(_copy_tree(_ultranerf(t, ["0.png"]), d / "un"), d),
        ),
        ("un", "SRC", "is the folder of sweep 'un'"),
    ),
    "simulate_into_a_run": (
        lambda t, d: ["simulate", "--frames", "2", "--out", str(_run_like(t / "run") / "ds")],
        ("ds", "--out", "lies inside", "an ultron run (run.json)"),
    ),
    "simulate_over_a_simulation_with_an_imported_sweep": (
        lambda t, d: _after(
            _imported_simulation(d), ["simulate", "--frames", "2", "--out", str(d)]
        ),
        ("--out", "holds a simulation with imported sweeps (row)"),
    ),
    "benchmark_out_onto_a_run": (
        lambda t, d: ["benchmark", "--quick", "--out", str(_run_like(t / "run"))],
        ("run", "--out", "is an ultron run's directory"),
    ),
    "reconstruct_every_label_unsure": (
        lambda t, d: _recon(_labels_all(t, d, 255), t / "out"),
        ("relabelled", "labels", "no annotated frame", "auto_labels_quality.csv"),
    ),
    "reconstruct_no_bone_labelled": (
        lambda t, d: _recon(_labels_all(t, d, 0), t / "out"),
        ("relabelled", "labels", "contain no bone pixel"),
    ),
    "demo_into_foreign_method_dir": (
        lambda t, d: ["demo", "--out", str(_foreign_dir(t / "demo" / "ultron").parent)],
        ("ultron", "--out", "holds no run.json"),
    ),
    # 2. everything cheap first: the output path, the reference
    "reconstruct_out_is_a_file": (
        lambda t, d: _recon(d, _file(t / "out")),
        ("out", "--out", "not a directory"),
    ),
    "reconstruct_out_below_a_file": (
        lambda t, d: _recon(d, _file(t / "out") / "sub"),
        ("out", "--out", "cannot be created"),
    ),
    # 4. a file that names a path outside its own folder (nothing outside is read)
    "reconstruct_reference_outside_the_dataset": (
        lambda t, d: _after(
            _edit_dataset(d, lambda m: m.update(reference="../r.ply")), _recon(d, t / "out")
        ),
        ("dataset.json", "reference", "points outside"),
    ),
    "import_plus_data_file_outside_its_folder": (
        lambda t, d: _detached_sequence(t, "/etc/passwd"),
        ("rec.igs.mha", "ElementDataFile", "points outside"),
    ),
    # 5. work beyond the memory this process may use, refused before it starts
    "simulate_voxel_beyond_memory": (
        lambda t, d: ["simulate", "--voxel-mm", "0.0001", "--out", str(t / "sim")],
        ("--voxel-mm", "more than"),
    ),
    "evaluate_points_beyond_memory": (
        lambda t, d: _after(
            _point_cloud(t / "m.ply"),
            ["evaluate", str(t / "r.ply"), str(t / "r.ply"), "--points", "1000000000"],
        ),
        ("--points", "more than"),
    ),
    "evaluate_point_cloud": (
        lambda t, d: _after(_point_cloud(t / "m.ply"), _evaluate(t, "--out", str(t / "x.json"))),
        ("m.ply", "mesh", "no triangles"),
    ),
    "evaluate_text_as_stl": (
        lambda t, d: _after(
            (_point_cloud(t / "m.ply"), (t / "m.stl").write_text("not a mesh\n")),
            ["evaluate", str(t / "m.stl"), str(t / "r.ply"), "--out", str(t / "x.json")],
        ),
        ("m.stl", "mesh", "not a readable mesh"),
    ),
    "evaluate_bytes_as_obj": (
        lambda t, d: _after(
            (_point_cloud(t / "m.ply"), (t / "m.obj").write_bytes(bytes(range(256)))),
            ["evaluate", str(t / "m.obj"), str(t / "r.ply"), "--out", str(t / "x.json")],
        ),
        ("m.obj", "mesh", "not a readable mesh"),
    ),
    "evaluate_out_is_the_reference": (
        lambda t, d: _after(_point_cloud(t / "m.ply"), _evaluate(t, "--out", str(t / "r.ply"))),
        ("r.ply", "--out", "is REFERENCE, an input"),
    ),
    "reconstruct_unreadable_reference": (
        lambda t, d: _after(_bad_reference(d), _recon(d, t / "out")),
        ("reference.ply", "not a readable mesh"),
    ),
    "demo_out_is_a_file": (
        lambda t, d: ["demo", "--out", str(_file(t / "demo"))],
        ("demo", "--out", "not a directory"),
    ),
    # 3. a directory where a file is expected, or a file where a directory is expected
    "finetune_out_is_a_file": (
        lambda t, d: _finetune(_run_dir(t / "model", "reconstruct"), d, _file(t / "out")),
        ("out", "--out", "not a directory"),
    ),
    "evaluate_out_is_a_dir": (
        lambda t, d: _evaluate(t, "--out", str(_foreign_dir(t / "metrics.json"))),
        ("metrics.json", "--out", "is a directory"),
    ),
    "evaluate_default_out_is_a_dir": (
        lambda t, d: _after(_foreign_dir(t / "m.metrics.json"), _evaluate(t)),
        ("m.metrics.json", "--out", "is a directory"),
    ),
    "render_out_is_a_dir": (
        lambda t, d: _render(t, _foreign_dir(t / "frames.npy")),
        ("frames.npy", "--out", "is a directory"),
    ),
    "render_maps_out_is_a_dir": (
        lambda t, d: _after(_foreign_dir(t / "f.theta.npy"), _render(t, t / "f.npy", "--maps")),
        ("f.theta.npy", "--out", "is a directory"),
    ),
    "import_out_is_a_file": (
        lambda t, d: _import(_ultranerf(t, ["0.png"]), _file(t / "ds")),
        ("ds", "--out", "not a directory"),
    ),
    "fit_field_out_is_a_file": (
        lambda t, d: ["fit-field", str(d), "--out", str(_file(t / "field"))],
        ("field", "--out", "not a directory"),
    ),
    "label_export_to_a_directory": (
        lambda t, d: ["label", str(d), "--export", str(_foreign_dir(t / "masks.npy"))],
        ("masks.npy", "--export", "is a directory"),
    ),
    "label_export_under_a_file": (
        lambda t, d: ["label", str(d), "--export", str(_file(t / "notes") / "masks.npy")],
        ("notes/masks.npy", "--export", "not a directory"),
    ),
    "auto_label_frames_under_3_pixels": (
        lambda t, d: ["label", str(_two_pixel_frames(t / "small")), "--auto"],
        ("small/dataset.json", "probe", "frames of 2 × 6 pixels", "at least 3 × 3"),
    ),
    "simulate_into_a_folder_of_other_files": (
        lambda t, d: ["simulate", "--frames", "2", "--out", str(_foreign_dir(t / "sim"))],
        ("sim", "--out", "holds no dataset.json"),
    ),
    "simulate_over_a_dataset_it_did_not_write": (
        lambda t, d: ["simulate", "--frames", "2", "--out", str(d)],
        ("--out", "ultron simulate did not write"),
    ),
    "import_into_a_folder_of_other_files": (
        lambda t, d: _import(_ultranerf(t, ["0.png"]), _foreign_dir(t / "ds")),
        ("ds", "out", "holds no dataset.json"),
    ),
    "simulate_out_is_a_file": (
        lambda t, d: ["simulate", "--out", str(_file(t / "sim"))],
        ("sim", "--out", "not a directory"),
    ),
    # 4. importer numbering and symlinks
    "import_png_gap": (
        lambda t, d: _import(
            _ultranerf(t, ["0.png", "1.png", "2.png", "30.png", "4.png"]), t / "ds"
        ),
        ("3.png", "frame 3 is missing"),
    ),
    "import_png_same_number_twice": (
        lambda t, d: _import(_ultranerf(t, ["0.png", "1.png", "01.png"]), t / "ds"),
        ("images", "01.png", "1.png", "both number frame 1"),
    ),
    "import_dangling_poses_symlink": (_dangling_poses, ("poses.npy", "dangling symlink")),
    "import_images_symlink_loop": (_looping_images, ("images.npy", "symlink loop")),
    # 5. resources, estimated before any allocation
    "reconstruct_outlier_pose": (
        lambda t, d: _after(_move_pose(d, 1, 1e6), _recon(d, t / "out")),
        ("poses.npy", "sweep row, frame 1", "median position"),
    ),
    "finetune_outlier_pose": (
        lambda t, d: _after(
            _move_pose(d, 2, -1e6), _finetune(_run_dir(t / "model", "reconstruct"), d, t / "out")
        ),
        ("poses.npy", "sweep row, frame 2"),
    ),
    "fit_field_outlier_pose": (
        lambda t, d: _after(_move_pose(d, 0, 1e6), ["fit-field", str(d), "--out", str(t / "f")]),
        ("poses.npy", "sweep row, frame 0"),
    ),
    "reconstruct_tiny_probe": (
        lambda t, d: _after(_tiny_probe(d), _recon(d, t / "out")),
        ("dataset.json", "probe", "pixels are", "0.001 mm wide / 6 columns"),
    ),
    "fit_field_tiny_probe": (
        lambda t, d: _after(_tiny_probe(d), ["fit-field", str(d), "--out", str(t / "f")]),
        ("dataset.json", "probe", "pixels are", "width_mm and depth_mm"),
    ),
    "reconstruct_over_max_memory": (
        lambda t, d: _recon(d, t / "out", "--max-memory", "1e-6"),
        ("dataset.json", "meshing grid", "--max-memory 1e-06 GiB"),
    ),
    "fit_field_over_max_memory": (
        lambda t, d: ["fit-field", str(d), "--out", str(t / "f"), "--max-memory", "1e-6"],
        ("dataset.json", "acoustic field", "fitting it needs", "--max-memory 1e-06 GiB"),
    ),
    "render_outlier_pose": (
        lambda t, d: _after(_outlier_poses_file(t, d), _render(t, t / "f.npy")),
        ("p.npy", "poses", "frame 2: pose translation (1e+06", "median position"),
    ),
    "rocosdf_one_frame_dataset": (
        _rocosdf_one_frame,
        ("one", "labels", "lie in one plane", "≥ 1 mm apart"),
    ),
    "fit_field_frames_below_ssim_window": (
        lambda t, d: ["fit-field", str(d), "--out", str(t / "f")],
        ("dataset.json", "probe", "8 × 6 px", "SSIM window"),
    ),
    # 6. a field fit's progress
    "fit_field_iters_below_checkpoint": (
        lambda t, d: [*_fitted_field(t, d, 4), "--iters", "2"],
        ("f/field.json", "step", "checkpoint is at step 4", "--iters 2", "--no-resume"),
    ),
}


def snapshot(root: Path) -> dict[str, object]:
    """Every entry under ``root``: file bytes, ``dir``, or a symlink's target (not followed)."""
    entries: dict[str, object] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            key = str(path.relative_to(root))
            if path.is_symlink():
                entries[key] = f"link:{os.readlink(path)}"
            elif path.is_dir():
                entries[key] = "dir"
            else:
                entries[key] = path.read_bytes()
    return entries


def check_refused(result, hints: tuple[str, ...]) -> None:
    """Exit 2, one ``error:`` line on stderr holding every hint, no traceback."""
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: "), lines[0]
    for hint in hints:
        assert hint in lines[0], (hint, lines[0])
    assert "Traceback" not in result.output and isinstance(result.exception, SystemExit)


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_refused(case: str, tmp_path: Path, tiny_dataset_dir: Path, monkeypatch):
    monkeypatch.setenv("ULTRON_CACHE", str(tmp_path / "cache"))
    build, hints = CASES[case]
    args = build(tmp_path, tiny_dataset_dir)
    before = snapshot(tmp_path)
    check_refused(runner.invoke(app, args), hints)
    assert snapshot(tmp_path) == before  # nothing written, an earlier run untouched


def test_info_warns_about_outlier_poses(tiny_dataset_dir: Path):
    _move_pose(tiny_dataset_dir, 1, 1e6)
    result = runner.invoke(app, ["info", str(tiny_dataset_dir)], terminal_width=400)
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.output.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 2, warnings
    assert "sweep row, frame 1: pose translation (1e+06, 2, -0.5) mm" in warnings[0]
    assert "refuse" in warnings[1]


def test_info_quiet_without_outliers(tiny_dataset_dir: Path):
    result = runner.invoke(app, ["info", str(tiny_dataset_dir)], terminal_width=400)
    assert result.exit_code == 0 and "warning" not in result.output
