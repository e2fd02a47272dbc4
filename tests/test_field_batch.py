"""The field fit's batch and loss (ultron.train.field_batch): the draws in one fixed order, the
loss as device work alone (what a CUDA graph can capture), and the graphed loss on a GPU."""

from __future__ import annotations

import copy
from dataclasses import replace

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from field_configs import quick_field_config
from ultron.data.dataset import SweepDataset
from ultron.data.geometry import UnitCube
from ultron.fields.factory import build_field
from ultron.fields.grid import (
    TV_WINDOW,
    VOLUME_TV_WINDOW,
    GridField,
    GridFieldConfig,
    _indexed_window_tv,
    _window_tv,
)
from ultron.pipeline.presets import pipeline_preset
from ultron.train.field_batch import FieldObjective, batch_inputs, draw_batch
from ultron.train.field_fit import make_optimizer, training_objective
from ultron.train.frames import FrameSet
from ultron.train.loop import descend

META = torch.device("meta")
NO_CUDA = not torch.cuda.is_available()


def _grid_field(axis_extent, cell_mm: float) -> GridField:
    """One-level grid field, 10 mm half extent: planes of 2 · 10 / cell_mm + 1 nodes."""
    config = GridFieldConfig(n_levels=1, smoothness_weight=1.0).resolved(10.0, cell_mm, axis_extent)
    return GridField(config, generator=torch.Generator().manual_seed(0)).double()


@pytest.mark.parametrize(
    "axis_extent", [(0.9, 0.8, 1.0), (0.25, 0.25, 1.0)], ids=["square", "per-axis"]
)
def test_drawn_regularisation_is_the_generator_one(axis_extent):
    # sides of 201 nodes (> TV_WINDOW = 96) draw a window; the per-axis xy plane (51²) not
    field = _grid_field(axis_extent, 0.1)
    shapes = [p.shape[-2:] for p in (field.planes[0] if field.per_axis else [field.planes[0]])]
    drawing = sum(max(shape) > TV_WINDOW for shape in shapes)
    assert drawing == (2 if field.per_axis else 1)
    for seed in range(6):  # windows kept and skipped (p = 0.25)
        drawn, direct = (torch.Generator().manual_seed(seed) for _ in range(2))
        draws = field.regularization_draws(drawn)
        assert draws.dtype == torch.int64 and draws.shape == (drawing, 3)
        assert torch.equal(field.regularization(draws=draws), field.regularization(direct))
        assert torch.equal(drawn.get_state(), direct.get_state())  # the same draws, no more


def test_indexed_window_equals_the_sliced_one():
    generator = torch.Generator().manual_seed(1)
    plane = torch.randn(3, 4, 130, 100, generator=generator, dtype=torch.float64)
    narrow = torch.randn(4, 60, 140, generator=generator, dtype=torch.float64)  # a side < window
    for target, (i, j) in ((plane, (30, 4)), (plane, (0, 0)), (narrow, (0, 44))):
        for kept in (True, False):
            row = torch.tensor([i, j, int(kept)])
            indexed = _indexed_window_tv(target, row)
            assert indexed.item() == pytest.approx(_window_tv(target, (i, j, kept)).item(), 1e-12)
            assert (indexed.item() == 0) == (not kept)


def test_small_planes_draw_nothing():
    field = _grid_field(None, 1.0)  # 21 nodes a side
    assert field.regularization_draws(torch.Generator().manual_seed(0)) is None


class HostTraffic(TorchDispatchMode):
    """Records every operation that reads a value back to the host or takes a CPU tensor
    (other than a 0-dim one) while computing on another device."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        flat, _ = tree_flatten((args, kwargs or {}))
        tensors = [t for t in flat if isinstance(t, torch.Tensor)]
        if func is torch.ops.aten._local_scalar_dense.default or any(
            t.device.type == "cpu" and t.dim() > 0 for t in tensors
        ):
            self.seen.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize(
    "scatterers, prior, hold, paper_field, volume_cell_mm",
    [
        ("expected", 0.0, False, False, None),
        ("sample", 1.0, False, False, None),
        ("expected", 1.0, True, False, None),
        ("sample", 0.0, False, True, None),
        ("expected", 1.0, False, False, 0.5),  # a dense volume of > 32 nodes: windowed prior
    ],
)
def test_field_loss_is_device_work_alone(
    tiny_l3, scatterers, prior, hold, paper_field, volume_cell_mm
):
    """Forward and backward of the loss touch no host tensor and read nothing back — what a
    CUDA graph needs to capture them (checked on the meta device, where a host read fails)."""
    dataset = SweepDataset.load(tiny_l3)
    config = quick_field_config(
        cell_mm=0.05, train_scatterers=scatterers, confidence_prior_weight=prior,
        scattering_tv_weight=0.1,
    )  # fmt: skip
    if volume_cell_mm is not None:
        config = config.with_volume(volume_cell_mm)
    if paper_field:  # Ultra-NeRF's MLP with its heads (no regulariser draws)
        config = replace(config, field=pipeline_preset("paper").field.field)
    cube = UnitCube((0.0, 20.0, 0.0), 40.0)
    module, _ = build_field(config.field, cube.half_extent_mm, 0.5, seed=0)
    frames = FrameSet.from_dataset(dataset, None, config.holdout_every)
    frames = (frames.with_confidence() if prior else frames).to(META)
    module = module.to(META)
    if volume_cell_mm is not None:
        assert max(module.config.volume_nodes) > VOLUME_TV_WINDOW
    batch = draw_batch(module, frames, cube, config, torch.Generator().manual_seed(0))
    assert (batch.draws is None) == paper_field and (batch.noise is None) == (
        scatterers != "sample"
    )
    inputs = batch_inputs(batch, frames, config, META)
    assert set(inputs) == {"points_unit", "target"} | ({"confidence"} if prior else set()) | (
        {"noise"} if scatterers == "sample" else set()
    ) | (set() if paper_field else {"draws"})
    objective = FieldObjective(module, config.render, config, frames.probe.axial_spacing_mm)
    hold_value = module.head_config.initial_scattering if hold else None
    objective(inputs, hold_value)  # builds the phase's loss (its kernels: host work, once)
    traffic = HostTraffic()
    with traffic:
        total, loss, mse = objective(inputs, hold_value)
        total.backward()
    assert traffic.seen == []
    assert total.device == META and not loss.requires_grad and not mse.requires_grad


def _objective_inputs(dataset_dir, device: torch.device):
    """A tiny field on ``device``, its fit config and step, and one batch's inputs there."""
    dataset = SweepDataset.load(dataset_dir)
    config = quick_field_config(confidence_prior_weight=0.0)
    cube = UnitCube((0.0, 20.0, 0.0), 40.0)
    module, _ = build_field(config.field, cube.half_extent_mm, 0.5, seed=0)
    frames = FrameSet.from_dataset(dataset, None, config.holdout_every).to(device)
    module = module.to(device)
    batch = draw_batch(module, frames, cube, config, torch.Generator().manual_seed(0))
    inputs = batch_inputs(batch, frames, config, device)
    return module, config, frames.probe.axial_spacing_mm, inputs


def _fallback_equals_eager(module, config, step_mm, inputs, reason: str) -> None:
    with pytest.warns(RuntimeWarning, match=f"CUDA graph capture failed.*{reason}") as caught:
        objective = FieldObjective(module, config.render, config, step_mm, graphs=True)
        graphed = objective(inputs)
        objective(inputs)  # the fall-back is remembered: no second capture, no second warning
    assert len(caught) == 1 and not objective.graphed
    eager = FieldObjective(module, config.render, config, step_mm)(inputs)
    assert all(torch.equal(a, b) for a, b in zip(graphed, eager, strict=True))


def test_graphs_asked_for_a_cpu_field_warn_and_fit_eagerly(tiny_l3):
    """A field that is not on a CUDA device cannot be captured, on any build (a CUDA build
    would otherwise record its CPU work as an empty graph): one warning, the eager loss."""
    parts = _objective_inputs(tiny_l3, torch.device("cpu"))
    _fallback_equals_eager(*parts, reason="the field is on cpu, not a CUDA device")


# ---------------------------------------------------------------------------------- GPU
@pytest.mark.skipif(NO_CUDA, reason="needs a CUDA device")
def test_a_failed_capture_on_cuda_warns_and_fits_eagerly(tiny_l3, monkeypatch):
    """An operation a CUDA graph cannot capture (here: the capture made to raise as PyTorch
    does) leaves a CUDA fit eager, with one warning quoting PyTorch's first line."""

    def refuse(*args, **kwargs):
        raise RuntimeError("operation not permitted when stream is capturing\nmore detail")

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", refuse)
    parts = _objective_inputs(tiny_l3, torch.device("cuda"))
    _fallback_equals_eager(*parts, reason="operation not permitted when stream is capturing")


@pytest.mark.skipif(NO_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("preset", ["fast", "paper", "fast-volume"])
def test_graphed_fit_steps_equal_the_eager_ones_on_cuda(tiny_l3, preset):
    """Ten updates replayed from CUDA graphs (both curriculum phases, so two captures) give
    the eager updates' losses and parameters on the same device, from the same batches
    (``fast-volume``: the grid field with its dense volume at 0.5 mm, its prior windowed)."""
    from ultron.train.field_fit import _prepare
    from ultron.train.fit_shape import resolve_fit_shape

    dataset = SweepDataset.load(tiny_l3)
    config = pipeline_preset(preset.removesuffix("-volume")).field
    if preset.endswith("-volume"):
        config = config.with_volume(0.5)
    config = resolve_fit_shape(config, dataset)
    frames, cube, module, _ = _prepare(dataset, config)
    frames = frames.to("cuda")
    render = config.render.rescaled(dataset.probe, frames.probe)
    runs = {}
    for graphs in (False, True):
        field = copy.deepcopy(module).to("cuda")
        optimizer = make_optimizer(field, config.lr)
        objective = FieldObjective(field, render, config, frames.probe.axial_spacing_mm, graphs)
        generator = torch.Generator().manual_seed(0)
        losses = []
        for k in range(10):
            total, _, _ = training_objective(
                field, frames, cube, render, config, generator, k < 4, objective
            )
            descend([optimizer], total)
            losses.append(float(total.detach()))
        assert objective.graphed == graphs, objective.failed
        runs[graphs] = (losses, torch.cat([p.detach().flatten() for p in field.parameters()]))
    (eager, eager_params), (graphed, graphed_params) = runs[False], runs[True]
    assert graphed == pytest.approx(eager, rel=1e-5)
    assert float((graphed_params - eager_params).norm() / eager_params.norm()) < 1e-5
