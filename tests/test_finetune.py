"""Fine-tuning a trained UltrON network to a new shape, and the saved network files."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
from ultron.fields.sdf import SDFNetwork, SDFNetworkConfig
from ultron.mesh.occupancy_mesh import mesh_occupancy
from ultron.methods.finetune import (
    FinetuneConfig,
    ThetaModel,
    anchor_pixels,
    check_theta_model,
    finetune_ultron,
    freeze_last_layers,
)
from ultron.methods.ultron_method import UltronConfig, occupancy_function
from ultron.metrics.surface import MetricsConfig
from ultron.models.fitted import load_field
from ultron.phantom import SimulationConfig, simulate_dataset
from ultron.phantom.protocols import ScanConfig
from ultron.pipeline.finetune import finetune
from ultron.pipeline.model_io import NETWORK_FILE, load_network, save_network
from ultron.pipeline.run import ReconstructionRequest, reconstruct
from ultron.timing import StageTimer
from ultron.train.field_fit import FieldTrainConfig, fit_field
from ultron.train.occupancy import OccupancyTrainConfig
from ultron.train.visibility import VisibilityConfig

FAST_METRICS = MetricsConfig(n_points=3_000, repeats=1)
TINY_FIELD = FieldTrainConfig(iterations=400, check_every=1000, checkpoint_every=1000)


def _tiny(root: Path) -> tuple[Path, Path]:
    config = SimulationConfig(
        sweeps=("row", "column"),
        scan=ScanConfig(frames_per_sweep=12),
        height_px=64,
        width_px=48,
    )
    dataset_dir = root / "dataset"
    simulate_dataset(config, out=dataset_dir)
    field_dir = root / "field"
    fit_field(SweepDataset.load(dataset_dir), TINY_FIELD, field_dir)
    return dataset_dir, field_dir


@pytest.fixture(scope="module")
def shapes(tmp_path_factory) -> dict[str, Path]:
    """A tiny L3 with its field and an UltrON model trained on it.

    The "new shape" is the same tiny dataset: what is tested here is the mechanics (copying,
    freezing, direct application, outputs); generalisation L3 → L2 is measured by
    ``ultron benchmark``. A second simulation and field fit would double the test's cost.
    """
    root = tmp_path_factory.mktemp("finetune")
    l3, l3_field = _tiny(root)
    request = ReconstructionRequest(
        method="ultron",
        label_fraction=0.5,
        method_config=UltronConfig(
            occupancy=OccupancyTrainConfig(
                iters=600, batch_size=1024, lr=1e-3, positive_weight=None
            )
        ),
        metrics=FAST_METRICS,
    )
    reconstruct(l3, request, root / "model", field_dir=l3_field, report=False)
    return {"model": root / "model", "new": l3, "field": l3_field, "l3": l3}


def _config(**changes) -> FinetuneConfig:
    base = FinetuneConfig(label_fraction=0.2, iters=20, batch_size=1024, lr=1e-3,
                          metrics=FAST_METRICS)  # fmt: skip
    return replace(base, **changes)


def test_reconstruct_saves_a_loadable_network(shapes):
    network, meta = load_network(shapes["model"])
    assert isinstance(network, OccupancyNetwork)
    assert meta["method"] == "ultron" and meta["input"] == "theta" and meta["loss"] == "ultron"
    assert meta["theta_channels"] == list(load_field(shapes["field"]).channels)
    assert meta["transmission_source"] == "field" and meta["diagnostic"] is False
    run = json.loads((shapes["model"] / "run.json").read_text())
    assert Path(run["dataset_dir"]) == shapes["l3"].resolve()
    assert "network" not in run and "model" not in run


def test_model_meta_records_the_negatives_and_finetuning_keeps_them():
    model = ThetaModel(negatives="observed")
    meta = model.to_meta(("attenuation",), VisibilityConfig())
    assert meta["negatives"] == "observed"
    assert ThetaModel.from_meta(meta) == model
    assert FinetuneConfig().training(model).negatives == "observed"
    # a network.pt written before the option existed was trained with T-weighted negatives
    old = {k: v for k, v in meta.items() if k != "negatives"}
    assert ThetaModel.from_meta(old).negatives == "weighted"
    # and read its labels as stored; one written since reads the gap above a band as background
    assert meta["label_outer_side_mm"] == model.label_outer_side_mm > 0
    old = {k: v for k, v in meta.items() if k != "label_outer_side_mm"}
    assert ThetaModel.from_meta(old).label_outer_side_mm == 0.0


def test_freezing_keeps_last_two_layers_bit_identical(shapes):
    network, meta = load_network(shapes["model"])
    before = {k: v.clone() for k, v in network.state_dict().items()}
    dataset, fitted = SweepDataset.load(shapes["new"]), load_field(shapes["field"])
    result = finetune_ultron(dataset, fitted, network, ThetaModel.from_meta(meta), _config())
    tuned = result.model.network.state_dict()
    frozen = {f"trunk.output.{p}" for p in ("weight", "bias")}
    frozen |= {f"trunk.hidden.{len(network.trunk.hidden) - 1}.{p}" for p in ("weight", "bias")}
    for name, value in before.items():
        if name in frozen:
            assert torch.equal(tuned[name], value), name
        else:
            assert not torch.equal(tuned[name], value), f"{name} did not change"
    # the loaded model itself is a copy source: untouched
    for name, value in network.state_dict().items():
        assert torch.equal(value, before[name])
    assert all(p.requires_grad for p in result.model.network.parameters())
    assert result.info["n_label_frames"] == 5  # ⌈0.2 × 24⌉
    assert len(result.info["occupancy_log"]) >= 1


def test_iters_zero_equals_direct_application(shapes, tmp_path):
    config = _config(iters=0)
    summary = finetune(shapes["model"], shapes["new"], config, tmp_path / "direct",
                       field_dir=shapes["field"], report=False)  # fmt: skip
    network, meta = load_network(shapes["model"])
    dataset, fitted = SweepDataset.load(shapes["new"]), load_field(shapes["field"])
    context = ThetaModel.from_meta(meta).context
    _, volume, _ = mesh_occupancy(
        occupancy_function(fitted, network, context),
        dataset,
        config.meshing.meshing,
        StageTimer(),
    )
    import nibabel

    written = np.asarray(nibabel.load(tmp_path / "direct" / "occupancy.nii.gz").dataobj)
    np.testing.assert_array_equal(written, volume.astype(written.dtype))
    run = json.loads((tmp_path / "direct" / "run.json").read_text())
    assert run["method"] == "ultron-finetune" and run["label_fraction"] == 0.0
    assert "selection" not in run and summary["metrics"] is not None
    direct, _ = load_network(tmp_path / "direct")  # the output is itself a MODEL_DIR
    for name, value in network.state_dict().items():
        assert torch.equal(direct.state_dict()[name], value)


def test_finetune_cli_writes_reconstruct_outputs(shapes, tmp_path):
    from typer.testing import CliRunner

    from ultron.cli.main import app

    out = tmp_path / "tuned"
    result = CliRunner().invoke(
        app,
        ["finetune", str(shapes["model"]), str(shapes["new"]), "--out", str(out),
         "--field", str(shapes["field"]), "--label-fraction", "0.1", "--iters", "5",
         "--points", "2000"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    for name in ("mesh.ply", "occupancy.nii.gz", "metrics.json", "run.json", NETWORK_FILE):
        assert (out / name).is_file(), name
    run = json.loads((out / "run.json").read_text())
    assert run["finetune_config"]["iters"] == 5 and run["n_label_frames"] == 3
    assert run["transmission_source"] == "field"  # the model's own source
    assert Path(run["model_dir"]) == shapes["model"].resolve()
    stages = [s for s in run["timings_s"] if s != "total"]  # each printed as it starts and ends
    lines = result.output.splitlines()
    for stage in stages:
        assert f"{stage} …" in lines and any(t.startswith(f"{stage}: ") for t in lines), stage


def test_finetune_rejects_wrong_models(shapes, tmp_path):
    with pytest.raises(UltronInputError, match=NETWORK_FILE):
        finetune(tmp_path, shapes["new"], _config(), tmp_path / "x", shapes["field"])
    save_network(tmp_path / "on", OccupancyNetwork(OccupancyNetworkConfig()), {"method": "on",
                 "input": "unit_cube"})  # fmt: skip
    with pytest.raises(UltronInputError, match="UltrON network"):
        finetune(tmp_path / "on", shapes["new"], _config(), tmp_path / "x", shapes["field"])
    # a θ model whose width does not fit its recorded context (39 inputs for 3 channels and
    # two radii; this one takes θ alone)
    channels = list(load_field(shapes["field"]).channels)
    save_network(tmp_path / "narrow", OccupancyNetwork(OccupancyNetworkConfig()), {
        "method": "ultron", "input": "theta", "theta_channels": channels,
        "theta_context": {"radii_mm": [1.0, 2.0]}})  # fmt: skip
    with pytest.raises(UltronInputError, match=r"theta_context.*39 inputs.*takes 3"):
        finetune(tmp_path / "narrow", shapes["new"], _config(), tmp_path / "x", shapes["field"])
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / NETWORK_FILE).write_bytes(b"not a torch file")
    with pytest.raises(UltronInputError, match=r"network\.pt: cannot be read") as caught:
        load_network(tmp_path / "bad")
    assert "\n" not in str(caught.value) and "weights_only" not in str(caught.value)
    assert not (tmp_path / "x").exists()


def test_finetune_uses_the_given_or_the_models_transmission_source(shapes, tmp_path):
    from ultron.train.visibility import VisibilityConfig

    network, meta = load_network(shapes["model"])
    dataset, fitted = SweepDataset.load(shapes["new"]), load_field(shapes["field"])
    labels = VisibilityConfig("labels")
    config = _config(iters=5, visibility=labels, meshing=UltronConfig(voxel_mm=2.0))
    result = finetune_ultron(dataset, fitted, network, ThetaModel.from_meta(meta), config)
    assert result.info["transmission_source"] == "labels"
    assert result.model.meta["transmission_source"] == "labels"
    assert result.model.meta["transmission_parameters"] == {"margin_mm": 0.0, "decay_mm": 1.0}
    assert result.info["transmission_stats"]["bone_mean"] == 1.0  # T = 1 through the band
    # a model trained with the oracle keeps it: the new dataset's true T must exist, checked
    # before any work (no field fitted, nothing written)
    save_network(tmp_path / "oracle", network, {"method": "ultron", "input": "theta",
                 "loss": "ultron", "theta_channels": list(fitted.channels),
                 "transmission_source": "oracle"})  # fmt: skip
    plain = tmp_path / "plain"  # the new dataset without the simulator's transmission.npy
    shutil.copytree(shapes["new"], plain)
    for path in plain.glob("*/transmission.npy"):
        path.unlink()
    with pytest.raises(UltronInputError, match=r"transmission\.npy.*ultron simulate"):
        finetune(tmp_path / "oracle", plain, _config(), tmp_path / "x", shapes["field"])
    assert not (tmp_path / "x").exists()
    from typer.testing import CliRunner

    from ultron.cli.main import app

    result = CliRunner().invoke(app, ["finetune", str(shapes["model"]), str(shapes["new"]),
                                      "--out", str(tmp_path / "y"), "--visibility", "magic"])  # fmt: skip
    assert result.exit_code == 2 and "visibility" in result.stderr
    assert not (tmp_path / "y").exists()


@pytest.mark.parametrize("value", ["2", -1.0, float("nan"), float("inf"), True, None])
def test_a_model_with_a_bad_label_outer_side_is_refused(value):
    meta = {"input": "theta", "theta_channels": ["a"], "label_outer_side_mm": value}
    fitted = type("Fitted", (), {"channels": ("a",)})()
    with pytest.raises(
        UltronInputError, match=r"net\.pt: label_outer_side_mm: expected a finite number"
    ):
        check_theta_model(OccupancyNetwork(), meta, fitted, "net.pt")


def test_finetune_config_validation():
    with pytest.raises(ValueError, match="label_fraction"):
        FinetuneConfig(label_fraction=0)
    with pytest.raises(ValueError, match="iters"):
        FinetuneConfig(iters=-1)
    with pytest.raises(ValueError, match="frozen_layers"):
        freeze_last_layers(OccupancyNetwork(), 10)
    for weight in (-1.0, float("nan"), float("inf"), True, "1"):
        with pytest.raises(ValueError, match="anchor_weight"):
            FinetuneConfig(anchor_weight=weight)
    for points in (0, -5, 1.5, True):
        with pytest.raises(ValueError, match="anchor_points"):
            FinetuneConfig(anchor_points=points)


def test_anchor_pixels_are_drawn_evenly_from_every_frame(shapes):
    dataset = SweepDataset.load(shapes["new"])  # 2 sweeps × 12 frames of 64 × 48
    pixels = anchor_pixels(dataset, 120_000, seed=3)
    counts = np.zeros((2, 12))
    np.add.at(counts, (pixels.sweep_index, pixels.frame), 1)
    # 5000 expected per frame, binomial sd ≈ 70
    assert counts.min() > 4700 and counts.max() < 5300
    assert pixels.row.min() == 0 and pixels.row.max() == 63
    assert pixels.col.min() == 0 and pixels.col.max() == 47
    rows = np.bincount(pixels.row, minlength=64)
    assert rows.min() > 0.85 * rows.mean()
    again = anchor_pixels(dataset, 120_000, seed=3)
    assert np.array_equal(again.frame, pixels.frame) and np.array_equal(again.col, pixels.col)
    assert not np.array_equal(anchor_pixels(dataset, 120_000, seed=4).col, pixels.col)
    world = pixels.take(np.arange(5)).world_mm(dataset)
    assert world.shape == (5, 3) and np.isfinite(world).all()
    with pytest.raises(ValueError, match="n"):
        anchor_pixels(dataset, 0, seed=0)


def test_the_anchor_is_recorded_and_zero_weight_is_the_plain_fine_tuning(shapes):
    network, meta = load_network(shapes["model"])
    dataset, fitted = SweepDataset.load(shapes["new"]), load_field(shapes["field"])
    spec = ThetaModel.from_meta(meta)
    anchored = finetune_ultron(dataset, fitted, network, spec, _config(anchor_points=4096))
    plain = finetune_ultron(dataset, fitted, network, spec, _config(anchor_weight=0.0))
    assert "anchor" in anchored.info["occupancy_log"][-1]
    assert "anchor" not in plain.info["occupancy_log"][-1]
    assert anchored.info["finetune_config"]["anchor_weight"] == 1.0
    assert plain.info["finetune_config"]["anchor_weight"] == 0.0
    # the same labels, batches and start: the anchor is the only difference
    assert plain.info["occupancy_log"][0]["loss"] == anchored.info["occupancy_log"][0]["loss"]


def test_network_round_trip(tmp_path):
    torch.manual_seed(0)
    points = torch.rand(50, 3)
    for network in (
        OccupancyNetwork(),
        SDFNetwork(SDFNetworkConfig(hidden=32, layers=4, skip_at=2)),
    ):
        save_network(tmp_path / type(network).__name__, network, {"input": "x"})
        loaded, meta = load_network(tmp_path / type(network).__name__)
        assert meta == {"input": "x"}
        torch.testing.assert_close(loaded(points), network(points), rtol=0, atol=0)
