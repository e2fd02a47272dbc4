"""Benchmark: fine-tuning speed, 100 iterations with the last two layers frozen (target ≤ 2 s).

Times what ``ultron finetune`` does on a dataset and its fitted field: gathering θ and T of the
1 % label frames and the anchor (the model's occupancy at ``anchor_points`` pixels; once), then
the 100-iteration fine-tuning loop of a copy of the model with its last two layers frozen,
``--repeats`` times (median and min are printed), then meshing once.
The model is MODEL_DIR's network (``--model``, an ``ultron reconstruct --method ultron`` output);
without it a freshly initialised f_ω of the same architecture is timed (the loop's cost does
not depend on the weights).

Usage::

    python benchmarks/finetune.py                                  # simulates L2 into --out
    python benchmarks/finetune.py --dataset DIR --field FIELD_DIR [--model MODEL_DIR]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

from common import add_arguments, prepare


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, "runs/bench-finetune")
    parser.add_argument("--phantom", default="L2", help="simulated when --dataset is not given")
    parser.add_argument("--model", type=Path, default=None, help="MODEL_DIR (default: fresh f_ω)")
    parser.add_argument("--iters", type=int, default=100)
    parser.add_argument("--label-fraction", type=float, default=0.01)
    parser.add_argument("--anchor-weight", type=float, default=1.0, help="0: no anchor")
    args = parser.parse_args()

    import torch

    from ultron.data.dataset import SweepDataset
    from ultron.data.labels import select_label_frames
    from ultron.fields.occupancy import OccupancyNetwork, OccupancyNetworkConfig
    from ultron.mesh.occupancy_mesh import mesh_occupancy
    from ultron.methods.finetune import (
        FinetuneConfig,
        ThetaModel,
        freeze_last_layers,
        prediction_anchor,
    )
    from ultron.methods.ultron_method import occupancy_function, occupancy_training_data
    from ultron.models.fitted import load_field
    from ultron.pipeline.model_io import load_network
    from ultron.timing import StageTimer
    from ultron.train.occupancy import fit_occupancy

    dataset_dir, field_dir, _ = prepare(args)
    dataset, fitted = SweepDataset.load(dataset_dir), load_field(field_dir)
    if args.model is not None:
        network, meta = load_network(args.model)
        spec = ThetaModel.from_meta(meta)
    else:
        torch.manual_seed(args.seed)
        spec = ThetaModel()
        width = spec.context.n_inputs(len(fitted.channels))
        network = OccupancyNetwork(OccupancyNetworkConfig(in_dim=width))
        print("no --model: timing a freshly initialised f_ω (same architecture)")
    config = FinetuneConfig(
        label_fraction=args.label_fraction,
        iters=args.iters,
        seed=args.seed,
        anchor_weight=args.anchor_weight,
    )

    start = time.perf_counter()
    selection = select_label_frames(dataset, config.label_fraction, config.seed)
    data = occupancy_training_data(dataset, fitted, selection, context=spec.context)
    gather_s = time.perf_counter() - start
    start = time.perf_counter()
    anchor = None
    if config.anchor_weight > 0:
        anchor = prediction_anchor(dataset, fitted, network, spec, config)
    anchor_s = time.perf_counter() - start

    loop_s = []
    for _ in range(args.repeats):
        model = copy.deepcopy(network)
        trainable = freeze_last_layers(model, config.frozen_layers)
        start = time.perf_counter()
        model, _ = fit_occupancy(
            data, config.training(spec), model, lambda _, params=trainable: params, anchor=anchor
        )
        loop_s.append(time.perf_counter() - start)

    timer = StageTimer()
    fn = occupancy_function(fitted, model, spec.context)
    mesh_occupancy(fn, dataset, config.meshing.meshing, timer)

    print(f"\ndataset {dataset_dir}; field {field_dir}; torch threads {torch.get_num_threads()}")
    print(
        f"labels: {selection.n_frames} frames ({100 * config.label_fraction:g} %), "
        f"{len(data.labels)} labelled pixels, batch {config.batch_size}; θ/T gathering {gather_s:.2f} s"
    )
    held = f"{config.anchor_points} pixels, weight {config.anchor_weight:g}" if anchor else "none"
    print(f"anchor: {held}; its θ and occupancy {anchor_s:.2f} s")
    print(
        f"fine-tuning {config.iters} iterations, last {config.frozen_layers} layers frozen, "
        f"{args.repeats} repeats: median {statistics.median(loop_s):.2f} s, min {min(loop_s):.2f} s"
        f" ({', '.join(f'{s:.2f}' for s in loop_s)})"
    )
    meshing = ", ".join(f"{k} {v:.1f} s" for k, v in timer.seconds.items())
    print(f"meshing once: {timer.total:.1f} s ({meshing})")
    median = statistics.median(loop_s)
    verdict = "met" if median <= 2.0 else "MISSED"
    print(f"\ntarget: {config.iters} iterations ≤ 2 s → {verdict} (median {median:.2f} s)")


if __name__ == "__main__":
    main()
