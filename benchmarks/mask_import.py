"""Benchmark: an annotator's masks of a full-size PLUS recording (``ultron label --masks``), and
the labels written back as masks of the recording (``ultron label --export``).

Writes a synthetic tracked recording at a real probe's full size — by default 1000 frames of
810 × 950 pixels at 0.054 mm, the size of the UltraBones100k fibula recording before it was
block-averaged — with a bright band (the bone's echo) that moves down the frames, a 2° sheared
Image → Probe calibration (so the import resamples every frame onto the rigid grid) and 20
blank columns; masks of the band on every 10th frame (an annotator who labels a tenth of the
frames; the others empty). Then, each as its own process (wall time and peak RSS from its own
rusage, as ``benchmarks/long_sweep.py`` measures them):

1. ``ultron import-plus`` of the recording;
2. ``ultron label --masks`` of the masks (a memory-mapped ``.npy``, read a few frames at a time;
   the frames nobody annotated are not resampled);
3. ``ultron label --export`` of those labels as a ``.seq.mha`` twin of the recording
   (``--recording``: its header and per-frame fields copied);
4. ``ultron label --masks`` of that export, replacing the labels (the round trip a person makes
   who corrects the labels in Slicer without changing them).

It prints a table, how well the labels sit on the imported echo: the share of annotated
pixels where "bone" equals "brighter than the midpoint of tissue and echo" in the imported
frames (both went through the same steps), and the share of sweep pixels whose label the round
trip (3, 4) kept. Nothing is tuned here; the recording is synthetic,
so the figures are of speed and memory, and of the geometry's agreement, not of accuracy on
bone. A stage whose output exists is not run again.

Usage::

    python benchmarks/mask_import.py --out runs/mask_import [--frames 1000 --height 810 --width 950]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from long_sweep import GIB, run_unless_done

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from plus_synthetic import Recording, calibration, rigid, write_config, write_mha

#: Grey levels of tissue and of the bone's echo band.
TISSUE, ECHO = 30, 240


def write_recording(out: Path, n: int, height: int, width: int, every: int) -> None:
    """The recording, its PLUS configuration and the masks (module doc)."""
    frames = np.full((n, height, width), TISSUE, dtype=np.uint8)
    masks = np.zeros((n, height, width), dtype=np.uint8)
    band = max(1, height // 20)
    for k in range(n):
        top = height // 3 + k % (height // 8)
        frames[k, top : top + band, width // 5 : 4 * width // 5] = ECHO
        if k % every == 0:
            masks[k, top : top + band, width // 5 : 4 * width // 5] = 1
    frames[:, :, :20] = 0
    probe = np.stack(
        [rigid((1, 2, 3), 10.0 + 0.01 * k, (100.0 + 0.2 * k, -50, 20)) for k in range(n)]
    )
    reference = np.repeat(rigid((0, 1, 0.2), 40.0, (250.0, 90.0, 3.0))[None], n, axis=0)
    rec = Recording(frames, {"ProbeToTracker": probe, "ReferenceToTracker": reference})
    write_mha(out / "recording.seq.mha", rec, "MF")
    write_config(out / "config.xml", calibration(spacing=(0.054, 0.054), shear_deg=2.0))
    np.save(out / "masks.npy", masks)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--height", type=int, default=810)
    parser.add_argument("--width", type=int, default=950)
    parser.add_argument("--every", type=int, default=10, help="annotate every N-th frame")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "masks.npy").exists():
        write_recording(out, args.frames, args.height, args.width, args.every)
    dataset = out / "dataset"
    stages = [
        ("import-plus", ["ultron", "import-plus", str(out / "recording.seq.mha"), "--config",
                         str(out / "config.xml"), "--out", str(dataset)], dataset / "dataset.json"),
        ("label --masks", ["ultron", "label", str(dataset), "--masks", str(out / "masks.npy")],
         dataset / "recording" / "labels.npy"),
    ]  # fmt: skip
    rows = [run_unless_done(name, command, done, out / "logs") for name, command, done in stages]
    rows += _round_trip(out, dataset)  # before this process loads anything: a child's peak
    from ultron.data.dataset import SweepDataset  # RSS counts its parent's at the fork

    sweep = SweepDataset.load(dataset).sweeps[0]
    labels_in = np.load(out / "labels_in.npy")
    known = labels_in != 255
    agree = (labels_in == 1) == (sweep.images >= (TISSUE + ECHO) / 2)
    figures = {
        "frames": args.frames,
        "frame_px": [args.height, args.width],
        "sweep_px": list(sweep.images.shape[1:]),
        "annotated_frames": int(known.any(axis=(1, 2)).sum()),
        "agreement_on_annotated_pixels": float(agree[known].mean()),
        "round_trip_kept": float(np.mean(sweep.labels == labels_in)),
        "stages": [row for row in rows if row is not None],
    }
    print(
        f"\n{args.frames} frames of {args.height} × {args.width} px, every {args.every}th annotated"
    )
    print("| stage | wall (s) | peak RSS (GiB) |\n|---|---|---|")
    for row in figures["stages"]:
        print(f"| {row['stage']} | {row['seconds']:.1f} | {row['peak_rss_bytes'] / GIB:.2f} |")
    print(
        f"labels on {figures['annotated_frames']} frames; bone ⇔ the imported echo on"
        f" {100 * figures['agreement_on_annotated_pixels']:.2f} % of their known pixels"
    )
    print(
        f"export and read back: {100 * figures['round_trip_kept']:.2f} % of the sweep's labels kept"
    )
    (out / "mask_import.json").write_text(json.dumps(figures, indent=2))


def _round_trip(out: Path, dataset: Path) -> list[dict | None]:
    """Stages 3 and 4 (module doc); the labels before them kept in ``labels_in.npy``."""
    if not (out / "labels_in.npy").exists():
        shutil.copyfile(dataset / "recording" / "labels.npy", out / "labels_in.npy")
    exported = out / "exported.seq.mha"
    stages = [
        ("label --export", ["ultron", "label", str(dataset), "--export", str(exported),
                            "--recording", str(out / "recording.seq.mha")], exported),
        ("label --masks (exported)", ["ultron", "label", str(dataset), "--masks", str(exported),
                                      "--unsure-value", "2", "--replace"], out / "round_trip.done"),
    ]  # fmt: skip
    rows = [run_unless_done(name, command, done, out / "logs") for name, command, done in stages]
    (out / "round_trip.done").touch()
    return rows


if __name__ == "__main__":
    main()
