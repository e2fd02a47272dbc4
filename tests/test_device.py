"""``--device``: resolution, one-line errors, device-correct compute paths, portable files.

No GPU is needed: the compute paths are run with their networks on PyTorch's ``meta`` device,
which refuses to mix with CPU tensors (as CUDA does) except 0-dim ones, so a tensor created
without the module's device in the renderer, the field fit or the occupancy loss fails here.
The test that compares CUDA with CPU runs only where CUDA is present.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from field_configs import quick_field_config
from strict_device import StrictDevices
from ultron.cli.main import app
from ultron.data.geometry import UnitCube
from ultron.device import (
    cpu_state,
    describe_device,
    module_device,
    native_bfloat16,
    resolve_device,
)
from ultron.errors import UltronInputError
from ultron.fields.factory import build_field
from ultron.render.renderer import RenderConfig, render_field
from ultron.train.field_config import FieldTrainConfig
from ultron.train.field_fit import training_objective
from ultron.train.frames import FrameSet
from ultron.train.loop import descend
from ultron.train.occupancy import OccupancyTrainConfig, observed_negatives_bce

NO_CUDA = not torch.cuda.is_available()
META = torch.device("meta")


# ------------------------------------------------------------------------------ resolution
def test_cpu_and_auto_resolve():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(" CPU ") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert resolve_device(None).type == expected


@pytest.mark.parametrize("spec", ["tpu", "cuda:x", "gpu", "", "meta"])
def test_malformed_device_names_the_option(spec):
    with pytest.raises(
        UltronInputError, match=r"--device: expected auto, cpu, cuda, cuda:N or mps"
    ):
        resolve_device(spec)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
@pytest.mark.parametrize("spec", ["cuda", "cuda:0", "cuda:3"])
def test_unavailable_cuda_is_one_line(spec):
    with pytest.raises(UltronInputError) as info:
        resolve_device(spec, "--device")
    message = str(info.value)
    assert message.startswith("argument: --device:") and "\n" not in message
    assert spec in message and "--device cpu" in message


def test_describe_device_records_name_and_torch():
    record = describe_device(torch.device("cpu"))
    assert record["device"] == "cpu" and record["torch"] == torch.__version__
    assert json.loads(json.dumps(record)) == record  # JSON round-trips, for run.json


def test_cpu_state_moves_nested_tensors_to_cpu_detached():
    weight = torch.ones(2, requires_grad=True)
    state = {"a": weight * 2, "b": [torch.zeros(1), 3], "c": {"d": (torch.arange(3), "x")}}
    moved = cpu_state(state)
    assert moved.keys() == state.keys() and type(moved["b"]) is list
    assert type(moved["c"]["d"]) is tuple and moved["c"]["d"][1] == "x" and moved["b"][1] == 3
    assert torch.equal(moved["c"]["d"][0], torch.arange(3))
    assert torch.equal(moved["a"], torch.full((2,), 2.0))
    assert moved["a"].grad_fn is None and not moved["a"].requires_grad  # detached
    tensors = [moved["a"], moved["b"][0], moved["c"]["d"][0]]
    assert all(t.device == torch.device("cpu") for t in tensors)


# ------------------------------------------------------------------ device-correct compute
def _meta_field():
    config = quick_field_config()
    cube = UnitCube((0.0, 20.0, 0.0), 40.0)
    module, _ = build_field(config.field, cube.half_extent_mm, 0.5, seed=0)
    return config, cube, module.to(META)


def test_render_field_computes_on_the_field_device(tiny_dataset):
    _, cube, module = _meta_field()
    poses = torch.as_tensor(tiny_dataset.all_poses()[:2])
    for expected in (True, False):
        with StrictDevices():
            rendered = render_field(
                module, cube, tiny_dataset.probe, poses, RenderConfig(), torch.arange(8),
                generator=torch.Generator().manual_seed(0), expected=expected,
            )  # fmt: skip
        assert rendered.intensity.device == META and rendered.transmission.device == META
        assert rendered.intensity.shape == (2, tiny_dataset.probe.height_px, 8)
    assert module_device(module) == META


@pytest.mark.parametrize("prior", [0.0, 1.0])
def test_training_step_runs_on_the_field_device(tiny_l3, prior):
    from ultron.data.dataset import SweepDataset

    tiny_dataset = SweepDataset.load(tiny_l3)
    config = quick_field_config(confidence_prior_weight=prior, scattering_tv_weight=0.1)
    _, cube, module = _meta_field()
    frames = FrameSet.from_dataset(tiny_dataset, None, config.holdout_every)
    if prior:
        frames = frames.with_confidence()
    frames = frames.to(META)
    assert frames.probe_to_world.device.type == "cpu"  # geometry and batches stay on the CPU
    optimizer = torch.optim.Adam(module.parameters(), lr=config.lr)  # fused has no meta kernel
    generator = torch.Generator().manual_seed(0)
    with StrictDevices():
        total, loss, mse = training_objective(
            module, frames, cube, config.render, config, generator
        )
        descend([optimizer], total)
    assert loss.device == META and mse.device == META


def test_occupancy_losses_on_the_network_device():
    from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig

    network = OccupancyNetwork(OccupancyNetworkConfig(in_dim=3)).to(META)
    inputs = torch.rand(16, 3).to(META)
    with StrictDevices():
        f = network.occupancy(inputs)
        y = torch.zeros(16, device=META)
        loss = observed_negatives_bce(f, torch.ones(16, device=META), y, 0.3)
    assert loss.device == META


# ----------------------------------------------------------------------- portable outputs
def _saved_tensors(path: Path) -> list[torch.Tensor]:
    payload = torch.load(io.BytesIO(path.read_bytes()), weights_only=True)
    found: list[torch.Tensor] = []

    def walk(value):
        if torch.is_tensor(value):
            found.append(value)
        elif isinstance(value, dict):
            for v in value.values():
                walk(v)
        elif isinstance(value, list | tuple):
            for v in value:
                walk(v)

    walk(payload)
    return found


def test_field_checkpoint_is_cpu_and_loads_with_map_location(tiny_l3, tmp_path):
    from ultron.data.dataset import SweepDataset
    from ultron.models.field_dir import CHECKPOINT, FIELD_JSON
    from ultron.models.fitted import load_field
    from ultron.train.field_fit import fit_field

    tiny_dataset = SweepDataset.load(tiny_l3)
    config = quick_field_config(iterations=4, checkpoint_every=2)
    fitted = fit_field(tiny_dataset, config, tmp_path / "f", device="cpu")
    tensors = _saved_tensors(tmp_path / "f" / CHECKPOINT)
    assert tensors and all(t.device.type == "cpu" for t in tensors)
    meta = json.loads((tmp_path / "f" / FIELD_JSON).read_text())
    assert meta["fitted_on"]["device"] == "cpu"
    loaded = load_field(tmp_path / "f", device="cpu")
    assert loaded.device.type == "cpu"
    poses = tiny_dataset.all_poses()[:1]
    np.testing.assert_array_equal(
        loaded.render(poses, expected=True), fitted.render(poses, expected=True)
    )
    with pytest.raises(UltronInputError, match="device"):
        load_field(tmp_path / "f", device="tpu")


def test_a_fit_repeats_bit_for_bit_with_the_device_as_a_torch_device(tiny_l3, tmp_path):
    """The same seed gives the same field, whether the device comes as the default string or
    as a ``torch.device`` (what a library caller holds)."""
    from ultron.data.dataset import SweepDataset
    from ultron.train.field_fit import fit_field

    tiny_dataset = SweepDataset.load(tiny_l3)
    config = quick_field_config(iterations=6)
    a = fit_field(tiny_dataset, config, tmp_path / "a")
    b = fit_field(tiny_dataset, config, tmp_path / "b", device=torch.device("cpu"))
    assert next(b.field.parameters()).device == torch.device("cpu")
    for (name, x), (_, y) in zip(
        a.field.state_dict().items(), b.field.state_dict().items(), strict=True
    ):
        assert torch.equal(x, y), name


# ------------------------------------------------------------------------------------ CLI
COMMANDS = {
    "fit-field": ["fit-field", "{d}", "--out", "{o}"],
    "render": ["render", "{d}", "--out", "{o}.npy", "--poses", "{d}/p.npy"],
    "reconstruct": ["reconstruct", "{d}", "--out", "{o}"],
    "finetune": ["finetune", "{d}", "{d}", "--out", "{o}"],
    "demo": ["demo", "--out", "{o}"],
    "benchmark": ["benchmark", "--out", "{o}", "--quick"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_device_option(command):
    result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
    assert result.exit_code == 0 and "--device" in result.output


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_unavailable_cuda_fails_in_one_line_before_any_work(command, tmp_path):
    out = tmp_path / "out"
    args = [a.format(d=tmp_path, o=out) for a in COMMANDS[command]] + ["--device", "cuda"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--device" in lines[0] and "Traceback" not in result.output
    assert not out.exists() and not Path(f"{out}.npy").exists()


def test_reconstruct_records_the_device(tiny_l3, tmp_path):
    result = CliRunner().invoke(
        app,
        ["reconstruct", str(tiny_l3), "--out", str(tmp_path / "r"), "--method", "compounding",
         "--label-fraction", "0.5", "--points", "2000", "--device", "cpu"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    assert run["device"]["device"] == "cpu" and run["device"]["torch"] == torch.__version__


def test_request_rejects_a_bad_device():
    from ultron.pipeline.run import ReconstructionRequest

    with pytest.raises(UltronInputError, match="device"):
        ReconstructionRequest(device="tpu")


# ---------------------------------------------------------------------------------- GPU
@pytest.mark.skipif(NO_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_field_step_on_cuda_matches_cpu(tiny_l3, preset):
    """One step of the field fit computes the same loss and gradients on CUDA as on the CPU
    (same initial field, same CPU generator): the batch, the scatterers and the physics are
    the same; only the order of float32 sums differs (measured on an H200 with the fast
    preset: gradients within 2.3e-7 of the CPU's, relative norm)."""
    import copy

    from ultron.data.dataset import SweepDataset
    from ultron.pipeline.presets import pipeline_preset
    from ultron.train.field_fit import _prepare
    from ultron.train.fit_shape import resolve_fit_shape

    dataset = SweepDataset.load(tiny_l3)
    config = resolve_fit_shape(pipeline_preset(preset).field, dataset)
    frames, cube, module, _ = _prepare(dataset, config)
    render = config.render.rescaled(dataset.probe, frames.probe)
    results = {}
    for device in ("cpu", "cuda"):
        field = copy.deepcopy(module).to(device)
        generator = torch.Generator().manual_seed(0)
        total = training_objective(field, frames.to(device), cube, render, config, generator)[0]
        total.backward()
        grads = [p.grad.flatten().cpu() for p in field.parameters() if p.grad is not None]
        results[device] = (float(total.detach()), torch.cat(grads))
    (loss_cpu, grad_cpu), (loss_cuda, grad_cuda) = results["cpu"], results["cuda"]
    assert loss_cuda == pytest.approx(loss_cpu, rel=1e-5)
    assert float((grad_cuda - grad_cpu).norm() / grad_cpu.norm()) < 1e-4


@pytest.mark.skipif(NO_CUDA, reason="needs a CUDA device")
def test_tiny_ultron_on_cuda_matches_cpu(tiny_l3, tmp_path, monkeypatch):
    from ultron.methods.ultron_method import UltronConfig
    from ultron.metrics.surface import MetricsConfig
    from ultron.pipeline.run import ReconstructionRequest, reconstruct

    monkeypatch.setenv("ULTRON_CACHE", str(tmp_path / "cache"))
    occupancy = OccupancyTrainConfig(iters=600, batch_size=1024, lr=1e-3)
    field = FieldTrainConfig(iterations=400, check_every=1000, checkpoint_every=1000)
    metrics = {}
    for device in ("cpu", "cuda"):
        request = ReconstructionRequest(
            method="ultron", label_fraction=0.5, method_config=UltronConfig(occupancy=occupancy),
            metrics=MetricsConfig(n_points=20_000, repeats=1), device=device,
        )  # fmt: skip
        summary = reconstruct(tiny_l3, request, tmp_path / device, field_config=field)
        metrics[device] = summary["metrics"]["mean"]
    # The fit amplifies float32 rounding (the step test above: 2e-7) over 1000 steps, and a
    # CUDA fit is not even reproducible: grid_sample's backward adds with atomics, in no fixed
    # order. Four fresh CUDA runs of this reconstruction on one H200 (fitted with CUDA graphs
    # thrice, eagerly once): CD 8.31, 8.37, 8.21, 7.10 mm and MAD 1.060, 1.103, 1.058, 1.072,
    # against its CPU's 8.363 / 1.080 (docs/devices.md); a 5 % bound on CD failed once. A GPU
    # path that computed anything else (another geometry, T, loss) lands far further off.
    tolerance = {"cd": 0.25, "mad": 0.05}
    for name, rel in tolerance.items():
        assert metrics["cuda"][name] == pytest.approx(metrics["cpu"][name], rel=rel), (
            name, metrics["cpu"], metrics["cuda"],
        )  # fmt: skip


def test_map_chunks_equals_one_call_and_keeps_no_graph():
    from ultron.device import map_chunks

    weight = torch.randn(3, 2, requires_grad=True)
    inputs = torch.randn(10, 3)
    whole = (inputs @ weight).detach()
    for chunk in (1, 3, 10, 100):
        out = map_chunks(lambda x: x @ weight, inputs, chunk, torch.device("cpu"))
        assert torch.equal(out, whole) and not out.requires_grad
    assert map_chunks(lambda x: x, torch.zeros(0, 3), 4).shape == (0,)
    assert map_chunks(lambda x: x, torch.zeros(0, 3), 4, empty=torch.zeros(0, 3)).shape == (0, 3)
    # gradients only when asked (and enabled), e.g. the phantoms' SDF
    kept = map_chunks(lambda x: x @ weight, inputs, 3, gradients=True)
    assert kept.requires_grad and torch.equal(kept.detach(), whole)
    with torch.no_grad():
        assert not map_chunks(lambda x: x @ weight, inputs, 3, gradients=True).requires_grad
    for bad in (0, -1, 1.5, True):
        with pytest.raises(UltronInputError, match="chunk"):
            map_chunks(lambda x: x, inputs, bad)


def _cpu_flags() -> set[str] | None:
    """The CPU's feature flags from /proc/cpuinfo (None where there is no such file)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    return {flag for line in text.splitlines() if line.startswith("flags") for flag in line.split()}


def test_native_bfloat16_follows_onednn_and_its_isa_cap():
    answer = native_bfloat16(torch.device("cpu"))
    assert isinstance(answer, bool)
    flags = _cpu_flags()
    if flags is not None and not any(f.startswith(("avx512", "amx")) for f in flags):
        assert answer is False  # no AVX-512 nor AMX: no bfloat16 products in hardware
    assert native_bfloat16(torch.device("meta")) is True  # no emulation to warn of
    # oneDNN capped at AVX2 has no bfloat16 products, whatever this CPU has
    code = "import torch; from ultron.device import native_bfloat16 as n; print(n(torch.device('cpu')))"
    env = {**os.environ, "ONEDNN_MAX_CPU_ISA": "AVX2"}
    capped = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert capped.returncode == 0 and capped.stdout.strip() == "False"
