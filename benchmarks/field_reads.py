"""Benchmark: θ queries of a fitted field, its grid reads shared out over the CPU threads or not.

Loads FIELD_DIR, draws ``--points`` points uniformly in the inner 80 % of the field's cube
(seeded), and times ``FittedField.query`` on them, in the drawn order and sorted along the
world axis they spread most along (a sweep's pixels and the meshing's tiles come in such an
order), with ``fields.grid.threaded_read`` sharing each read of a single plane or volume out
over torch's threads and with every read one call. The two are timed alternately, ``--repeats`` times
each, and must give the same bits. Prints the median seconds of each and their ratio.

A field with square planes (a compact box) reads them as one batch of three, which torch
already shares out: there the two columns time the same code.

Usage::

    python benchmarks/field_reads.py FIELD_DIR [--points 1000000] [--repeats 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

import ultron.fields.grid as grid
from ultron.errors import UltronError
from ultron.models.fitted import load_field


def cube_points(fitted, n: int, seed: int) -> torch.Tensor:
    """``n`` world points (mm, float64) uniform in the inner 80 % of the field's unit cube."""
    cube = fitted.unit_cube
    unit = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    unit = 1.6 * unit - 0.8
    axes = torch.eye(3, dtype=torch.float64) if cube.axes is None else torch.tensor(cube.axes)
    return unit * cube.half_extent_mm @ axes.to(torch.float64) + torch.tensor(cube.center_mm)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("field_dir")
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        fitted = load_field(args.field_dir)
    except UltronError as exc:  # one line naming the file, exit 2, as the commands do
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    points = cube_points(fitted, args.points, args.seed)
    longest = int(points.std(0).argmax())  # the world axis along which the points spread most
    orders = {"drawn": points, "sorted": points[torch.argsort(points[:, longest])]}
    shared_out = grid._POINTS_PER_THREAD
    print(f"{args.field_dir}: {args.points} points, {args.threads} threads")
    for name, where in orders.items():
        seconds: dict[str, list[float]] = {"shared out": [], "one call": []}
        results = {}
        for _ in range(args.repeats):
            for mode in seconds:
                grid._POINTS_PER_THREAD = shared_out if mode == "shared out" else 2**62
                started = time.perf_counter()
                results[mode] = fitted.query(where).stack()
                seconds[mode].append(time.perf_counter() - started)
        grid._POINTS_PER_THREAD = shared_out
        if not torch.equal(results["shared out"], results["one call"]):
            raise SystemExit(f"{name}: the two reads differ")
        median = {mode: statistics.median(values) for mode, values in seconds.items()}
        print(
            f"{name:>6}: shared out {median['shared out']:.3f} s, one call "
            f"{median['one call']:.3f} s ({median['one call'] / median['shared out']:.2f}×), "
            "the same bits"
        )


if __name__ == "__main__":
    main()
