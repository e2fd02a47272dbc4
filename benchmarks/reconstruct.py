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

from common import add_arguments, meshing_seconds, prepare, print_results, print_targets, run_all

RUNS = (
    ("UltrON (10%)", "ultron", 0.10),
    ("UltrON w/o loss (10%)", "ultron-noloss", 0.10),
    ("UltrON (5%)", "ultron", 0.05),
    ("compounding (10%)", "compounding", 0.10),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, "runs/bench-reconstruct")
    args = parser.parse_args()
    dataset_dir, field_dir, field_seconds = prepare(args)
    results = run_all(args, RUNS, dataset_dir, field_dir)
    print_results(args, results, dataset_dir, field_dir, field_seconds)

    cd = {label: summary["metrics"]["mean"]["cd"] for label, summary in results.items()}
    ultron = cd["UltrON (10%)"]
    fit = results["UltrON (10%)"]["timings_s"].get("occupancy_fit", float("nan"))
    print_targets(
        [
            ("UltrON(10%) CD ≤ 1.0 mm", ultron, 1.0),
            ("UltrON(10%) CD < UltrON w/o loss(10%) CD", ultron, cd["UltrON w/o loss (10%)"]),
            ("UltrON(10%) CD < compounding(10%) CD", ultron, cd["compounding (10%)"]),
            ("UltrON(5%) CD ≤ 1.1 × UltrON(10%) CD", cd["UltrON (5%)"], 1.1 * ultron),
            ("occupancy fit ≤ 60 s", fit, 60.0),
            ("meshing ≤ 30 s", meshing_seconds(results["UltrON (10%)"]), 30.0),
        ]
    )


if __name__ == "__main__":
    main()
