"""Benchmark: every method on a real cadaver fibula sweep with CT truth (issue 31, item 1).

The data is ``../shared/data/ultrabones-fibula`` (UltraBones100k, passes 1–2: 985 real tracked
frames of 162 × 187, CT-derived labels, the CT fibula and its visible part; its README says how
it was made and how to score on it). Every command runs as its own process, so that each row's
wall time and peak RSS are its own (``os.wait4``'s rusage of the child, as
``benchmarks/long_sweep.py`` measures them):

1. ``ultron label --auto`` on a copy of the dataset (images and poses copied, the CT-derived
   labels left behind): what a user without an annotator has. The auto labels are scored
   against the CT-derived ones per sweep (precision counted where the CT says bone or
   background, recall of the CT bone, both within 1 mm in depth; the share of CT bone the auto
   labels call background; issue 31's targets are on ``pass2``, the detector was set on
   ``pass1``).
2. ``ultron fit-field`` once (the acoustic field depends on the B-mode only); every UltrON row
   reuses it (``--field``; the auto-labelled copy with ``--allow-other-field``).
3. ``ultron reconstruct`` for each label condition — the CT-derived labels on 10 % and 5 % of
   the frames (``--fractions``), the auto labels on every frame — and each method
   (``--methods``: compounding, UltrON, UltrON w/o loss, ON, RoCoSDF). With ``--seeds 0,1,2``
   every row runs once per ``reconstruct --seed`` (for the CT-derived labels which frames are
   labelled and the training's seed; for the auto labels, every frame labelled, the training's
   seed alone; the rows of seed 0 keep their names and commands) and the table ends with each
   method's mean over the seeds.
4. Scoring as the data's README says, with ``ultron evaluate``'s crop (``--crop-mm``, 5): the
   faces within 5 mm of the visible CT surface are kept (the tibia and soft tissue are imaged
   but have no CT here; the area outside is reported), accuracy (MAD, HD95) to the whole CT
   fibula, completeness of the visible part, CD = their mean (``cd_visible``), F-score at 1 mm
   against the visible part.

Nothing is tuned here: the script only runs the defaults. Re-running it resumes: a stage whose
output exists is not run again (``--fresh`` reruns everything). It prints each row as soon as it
is scored and rewrites ``OUT/real_fibula.json`` then (``"complete": false`` until the last row),
so a run stopped part-way keeps the rows it finished; at the end it prints the table in
markdown.

Usage::

    python benchmarks/real_fibula.py --out runs/real_fibula
    python benchmarks/real_fibula.py --out runs/real_fibula --methods compounding --skip-auto
    python benchmarks/real_fibula.py --out runs/real_fibula --seeds 0,1,2 --skip-auto
    python benchmarks/real_fibula.py --out runs/real_fibula_gpu --device cuda
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from long_sweep import GIB, run_stage
from ultron.atomic import write_json
from ultron.methods.catalog import FIELD_METHODS

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ultrabones-fibula"
METHODS = ("compounding", "ultron", "ultron-noloss", "on", "rocosdf")
#: Each stage's wall time and peak RSS (or its error), kept across resumed runs: OUT/STAGES.
STAGES = "stages.json"
#: Depth tolerance of the auto-label scores: 1 mm in rows of 0.2696 mm, rounded down.
TOLERANCE_MM = 1.0


def auto_labelled_copy(data: Path, out: Path) -> Path:
    """``out``: the dataset's images, poses and references without its labels (copied once)."""
    if (out / "dataset.json").is_file():
        return out
    staging = out.with_name(out.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    meta = json.loads((data / "dataset.json").read_text())
    for sweep in meta["sweeps"]:
        (staging / sweep["name"]).mkdir()
        for name in ("images.npy", "poses.npy"):
            shutil.copyfile(data / sweep["name"] / name, staging / sweep["name"] / name)
    for key in ("reference", "reference_visible"):
        if meta.get(key):
            shutil.copyfile(data / meta[key], staging / meta[key])
    (staging / "dataset.json").write_text(json.dumps(meta, indent=2))
    staging.rename(out)
    return out


def score_auto_labels(data: Path, auto: Path) -> dict[str, dict[str, float]]:
    """Per sweep: the auto labels against the CT-derived labels (module doc, step 1)."""
    import numpy as np

    from ultron.data.auto_labels import bone_precision_recall
    from ultron.data.dataset import SweepDataset

    truth, guess = SweepDataset.load(data), SweepDataset.load(auto)
    tolerance = int(TOLERANCE_MM / truth.probe.axial_spacing_mm)
    scores = {}
    for sweep in truth.sweeps:
        true = np.asarray(sweep.labels)
        pred = np.asarray(guess.sweep(sweep.name).labels)
        precision, recall, _, _ = bone_precision_recall(pred, true, tolerance, where_annotated=True)
        bone = true == 1
        scores[sweep.name] = {
            "precision": precision,
            "recall": recall,
            "bone_called_background": float((pred[bone] == 0).mean()),
            "unsure": float((pred == 255).mean()),
        }
    return scores


def seed_suffix(seed: int) -> str:
    """What a row's name gains from its seed: nothing for seed 0 (the runs before ``--seeds``)."""
    return "" if seed == 0 else f" seed {seed}"


def conditions(args: argparse.Namespace) -> list[tuple[str, Path, float, int]]:
    """(name, dataset, label fraction, seed) of each label condition (module doc, step 3)."""
    rows = [
        (f"CT {round(100 * f)} %{seed_suffix(seed)}", args.data, f, seed)
        for f in args.fractions
        for seed in args.seeds
    ]
    if not args.skip_auto:
        auto = args.out / "auto"
        rows += [(f"auto 100 %{seed_suffix(seed)}", auto, 1.0, seed) for seed in args.seeds]
    return rows


def reconstruct_command(
    args, dataset: Path, method: str, fraction: float, out: Path, seed: int = 0
) -> list:
    command = [
        "ultron", "reconstruct", str(dataset), "--method", method, "--label-fraction",
        str(fraction), "--points", str(args.points), "--out", str(out),
    ]  # fmt: skip
    if seed != 0:
        command += ["--seed", str(seed)]
    if method in FIELD_METHODS:
        command += ["--field", str(args.out / "field")]
        if dataset != args.data:
            command.append("--allow-other-field")
    return command + device_option(args)


def device_option(args) -> list[str]:
    """``--device D`` for the commands that train, when the benchmark was given one."""
    return [] if args.device is None else ["--device", args.device]


def timed(name: str, command: list[str], done: Path, args, log: dict) -> dict:
    """Run ``command`` unless ``done`` exists (then the timing recorded before is kept), and
    save ``log`` with its timing to ``OUT/stages.json``. A command that refuses the data (e.g.
    RoCoSDF without a column sweep) gives ``{"error": its one-line message}``."""
    if name in log and (done.exists() or "error" in log[name]):
        print(f"[{name}] done before", flush=True)
        return log[name]
    stage = name.replace(" ", "_").replace("%", "pct")
    try:
        log[name] = run_stage(stage, command, args.out / "logs")
    except SystemExit:
        text = (args.out / "logs" / f"{stage}.log").read_text(encoding="utf-8", errors="replace")
        errors = [line for line in text.splitlines() if line.startswith("error:")]
        log[name] = {"error": errors[-1] if errors else text.strip().splitlines()[-1]}
    write_json(args.out / STAGES, log, default=float)
    return log[name]


def evaluate(args, mesh: Path) -> dict:
    """The data README's scores of ``mesh`` (module doc, step 4)."""
    from ultron.mesh.export import load_mesh
    from ultron.metrics.surface import MetricsConfig, evaluate_meshes

    config = MetricsConfig(n_points=args.points, repeats=args.repeats, crop_mm=args.crop_mm)
    reference = load_mesh(args.data / "reference.ply")
    visible = load_mesh(args.data / "reference_visible.ply")
    result = evaluate_meshes(load_mesh(mesh, allow_empty=True), reference, config, visible)
    return {"mean": result["mean"], "std": result["std"], "crop": result["crop"]}


TABLE_HEADER = (
    "| labels | method | CD | accuracy MAD | completeness vis. | HD95 | F@1 mm vis. |"
    " area outside crop (mm²) | wall (s) | peak RSS (GiB) |"
)


def table_row(row: dict) -> str:
    """``row`` as a line of the markdown table (:data:`TABLE_HEADER`)."""
    if "error" in row:
        return f"| {row['labels']} | {row['method']} | n/a: {row['error']} |" + " |" * 7
    m = row["metrics"]["mean"]
    crop = row["metrics"]["crop"]
    return (
        f"| {row['labels']} | {row['method']} | {m['cd_visible']:.3f} | {m['mad']:.3f} |"
        f" {m['completeness_visible']:.3f} | {m['hd95']:.3f} |"
        f" {m['fscore_visible_1mm']:.3f} | {crop['area_outside_mm2']:.0f} |"
        f" {row['seconds']:.1f} | {row['peak_rss_bytes'] / GIB:.2f} |"
    )


def print_table(rows: list[dict], field_stage: dict | None) -> None:
    print("\n" + TABLE_HEADER)
    print("|---" * 10 + "|")
    for row in rows:
        print(table_row(row))
    for line in seed_means(rows):
        print(line)
    if field_stage is not None:
        print(
            f"\nfield fit (shared by the UltrON rows): {field_stage['seconds']:.1f} s,"
            f" peak RSS {field_stage['peak_rss_bytes'] / GIB:.2f} GiB"
        )


def seed_means(rows: list[dict]) -> list[str]:
    """Per label condition (``CT 10 %``, ``auto 100 %``) and method run at more than one seed,
    its mean CD over the seeds (none when a seed's row failed)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        condition = row["labels"].removesuffix(seed_suffix(row["seed"]))
        groups.setdefault((condition, row["method"]), []).append(row)
    lines = []
    for (condition, method), group in groups.items():
        if len(group) < 2 or any("error" in row for row in group):
            continue
        cds = [row["metrics"]["mean"]["cd_visible"] for row in group]
        seeds = ", ".join(str(row["seed"]) for row in group)
        lines.append(
            f"mean CD over seeds {seeds}, {condition} labels, {method}:"
            f" {sum(cds) / len(cds):.3f} (from {min(cds):.3f} to {max(cds):.3f})"
        )
    return lines


def run_rows(args, methods: list[str], log: dict, result: dict) -> list[dict]:
    """Every label condition × method (module doc, step 3). Each row is printed as soon as it
    is scored and ``OUT/real_fibula.json`` rewritten (atomically, ``"complete": false``), so a
    run stopped part-way — a GPU lease's time limit — keeps the rows it finished."""
    rows = result.setdefault("rows", [])
    for labels, dataset, fraction, seed in conditions(args):
        for method in methods:
            name = f"{labels} {method}"
            out = args.out / "runs" / name.replace(" ", "-").replace("%", "pct")
            command = reconstruct_command(args, dataset, method, fraction, out, seed)
            stage = timed(name, command, out / "run.json", args, log)
            row = {"labels": labels, "method": method, "fraction": fraction, "seed": seed}
            row.update(stage)
            if "error" not in stage:
                row["metrics"] = evaluate(args, out / "mesh.ply")
            rows.append(row)
            print(f"[{name}] scored: {table_row(row)}", flush=True)
            write_json(args.out / "real_fibula.json", {**result, "complete": False}, default=float)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=Path("runs/real_fibula"))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--fractions", default="0.1,0.05", help="of the CT-derived labels")
    parser.add_argument("--seeds", default="0", help="reconstruct --seed of every row")
    parser.add_argument("--skip-auto", action="store_true", help="no auto-label rows")
    parser.add_argument("--points", type=int, default=30_000, help="per surface, metrics")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--crop-mm", type=float, default=5.0)
    parser.add_argument("--fresh", action="store_true", help="rerun every stage")
    parser.add_argument(
        "--device", default=None, help="fit-field's and reconstruct's --device (default: theirs)"
    )
    args = parser.parse_args()
    args.fractions = [float(f) for f in args.fractions.split(",")]
    args.seeds = [int(s) for s in args.seeds.split(",")]
    methods = [m for m in args.methods.split(",") if m]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise SystemExit(f"--methods: unknown {unknown}; choose from {', '.join(METHODS)}")
    if args.fresh:
        shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    log_file = args.out / STAGES
    log = json.loads(log_file.read_text()) if log_file.is_file() else {}
    started = time.perf_counter()

    result: dict = {"data": str(args.data), "crop_mm": args.crop_mm}
    if not args.skip_auto:
        auto = auto_labelled_copy(args.data, args.out / "auto")
        command = ["ultron", "label", str(auto), "--auto", "--replace"]
        result["auto_labels_stage"] = timed("auto labels", command, auto / "pass1" / "labels.npy",
                                            args, log)  # fmt: skip
        result["auto_labels"] = score_auto_labels(args.data, auto)
        for sweep, s in result["auto_labels"].items():
            print(f"auto labels {sweep}: precision {s['precision']:.3f}, recall {s['recall']:.3f}"
                  f" (±{TOLERANCE_MM:g} mm), CT bone called background"
                  f" {100 * s['bone_called_background']:.2f} %, unsure {100 * s['unsure']:.1f} %")  # fmt: skip
    field_stage = None
    if any(m in FIELD_METHODS for m in methods):
        command = ["ultron", "fit-field", str(args.data), "--out", str(args.out / "field")]
        command += device_option(args)
        field_stage = timed("fit field", command, args.out / "field" / "field.json", args, log)
    result["field_stage"] = field_stage
    rows = run_rows(args, methods, log, result)
    write_json(args.out / "real_fibula.json", {**result, "complete": True}, default=float)
    print_table(rows, field_stage)
    print(f"\nbenchmark wall time {time.perf_counter() - started:.0f} s; {args.out}")


if __name__ == "__main__":
    main()
