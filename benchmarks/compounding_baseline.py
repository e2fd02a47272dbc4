"""Benchmark: the label-compounding baseline against plain nearest-voxel compounding.

On a simulated dataset with a reference (use the tuning datasets, never the benchmark's seeds
0–2: ``ultron simulate --phantom L3 --seed 11 --out D``, ``--phantom L4 --seed 12``), with the
same 10 % of labelled frames (seed 0) and the same metrics as ``ultron reconstruct D --method
compounding --label-fraction 0.1 --points 30000``, prints CD vis., Comp. vis., CD, HD95 and MAD
of

* **plain**: every labelled pixel's label pasted into its nearest voxel (the finer pixel
  spacing), mean, no hole filling, no smoothing, marching cubes at 0.5 — the textbook
  compounding;
* **plain, facing**: the same, keeping the faces some frame sees facing the probe;
* **baseline**: ``reconstruct --method compounding`` as it runs now (signed distances, stick +
  nearest hole filling, constrained smoothing, the faces some frame sees facing the probe).

Usage::

    python benchmarks/compounding_baseline.py D [--label-fraction 0.1] [--points 30000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ultron.data.dataset import SweepDataset
from ultron.data.labels import select_label_frames
from ultron.mesh.compounding import CompoundingConfig, compound_labels
from ultron.mesh.extract import ExtractionConfig, extract_surface
from ultron.mesh.observed import ObservedSurfaceConfig
from ultron.methods.evidence import faced_observation
from ultron.metrics.surface import MetricsConfig, evaluate_meshes
from ultron.pipeline.run import ReconstructionRequest, load_references, run_method
from ultron.timing import StageTimer

COLUMNS = ("cd_visible", "completeness_visible", "cd", "hd95", "mad")


def plain_mesh(dataset: SweepDataset, fraction: float, seed: int, facing: bool):
    """Plain nearest-voxel compounding of the selected frames' labels (module doc)."""
    selection = select_label_frames(dataset, fraction, seed)
    config = CompoundingConfig(signed_distance=False, hole_fill_radius_mm=0.0)
    compounded = compound_labels(dataset, selection, config)
    mesh = extract_surface(compounded.volume, compounded.grid, ExtractionConfig(smooth=False))
    if facing:
        mesh = faced_observation(
            mesh, dataset, compounded.grid.voxel_mm, ObservedSurfaceConfig()
        ).kept
    return mesh


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--label-fraction", type=float, default=0.1)
    parser.add_argument("--points", type=int, default=30000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    dataset = SweepDataset.load(args.dataset)
    reference, visible = load_references(dataset)
    if reference is None:
        raise SystemExit(f"{args.dataset}: no reference mesh to measure against")
    metrics = MetricsConfig(n_points=args.points)
    request = ReconstructionRequest(
        method="compounding", label_fraction=args.label_fraction, seed=args.seed
    )
    runs = {
        "plain": lambda: plain_mesh(dataset, args.label_fraction, args.seed, False),
        "plain, facing": lambda: plain_mesh(dataset, args.label_fraction, args.seed, True),
        "baseline": lambda: run_method(dataset, request, None, StageTimer()).mesh,
    }
    print(f"{'':16s}" + "".join(f"{c:>22s}" for c in COLUMNS) + "   area mm²   time")
    for name, build in runs.items():
        start = time.perf_counter()
        mesh = build()
        seconds = time.perf_counter() - start
        figures = evaluate_meshes(mesh, reference, metrics, reference_visible=visible)
        cells = "".join(f"{figures['mean'][c]:>14.3f} ± {figures['std'][c]:5.3f}" for c in COLUMNS)
        print(f"{name:16s}{cells}   {mesh.area:9.0f}  {seconds:5.1f} s")


if __name__ == "__main__":
    main()
