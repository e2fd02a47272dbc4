"""Shared by the reconstruction benchmarks: dataset + field preparation, runs, tables."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

METRICS = ("cd", "hd", "mad", "rmse", "hd95", "completeness")


def imaged_share_of_reference(dataset_dir: Path, n_points: int = 50_000) -> float:
    """Share of the reference surface (by area) inside some frame's imaged slab."""
    import numpy as np

    from ultron.data.dataset import SweepDataset
    from ultron.mesh.export import load_mesh
    from ultron.mesh.grid import field_of_view_mask
    from ultron.mesh.occupancy_mesh import elevation_half_thickness_mm, scan_grid
    from ultron.metrics.surface import sample_surface

    dataset = SweepDataset.load(dataset_dir)
    grid = scan_grid(dataset, None).coarsened(2)
    mask = field_of_view_mask(
        grid, dataset.all_poses(), dataset.probe, elevation_half_thickness_mm(dataset, 0.0)
    )
    points, _ = sample_surface(load_mesh(dataset.reference), n_points, seed=0)
    ijk = np.rint(grid.world_to_index(points)).astype(int)
    inside = ((ijk >= 0) & (ijk < np.asarray(grid.shape))).all(axis=1)
    seen = np.zeros(len(points), dtype=bool)
    seen[inside] = mask[tuple(ijk[inside].T)]
    return float(seen.mean())


def add_arguments(parser: argparse.ArgumentParser, default_out: str) -> None:
    parser.add_argument("--dataset", type=Path, default=None, help="default: simulate L3")
    parser.add_argument("--field", type=Path, default=None, help="default: fit one into --out")
    parser.add_argument("--out", type=Path, default=Path(default_out))
    parser.add_argument("--seed", type=int, default=0, help="simulation, labels and training")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)


def prepare(args: argparse.Namespace) -> tuple[Path, Path, float]:
    """The dataset (simulated ``args.phantom``, default L3, unless given) and its fitted field
    (fitted unless given)."""
    from ultron.data.dataset import SweepDataset
    from ultron.phantom import SimulationConfig, simulate_dataset
    from ultron.train.field_fit import FieldTrainConfig, fit_field

    dataset_dir = args.dataset
    if dataset_dir is None:
        dataset_dir = args.out / "dataset"
        if not (dataset_dir / "dataset.json").is_file():
            phantom = getattr(args, "phantom", "L3")
            simulate_dataset(SimulationConfig(phantom=phantom, seed=args.seed), out=dataset_dir)
    field_dir = args.field
    field_seconds = 0.0
    if field_dir is None:
        field_dir = args.out / "field"
        start = time.perf_counter()
        fit_field(
            SweepDataset.load(dataset_dir), FieldTrainConfig(seed=args.seed), field_dir, resume=True
        )
        field_seconds = time.perf_counter() - start
    return dataset_dir, field_dir, field_seconds


def run_all(args, runs, dataset_dir: Path, field_dir: Path, requests: dict | None = None) -> dict:
    """Run each (label, method, fraction) as ``ultron reconstruct`` does; summaries by label."""
    from ultron.metrics.surface import MetricsConfig
    from ultron.pipeline.run import ReconstructionRequest, reconstruct

    results = {}
    for label, method, fraction in runs:
        request = ReconstructionRequest(
            method=method,
            label_fraction=fraction,
            seed=args.seed,
            metrics=MetricsConfig(n_points=args.points, repeats=args.repeats),
            **(requests or {}).get(label, {}),
        )
        out = args.out / f"{method}-{round(fraction * 100)}"
        results[label] = reconstruct(dataset_dir, request, out, field_dir=field_dir)
        print(f"done: {label} → {out}", flush=True)
    return results


def meshing_seconds(summary: dict) -> float:
    return sum(v for k, v in summary["timings_s"].items() if k.startswith("mesh"))


def print_results(args, results: dict, dataset_dir: Path, field_dir: Path, field_s: float) -> None:
    from ultron.timing import peak_rss_mb

    print(f"\ndataset {dataset_dir}; field {field_dir} (fit {field_s:.1f} s)")
    print(f"metrics: {args.points} points per surface, {args.repeats} repeats, mean ± std (mm)\n")
    print("| method | " + " | ".join(m.upper() for m in METRICS) + " |")
    print("|---" * (len(METRICS) + 1) + "|")
    for label, summary in results.items():
        mean, std = summary["metrics"]["mean"], summary["metrics"]["std"]
        cells = " | ".join(f"{mean[m]:.3f} ± {std[m]:.3f}" for m in METRICS)
        print(f"| {label} | {cells} |")
    print("\ntimings (s):")
    for label, summary in results.items():
        t = summary["timings_s"]
        stages = ", ".join(f"{k} {v:.1f}" for k, v in t.items())
        total = sum(t.values())
        print(f"  {label}: total {total:.1f}, meshing {meshing_seconds(summary):.1f} ({stages})")
    print(f"peak RSS of this process: {peak_rss_mb() / 1024:.2f} GB")
    share = imaged_share_of_reference(dataset_dir)
    print(
        f"reference surface inside the imaged field of view: {100 * share:.1f}% (the rest is"
        " never imaged, e.g. beyond the imaging depth: completeness and CD cannot reach 0 there)"
    )


def print_targets(checks: list[tuple[str, float, float]]) -> None:
    print("\ntargets:")
    for name, value, bound in checks:
        verdict = "met" if value <= bound else "MISSED"
        print(f"  {name}: {value:.3f} vs {bound:.3f} → {verdict} (margin {bound - value:+.3f})")
