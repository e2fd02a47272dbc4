"""Benchmark: per-step and end-to-end times of the pipeline on the CPU and on a GPU (issue 18).

For one simulated dataset (default L3, seed 0) and every device asked for (default: ``cpu``,
plus ``cuda`` when this machine has one) it measures

1. per-step times (median of ``--steps`` steps after 3 warm-up steps, the device synchronised
   around each): a field step of the ``fast`` preset (grid field, 8 patches of 32 scanlines)
   and of the ``paper`` preset (8 × 128 MLP, 4 whole frames) as the fit takes it (on a GPU
   replayed from CUDA graphs, :mod:`ultron.train.field_batch`), an occupancy step of each
   preset's f_ω (4096 labelled pixels), and 100 fine-tuning iterations (1024 pixels a step,
   the last two layers frozen, as ``ultron finetune``); with the operations a field step
   launches (:func:`field_step_operations`, counted on the CPU);
2. end to end, through the library exactly as ``ultron reconstruct`` runs it: simulate → fit
   the field → UltrON (10 %) → mesh → metrics, with the ``fast`` preset on every device and,
   on a GPU (or with ``--paper-end-to-end``), the ``paper`` preset (75k + 50k iterations);
   a preset not run end to end is estimated from its per-step times × its iterations.
   ``--paper-fraction F`` runs the paper preset end to end with F of its field and f_ω
   iterations and extrapolates the whole run: the measured end-to-end seconds plus
   (1/F − 1) × the measured field and f_ω fitting seconds (meshing and metrics do not scale
   with the iterations).

It prints one table; the figures quoted in the README and the issue notes come from it.
Targets on one GPU of the H100 class (issue 18): the paper preset end to end ≤ 15 min, the
fast preset ≥ 10× faster than on 2 CPU cores, 100 fine-tuning iterations ≤ 0.5 s.

Usage::

    python benchmarks/device.py --out runs/device            # cpu (+ cuda when present)
    python benchmarks/device.py --out runs/device --devices cuda --paper-end-to-end
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from ultron.data.dataset import SweepDataset
from ultron.device import describe_device, resolve_device
from ultron.errors import UltronError
from ultron.fields.occupancy import OccupancyNetwork
from ultron.methods.finetune import freeze_last_layers
from ultron.metrics.surface import MetricsConfig
from ultron.phantom import SimulationConfig, simulate_dataset
from ultron.pipeline.presets import pipeline_preset
from ultron.pipeline.run import ReconstructionRequest, reconstruct
from ultron.train.field_batch import FieldObjective
from ultron.train.field_config import FieldTrainConfig
from ultron.train.field_fit import _prepare, make_optimizer, training_objective
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.loop import descend
from ultron.train.occupancy import OccupancyTrainConfig, OccupancyTrainingData, fit_occupancy


def synchronise(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(device: torch.device, fn, steps: int, warmup: int = 3) -> float:
    """Median seconds of ``fn()`` over ``steps`` calls after ``warmup`` ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(steps):
        synchronise(device)
        start = time.perf_counter()
        fn()
        synchronise(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def preset_field(preset: str, volume_cell_mm: float | None = None) -> FieldTrainConfig:
    """``preset``'s field fit, with the grid field's dense volume at ``volume_cell_mm`` when
    given (``ultron fit-field --volume-cell``; the MLP of the paper preset has none)."""
    config = pipeline_preset(preset).field
    if volume_cell_mm is None or config.field.backend != "grid":
        return config
    return config.with_volume(volume_cell_mm)


def field_step(
    dataset: SweepDataset,
    preset: str,
    device: torch.device,
    graphs: bool | None = None,
    volume_cell_mm: float | None = None,
):
    """One update of ``preset``'s field fit on ``device`` (a fresh field, seed 0), callable;
    replayed from CUDA graphs as the fit does (``graphs``, default: on a CUDA device)."""
    graphs = device.type == "cuda" if graphs is None else graphs
    config = resolve_fit_shape(preset_field(preset, volume_cell_mm), dataset)
    frames, cube, module, _ = _prepare(dataset, config)
    frames, module = frames.to(device), module.to(device)
    optimizer = make_optimizer(module, config.lr)
    generator = torch.Generator().manual_seed(0)
    render = config.render.rescaled(dataset.probe, frames.probe)
    objective = FieldObjective(module, render, config, frames.probe.axial_spacing_mm, graphs)

    def step() -> None:
        loss = training_objective(module, frames, cube, render, config, generator, False, objective)
        descend([optimizer], loss[0])

    return step


def field_step_seconds(
    dataset: SweepDataset, preset: str, device: torch.device, steps: int, volume_cell_mm=None
) -> float:
    return timed(device, field_step(dataset, preset, device, None, volume_cell_mm), steps)


#: Operations that only re-describe a tensor's memory (no kernel on any device).
VIEW_OPERATIONS = frozenset({
    "view", "_unsafe_view", "_reshape_alias", "expand", "slice", "select", "unsqueeze",
    "squeeze", "t", "transpose", "permute", "as_strided", "alias", "detach", "split",
    "split_with_sizes", "unbind", "narrow", "diagonal", "unfold",
})  # fmt: skip


def field_step_operations(dataset: SweepDataset, preset: str, volume_cell_mm=None) -> int:
    """Tensor operations (views excluded) one field step of ``preset`` dispatches on the CPU,
    forward, backward and optimiser together: each is at least one kernel launch on a GPU,
    where a step this small is bound by launches, not arithmetic (docs/devices.md)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.operations = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket.__name__ not in VIEW_OPERATIONS:
                self.operations += 1
            return func(*args, **(kwargs or {}))

    step = field_step(dataset, preset, torch.device("cpu"), None, volume_cell_mm)
    step()  # the first step creates the optimiser's state
    counter = Count()
    with counter:
        step()
    return counter.operations


def occupancy_data(in_dim: int, n: int = 200_000) -> OccupancyTrainingData:
    generator = torch.Generator().manual_seed(0)
    inputs = torch.randn(n, in_dim, generator=generator)
    labels = (torch.rand(n, generator=generator) < 0.05).to(torch.uint8)
    return OccupancyTrainingData(inputs, torch.rand(n, generator=generator), labels)


def occupancy_seconds(preset: str, device: torch.device, steps: int) -> tuple[float, float]:
    """(seconds per occupancy step of the preset, seconds for 100 fine-tuning iterations)."""
    ultron = pipeline_preset(preset).ultron
    network_config = ultron.context.network(ultron.occupancy.network, 3)
    data = occupancy_data(network_config.in_dim)
    config = replace(ultron.occupancy, iters=steps, network=network_config)
    synchronise(device)
    start = time.perf_counter()
    fit_occupancy(data, config, device=device)
    synchronise(device)
    per_step = (time.perf_counter() - start) / steps
    tuned = OccupancyNetwork(network_config)
    trainable = freeze_last_layers(tuned, 2)
    finetune = OccupancyTrainConfig(iters=100, batch_size=1024, lr=1e-3, network=network_config)
    fit_occupancy(data, replace(finetune, iters=3), tuned, lambda _: trainable, device=device)
    synchronise(device)
    start = time.perf_counter()
    fit_occupancy(data, finetune, tuned, lambda _: trainable, device=device)
    synchronise(device)
    return per_step, time.perf_counter() - start


def end_to_end(
    dataset_dir: Path,
    preset: str,
    device: torch.device,
    out: Path,
    fraction: float = 1.0,
    volume_cell_mm: float | None = None,
) -> dict:
    """Field fit + UltrON (10 %) + mesh + metrics through ``reconstruct``; stage seconds.

    With ``fraction`` < 1 the field and f_ω run that fraction of the preset's iterations, and
    ``extrapolated_s`` adds (1/fraction − 1) × their measured fitting seconds.
    """
    stages = pipeline_preset(preset)
    field = preset_field(preset, volume_cell_mm)
    field = replace(field, iterations=max(1, round(field.iterations * fraction)))
    occupancy = stages.ultron.occupancy
    occupancy = replace(occupancy, iters=max(1, round(occupancy.iters * fraction)))
    request = ReconstructionRequest(
        method="ultron", label_fraction=0.1, metrics=MetricsConfig(), device=str(device),
        method_config=replace(stages.ultron, occupancy=occupancy),
    )  # fmt: skip
    start = time.perf_counter()
    summary = reconstruct(
        dataset_dir, request, out, field_config=field, report=False, max_memory_gib=None
    )
    seconds = time.perf_counter() - start
    metrics = (summary.get("metrics") or {}).get("mean", {})
    timings = summary["timings_s"]
    fitting = timings.get("field", 0.0) + timings.get("occupancy_fit", 0.0)
    return {"seconds": seconds, "timings_s": timings, "cd": metrics.get("cd"),
            "cd_visible": metrics.get("cd_visible"), "fraction": fraction,
            "field_iterations": field.iterations, "occupancy_iterations": occupancy.iters,
            "extrapolated_s": seconds + (1 / fraction - 1) * fitting}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/device"))
    parser.add_argument("--phantom", default="L3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--devices", default=None, help="comma-separated (default: cpu[,cuda])")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per measurement")
    parser.add_argument("--paper-end-to-end", action="store_true",
                        help="run the paper preset end to end on every device (days on a CPU)")  # fmt: skip
    parser.add_argument("--presets", default="fast,paper", help="comma-separated presets")
    parser.add_argument("--paper-fraction", type=float, default=1.0,
                        help="fraction of the paper preset's iterations run end to end; the "
                             "whole run is extrapolated from the measured fitting seconds")  # fmt: skip
    parser.add_argument("--volume-cell", type=float, default=None, metavar="MM",
                        help="the grid field's dense volume at MM (fit-field --volume-cell; "
                             "the fast preset only)")  # fmt: skip
    args = parser.parse_args()
    if not 0 < args.paper_fraction <= 1:
        parser.error(f"--paper-fraction: expected a number in (0, 1], got {args.paper_fraction}")
    presets = [name.strip() for name in args.presets.split(",")]
    if not presets or not set(presets) <= {"fast", "paper"}:
        parser.error(f"--presets: expected fast and/or paper, got {args.presets!r}")
    if args.volume_cell is not None and not args.volume_cell > 0:
        parser.error(f"--volume-cell: expected a cell > 0 mm, got {args.volume_cell}")
    volume = args.volume_cell
    names = args.devices or ("cpu,cuda" if torch.cuda.is_available() else "cpu")
    devices = [resolve_device(name) for name in names.split(",")]
    dataset_dir = args.out / f"{args.phantom}-s{args.seed}"
    if not (dataset_dir / "dataset.json").is_file():
        simulate_dataset(SimulationConfig(phantom=args.phantom, seed=args.seed), out=dataset_dir)
    dataset = SweepDataset.load(dataset_dir)
    cache = args.out / "cache"
    shutil.rmtree(cache, ignore_errors=True)  # a fresh cache: end-to-end times fit the field
    os.environ["ULTRON_CACHE"] = str(cache)
    results = {}
    for device in devices:
        row: dict = {"device": describe_device(device)}
        for preset in presets:
            stages = pipeline_preset(preset)
            field_s = field_step_seconds(dataset, preset, device, args.steps, volume)
            occupancy_s, finetune_s = occupancy_seconds(preset, device, max(args.steps, 20))
            estimate = (
                field_s * stages.field.iterations + occupancy_s * stages.ultron.occupancy.iters
            )
            row[preset] = {"field_step_s": field_s, "occupancy_step_s": occupancy_s,
                           "finetune_100_s": finetune_s, "estimate_s": estimate,
                           "field_step_operations": field_step_operations(dataset, preset, volume),
                           "volume_cell_mm": volume if preset == "fast" else None}  # fmt: skip
            if preset == "fast" or device.type == "cuda" or args.paper_end_to_end:
                out = args.out / "runs" / f"{device.type}-{preset}{'-volume' if volume else ''}"
                fraction = args.paper_fraction if preset == "paper" else 1.0
                try:
                    e2e = end_to_end(dataset_dir, preset, device, out, fraction, volume)
                except UltronError as error:  # e.g. too few iterations to find a surface
                    e2e = {"error": str(error), "fraction": fraction}
                row[preset]["end_to_end"] = e2e
            print(json.dumps({str(device): {preset: row[preset]}}), flush=True)
        results[str(device)] = row
    (args.out / "device.json").write_text(json.dumps(results, indent=1))
    print()
    print("| device | preset | field step (s) | its operations | occupancy step (ms) "
          "| fine-tune 100 it (s) | end to end (s) | iterations run | extrapolated (s) "
          "| estimate (s) | CD (mm) |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, row in results.items():
        for preset in presets:
            r = row[preset]
            e2e = r.get("end_to_end", {})
            e2e = e2e if "seconds" in e2e else {}
            total = f"{e2e['seconds']:.1f}" if e2e else "—"
            ran = f"{e2e['field_iterations']} + {e2e['occupancy_iterations']}" if e2e else "—"
            whole = f"{e2e['extrapolated_s']:.0f}" if e2e and e2e["fraction"] < 1 else "—"
            cd = f"{e2e['cd']:.3f}" if e2e.get("cd") is not None else "—"
            print(f"| {name} | {preset} | {r['field_step_s']:.4f} | {r['field_step_operations']} "
                  f"| {1000 * r['occupancy_step_s']:.2f}"
                  f" | {r['finetune_100_s']:.3f} | {total} | {ran} | {whole} "
                  f"| {r['estimate_s']:.0f} | {cd} |")  # fmt: skip
    if len(results) > 1 and "cpu" in results and "fast" in presets:
        cpu = results["cpu"]["fast"].get("end_to_end", {}).get("seconds")
        for name, row in results.items():
            other = row["fast"].get("end_to_end", {}).get("seconds")
            if name != "cpu" and cpu and other:
                print(f"fast preset end to end: {name} is {cpu / other:.1f}× the CPU's speed")


if __name__ == "__main__":
    main()
