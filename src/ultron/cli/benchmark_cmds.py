"""``ultron benchmark``: the paper's Tables 1 and 2 (and robustness) on the digital phantoms."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ultron.arguments import check_choice, check_count
from ultron.cli.common import DeviceOption, check_device, console, user_errors
from ultron.errors import argument_error

#: Exit code when the benchmark ran but some cells failed.
EXIT_CELLS_FAILED = 1


def _phantom_list(text: str) -> tuple[str, ...]:
    return tuple(name.strip() for name in text.split(",") if name.strip())


BenchOut = Annotated[Path, typer.Option("--out", help="Output directory (resumed if it exists).")]
Quick = Annotated[
    bool,
    typer.Option(
        "--quick",
        help="L3 (+ L2 for Table 2), one seed, fewer field/occupancy iterations and metric"
        " points (≈ 10 min on 2 idle cores).",
    ),
]
Seeds = Annotated[
    int | None,
    typer.Option("--seeds", help="Seeds 0..K-1 per phantom (default 3; 1 with --quick)."),
]
Phantoms = Annotated[
    str | None,
    typer.Option(
        "--phantoms",
        help="Comma-separated phantoms (default L2,L3,L3b,L4,condyle; L3 with --quick).",
    ),
]
Jobs = Annotated[
    int, typer.Option("--jobs", help="Tasks run in parallel (spawned worker processes).")
]
TaskThreads = Annotated[
    int | None,
    typer.Option("--threads", help="torch threads per task (default: cores // jobs)."),
]
Robustness = Annotated[
    bool,
    typer.Option(
        "--robustness",
        help="Also UltrON (10%) vs RoCoSDF (100%) on L3 with larger annotation errors and"
        " with pose misalignment.",
    ),
]
NoGeneralisation = Annotated[
    bool,
    typer.Option("--no-generalisation", help="Skip Table 2 (train on L3, apply to L2)."),
]
NoCellReports = Annotated[
    bool,
    typer.Option(
        "--no-cell-reports",
        help="Skip each cell's own report.html (DIR/report.html still shows every row).",
    ),
]
BenchPreset = Annotated[
    str,
    typer.Option(
        "--preset",
        help="Settings of every stage: fast or paper (the UltrON paper's: 8 × 128 MLP field,"
        " 75k + 50k iterations, RoCoSDF's paper settings; days on a CPU, for GPUs).",
    ),
]
Executor = Annotated[
    str,
    typer.Option(
        "--executor",
        help="local (this machine, --jobs at a time) or ray (each task a Ray task of"
        " --threads CPUs; needs Ray: pip install ray).",
    ),
]
Address = Annotated[
    str | None,
    typer.Option(
        "--address",
        help="With --executor ray: the Ray cluster to join (auto, ray://host:10001);"
        " default: start a local one.",
    ),
]


@user_errors
def benchmark(
    out: BenchOut,
    quick: Quick = False,
    seeds: Seeds = None,
    phantoms: Phantoms = None,
    jobs: Jobs = 1,
    threads: TaskThreads = None,
    robustness: Robustness = False,
    no_generalisation: NoGeneralisation = False,
    no_cell_reports: NoCellReports = False,
    preset: BenchPreset = "fast",
    executor: Executor = "local",
    address: Address = None,
    device: DeviceOption = "auto",
) -> None:
    """Run the paper's Tables 1 and 2: simulate, fit, reconstruct every cell, aggregate,
    print the tables next to the paper's figures and the targets; write DIR/benchmark.json,
    DIR/tables.md and DIR/report.html. Exits 1 if any cell failed."""
    check_count("--seeds", seeds)
    check_count("--jobs", jobs)
    check_count("--threads", threads)
    device = check_device(device)

    from ultron.benchmark import run_benchmark
    from ultron.benchmark.config import benchmark_config
    from ultron.pipeline.presets import PIPELINE_PRESETS

    check_choice("--preset", preset, PIPELINE_PRESETS)
    if quick and preset != "fast":
        raise argument_error("--preset", "--quick runs the fast preset only")
    changes: dict = {
        "jobs": jobs,
        "threads": threads,
        "robustness": robustness,
        "generalisation": not no_generalisation,
        "cell_reports": not no_cell_reports,
        "device": device,
    }
    if seeds is not None:
        changes["seeds"] = seeds
    if phantoms is not None:
        changes["phantoms"] = _phantom_list(phantoms)
    config = benchmark_config(preset, quick, **changes)

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


def register(app: typer.Typer) -> None:
    app.command("benchmark")(benchmark)
