"""``simulate``: a digital phantom's tracked sweeps written as a dataset, with its preview.

:func:`simulate_to` checks the output directory, simulates the dataset there
(:func:`ultron.phantom.simulate_dataset`: the frames, labels, true transmission and reference
meshes, ``dataset.json`` last) and, when asked, writes ``preview.png`` (a few frames of each
sweep with their labels); it returns what the command reports.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from ultron.data.dataset import SweepDataset
from ultron.outputs import check_output_dir
from ultron.phantom import SimulationConfig, simulate_dataset
from ultron.phantom.dataset import Progress
from ultron.phantom.preview import write_preview


@dataclass(frozen=True)
class SimulatedDataset:
    """A simulated dataset as written: the dataset, the seconds the simulation took and the
    preview's path (None: not asked for)."""

    dataset: SweepDataset
    out: Path
    seconds: float
    preview: Path | None


def simulate_to(
    config: SimulationConfig,
    out: str | Path,
    preview: bool = False,
    progress: Progress | None = None,
) -> SimulatedDataset:
    """Simulate ``config``'s dataset into ``out`` (a new or empty directory; an existing file
    is an error naming ``--out``), then ``out/preview.png`` when ``preview``. ``progress(what,
    done, total)`` is told how the simulation advances."""
    out = check_output_dir(out)
    start = time.perf_counter()
    dataset = simulate_dataset(config, out=out, progress=progress)
    seconds = time.perf_counter() - start
    path = write_preview(dataset, out / "preview.png") if preview else None
    return SimulatedDataset(dataset, out, seconds, path)
