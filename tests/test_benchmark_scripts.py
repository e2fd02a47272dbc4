"""Every script in ``benchmarks/`` still imports against the current library and has a
``main``: the scripts are run by hand (and by a GPU session, with little time to spare), so
no other test notices when a refactor renames what they import."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(path.name for path in BENCHMARKS.glob("*.py"))
HELPERS = {"common.py"}  # imported by the scripts, not run


def _load(script: str, monkeypatch) -> ModuleType:
    """``benchmarks/<script>`` imported as a module (its siblings importable, as when run)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    name = f"benchmark_script_{Path(script).stem}"
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / script)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_scripts_are_found():
    assert {"device.py", "real_fibula.py", "plus_spine.py"} <= set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_benchmark_script_imports(script, monkeypatch):
    module = _load(script, monkeypatch)
    assert module.__doc__, f"{script}: no docstring saying what it measures"
    if script not in HELPERS:
        assert callable(getattr(module, "main", None)), f"{script}: no main()"


def test_device_benchmark_steps_run_on_the_cpu(tiny_l3, monkeypatch):
    """benchmarks/device.py's per-step timers and operation count run against the current
    library (they are what a GPU session runs first; a stale one costs it its device time)."""
    from ultron.data.dataset import SweepDataset

    bench = _load("device.py", monkeypatch)
    dataset = SweepDataset.load(tiny_l3)
    cpu = torch.device("cpu")
    for preset in ("fast", "paper"):
        seconds = bench.field_step_seconds(dataset, preset, cpu, steps=1)
        per_step, finetune = bench.occupancy_seconds(preset, cpu, steps=2)
        assert all(math.isfinite(t) and t > 0 for t in (seconds, per_step, finetune)), preset
        assert bench.field_step_operations(dataset, preset) > 100  # forward, backward, Adam


def test_real_fibula_passes_its_device_to_the_commands_that_train(monkeypatch, tmp_path):
    from types import SimpleNamespace

    bench = _load("real_fibula.py", monkeypatch)
    args = SimpleNamespace(points=100, out=tmp_path, data=tmp_path / "data", device=None)
    command = bench.reconstruct_command(args, args.data, "ultron", 0.1, tmp_path / "r")
    assert "--device" not in command and command[command.index("--field") + 1] == str(
        tmp_path / "field"
    )
    args.device = "cuda"
    command = bench.reconstruct_command(args, tmp_path / "auto", "compounding", 1.0, tmp_path / "r")
    assert command[-2:] == ["--device", "cuda"] and "--field" not in command


def test_real_fibula_runs_every_row_once_per_seed(monkeypatch, tmp_path):
    """--seeds: seed 0 keeps its row names and commands (earlier runs resume), another seed is
    named and passed on, to the auto-label rows too (their training's seed); the means cover
    the fractions and methods run at several seeds, and none with a failed seed."""
    from types import SimpleNamespace

    bench = _load("real_fibula.py", monkeypatch)
    args = SimpleNamespace(
        points=100, out=tmp_path, data=tmp_path / "data", device=None,
        fractions=[0.1, 0.05], seeds=[0, 2], skip_auto=False,
    )  # fmt: skip
    rows = bench.conditions(args)
    assert [(name, fraction, seed) for name, _, fraction, seed in rows] == [
        ("CT 10 %", 0.1, 0), ("CT 10 % seed 2", 0.1, 2), ("CT 5 %", 0.05, 0),
        ("CT 5 % seed 2", 0.05, 2), ("auto 100 %", 1.0, 0), ("auto 100 % seed 2", 1.0, 2),
    ]  # fmt: skip
    assert "--seed" not in bench.reconstruct_command(args, args.data, "ultron", 0.1, tmp_path)
    command = bench.reconstruct_command(args, args.data, "ultron", 0.1, tmp_path, seed=2)
    assert command[command.index("--seed") + 1] == "2"

    def row(labels, method, seed, cd=None):
        row = {"labels": labels, "method": method, "seed": seed}
        return row | (
            {"error": "refused"} if cd is None else {"metrics": {"mean": {"cd_visible": cd}}}
        )

    lines = bench.seed_means([
        row("CT 10 %", "ultron", 0, 0.5), row("CT 10 % seed 2", "ultron", 2, 0.7),
        row("CT 10 %", "on", 0, 1.0), row("CT 5 %", "ultron", 0, 0.6),
        row("CT 5 % seed 2", "ultron", 2), row("CT 100 %", "ultron", 0, 0.4),
        row("auto 100 %", "ultron", 0, 0.8), row("auto 100 % seed 2", "ultron", 2, 0.9),
    ])  # fmt: skip
    assert lines == [
        "mean CD over seeds 0, 2, CT 10 % labels, ultron: 0.600 (from 0.500 to 0.700)",
        "mean CD over seeds 0, 2, auto 100 % labels, ultron: 0.850 (from 0.800 to 0.900)",
    ]


def test_real_fibula_keeps_each_row_as_it_is_scored(monkeypatch, tmp_path, capsys):
    """A run stopped part-way (a GPU lease's limit) keeps the rows it finished: each is printed
    with its scores and written to real_fibula.json (marked incomplete) before the next runs."""
    import json
    from types import SimpleNamespace

    bench = _load("real_fibula.py", monkeypatch)
    args = SimpleNamespace(
        points=100, out=tmp_path, data=tmp_path / "data", device=None,
        fractions=[0.1], seeds=[0], skip_auto=True,
    )  # fmt: skip
    metrics = {
        "mean": {"cd_visible": 0.5, "mad": 0.4, "completeness_visible": 0.6, "hd95": 1.2,
                 "fscore_visible_1mm": 0.9},
        "crop": {"area_outside_mm2": 10.0},
    }  # fmt: skip
    calls = []

    def run_stage(stage, command, log_dir):
        calls.append(stage)
        if len(calls) == 2:  # the second row's command is killed
            raise KeyboardInterrupt
        return {"stage": stage, "seconds": 1.5, "peak_rss_bytes": 2**30}

    monkeypatch.setattr(bench, "run_stage", run_stage)
    monkeypatch.setattr(bench, "evaluate", lambda args, mesh: metrics)
    with pytest.raises(KeyboardInterrupt):
        bench.run_rows(args, ["ultron", "compounding"], {}, {"crop_mm": 5.0})
    saved = json.loads((tmp_path / "real_fibula.json").read_text())
    assert saved["complete"] is False and [r["method"] for r in saved["rows"]] == ["ultron"]
    assert saved["rows"][0]["metrics"]["mean"]["cd_visible"] == 0.5
    assert json.loads((tmp_path / "stages.json").read_text())["CT 10 % ultron"]["seconds"] == 1.5
    assert (
        "[CT 10 % ultron] scored: | CT 10 % | ultron | 0.500 | 0.400 |" in capsys.readouterr().out
    )


def _stage2_row(dataset: str, fraction: float, variant: str, cd: float) -> dict:
    return {"dataset": dataset, "fraction": fraction, "T": variant, "cd_visible": cd}


def test_stage2_checks_count_only_the_rows_that_ran(monkeypatch):
    bench = _load("stage2_transmission.py", monkeypatch)
    oracle, field, ones = (bench.VARIANTS[k][0] for k in ("oracle", "field", "ones"))
    rows = [
        _stage2_row("A", 0.1, oracle, 0.5), _stage2_row("A", 0.1, field, 0.4),
        _stage2_row("A", 0.1, ones, 0.8), _stage2_row("B", 0.1, field, 0.3),
        _stage2_row("B", 0.1, ones, 0.3),
    ]  # fmt: skip
    a, b = bench.checks(rows)
    assert a["monotone"] is False  # the oracle is worse than the field's T
    assert a["loss_margin"] == pytest.approx(0.5)
    assert b["monotone"] is None  # no oracle row
    assert b["loss_margin"] == pytest.approx(0.0)


def test_stage2_sparse_checks_against_issue_32s_targets(monkeypatch):
    """5 % within +10 % and 1 % within +30 % of the same cell's 10 %, and the mean row is the
    ratio of the means (not the mean of the ratios); a cell without a 10 % run is left out."""
    bench = _load("stage2_transmission.py", monkeypatch)
    field, ones = bench.VARIANTS["field"][0], bench.VARIANTS["ones"][0]
    rows = [
        _stage2_row("A", 0.1, field, 0.40), _stage2_row("A", 0.05, field, 0.43),
        _stage2_row("B", 0.1, field, 0.20), _stage2_row("B", 0.05, field, 0.24),
        _stage2_row("A", 0.01, field, 0.56), _stage2_row("C", 0.05, field, 0.1),
        _stage2_row("A", 0.05, ones, 9.0),
    ]  # fmt: skip
    got = {(c["dataset"], c["fraction"]): c for c in bench.sparse_checks(rows)}
    assert set(got) == {("A", 0.05), ("B", 0.05), ("mean", 0.05), ("A", 0.01), ("mean", 0.01)}
    assert got["A", 0.05]["rise"] == pytest.approx(0.075) and got["A", 0.05]["met"]
    assert got["B", 0.05]["rise"] == pytest.approx(0.2) and not got["B", 0.05]["met"]
    assert got["mean", 0.05]["rise"] == pytest.approx(0.67 / 0.60 - 1)  # +11.7 %: missed
    assert not got["mean", 0.05]["met"]
    assert got["A", 0.01]["rise"] == pytest.approx(0.4) and got["A", 0.01]["target"] == 0.3
    assert bench.sparse_checks([_stage2_row("A", 0.05, field, 0.4)]) == []


def test_mask_import_runs_at_a_small_size(monkeypatch, tmp_path, capsys):
    """benchmarks/mask_import.py end to end on 12 frames of 40 × 60: its four commands run,
    every 3rd frame is labelled, the labels sit on the imported echo, and the export read
    back keeps them."""
    import json

    bench = _load("mask_import.py", monkeypatch)
    argv = ["mask_import.py", "--out", str(tmp_path), "--frames", "12", "--height", "40",
            "--width", "60", "--every", "3"]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    bench.main()
    figures = json.loads((tmp_path / "mask_import.json").read_text())
    assert figures["annotated_frames"] == 4 and figures["agreement_on_annotated_pixels"] > 0.99
    assert [row["stage"] for row in figures["stages"]] == [
        "import-plus", "label_--masks", "label_--export", "label_--masks_(exported)"
    ]  # fmt: skip
    assert figures["round_trip_kept"] > 0.995  # the 2° shear resamples: edges may round
    assert "| label_--export |" in capsys.readouterr().out
