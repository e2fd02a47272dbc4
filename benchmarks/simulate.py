"""Benchmark: time and memory of ``simulate_dataset`` (the default four-sweep L3 dataset).

Prints wall time, CPU time, peak RSS, the time of each stage (SDF grid + scatterers, each
sweep, reference mesh + writing) and the dataset's size on disk. Targets (issue 3): ≤ 60 s
wall on 2 cores and ≤ 2 GB peak RSS for the defaults. The simulation itself runs on one torch
thread (see ``ultron.phantom.dataset``). On a shared machine the wall time includes waiting for
the CPU: compare it with the CPU time printed next to it.

Usage::

    python benchmarks/simulate.py                 # default L3 dataset into a temporary folder
    python benchmarks/simulate.py --phantom L4 --frames 60 --out /tmp/l4
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path


def peak_rss_gb() -> float:
    """Peak resident set size of this process, GB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--phantom", default="L3")
    parser.add_argument("--frames", type=int, default=None, help="frames per sweep (default 60)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="keep the dataset here")
    args = parser.parse_args()

    import torch

    from ultron.phantom import ScanConfig, SimulationConfig, simulate_dataset

    config = SimulationConfig(phantom=args.phantom, seed=args.seed)
    if args.frames is not None:
        config = config.replace(scan=ScanConfig(frames_per_sweep=args.frames))

    stages: list[tuple[str, float]] = []
    start = time.perf_counter()
    last = [start, ""]

    def progress(what: str, done: int, total: int) -> None:
        now = time.perf_counter()
        if last[1] and what != last[1]:
            stages.append((last[1], now - last[0]))
            last[0] = now
        if what != last[1]:
            last[0], last[1] = now, what

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "dataset"
        cpu0 = cpu_seconds()
        dataset = simulate_dataset(config, out=out, progress=progress)
        wall = time.perf_counter() - start
        cpu = cpu_seconds() - cpu0
        size_mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 1e6

    probe = dataset.probe
    print(f"phantom {args.phantom}, sweeps {[s.name for s in dataset.sweeps]}")
    print(
        f"{dataset.n_frames} frames of {probe.height_px}×{probe.width_px}"
        f" ({probe.width_mm:g} mm × {probe.depth_mm:g} mm), voxel {config.voxel_mm} mm"
    )
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs visible, simulation on 1 thread")
    for name, seconds in stages:
        print(f"  {name:<20} {seconds:7.2f} s")
    print(f"wall time:  {wall:7.2f} s   (target ≤ 60 s)")
    print(f"CPU time:   {cpu:7.2f} s")
    print(f"peak RSS:   {peak_rss_gb():7.3f} GB (target ≤ 2 GB)")
    print(f"frames/s:   {dataset.n_frames / wall:7.1f}")
    print(f"on disk:    {size_mb:7.1f} MB")


if __name__ == "__main__":
    main()
