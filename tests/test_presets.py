"""Whole-pipeline presets (``--preset fast|paper``) and the CLI options that override them."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from ultron.benchmark.config import BenchmarkConfig, benchmark_config, quick_config
from ultron.cli.main import app
from ultron.device import ACCELERATOR_CHUNK_FACTOR, evaluation_chunk
from ultron.errors import UltronInputError
from ultron.mesh.extract import ExtractionConfig
from ultron.mesh.label_fusion import LabelFusionConfig
from ultron.mesh.observed import OBSERVED_EXTRACTION, ObservedSurfaceConfig
from ultron.methods.compounding_method import CompoundingMethodConfig
from ultron.methods.on_method import ONConfig
from ultron.methods.rocosdf import RoCoSDFConfig
from ultron.methods.ultron_method import UltronConfig
from ultron.pipeline.presets import (
    PAPER_OCCUPANCY_ITERS,
    pipeline_preset,
    preset_field_config,
    preset_request,
)
from ultron.train.field_config import PAPER_ITERATIONS, FieldTrainConfig
from ultron.train.occupancy import OccupancyTrainConfig


def test_fast_preset_is_every_component_default():
    preset = pipeline_preset("fast", seed=3)
    assert preset.field == FieldTrainConfig(seed=3)
    assert preset.ultron.occupancy.seed == 3
    assert preset.ultron == UltronConfig(occupancy=OccupancyTrainConfig(seed=3))
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
    assert preset.ultron.echo_support is None and preset.ultron.label_outer_side_mm == 0
    assert preset.ultron.observed.label_support_mm == 0
    assert pipeline_preset("fast").ultron.echo_support is not None  # ultron's own crop
    assert pipeline_preset("fast").ultron.observed.label_support_mm == 1.0
    assert preset.on.occupancy.iters == 50_000 and preset.rocosdf_preset == "paper"


def test_the_extraction_follows_the_surface():
    """The observed crop decides what UltrON and compounding keep, so their extraction meshes
    every piece; the whole iso-surface (the paper's, or --surface all) drops small pieces."""
    fast, paper = pipeline_preset("fast"), pipeline_preset("paper")
    assert fast.ultron.surface_extraction.min_component_fraction == 0
    assert paper.ultron.surface_extraction.min_component_fraction == 0.05
    for method in ("ultron", "ultron-noloss", "compounding"):
        config = preset_request("fast", method).method_config
        assert config.surface_extraction.min_component_fraction == 0
        config = preset_request("fast", method, surface="all").method_config
        assert config.surface_extraction.min_component_fraction == 0.05
        config = preset_request("paper", method, surface="observed").method_config
        assert config.surface_extraction.min_component_fraction == 0
    assert preset_request("fast", "on").method_config.meshing.extraction.min_component_fraction


def test_a_config_built_by_hand_extracts_as_its_surface_says():
    """Without an explicit extraction, a config keeping the whole surface drops small pieces
    and one keeping the observed part meshes every piece; an explicit extraction wins."""
    whole = ObservedSurfaceConfig(surface="all")
    for config_class in (UltronConfig, CompoundingMethodConfig):
        assert config_class().surface_extraction == OBSERVED_EXTRACTION
        assert config_class(observed=whole).surface_extraction == ExtractionConfig()
        chosen = ExtractionConfig(min_component_fraction=0.2)
        assert config_class(observed=whole, extraction=chosen).surface_extraction == chosen
    assert UltronConfig(observed=whole).meshing.extraction == ExtractionConfig()


def test_presets_are_built_anew():
    assert pipeline_preset("paper") == pipeline_preset("paper")
    assert pipeline_preset("paper") is not pipeline_preset("paper")


def test_unknown_preset_names_the_argument():
    with pytest.raises(UltronInputError, match=r"preset: expected one of \('fast', 'paper'\)"):
        pipeline_preset("slow")


def test_request_takes_the_preset_and_options_win():
    request = preset_request("paper", "ultron", 0.1, 0, points=1000)
    ultron = request.method_config
    assert ultron.context.radii_mm == () and ultron.occupancy.iters == 50_000
    assert request.metrics.n_points == 1000
    assert preset_request("paper", "rocosdf").method_config == RoCoSDFConfig.preset("paper")
    options = {
        "occupancy_iters": 200, "theta_context": "1,2", "negatives": "observed",
        "surface": "observed", "mesh_coordinates": "ras",
    }  # fmt: skip
    request = preset_request("paper", "ultron", 0.1, 0, **options)
    ultron = request.method_config
    assert ultron.context.radii_mm == (1.0, 2.0)
    assert ultron.occupancy.negatives == "observed" and ultron.occupancy.iters == 200
    assert ultron.observed.surface == "observed" and request.mesh_coordinates == "ras"
    assert ultron.occupancy.positive_weight == 1.0
    assert preset_request("paper", "on", **options).method_config.occupancy.iters == 200
    compounding = preset_request("paper", "compounding", **options).method_config
    assert compounding.observed.surface == "observed"
    assert preset_request("paper", "compounding").method_config.observed.surface == "all"
    balanced = preset_request(positive_weight="balanced").method_config
    assert balanced.occupancy.positive_weight is None
    assert preset_request(positive_weight="3").method_config.occupancy.positive_weight == 3
    assert preset_request(visibility="labels").method_config.visibility.source == "labels"
    assert preset_request(oracle=True).method_config.visibility.source == "oracle"
    assert preset_request(echo_support=False).method_config.echo_support is None
    assert preset_request(label_support_mm=0.5).method_config.observed.label_support_mm == 0.5
    assert preset_request(negatives="front").method_config.occupancy.negatives == "front"
    assert preset_request().method_config.occupancy.negatives == "observed"
    assert preset_request().method_config.observed.label_bridges
    assert not preset_request(label_bridges=False).method_config.observed.label_bridges
    assert not preset_request("paper").method_config.observed.label_bridges
    assert preset_request("paper", label_fusion=True).method_config.label_fusion == (
        LabelFusionConfig(min_frame_share=0.0)
    )
    assert preset_request(label_fusion=False).method_config.label_fusion is None
    assert preset_request().method_config.label_fusion == LabelFusionConfig()
    assert preset_request("paper").method_config.label_fusion is None
    on_again = preset_request("paper", "ultron", echo_support=True).method_config.echo_support
    assert on_again is not None and on_again == pipeline_preset("fast").ultron.echo_support
    fast = preset_request()
    assert fast.method_config == UltronConfig(occupancy=OccupancyTrainConfig(seed=fast.seed))
    assert preset_request(method="on").method_config == ONConfig()
    assert preset_request().method_config.occupancy.precision == "float32"
    bf16 = preset_request(occupancy_precision="bfloat16").method_config.occupancy
    assert bf16.precision == "bfloat16" and bf16.iters == 1500  # the preset's other settings
    on_bf16 = preset_request(method="on", occupancy_precision="bfloat16").method_config
    assert on_bf16.occupancy.precision == "bfloat16"
    with pytest.raises(UltronInputError, match="precision"):
        preset_request(occupancy_precision="half")
    assert fast.method == "ultron" and fast.label_fraction == 0.1
    assert preset_field_config("paper", 1).iterations == 75_000
    assert preset_field_config("paper", 1, 10).iterations == 10
    assert preset_field_config("fast", 1) == FieldTrainConfig(seed=1)


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


def test_benchmark_config_of_a_preset_sets_every_stage():
    paper = pipeline_preset("paper")
    config = benchmark_config("paper", seeds=2)
    assert config.field_fit == paper.field and config.ultron == paper.ultron
    assert config.on == paper.on and config.rocosdf_preset == paper.rocosdf_preset == "paper"
    assert config.seeds == 2 and not config.quick
    assert benchmark_config() == BenchmarkConfig()
    assert benchmark_config("fast", quick=True, jobs=2) == quick_config(jobs=2)
    with pytest.raises(UltronInputError, match="preset"):
        benchmark_config("paper", quick=True)
    with pytest.raises(UltronInputError, match="preset"):
        benchmark_config("slow")


def test_evaluation_chunk_grows_only_off_the_cpu():
    assert evaluation_chunk(torch.device("cpu"), 1000) == 1000
    assert evaluation_chunk(None, 1000) == 1000
    assert evaluation_chunk(torch.device("cuda"), 1000) == 1000 * ACCELERATOR_CHUNK_FACTOR


@pytest.mark.parametrize(
    ("preset", "flag", "expected"),
    [("fast", "--no-echo-support", False), ("paper", "--echo-support", True)],
)
def test_cli_echo_support_flag_wins_over_the_preset(
    preset, flag, expected, tmp_path: Path, monkeypatch
):
    import ultron.pipeline.run

    seen = {}

    def fake_run(dataset, request, out, *args, **kwargs):
        seen["request"] = request
        return {"metrics": None, "timings_s": {}}

    monkeypatch.setattr(ultron.pipeline.run, "reconstruct", fake_run)
    args = ["reconstruct", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", preset, flag]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (seen["request"].method_config.echo_support is not None) is expected


@pytest.mark.parametrize(("value", "expected"), [("0", 0.0), ("2.5", 2.5), ("-1", None)])
def test_cli_label_support_reaches_the_request_or_exits_2(
    value, expected, tmp_path: Path, monkeypatch
):
    import ultron.pipeline.run

    seen = {}

    def fake_run(dataset, request, out, *args, **kwargs):
        seen["request"] = request
        return {"metrics": None, "timings_s": {}}

    monkeypatch.setattr(ultron.pipeline.run, "reconstruct", fake_run)
    args = ["reconstruct", str(tmp_path), "--out", str(tmp_path / "o"), "--label-support", value]
    result = CliRunner().invoke(app, args)
    if expected is None:
        assert result.exit_code == 2 and "--label-support" in result.output
        assert "request" not in seen
    else:
        assert result.exit_code == 0, result.output
        assert seen["request"].method_config.observed.label_support_mm == expected


@pytest.mark.parametrize("name", ["echo_support", "label_fusion"])
def test_ultron_config_refuses_a_wrong_optional_part(name):
    with pytest.raises(UltronInputError, match=name):
        UltronConfig(**{name: "on"})


def test_cli_label_fusion_flag_reaches_the_request(tmp_path: Path, monkeypatch):
    import ultron.pipeline.run

    seen = []

    def fake_run(dataset, request, out, *args, **kwargs):
        seen.append(request.method_config.label_fusion)
        return {"metrics": None, "timings_s": {}}

    monkeypatch.setattr(ultron.pipeline.run, "reconstruct", fake_run)
    for flags in (["--label-fusion"], ["--no-label-fusion"], [], ["--preset", "paper"]):
        args = ["reconstruct", str(tmp_path), "--out", str(tmp_path / "o"), *flags]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
    # given: at any label fraction, or never; not given: the preset's (fast: nearly every frame)
    assert seen == [LabelFusionConfig(min_frame_share=0.0), None, LabelFusionConfig(), None]


def test_a_bfloat16_fit_without_native_products_is_warned_of(monkeypatch):
    import ultron.pipeline.run as run

    cpu = torch.device("cpu")
    bf16 = preset_request(occupancy_precision="bfloat16").method_config
    monkeypatch.setattr(run, "native_bfloat16", lambda device: False)
    (line,) = run.precision_warnings(bf16, cpu)
    assert line.startswith("--occupancy-precision bfloat16: cpu has no native bfloat16")
    on = preset_request(method="on", occupancy_precision="bfloat16").method_config
    assert len(run.precision_warnings(on, cpu)) == 1
    assert run.precision_warnings(preset_request().method_config, cpu) == []  # float32
    compounding = preset_request(method="compounding").method_config  # no occupancy fit
    assert run.precision_warnings(compounding, cpu) == []
    monkeypatch.setattr(run, "native_bfloat16", lambda device: True)
    assert run.precision_warnings(bf16, cpu) == []
