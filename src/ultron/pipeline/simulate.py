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
from ultron.outputs import check_dataset_out
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

    def lines(self, phantom: str) -> list[str]:
        """What ``simulate`` prints: the sweeps and frames made and the files written."""
        dataset, out, probe = self.dataset, self.out, self.dataset.probe
        visible = dataset.reference_visible_path
        lines = [
            f"simulated {phantom}: {len(dataset.sweeps)} sweeps, {dataset.n_frames} frames of"
            f" {probe.height_px}×{probe.width_px} ({probe.width_mm:g} mm × {probe.depth_mm:g}"
            f" mm) in {self.seconds:.1f} s → {out}",
            f"wrote {out / 'dataset.json'}, {out / 'reference.ply'}, {out / 'phantom.json'}"
            + (f", {visible}" if visible is not None else "")
            + " and each sweep's transmission.npy (ground truth for diagnosis)",
        ]
        if self.preview is not None:
            lines.append(f"preview: {self.preview}")
        return lines


def simulate_to(
    config: SimulationConfig,
    out: str | Path,
    preview: bool = False,
    progress: Progress | None = None,
) -> SimulatedDataset:
    """Simulate ``config``'s dataset into ``out`` (a new or empty directory, or an earlier
    dataset's, which it replaces; a file or a folder of other files is an error naming
    ``--out``), then ``out/preview.png`` when ``preview``. ``progress(what,
    done, total)`` is told how the simulation advances."""
    out = check_dataset_out(out)
    start = time.perf_counter()
    dataset = simulate_dataset(config, out=out, progress=progress)
    seconds = time.perf_counter() - start
    path = write_preview(dataset, out / "preview.png") if preview else None
    return SimulatedDataset(dataset, out, seconds, path)
