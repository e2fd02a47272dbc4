"""Benchmark: a killed ``reconstruct`` resumed from its stage-2 checkpoint, and what the
checkpoints cost.

On one dataset and its fitted field (``--dataset`` and ``--field``; default: L3 simulated and
fitted into ``--out``, as ``benchmarks/reconstruct.py`` prepares them), with the fast preset's
UltrON at ``--label-fraction`` (default 10 %):

1. **Cost.** UltrON's stage 2 (:func:`ultron.methods.ultron_method.train_ultron`) run twice on
   the same labels and field, without and with a checkpoint file, alternately ``--repeats``
   times (here the number of such pairs, not of metric repeats): the occupancy fit's seconds each way (the checkpoint's saves and the fingerprint of
   its data are the difference), the checkpoint's size, and whether both fits end on the same
   network, bit for bit.
2. **Resume.** ``reconstruct`` into ``OUT/whole`` uninterrupted; into ``OUT/run`` killed once
   the occupancy fit reports ``--kill-at`` updates (an exception from its progress callback,
   as a ``SIGINT`` would stop it), then run again: the update it resumed from, the second
   run's wall time against the whole run's, and whether its mesh and metrics are the
   uninterrupted run's, vertex for vertex.

Prints the figures; nothing is hard-coded or tuned.

Usage::

    python benchmarks/resume.py --dataset DIR --field FIELD_DIR --out /tmp/resume --repeats 2
        --points 30000
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from common import add_arguments, prepare


class Killed(Exception):
    """Stands for the process being killed."""


def stage2_cost(dataset_dir: Path, field_dir: Path, out: Path, fraction: float, repeats: int):
    """(seconds without, seconds with, checkpoint MiB, same network) of stage 2."""
    import torch

    from ultron.data.dataset import SweepDataset
    from ultron.methods.ultron_method import train_ultron
    from ultron.models.fitted import load_field
    from ultron.pipeline.presets import preset_request
    from ultron.timing import StageTimer
    from ultron.train.fit_checkpoint import OCCUPANCY_FIT, checkpoint_in

    dataset, fitted = SweepDataset.load(dataset_dir), load_field(field_dir)
    config = preset_request("fast", "ultron", fraction, 0).method_config
    seconds: dict[bool, list[float]] = {False: [], True: []}
    networks = {}
    for _ in range(repeats):
        for saved in (False, True):
            directory = out / "cost"
            shutil.rmtree(directory, ignore_errors=True)
            timer = StageTimer()
            trained = train_ultron(dataset, fitted, "ultron", fraction, 0, config, timer,
                                   checkpoints=directory if saved else None)  # fmt: skip
            seconds[saved].append(timer.seconds["occupancy_fit"])
            networks[saved] = trained.network.state_dict()
    size_mib = checkpoint_in(directory, OCCUPANCY_FIT).path.stat().st_size / 2**20
    pairs = zip(networks[False].values(), networks[True].values(), strict=True)
    same = all(torch.equal(a, b) for a, b in pairs)
    return seconds[False], seconds[True], size_mib, same


def killed_and_resumed(args: argparse.Namespace, dataset_dir: Path, field_dir: Path):
    """Wall seconds of the whole run, the killed one and the resumed one; the resumed step;
    whether the resumed run's mesh and metrics are the whole run's."""
    import numpy as np

    from ultron.mesh.export import load_mesh
    from ultron.pipeline.presets import preset_request
    from ultron.pipeline.run import reconstruct
    from ultron.pipeline.rundir import resume_dir

    out, at = args.out, args.kill_at
    request = preset_request("fast", "ultron", args.label_fraction, 0, points=args.points)

    def kill(name: str, done: int, total: int, unit: str) -> None:
        if name == "occupancy_fit" and done >= at:
            raise Killed

    seconds = {}
    for name, target, advance in (("whole", "whole", None), ("killed", "run", kill),
                                  ("resumed", "run", None)):  # fmt: skip
        if name != "resumed":  # a fresh start: no earlier run, nothing to resume from
            shutil.rmtree(out / target, ignore_errors=True)
            shutil.rmtree(resume_dir(out / target), ignore_errors=True)
        start = time.perf_counter()
        try:
            summary = reconstruct(dataset_dir, request, out / target, field_dir, report=False,
                                  advance=advance)  # fmt: skip
        except Killed:
            pass
        seconds[name] = time.perf_counter() - start
    meshes = [load_mesh(out / d / "mesh.ply") for d in ("whole", "run")]
    metrics = [json.loads((out / d / "metrics.json").read_text())["mean"] for d in ("whole", "run")]
    same = (
        np.array_equal(meshes[0].vertices, meshes[1].vertices)
        and np.array_equal(meshes[0].faces, meshes[1].faces)
        and metrics[0] == metrics[1]
    )
    return seconds, summary.get("resumed_from_step", {}).get("occupancy"), same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, "runs/bench-resume")
    parser.add_argument("--label-fraction", type=float, default=0.1)
    parser.add_argument("--kill-at", type=int, default=1000, help="occupancy updates")
    args = parser.parse_args()
    dataset_dir, field_dir, _ = prepare(args)
    plain, saved, size_mib, same_fit = stage2_cost(
        dataset_dir, field_dir, args.out, args.label_fraction, args.repeats
    )
    print("| stage 2 (UltrON, fast preset) | occupancy fit (s), each run |")
    print("|---|---|")
    print(f"| without a checkpoint | {', '.join(f'{s:.2f}' for s in plain)} |")
    print(f"| with one | {', '.join(f'{s:.2f}' for s in saved)} |")
    print(f"checkpoint file {size_mib:.1f} MiB; the same network both ways: {same_fit}")
    seconds, resumed, same = killed_and_resumed(args, dataset_dir, field_dir)
    print(
        f"reconstruct: whole {seconds['whole']:.1f} s; killed after {args.kill_at} updates at"
        f" {seconds['killed']:.1f} s; the rerun resumed from update {resumed} and took"
        f" {seconds['resumed']:.1f} s; its mesh and metrics the whole run's: {same}"
    )


if __name__ == "__main__":
    main()
