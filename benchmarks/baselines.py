"""Benchmark: the baselines next to UltrON on the default simulated L3 (issue #6's table).

Runs UltrON (10%), ON (100%), RoCoSDF (100%, ``--preset``, default fast), UNSR-Row and
UNSR-Col (100%), and label compounding (10% and 100%) on one dataset and one fitted field, each
exactly as ``ultron reconstruct`` does, and prints CD, HD, MAD, RMSE, HD95 and completeness,
the runtime of each method on this machine (every stage but the metrics), and the targets (``rocosdf --preset fast``
≤ 5 min, ``on`` ≤ 2 min, ``compounding`` ≤ 20 s).

Usage::

    python benchmarks/baselines.py                       # simulates L3 (seed 0) into --out
    python benchmarks/baselines.py --dataset DIR --field FIELD_DIR --out /tmp/bench [--preset paper]
"""

from __future__ import annotations

import argparse

from common import add_arguments, prepare, print_results, print_targets, run_all
from ultron.methods.registry import METHODS
from ultron.methods.rocosdf import RoCoSDFConfig

RUNS = (
    ("UltrON (10%)", "ultron", 0.10),
    ("ON (100%)", "on", 1.0),
    ("RoCoSDF (100%)", "rocosdf", 1.0),
    ("UNSR-Row (100%)", "unsr-row", 1.0),
    ("UNSR-Col (100%)", "unsr-col", 1.0),
    ("compounding (10%)", "compounding", 0.10),
    ("compounding (100%)", "compounding", 1.0),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, "runs/bench-baselines")
    parser.add_argument("--preset", default="fast", choices=("fast", "paper"))
    parser.add_argument("--skip", default="", help="comma-separated labels' methods to skip")
    args = parser.parse_args()
    skip = {s for s in args.skip.split(",") if s}
    runs = [r for r in RUNS if r[1] not in skip]
    dataset_dir, field_dir, field_seconds = prepare(args)
    sdf = {"method_config": RoCoSDFConfig.preset(args.preset)}
    requests = {
        label: sdf for label, method, _ in runs if METHODS[method].config_class is RoCoSDFConfig
    }
    results = run_all(args, runs, dataset_dir, field_dir, requests)
    print(f"RoCoSDF / UNSR preset: {args.preset}")
    print_results(args, results, dataset_dir, field_dir, field_seconds)

    def total(label: str) -> float:
        summary = results.get(label)
        if not summary:
            return float("nan")
        return sum(v for k, v in summary["timings_s"].items() if k != "metrics")

    print_targets(
        [
            (f"rocosdf --preset {args.preset} runtime ≤ 300 s", total("RoCoSDF (100%)"), 300.0),
            ("on runtime ≤ 120 s", total("ON (100%)"), 120.0),
            ("compounding (100%) runtime ≤ 20 s", total("compounding (100%)"), 20.0),
        ]
    )


if __name__ == "__main__":
    main()
