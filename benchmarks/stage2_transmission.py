"""Benchmark: is UltrON's stage 2 monotone in the quality of its transmission T? (issue 32)

For each tuning dataset (a phantom and a seed the benchmark does not score, simulated with the
benchmark's imperfections: tracking 0.3 mm / 0.3° per axis, 0.3 mm edge jitter, 2 % coarse and
5 % unannotated frames — ``ultron.benchmark.config.BENCHMARK_TRACKING`` / ``BENCHMARK_ANNOTATION``)
it fits the acoustic field once and runs, through the CLI with default options:

* ``ultron reconstruct --method ultron --oracle-transmission`` — the simulator's true T in the
  loss and in the observed crop (a diagnostic: what a perfect T gives);
* ``ultron reconstruct --method ultron`` — the fitted field's T (the method);
* ``ultron reconstruct --method ultron-noloss`` — plain BCE, T ≡ 1 in the loss (the ablation;
  the observed crop still uses the field's T);

for each label fraction (``--fractions``, default 0.1), and prints visible CD, visible
completeness, HD95 and MAD (mm, ``metrics.json``'s means) with two checks per cell:
monotone (CD vis. with the oracle ≤ with the field's T ≤ with T ≡ 1) and the loss's margin
(UltrON ≥ 10 % below its ablation, issue 32 item 4). Every command runs as its own process;
wall time and peak RSS are printed per stage. Re-running resumes (a stage whose output exists
is skipped); ``--fresh`` reruns everything. Writes ``OUT/stage2_transmission.json``.

Usage::

    python benchmarks/stage2_transmission.py --out runs/stage2
    python benchmarks/stage2_transmission.py --out runs/stage2 --datasets L3:11 --fractions 0.1,0.05
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from long_sweep import run_unless_done

#: Tuning datasets: phantoms × seeds that ``ultron benchmark`` never scores (it uses 0 … n−1).
DEFAULT_DATASETS = "L3:11,L4:12,condyle:11"
#: (row name, reconstruct method, extra options)
VARIANTS = (
    ("true T (oracle)", "ultron", ["--oracle-transmission"]),
    ("field T", "ultron", []),
    ("T ≡ 1 (w/o loss)", "ultron-noloss", []),
)
METRICS = ("cd_visible", "completeness_visible", "hd95", "mad")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--datasets", default=DEFAULT_DATASETS, help="PHANTOM:SEED,…")
    parser.add_argument("--fractions", default="0.1", help="label fractions, e.g. 0.1,0.05")
    parser.add_argument("--points", type=int, default=30_000, help="metric points per mesh")
    parser.add_argument("--fresh", action="store_true", help="rerun every stage")
    return parser.parse_args()


def simulate_command(phantom: str, seed: int, out: Path) -> list[str]:
    from ultron.benchmark.config import BENCHMARK_ANNOTATION, BENCHMARK_TRACKING

    return [
        "ultron", "simulate", "--phantom", phantom, "--seed", str(seed), "--out", str(out),
        "--pose-noise-mm", str(BENCHMARK_TRACKING.translation_mm),
        "--pose-noise-deg", str(BENCHMARK_TRACKING.rotation_deg),
        "--label-noise-mm", str(BENCHMARK_ANNOTATION.jitter_mm),
        "--label-missing", str(BENCHMARK_ANNOTATION.missing_fraction),
        "--label-errors", str(BENCHMARK_ANNOTATION.error_rate),
    ]  # fmt: skip


def cell_rows(args: argparse.Namespace, phantom: str, seed: int) -> list[dict]:
    root = args.out / f"{phantom}-s{seed}"
    dataset, field = root / "dataset", root / "field"
    logs = args.out / "logs"
    tag = f"{phantom}-s{seed}"
    simulate = simulate_command(phantom, seed, dataset)
    run_unless_done(f"simulate {tag}", simulate, dataset / "dataset.json", logs)
    fit = ["ultron", "fit-field", str(dataset), "--out", str(field)]
    run_unless_done(f"fit-field {tag}", fit, field / "field.json", logs)
    rows = []
    for fraction in (float(f) for f in args.fractions.split(",")):
        for name, method, extra in VARIANTS:
            slug = f"{method}{'-oracle' if extra else ''}-{fraction:g}"
            run = root / "runs" / slug
            command = [
                "ultron", "reconstruct", str(dataset), "--field", str(field), "--method", method,
                "--label-fraction", str(fraction), "--points", str(args.points), "--out",
                str(run), *extra,
            ]  # fmt: skip
            run_unless_done(f"{tag} {slug}", command, run / "metrics.json", logs)
            metrics = json.loads((run / "metrics.json").read_text())["mean"]
            rows.append({"dataset": tag, "fraction": fraction, "T": name,
                         **{m: metrics[m] for m in METRICS}})  # fmt: skip
    return rows


def checks(rows: list[dict]) -> list[dict]:
    """Per dataset × fraction: monotone in T and the loss's margin over its ablation."""
    cd = {(r["dataset"], r["fraction"], r["T"]): r["cd_visible"] for r in rows}
    out = []
    for dataset, fraction in sorted({key[:2] for key in cd}):
        oracle, fitted, ones = (cd[dataset, fraction, name] for name, _, _ in VARIANTS)
        out.append({
            "dataset": dataset, "fraction": fraction,
            "monotone": oracle <= fitted <= ones,
            "loss_margin": 1.0 - fitted / ones,
        })  # fmt: skip
    return out


def print_table(rows: list[dict], verdicts: list[dict]) -> None:
    print("\n| dataset | labels | T in the loss | CD vis. | Comp. vis. | HD95 | MAD |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        values = " | ".join(f"{r[m]:.3f}" for m in METRICS)
        print(f"| {r['dataset']} | {100 * r['fraction']:g} % | {r['T']} | {values} |")
    print("\n| dataset | labels | oracle ≤ field ≤ T ≡ 1 | UltrON below its ablation by |")
    print("|---|---|---|---|")
    for v in verdicts:
        mark = "yes" if v["monotone"] else "**no**"
        print(f"| {v['dataset']} | {100 * v['fraction']:g} % | {mark} | "
              f"{100 * v['loss_margin']:.0f} % |")  # fmt: skip


def main() -> None:
    args = parse_args()
    if args.fresh:
        shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for item in args.datasets.split(","):
        phantom, seed = item.split(":")
        rows += cell_rows(args, phantom, int(seed))
    verdicts = checks(rows)
    print_table(rows, verdicts)
    (args.out / "stage2_transmission.json").write_text(
        json.dumps({"rows": rows, "checks": verdicts}, indent=2)
    )


if __name__ == "__main__":
    main()
