"""``ultron benchmark``: the paper's Tables 1 and 2 (and robustness) on the digital phantoms."""

from __future__ import annotations

from pathlib import Path

import typer

from ultron.cli.common import command, console

#: Exit code when the benchmark ran but some cells failed.
EXIT_CELLS_FAILED = 1


def _phantom_list(text: str) -> tuple[str, ...]:
    return tuple(name.strip() for name in text.split(",") if name.strip())


@command(
    torch_threads=False,
    documented_by=(
        "ultron.benchmark.config:BenchmarkConfig",
        "ultron.benchmark.pipeline:run_benchmark",
    ),
)
def benchmark(
    out: Path,
    quick: bool = False,
    seeds: int | None = None,
    phantoms: str | None = None,
    jobs: int = 1,
    threads: int | None = None,
    robustness: bool = False,
    no_generalisation: bool = False,
    no_cell_reports: bool = False,
    preset: str = "fast",
    executor: str = "local",
    address: str | None = None,
    device: str = "auto",
) -> None:
    """Run the paper's Tables 1 and 2: simulate, fit, reconstruct every cell, aggregate,
    print the tables next to the paper's figures and the targets; write DIR/benchmark.json,
    DIR/tables.md and DIR/report.html. Exits 1 if any cell failed.

    Args:
        quick: L3 (+ L2 for Table 2), one seed, fewer field/occupancy iterations and metric
            points (≈ 10 min on 2 idle cores).
        seeds: Seeds 0..K-1 per phantom (default 3; 1 with --quick).
        phantoms: Comma-separated phantoms (default L2,L3,L3b,L4,condyle; L3 with --quick).
        threads: torch threads per task (default: cores // jobs).
        no_generalisation: Skip Table 2 (train on L3, apply to L2).
        no_cell_reports: Skip each cell's own report.html (DIR/report.html still shows every
            row).
        preset: Settings of every stage: fast or paper (the UltrON paper's: 8 × 128 MLP field,
            75k + 50k iterations, RoCoSDF's paper settings; days on a CPU, for GPUs).
        executor: local (this machine, --jobs at a time) or ray (each task a Ray task of
            --threads CPUs; needs Ray: pip install ray).
    """
    from ultron.benchmark import run_benchmark
    from ultron.benchmark.config import benchmark_config

    given = {"seeds": seeds, "phantoms": None if phantoms is None else _phantom_list(phantoms)}
    config = benchmark_config(  # checks every setting
        preset,
        quick,
        **{name: value for name, value in given.items() if value is not None},
        jobs=jobs,
        threads=threads,
        robustness=robustness,
        generalisation=not no_generalisation,
        cell_reports=not no_cell_reports,
        device=device,
    )

    def log(line: str) -> None:
        console.print(line, markup=False, highlight=False, soft_wrap=True)

    result = run_benchmark(config, out, log=log, executor=executor, address=address)
    typer.echo("")
    typer.echo(result.markdown)
    typer.echo("")
    for note in result.notes:
        log(note)
    log(f"wrote {out / 'benchmark.json'} and {out / 'tables.md'}")
    failed = result.failed_cells
    if failed:
        log(f"{len(failed)} cell(s) failed (see the list above and each run's error.log)")
        raise typer.Exit(EXIT_CELLS_FAILED)
