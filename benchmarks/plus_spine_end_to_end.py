"""Benchmark: the real PLUS spine-phantom recording end to end (issue 17, item 7).

Runs the README's worked example, each command as its own process (wall time and peak RSS
per stage, as ``benchmarks/long_sweep.py`` measures them):

1. ``ultron import-plus`` of ``../shared/data/plus-spine-phantom/SpinePhantomFreehand.igs.mha``
   with its PLUS configuration, frames downsampled by ``--downsample`` (default 4: the 445 of
   820 columns that hold signal, 616 rows, ≈ 0.08 mm pixels, become 111 × 154 of ≈ 0.33 mm);
2. ``ultron label --auto`` (nobody annotated this recording);
3. ``ultron fit-field`` (default settings);
4. ``ultron reconstruct --method ultron`` and ``--method compounding`` on every frame's
   automatic labels (``--label-fraction 1``: labels cost nothing here), each with its
   ``report.html``.

There is no reference surface for a real recording, so no CD: the script prints what the
runs record about their surfaces (``run.json``'s ``surface_evidence``: vertices, the share
observed by some frame, the distance to the nearest bone-labelled pixel) and the label shares.

Usage::

    python benchmarks/plus_spine_end_to_end.py --out runs/spine-e2e
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from long_sweep import run_stage

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "plus-spine-phantom"


def commands(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """(stage, command) of the worked example, in order."""
    out, data = args.out, args.data
    dataset, field = str(out / "spine"), str(out / "field")
    reconstruct = ["ultron", "reconstruct", dataset, "--label-fraction", "1"]
    return [
        ("import_plus", [
            "ultron", "import-plus", str(data / "SpinePhantomFreehand.igs.mha"), "--config",
            str(data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"),
            "--downsample", str(args.downsample), "--out", dataset,
        ]),
        ("label_auto", ["ultron", "label", dataset, "--auto"]),
        ("fit_field", ["ultron", "fit-field", dataset, "--out", field]),
        ("reconstruct_ultron", [
            *reconstruct, "--method", "ultron", "--field", field, "--out", str(out / "ultron"),
        ]),
        ("reconstruct_compounding", [
            *reconstruct, "--method", "compounding", "--out", str(out / "compounding"),
        ]),
    ]  # fmt: skip


def evidence_lines(out: Path) -> list[str]:
    """One line per run and mesh file from run.json's ``surface_evidence``."""
    lines = []
    for method in ("ultron", "compounding"):
        run = json.loads((out / method / "run.json").read_text(encoding="utf-8"))
        for name, summary in (run.get("surface_evidence") or {}).items():
            distance = summary["label_distance_mm"]
            lines.append(
                f"{method} {name}: {summary['vertices']} vertices, "
                f"{100 * summary['observed_share']:.1f} % observed, label distance median "
                f"{distance['median']:.2f} mm, p95 {distance['p95']:.2f} mm, "
                f"max {distance['max']:.2f} mm"
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/spine-e2e"))
    parser.add_argument("--data", type=Path, default=DATA, help="the PLUS recording's folder")
    parser.add_argument("--downsample", type=int, default=4)
    args = parser.parse_args()
    if args.out.exists():
        shutil.rmtree(args.out)  # every stage from scratch: the times are the example's
    started = time.perf_counter()
    rows = [run_stage(name, command, args.out / "logs") for name, command in commands(args)]
    total = time.perf_counter() - started
    print("\n| stage | wall time (s) | peak RSS (GiB) |\n|---|---|---|")
    for row in rows:
        print(f"| {row['stage']} | {row['seconds']:.1f} | {row['peak_rss_bytes'] / 1024**3:.2f} |")
    print(f"\nend to end {total:.1f} s")
    print((args.out / "logs" / "label_auto.log").read_text(encoding="utf-8").strip())
    print("\n".join(evidence_lines(args.out)))


if __name__ == "__main__":
    main()
