"""Benchmark: the PLUS path with default options on the shared spine phantom (issue 31, item 4).

``../shared/data/plus-spine-phantom`` is a real PLUS recording (21 frames of 616 × 820 at
0.08 mm, of which ``import-plus`` keeps the 445 columns that hold signal) with its device-set
configuration. Every command runs as its own process with its
defaults (the import at two pixels per speckle grain, ``--downsample auto``; no
``--fit-shape``), so each row's wall time and peak RSS are its own (``os.wait4``'s rusage, as ``benchmarks/long_sweep.py`` measures them):

1. ``ultron import-plus`` → ``ultron label --auto`` (no annotator);
2. ``ultron reconstruct --method compounding --label-fraction 1``;
3. ``ultron fit-field`` (its held-out PSNR / SSIM per check from ``train_log.jsonl``, next to
   what copying the mean or the nearest training frame scores on the same held-out frames);
4. ``ultron reconstruct --method ultron --field F --label-fraction 1``.

For both surfaces it prints where they are against the evidence: the p95 / median distance of
the kept surface's vertices to the nearest bone label (run.json's ``surface_evidence``; issue
31's target: UltrON within 1.5× of compounding), and how many vertices lie more than 2 and 3 mm
from every label. The percentiles fall when surface near the labels is added; the counts do
not, so they show whether false surface was removed or only diluted (a count depends on the
mesh's resolution: compare a method with itself across releases, not two methods), and where
the vertices farther than 2 mm lie against the labels (``ultron.mesh.evidence.surface_places``:
between the labelled frames, on a bone or background label, or unsure in the shadow under a band
of bone labels, in the tissue above one, or in a scanline without one). Nothing is tuned here. It prints markdown and
writes ``OUT/plus_spine.json``; a stage whose output exists is not run again.

Usage::

    python benchmarks/plus_spine.py --out runs/plus_spine
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from long_sweep import GIB, run_unless_done

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "plus-spine-phantom"
SEQUENCE = "SpinePhantomFreehand.igs.mha"
CONFIG = "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"


def stages(data: Path, out: Path) -> list[tuple[str, list[str], Path]]:
    """(name, command, the output whose presence means done) in order."""
    dataset = out / "dataset"
    return [
        ("import-plus", ["ultron", "import-plus", str(data / SEQUENCE), "--config",
                         str(data / CONFIG), "--out", str(dataset)], dataset / "dataset.json"),
        ("label --auto", ["ultron", "label", str(dataset), "--auto"],
         out / "logs" / "label_--auto.done"),
        ("compounding", ["ultron", "reconstruct", str(dataset), "--method", "compounding",
                         "--label-fraction", "1", "--out", str(out / "compounding")],
         out / "compounding" / "run.json"),
        ("fit-field", ["ultron", "fit-field", str(dataset), "--out", str(out / "field")],
         out / "field" / "theta_stats.json"),
        ("ultron", ["ultron", "reconstruct", str(dataset), "--method", "ultron", "--field",
                    str(out / "field"), "--label-fraction", "1", "--out", str(out / "ultron")],
         out / "ultron" / "run.json"),
    ]  # fmt: skip


def held_out_baselines(dataset: Path, field: Path) -> dict[str, float]:
    """PSNR of copying the mean / the nearest (by probe position) training frame onto the
    field's held-out frames, at the field's fit resolution
    (:func:`ultron.train.frames.copy_baselines`)."""

    from ultron.data.dataset import SweepDataset
    from ultron.train.frames import FrameSet, copy_baselines

    meta = json.loads((field / "field.json").read_text())
    shape = meta["train"]["fit_shape"]
    frames = FrameSet.from_dataset(
        SweepDataset.load(dataset), tuple(shape) if shape else None, meta["train"]["holdout_every"]
    )
    found = copy_baselines(frames, meta["train"]["max_check_frames"])
    return {"mean frame": found["mean_frame"], "nearest frame": found["nearest_frame"]}


def far_surface_places(dataset, run: dict, run_dir: Path, beyond_mm: float = 2.0) -> dict[str, int]:
    """Where the vertices of ``run_dir/mesh.ply`` farther than ``beyond_mm`` from every bone label
    lie against the labels of the frames the run used (its ``run.json``, ``run``;
    :func:`ultron.mesh.evidence.surface_places`, in a slab of 0.75 × the median frame gap, the
    observed crop's where the voxel is finer)."""
    import numpy as np

    from ultron.mesh.evidence import SURFACE_PLACES, surface_places
    from ultron.mesh.export import load_mesh, load_vertex_properties
    from ultron.mesh.occupancy_mesh import elevation_half_thickness_mm

    if run["mesh"]["coordinates"] != "lps":
        raise SystemExit(f"{run_dir}: expected a mesh in world (lps) coordinates")
    poses, labels = [], []
    for sweep in dataset.sweeps:
        frames = run["selection"]["frames"].get(sweep.name, [])
        poses.append(sweep.probe_to_world[frames])
        labels.append(np.asarray(sweep.labels)[frames])
    mesh = load_mesh(run_dir / "mesh.ply")
    far = load_vertex_properties(run_dir / "mesh.ply")["label_distance_mm"] > beyond_mm
    slab = elevation_half_thickness_mm(dataset, 0.0)  # 0.75 × the median frame gap
    places = surface_places(
        np.asarray(mesh.vertices)[far], np.concatenate(poses), dataset.probe,
        np.concatenate(labels), slab,
    )  # fmt: skip
    counts = np.bincount(places, minlength=len(SURFACE_PLACES))
    return {name: int(n) for name, n in zip(SURFACE_PLACES, counts, strict=True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name, command, done in stages(args.data, args.out):
        row = run_unless_done(name, command, done, args.out / "logs")
        if row is None:
            continue
        rows[name] = row
        if name == "label --auto":
            done.write_text("ok\n")
    log = [json.loads(line) for line in (args.out / "field" / "train_log.jsonl").open()]
    checks = [(e["step"], e["holdout_psnr"], e["holdout_ssim"]) for e in log if "holdout_psnr" in e]
    field_json = json.loads((args.out / "field" / "field.json").read_text())
    from ultron.data.dataset import SweepDataset

    dataset = SweepDataset.load(args.out / "dataset")
    evidence, beyond, places = {}, {}, {}
    for method in ("compounding", "ultron"):
        run = json.loads((args.out / method / "run.json").read_text())
        evidence[method] = run["surface_evidence"]["mesh"]["label_distance_mm"]
        beyond[method] = run["surface_evidence"]["mesh"].get("vertices_beyond_mm")
        places[method] = far_surface_places(dataset, run, args.out / method)
    result = {
        "stages": rows,
        "fit_shape": field_json["train"]["fit_shape"],
        "held_out": checks,
        "baselines_psnr": held_out_baselines(args.out / "dataset", args.out / "field"),
        "label_distance_mm": evidence,
        "vertices_beyond_mm": beyond,
        "far_vertex_places": places,
    }
    (args.out / "plus_spine.json").write_text(json.dumps(result, indent=2))
    print("\n| stage | wall (s) | peak RSS (GiB) |\n|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['seconds']:.1f} | {row['peak_rss_bytes'] / GIB:.2f} |")
    print(f"\nfield fitted at {result['fit_shape'] or 'the frames own size'}; held-out checks:")
    print("| step | PSNR (dB) | SSIM |\n|---|---|---|")
    for step, value, ssim in checks:
        print(f"| {step} | {value:.2f} | {ssim:.3f} |")
    baselines = ", ".join(f"{k} {v:.2f} dB" for k, v in result["baselines_psnr"].items())
    print(f"copying onto the held-out frames: {baselines}")
    print("\n| surface | label distance median (mm) | p95 (mm) | vertices > 2 / > 3 mm |")
    print("|---|---|---|---|")
    for method, stats in evidence.items():
        far = beyond[method]  # None: a run from before run.json counted them
        counts = "—" if far is None else f"{far['2']} / {far['3']}"
        print(f"| {method} | {stats['median']:.2f} | {stats['p95']:.2f} | {counts} |")
    names = list(places["ultron"])
    print("\nwhere the vertices > 2 mm from every label lie (the labels of the nearest frame):")
    print("| surface | " + " | ".join(names) + " |\n|---|" + "---|" * len(names))
    for method, counts in places.items():
        print(f"| {method} | " + " | ".join(str(counts[n]) for n in names) + " |")
    ratio = evidence["ultron"]["p95"] / evidence["compounding"]["p95"]
    print(f"UltrON's p95 is {ratio:.2f}× compounding's (issue 31's target: ≤ 1.5×)")


if __name__ == "__main__":
    main()
