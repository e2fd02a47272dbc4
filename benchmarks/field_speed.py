"""Benchmark: speed of the acoustic field on 2 CPU threads.

Prints, in one run:

1. a full fit with the default configuration (grid backend, default iterations) on a dataset
   downsampled to a simulated-phantom-like size (default: the Ultra-NeRF l2 sweep, 200 frames,
   area-resampled to 128 × 96), with wall time and peak RSS;
2. the time to render one 128 × 96 frame from the fitted field (sampled and expected);
3. seconds per training step of the ``grid`` and the paper's ``mlp`` backend at the same batch
   (the default: 8 patches × 16 scanlines × H samples), steps interleaved so that both see the
   same machine load, and their ratio.

Usage::

    python benchmarks/field_speed.py /tmp/l2 --fit-shape 128x96
"""

from __future__ import annotations

# OpenMP keeps its default (spinning) wait policy: fastest on a dedicated 2-core machine. On a
# CPU shared with other jobs set OMP_WAIT_POLICY=PASSIVE (small parallel ops slow down up to 10x
# under oversubscription otherwise).
import argparse
import os
import resource
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import UnitCube
from ultron.data.orientation import field_cube
from ultron.fields import FieldConfig, build_field
from ultron.train import FieldTrainConfig, FrameSet, fit_field
from ultron.train.field_fit import make_optimizer, training_objective
from ultron.train.loop import descend


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def step_timer(backend: str, frames: FrameSet, cube: UnitCube, config: FieldTrainConfig):
    """A closure running one training step of ``backend``; returns its wall time in s."""
    pixel_mm = min(frames.probe.axial_spacing_mm, frames.probe.lateral_spacing_mm)
    field_config = FieldConfig(backend=backend)
    module, _ = build_field(field_config, cube.half_extent_mm, pixel_mm, seed=0)
    step_config = replace(config, field=field_config)
    optimizer = make_optimizer(module, step_config.lr)
    generator = torch.Generator().manual_seed(0)

    def run() -> float:
        started = time.perf_counter()
        loss = training_objective(module, frames, cube, config.render, step_config, generator)[0]
        descend([optimizer], loss)
        return time.perf_counter() - started

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--fit-shape", default="128x96")
    parser.add_argument("--iters", type=int, default=None, help="fit iterations [config default]")
    parser.add_argument("--speed-steps", type=int, default=12, help="timed steps per backend")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--skip-fit", action="store_true")
    parser.add_argument("--patch-width", type=int, default=None, help="[config default]")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    shape = tuple(int(s) for s in args.fit_shape.lower().split("x"))
    dataset = SweepDataset.load(args.dataset)
    overrides = {"iterations": args.iters} if args.iters else {}
    if args.patch_width:
        overrides["patch_width"] = args.patch_width
    config = FieldTrainConfig(fit_shape=shape, **overrides)
    frames = FrameSet.from_dataset(dataset, shape, config.holdout_every)
    if config.confidence_prior_weight > 0:  # the default prior reads the confidence maps
        frames = frames.with_confidence()
    print(
        f"dataset {args.dataset}: {frames.images.shape[0]} frames resampled to {shape[0]}x{shape[1]}"
        f" (native {dataset.probe.height_px}x{dataset.probe.width_px}); torch threads"
        f" {torch.get_num_threads()}; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')};"
        " the CPU is shared, so times may be inflated"
    )

    if not args.skip_fit:
        out = Path(tempfile.mkdtemp(prefix="ultron-field-speed-"))
        started = time.perf_counter()
        last: dict = {}
        fitted = fit_field(dataset, config, out, progress=last.update, resume=False)
        fit_s = time.perf_counter() - started
        print(
            f"fit: grid backend, {config.iterations} iterations (default config), batch"
            f" {config.frames_per_batch}x{config.patch_width} scanlines: wall {fit_s:.1f} s"
            f" (incl. data prep, checks, checkpoints), peak RSS {peak_rss_gb():.2f} GB;"
            f" last held-out PSNR {last.get('holdout_psnr', float('nan')):.2f} dB"
        )
        pose = frames.probe_to_world[:1]
        for expected in (False, True):
            fitted.render(pose, expected=expected)  # warm-up
            times = []
            for _ in range(10):
                started = time.perf_counter()
                fitted.render(pose, seed=1, expected=expected)
                times.append(time.perf_counter() - started)
            label = "expected" if expected else "sampled"
            print(
                f"render one {shape[0]}x{shape[1]} frame ({label}): median"
                f" {statistics.median(times):.4f} s, min {min(times):.4f} s"
            )

    cube, _ = field_cube(dataset.all_poses(), frames.probe, config.orientation)
    timers = {b: step_timer(b, frames, cube, config) for b in ("grid", "mlp")}
    for run in timers.values():  # warm-up
        run(), run()
    times: dict[str, list[float]] = {b: [] for b in timers}
    for _ in range(args.speed_steps):
        for backend, run in timers.items():
            times[backend].append(run())
    n_points = config.frames_per_batch * config.patch_width * shape[0]
    medians = {b: statistics.median(t) for b, t in times.items()}
    for backend, median in medians.items():
        print(
            f"step {backend:4s}: median {median:.4f} s ({1 / median:.2f} steps/s),"
            f" min {min(times[backend]):.4f} s, batch {n_points} samples"
        )
    print(f"grid speed-up over mlp: {medians['mlp'] / medians['grid']:.1f}x (median step times)")
    print(f"peak RSS of this process: {peak_rss_gb():.2f} GB")


if __name__ == "__main__":
    main()
