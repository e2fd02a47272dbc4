"""Whole-pipeline presets (``--preset fast|paper``) and the CLI options that override them."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from ultron.cli.main import app
from ultron.cli.reconstruct_cmds import _field_config, _request
from ultron.device import ACCELERATOR_CHUNK_FACTOR, evaluation_chunk
from ultron.errors import UltronInputError
from ultron.methods.on_method import ONConfig
from ultron.methods.presets import PAPER_OCCUPANCY_ITERS, pipeline_preset
from ultron.methods.ultron_method import UltronConfig
from ultron.train.field_config import PAPER_ITERATIONS, FieldTrainConfig


def test_fast_preset_is_every_component_default():
    preset = pipeline_preset("fast", seed=3)
    assert preset.field == FieldTrainConfig(seed=3)
    assert preset.ultron.occupancy.seed == 3
    assert preset.ultron == UltronConfig(occupancy=preset.ultron.occupancy)
    assert preset.on == ONConfig() and preset.rocosdf_preset == "fast"


def test_paper_preset_is_the_papers_configuration():
    preset = pipeline_preset("paper", seed=2)
    field = preset.field
    assert field.field.backend == "mlp" and field.iterations == PAPER_ITERATIONS == 75_000
    assert field.train_scatterers == "sample" and field.confidence_prior_weight == 0
    assert field.lr == 1e-4 and field.seed == 2
    assert field.patch_width >= 4096  # whole frames
    occupancy = preset.ultron.occupancy
    assert occupancy.iters == PAPER_OCCUPANCY_ITERS == 50_000
    assert occupancy.negatives == "weighted" and occupancy.positive_weight == 1.0
    assert occupancy.lr == 1e-4 and occupancy.seed == 2
    assert preset.ultron.context.radii_mm == ()  # θ(x) alone
    assert preset.ultron.observed.surface == "all"
    assert preset.on.occupancy.iters == 50_000 and preset.rocosdf_preset == "paper"


def test_presets_are_built_anew():
    assert pipeline_preset("paper") == pipeline_preset("paper")
    assert pipeline_preset("paper") is not pipeline_preset("paper")


def test_unknown_preset_names_the_argument():
    with pytest.raises(UltronInputError, match=r"preset: expected one of \('fast', 'paper'\)"):
        pipeline_preset("slow")


def test_cli_request_takes_the_preset_and_options_win():
    request = _request("ultron", 0.1, 0, None, 1000, preset="paper")
    assert request.ultron.context.radii_mm == () and request.ultron.occupancy.iters == 50_000
    assert request.rocosdf_preset == "paper"
    request = _request(
        "ultron", 0.1, 0, 200, 1000, preset="paper", theta_context="1,2", negatives="observed",
        surface="observed",
    )  # fmt: skip
    assert request.ultron.context.radii_mm == (1.0, 2.0)
    assert request.ultron.occupancy.negatives == "observed"
    assert request.ultron.occupancy.iters == 200 and request.on.occupancy.iters == 200
    assert request.ultron.observed.surface == "observed"
    assert request.ultron.occupancy.positive_weight == 1.0
    balanced = _request("ultron", 0.1, 0, None, 1000, positive_weight="balanced")
    assert balanced.ultron.occupancy.positive_weight is None
    assert (
        _request("ultron", 0.1, 0, None, 1, positive_weight="3").ultron.occupancy.positive_weight
        == 3
    )
    fast = _request("ultron", 0.1, 0, None, 1000)
    assert fast.ultron == UltronConfig(occupancy=fast.ultron.occupancy)
    assert _field_config(None, 1, "paper").iterations == 75_000
    assert _field_config(10, 1, "paper").iterations == 10
    assert _field_config(None, 1) == FieldTrainConfig(seed=1)


@pytest.mark.parametrize("command", ["reconstruct", "benchmark"])
def test_cli_rejects_an_unknown_preset(command, tmp_path: Path):
    args = [command, *([str(tmp_path)] if command == "reconstruct" else []), "--out"]
    result = CliRunner().invoke(app, [*args, str(tmp_path / "o"), "--preset", "slow"])
    assert result.exit_code == 2 and "--preset" in result.output
    assert not (tmp_path / "o").exists()


def test_quick_benchmark_refuses_the_paper_preset(tmp_path: Path):
    args = ["benchmark", "--out", str(tmp_path / "b"), "--quick", "--preset", "paper"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and "--quick" in result.output
    assert not (tmp_path / "b").exists()


def test_evaluation_chunk_grows_only_off_the_cpu():
    assert evaluation_chunk(torch.device("cpu"), 1000) == 1000
    assert evaluation_chunk(None, 1000) == 1000
    assert evaluation_chunk(torch.device("cuda"), 1000) == 1000 * ACCELERATOR_CHUNK_FACTOR
