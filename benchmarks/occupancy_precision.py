"""Benchmark: the occupancy fit's step in float32 and in bfloat16 mixed precision.

Builds UltrON's default f_ω (θ and its stencil neighbours: 39 inputs, width 128, depth 8) and
seeded synthetic training data, then times ``fit_occupancy`` for ``--iters`` steps at the
default batch in each precision (``OccupancyTrainConfig.precision``), alternately,
``--repeats`` times each. Prints the median milliseconds per step of each, their ratio, the
largest difference between the two trained networks' f on the data, the CPU's bfloat16 flags
(/proc/cpuinfo) and whether oneDNN multiplies bfloat16 natively here
(:func:`ultron.device.native_bfloat16`, which ``ONEDNN_MAX_CPU_ISA`` can cap): without that,
torch emulates bfloat16 and it is by far the slower one.

Usage::

    python benchmarks/occupancy_precision.py [--iters 200] [--repeats 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from ultron.device import native_bfloat16
from ultron.fields.context import ThetaContextConfig
from ultron.fields.occupancy import OccupancyNetworkConfig
from ultron.train.occupancy import OccupancyTrainConfig, OccupancyTrainingData, fit_occupancy


def cpu_flags() -> str:
    """The bfloat16 flags /proc/cpuinfo lists (``none``; ``unknown`` off Linux)."""
    info = Path("/proc/cpuinfo")
    if not info.exists():
        return "unknown"
    flags = set(info.read_text().split())
    found = sorted(flags & {"avx512_bf16", "amx_bf16"})
    return ", ".join(found) or "none"


def synthetic_data(n: int, in_dim: int, seed: int) -> OccupancyTrainingData:
    """``n`` pixels of ``in_dim`` standard-normal inputs, a few percent bone, T uniform."""
    generator = torch.Generator().manual_seed(seed)
    inputs = torch.randn(n, in_dim, generator=generator)
    labels = (inputs[:, 0] > 1.5).to(torch.uint8)
    return OccupancyTrainingData(inputs, torch.rand(n, generator=generator), labels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iters", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--pixels", type=int, default=400_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    network = ThetaContextConfig().network(OccupancyNetworkConfig(), 3)
    data = synthetic_data(args.pixels, network.in_dim, args.seed)
    base = OccupancyTrainConfig(iters=args.iters, network=network, seed=args.seed)
    print(f"{args.iters} steps of batch {base.batch_size}, {args.threads} threads; CPU flags: "
          f"{cpu_flags()}; oneDNN native bfloat16: {native_bfloat16(torch.device('cpu'))}")  # fmt: skip
    timings: dict[str, list[float]] = {"float32": [], "bfloat16": []}
    trained = {}
    for _ in range(args.repeats):
        for precision, times in timings.items():
            start = time.perf_counter()
            trained[precision], _ = fit_occupancy(data, replace(base, precision=precision))
            times.append((time.perf_counter() - start) / args.iters * 1000)
    with torch.no_grad():
        probe = data.inputs[:65536]
        gap = (trained["float32"].occupancy(probe) - trained["bfloat16"].occupancy(probe)).abs()
    medians = {name: statistics.median(times) for name, times in timings.items()}
    for name, value in medians.items():
        print(f"{name:9s} {value:7.2f} ms/step")
    print(f"float32 / bfloat16: {medians['float32'] / medians['bfloat16']:.2f}x")
    print(f"max |f_float32 - f_bfloat16| after the fits: {float(gap.max()):.4f}")


if __name__ == "__main__":
    main()
