"""``ultron demo``: the whole method on the built-in digital phantom, in minutes on a CPU.

Simulate the L3 vertebra phantom (four tracked sweeps with labels), fit its acoustic field
(the fast preset), reconstruct with UltrON and with its ablation (UltrON w/o the compensated
loss) from 10 % of the labelled frames, and measure both against the phantom's reference
surface. ``OUT/dataset`` and ``OUT/field`` are reused when present (an interrupted demo
resumes); ``OUT/ultron`` and ``OUT/ultron-noloss`` are run directories
(:mod:`ultron.pipeline.rundir`).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

from ultron.arguments import check_seed
from ultron.data.dataset import SweepDataset
from ultron.outputs import check_output_dir
from ultron.phantom import SimulationConfig, simulate_dataset
from ultron.pipeline.presets import preset_field_config, preset_request
from ultron.pipeline.run import reconstruct
from ultron.pipeline.rundir import check_run_dir
from ultron.timing import Advance, Announce
from ultron.train.field_fit import fit_field
from ultron.train.loop import Progress

DEMO_PHANTOM = "L3"
DEMO_LABEL_FRACTION = 0.1
#: The demo's methods and how the summary names them.
DEMO_METHODS = {"ultron": "UltrON (10%)", "ultron-noloss": "UltrON w/o loss (10%)"}


def check_demo_out(out: str | Path) -> Path:
    """Refuse (one line, before any work) an ``out`` whose run directories the demo may not
    replace; returns ``out`` as a Path."""
    out = Path(out)
    check_output_dir(out)
    for method in DEMO_METHODS:
        check_run_dir(out / method, "reconstruct")
    return out


def run_demo(
    out: str | Path,
    seed: int = 0,
    device: str = "cpu",
    field_progress: Callable[[], AbstractContextManager[Progress | None]] | None = None,
    status: Callable[[str], AbstractContextManager[Any]] | None = None,
    log: Callable[[str], None] | None = None,
    announce: Announce | None = None,
    advance: Advance | None = None,
) -> dict[str, dict[str, Any]]:
    """Run the demo (module doc) into ``out``; returns each method's summary by its name in
    :data:`DEMO_METHODS`. ``field_progress()`` wraps the field fit and gives the callback of its
    per-step dicts (e.g. a progress bar's), ``status(text)`` wraps the simulation (e.g. a
    spinner), ``log(line)`` reports what was done; ``announce`` and ``advance`` are told each
    reconstruction's stages and how far a long one has come, as
    :func:`~ultron.pipeline.run.reconstruct` tells them, after ``log`` has named the method."""
    check_seed("seed", seed)
    out = check_demo_out(out)
    field_progress = field_progress or nullcontext
    status = status or (lambda text: nullcontext())
    log = log or (lambda line: None)
    dataset_dir = out / "dataset"
    if (dataset_dir / "dataset.json").is_file():
        log(f"using the simulated dataset in {dataset_dir}")
    else:
        with status(f"simulating the {DEMO_PHANTOM} phantom"):
            simulate_dataset(SimulationConfig(phantom=DEMO_PHANTOM, seed=seed), out=dataset_dir)
        log(f"simulated {DEMO_PHANTOM} → {dataset_dir}")
    dataset = SweepDataset.load(dataset_dir)
    field_dir = out / "field"
    field_config = preset_field_config("fast", seed)
    with field_progress() as progress:
        fit_field(dataset, field_config, field_dir, progress, resume=True, device=device)
    log(f"acoustic field → {field_dir} (fitted on {device})")
    summaries = {}
    for method, label in DEMO_METHODS.items():
        log(f"{label} → {out / method}")
        request = preset_request("fast", method, DEMO_LABEL_FRACTION, seed, device=device)
        summaries[label] = reconstruct(
            dataset_dir, request, out / method, field_dir, announce=announce, advance=advance
        )
    return summaries
