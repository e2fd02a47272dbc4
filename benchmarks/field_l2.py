"""Benchmark: fit an acoustic field on the Ultra-NeRF l2 sweep, every 10th frame held out.

Prints PSNR and SSIM (Gaussian window 7, σ 1.5, k1 0.01, k2 0.03) of the held-out frames at the
fitted (rendered) resolution, for

- the field's expected B-mode (scatterers replaced by their expectation: the speckle-free mean
  image, the MSE-optimal prediction of a frame whose speckle is unknown),
- the field's sampled B-mode (one speckle realisation, seed 0),
- the baseline "copy the nearest training frame by pose" (nearest frame centre in world mm),

against the real frames resampled to that resolution (area average, ultron pixel geometry).

Usage (after ``ultron import-ultranerf /work/shared/data/ultranerf-synthetic-l2 --width-mm 80
--depth-mm 140 --out /tmp/l2``)::

    python benchmarks/field_l2.py /tmp/l2 --fit-shape 256x128 --iters 3000
"""

from __future__ import annotations

# OpenMP keeps its default (spinning) wait policy: fastest on a dedicated 2-core machine. On a
# CPU shared with other jobs set OMP_WAIT_POLICY=PASSIVE (small parallel ops slow down up to 10x
# under oversubscription otherwise).
import argparse
import resource
import tempfile
import time
from pathlib import Path

import torch

from ultron.data.dataset import SweepDataset
from ultron.data.geometry import frame_pixels_world
from ultron.fields import FieldConfig
from ultron.train import FieldTrainConfig, FrameSet, fit_field, psnr, ssim
from ultron.train.losses import METRIC_SSIM_K2


def frame_centres_mm(frames: FrameSet) -> torch.Tensor:
    """World position of each frame's centre pixel, (N, 3)."""
    pixels = frame_pixels_world(frames.probe_to_world, frames.probe)
    h, w = frames.probe.image_shape
    return pixels[:, h // 2, w // 2]


def metrics(pred: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    return psnr(pred, target), float(ssim(pred, target, k1=0.01, k2=METRIC_SSIM_K2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--fit-shape", default="256x128", help="HxW at which to fit and compare")
    parser.add_argument("--iters", type=int, default=3000)  # the field's default fit length
    parser.add_argument("--backend", default="grid", choices=("grid", "mlp"))
    parser.add_argument("--train-scatterers", default="expected", choices=("sample", "expected"))
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None, help="FIELD_DIR (default: a temp dir)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    shape = tuple(int(s) for s in args.fit_shape.lower().split("x"))
    dataset = SweepDataset.load(args.dataset)
    config = FieldTrainConfig(
        field=FieldConfig(backend=args.backend),
        iterations=args.iters,
        seed=args.seed,
        holdout_every=args.holdout_every,
        fit_shape=shape,
        train_scatterers=args.train_scatterers,
        check_every=max(1, args.iters // 5),
    )
    out = args.out or Path(tempfile.mkdtemp(prefix="ultron-field-l2-"))

    def report(entry: dict) -> None:
        if "holdout_psnr" in entry:
            print(
                f"  step {entry['step']:5d}  loss {entry['loss']:.4f}  batch PSNR {entry['psnr']:.2f}"
                f"  held-out PSNR {entry['holdout_psnr']:.2f} SSIM {entry['holdout_ssim']:.4f}"
                f"  ({entry['seconds']:.0f} s)",
                flush=True,
            )

    started = time.perf_counter()
    fitted = fit_field(dataset, config, out, progress=report, resume=False)
    fit_s = time.perf_counter() - started

    frames = FrameSet.from_dataset(dataset, shape, args.holdout_every)
    held, train = frames.holdout_index, frames.train_index
    target = frames.images[held]
    expected = torch.from_numpy(fitted.render(frames.probe_to_world[held], expected=True))
    sampled = torch.from_numpy(fitted.render(frames.probe_to_world[held], seed=0))
    centres = frame_centres_mm(frames)
    nearest = train[torch.cdist(centres[held], centres[train]).argmin(dim=1)]
    baseline = frames.images[nearest]

    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(
        f"dataset {args.dataset}: {frames.images.shape[0]} frames, fitted and compared at"
        f" {shape[0]}x{shape[1]} (native {dataset.probe.height_px}x{dataset.probe.width_px})"
    )
    print(
        f"held out: every {args.holdout_every}th frame -> {held.numel()} frames;"
        f" backend {args.backend}, {args.iters} iterations, training scatterers"
        f" {args.train_scatterers}, seed {args.seed}, {args.threads} threads"
    )
    print(f"fit wall time {fit_s:.1f} s, peak RSS {rss_gb:.2f} GB, FIELD_DIR {out}")
    print(f"{'method':38s} {'PSNR dB':>8s} {'SSIM':>7s}")
    for name, pred in (
        ("field, expected B-mode", expected),
        ("field, sampled B-mode (seed 0)", sampled),
        ("baseline: nearest training frame", baseline),
    ):
        p, s = metrics(pred, target)
        print(f"{name:38s} {p:8.2f} {s:7.4f}")


if __name__ == "__main__":
    main()
