"""Benchmark: time and peak memory of a real recording's scale (issue 17, item 6).

A whole long bone is 1000+ frames over 40 cm in several passes. This script simulates such a
sweep of the ``femur`` phantom (:mod:`ultron.phantom.long_bone`: 2 passes × 520 frames,
``row`` and ``tilt_p10``, over its 47 cm), then runs every stage as its own process, so that
each stage's peak RSS is its own (``os.wait4``'s rusage of the child):

1. ``ultron simulate`` of the long sweep, and of a short one (60 frames per pass, the same
   bone and extent) to check that a field step's cost does not grow with the frame count;
2. ``ultron fit-field`` with few iterations on both (seconds per step from train_log.jsonl,
   setup and θ statistics included in the stage's wall time);
3. ``ultron reconstruct --method ultron`` and ``--method compounding`` at 10 % labels, and
   both again at a finer meshing voxel (``--fine-voxel-mm``, 0.25 mm: what a real probe's
   pixels ask for; the same ``reconstruct`` through the Python API, which takes the voxel);
4. with ``--compact``, a field fit on the L3 vertebra (2 × 60 frames, a 10 cm box) for the
   step's dependence on the box (the grid field's planes span it).

It prints a table of wall time and peak RSS per stage, the grids involved (the meshing grid
over the field of view's bounding box, the tiles of it the field of view reaches and the
voxels they hold, the volume written, the field's planes) and each reconstruction's own stage
timings. The defaults finish in about 15 minutes on 2 cores.

Usage::

    python benchmarks/long_sweep.py --out runs/long_sweep
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from ultron.methods.catalog import FIELD_METHODS

GIB = 1024**3
#: A reconstruction at another meshing voxel: ``reconstruct`` with the CLI's own request.
FINE_RECONSTRUCT = """
import sys
from dataclasses import replace
from ultron.methods.compounding_method import CompoundingMethodConfig
from ultron.methods.registry import get_method
from ultron.pipeline.presets import preset_request
from ultron.pipeline.run import reconstruct
dataset, field, out, method, fraction, seed, iters, points, voxel = sys.argv[1:]
request = preset_request("fast", method, float(fraction), int(seed), points=int(points),
                         occupancy_iters=int(iters))
config, voxel = request.method_config, float(voxel)
if isinstance(config, CompoundingMethodConfig):
    config = replace(config, volume=replace(config.volume, voxel_mm=voxel))
else:
    config = replace(config, voxel_mm=voxel)
request = replace(request, method_config=config)
needs_field = get_method(method).needs_field
reconstruct(dataset, request, out, field_dir=field if needs_field else None)
"""


def run_stage(name: str, command: list[str], log_dir: Path) -> dict:
    """Run ``command`` as a child process; its wall time and peak RSS (its own rusage)."""
    log_dir.mkdir(parents=True, exist_ok=True)
    log = log_dir / f"{name}.log"
    print(f"[{name}] {' '.join(command)}", flush=True)
    started = time.perf_counter()
    with open(log, "w", encoding="utf-8") as handle:
        child = subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - started
    if child.returncode != 0:
        tail = log.read_text(encoding="utf-8", errors="replace")[-3000:]
        raise SystemExit(f"[{name}] failed with exit code {child.returncode}:\n{tail}")
    peak = usage.ru_maxrss * 1024  # Linux: KiB
    print(f"[{name}] {seconds:.1f} s, peak RSS {peak / GIB:.2f} GiB", flush=True)
    return {"stage": name, "seconds": seconds, "peak_rss_bytes": peak}


def run_unless_done(name: str, command: list[str], done: Path, log_dir: Path) -> dict | None:
    """:func:`run_stage` unless ``done`` exists (a resumed benchmark; then None). The log file
    is named after ``name`` with spaces as underscores."""
    if done.exists():
        print(f"[{name}] done before", flush=True)
        return None
    return run_stage(name.replace(" ", "_"), command, log_dir)


def simulate_command(out: Path, args: argparse.Namespace, frames: int, phantom: str) -> list[str]:
    return [
        "ultron", "simulate", "--phantom", phantom, "--out", str(out), "--seed",
        str(args.seed), "--sweeps", args.sweeps, "--frames", str(frames), "--height-px",
        str(args.height_px), "--width-px", str(args.width_px), "--voxel-mm", str(args.sdf_voxel_mm),
    ]  # fmt: skip


def field_command(dataset: Path, out: Path, args: argparse.Namespace) -> list[str]:
    return [
        "ultron", "fit-field", str(dataset), "--out", str(out), "--iters",
        str(args.field_iters), "--seed", str(args.seed), "--no-resume",
    ]  # fmt: skip


def reconstruct_command(dataset: Path, field: Path, out: Path, method: str, args) -> list[str]:
    command = [
        "ultron", "reconstruct", str(dataset), "--out", str(out), "--method", method,
        "--label-fraction", str(args.label_fraction), "--seed", str(args.seed),
        "--points", str(args.points),
    ]  # fmt: skip
    if method in FIELD_METHODS:
        command += ["--field", str(field), "--occupancy-iters", str(args.occupancy_iters)]
    return command


def fine_command(dataset: Path, field: Path, out: Path, method: str, args) -> list[str]:
    return [
        sys.executable, "-c", FINE_RECONSTRUCT, str(dataset), str(field), str(out), method,
        str(args.label_fraction), str(args.seed), str(args.occupancy_iters), str(args.points),
        str(args.fine_voxel_mm),
    ]  # fmt: skip


def seconds_per_step(field_dir: Path) -> float:
    """Median seconds per training step between logged steps (held-out checks excluded: a
    step's ``seconds`` is taken before its check)."""
    entries = [
        json.loads(line) for line in (field_dir / "train_log.jsonl").read_text().split("\n") if line
    ]
    pairs = itertools.pairwise(entries)
    rates = sorted((b["seconds"] - a["seconds"]) / (b["step"] - a["step"]) for a, b in pairs)
    return rates[len(rates) // 2] if rates else math.nan


def datasets(args: argparse.Namespace) -> dict[str, tuple[str, int]]:
    """Name → (phantom, frames per pass) of the datasets to simulate."""
    out = {"long": (args.phantom, args.frames), "short": (args.phantom, args.short_frames)}
    if args.compact:
        out["compact"] = ("L3", args.short_frames)
    return out


def run_all(args: argparse.Namespace) -> list[dict]:
    """Every stage, in order (a dataset or field already in ``--out`` is reused)."""
    out, logs, rows = args.out, args.out / "logs", []
    for name, (phantom, frames) in datasets(args).items():
        dataset = out / f"dataset_{name}"
        if not (dataset / "dataset.json").is_file():
            command = simulate_command(dataset, args, frames, phantom)
            rows.append(run_stage(f"simulate_{name}", command, logs))
    for name in datasets(args):
        command = field_command(out / f"dataset_{name}", out / f"field_{name}", args)
        rows.append(run_stage(f"fit_field_{name}", command, logs))
    dataset, field = out / "dataset_long", out / "field_long"
    for method in ("ultron", "compounding"):
        run_dir = out / f"{method}-{round(args.label_fraction * 100)}"
        command = reconstruct_command(dataset, field, run_dir, method, args)
        rows.append(run_stage(f"reconstruct_{method}", command, logs))
    if args.fine_voxel_mm:
        for method in ("ultron", "compounding"):
            run_dir = out / f"{method}-{round(args.label_fraction * 100)}-fine"
            command = fine_command(dataset, field, run_dir, method, args)
            rows.append(run_stage(f"reconstruct_{method}_{args.fine_voxel_mm:g}mm", command, logs))
    return rows


def meshing_lines(dataset, voxel_mm: float | None) -> list[str]:
    """The meshing grid at ``voxel_mm`` and the tiles of it the field of view reaches."""
    from ultron.mesh.occupancy_mesh import MeshingConfig, elevation_half_thickness_mm, scan_grid
    from ultron.mesh.tiles import field_of_view_tiles, tile_for_factor
    from ultron.pipeline.resources import meshing_memory

    grid = scan_grid(dataset, voxel_mm)
    factor = MeshingConfig().coarse_factor
    tile = tile_for_factor(factor)
    half = elevation_half_thickness_mm(dataset, grid.voxel_mm)
    mask = field_of_view_tiles(grid.coarsened(factor), dataset.all_poses(), dataset.probe, half,
                               tile // factor)  # fmt: skip
    fov = factor**3 * sum(int(m.sum()) for m in mask.values())
    memory = meshing_memory(dataset, voxel_mm)
    return [
        f"meshing grid at {grid.voxel_mm:.3f} mm over the field of view's box:"
        f" {' × '.join(map(str, grid.shape))} = {grid.n_voxels / 1e6:.1f} M voxels"
        f" (dense float32: {grid.n_voxels * 4 / GIB:.2f} GiB); field of view ≈ {fov / 1e6:.1f} M"
        f" voxels in {len(mask)} tiles of {tile}³; the guard's estimate"
        f" {memory.total / GIB:.2f} GiB ({memory.fov_voxels / 1e6:.1f} M voxels counted)",
    ]


def run_lines(run_dir: Path) -> list[str]:
    """A reconstruction's volume grid, mesh and stage timings, from its run.json."""
    if not (run_dir / "run.json").is_file():
        return []
    run = json.loads((run_dir / "run.json").read_text())
    grid = run.get("grid") or {}
    shape = grid.get("shape")
    volume = f"volume {' × '.join(map(str, shape))} of {grid['voxel_mm']:.3f} mm" if shape else ""
    stages = ", ".join(f"{k} {v:.1f}" for k, v in run["timings_s"].items())
    return [f"{run_dir.name}: {volume}; mesh {run['mesh']['faces']} faces; stages (s): {stages}"]


def grid_lines(args: argparse.Namespace) -> list[str]:
    """The grids of the long sweep's runs."""
    from ultron.data.dataset import SweepDataset

    dataset = SweepDataset.load(args.out / "dataset_long")
    n_frames = sum(s.n_frames for s in dataset.sweeps)
    lines = [
        f"sweep: {n_frames} frames in {len(dataset.sweeps)} passes of"
        f" {dataset.probe.height_px} × {dataset.probe.width_px} px",
    ]
    lines += meshing_lines(dataset, None)
    if args.fine_voxel_mm:
        lines += meshing_lines(dataset, args.fine_voxel_mm)
    for name in datasets(args):
        field = json.loads((args.out / f"field_{name}" / "field.json").read_text())
        sides = field["field"].get("grid", {}).get("resolutions")
        lines.append(f"field planes ({name}): {sides} nodes per side")
    for run_dir in sorted(args.out.glob("*-[0-9]*")):
        lines += run_lines(run_dir)
    return lines


def print_report(args: argparse.Namespace, rows: list[dict]) -> None:
    print("\n| stage | wall time (s) | peak RSS (GiB) |\n|---|---|---|")
    for row in rows:
        print(f"| {row['stage']} | {row['seconds']:.1f} | {row['peak_rss_bytes'] / GIB:.2f} |")
    rates = {name: seconds_per_step(args.out / f"field_{name}") for name in datasets(args)}
    print("\nfield step (s): " + ", ".join(f"{n} {r:.3f}" for n, r in rates.items())
          + f"; long / short {rates['long'] / rates['short']:.2f}")  # fmt: skip
    for line in grid_lines(args):
        print(line)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/long_sweep"))
    parser.add_argument("--phantom", default="femur")
    parser.add_argument("--sweeps", default="row,tilt_p10", help="the passes")
    parser.add_argument("--frames", type=int, default=520, help="frames per pass")
    parser.add_argument("--short-frames", type=int, default=60, help="frames per pass, short")
    parser.add_argument("--height-px", type=int, default=128)
    parser.add_argument("--width-px", type=int, default=96)
    parser.add_argument("--sdf-voxel-mm", type=float, default=0.5, help="phantom SDF / reference")
    parser.add_argument("--field-iters", type=int, default=200)
    parser.add_argument("--occupancy-iters", type=int, default=200)
    parser.add_argument("--label-fraction", type=float, default=0.1)
    parser.add_argument("--points", type=int, default=20_000, help="metric points per surface")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fine-voxel-mm", type=float, default=0.25, help="0: no fine runs")
    parser.add_argument("--compact", action=argparse.BooleanOptionalAction, default=True,
                        help="also fit a field on L3 (a 10 cm box)")  # fmt: skip
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows = run_all(args)
    print_report(args, rows)
    print(f"\ntotal {time.perf_counter() - started:.0f} s; python {sys.version.split()[0]}")


if __name__ == "__main__":
    main()
