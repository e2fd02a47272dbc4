"""Benchmark: UltrON on the default simulated L3 against its ablation and label compounding.

Runs, on one dataset and one fitted acoustic field (fitted once, or given with ``--field``):
UltrON (10%), UltrON w/o loss (10%), UltrON (5%) and label compounding (10%), each exactly as
``ultron reconstruct`` does (outputs under ``--out``), then prints the surface metrics (mean ±
std over the metric repeats), the per-stage timings, the process's peak memory, and the targets
of issue #5 with the margin by which each is met or missed.

Usage::

    python benchmarks/reconstruct.py                     # simulates L3 (seed 0) into --out
    python benchmarks/reconstruct.py --dataset DIR --field FIELD_DIR --out /tmp/bench
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

RUNS = (
    ("UltrON (10%)", "ultron", 0.10),
    ("UltrON w/o loss (10%)", "ultron-noloss", 0.10),
    ("UltrON (5%)", "ultron", 0.05),
    ("compounding (10%)", "compounding", 0.10),
)
METRICS = ("cd", "hd", "mad", "rmse", "hd95", "completeness")


def main() -> None:
    from ultron.methods.run import ReconstructionRequest, reconstruct
    from ultron.methods.runinfo import peak_rss_mb
    from ultron.metrics.surface import MetricsConfig
    from ultron.phantom import SimulationConfig, simulate_dataset
    from ultron.train.field_fit import FieldTrainConfig, fit_field

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, default=None, help="default: simulate L3")
    parser.add_argument("--field", type=Path, default=None, help="default: fit one into --out")
    parser.add_argument("--out", type=Path, default=Path("runs/bench-reconstruct"))
    parser.add_argument("--seed", type=int, default=0, help="simulation, labels and training")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    dataset_dir = args.dataset
    if dataset_dir is None:
        dataset_dir = args.out / "dataset"
        if not (dataset_dir / "dataset.json").is_file():
            simulate_dataset(SimulationConfig(phantom="L3", seed=args.seed), out=dataset_dir)
    field_dir = args.field
    field_seconds = 0.0
    if field_dir is None:
        from ultron.data.dataset import SweepDataset

        field_dir = args.out / "field"
        start = time.perf_counter()
        fit_field(
            SweepDataset.load(dataset_dir), FieldTrainConfig(seed=args.seed), field_dir, resume=True
        )
        field_seconds = time.perf_counter() - start

    results = {}
    for label, method, fraction in RUNS:
        request = ReconstructionRequest(
            method=method,
            label_fraction=fraction,
            seed=args.seed,
            metrics=MetricsConfig(n_points=args.points, repeats=args.repeats),
        )
        out = args.out / f"{method}-{int(round(fraction * 100))}"
        results[label] = reconstruct(dataset_dir, request, out, field_dir=field_dir)
        print(f"done: {label} → {out}", flush=True)

    print(f"\ndataset {dataset_dir}; field {field_dir} (fit {field_seconds:.1f} s)")
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
        mesh = sum(v for k, v in t.items() if k.startswith("mesh"))
        stages = ", ".join(f"{k} {v:.1f}" for k, v in t.items())
        print(f"  {label}: meshing {mesh:.1f} (all stages: {stages})")
    print(f"peak RSS of this process: {peak_rss_mb() / 1024:.2f} GB")

    cd = {label: summary["metrics"]["mean"]["cd"] for label, summary in results.items()}
    ultron = cd["UltrON (10%)"]
    fit = results["UltrON (10%)"]["timings_s"].get("occupancy_fit", float("nan"))
    mesh = sum(v for k, v in results["UltrON (10%)"]["timings_s"].items() if k.startswith("mesh"))
    checks = [
        ("UltrON(10%) CD ≤ 1.0 mm", ultron, 1.0),
        ("UltrON(10%) CD < UltrON w/o loss(10%) CD", ultron, cd["UltrON w/o loss (10%)"]),
        ("UltrON(10%) CD < compounding(10%) CD", ultron, cd["compounding (10%)"]),
        ("UltrON(5%) CD ≤ 1.1 × UltrON(10%) CD", cd["UltrON (5%)"], 1.1 * ultron),
        ("occupancy fit ≤ 60 s", fit, 60.0),
        ("meshing ≤ 30 s", mesh, 30.0),
    ]
    print("\ntargets:")
    for name, value, bound in checks:
        verdict = "met" if value <= bound else "MISSED"
        print(f"  {name}: {value:.3f} vs {bound:.3f} → {verdict} (margin {bound - value:+.3f})")


if __name__ == "__main__":
    main()
