"""``simulate``: a digital phantom's tracked sweeps written as a dataset, with its preview.

:func:`simulate_to` checks the output directory, simulates the dataset there
(:func:`ultron.phantom.simulate_dataset`: the frames, labels, true transmission and reference
meshes, ``dataset.json`` last) and, when asked, writes ``preview.png`` (a few frames of each
sweep with their labels); it returns what the command reports.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.outputs import check_dataset_out
from ultron.phantom import SimulationConfig, simulate_dataset
from ultron.phantom.dataset import GENERATOR, Progress
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


def _check_replaces_a_simulation(out: Path) -> None:
    """Refuse an ``out`` holding a dataset that no simulation wrote (an imported recording,
    labels a person made): a simulation replaces an earlier one's dataset.json, and would
    leave that dataset's sweeps unlisted and its records gone."""
    meta_path = out / "dataset.json"
    if not meta_path.is_file():
        return
    try:
        metadata = json.loads(meta_path.read_text(encoding="utf-8")).get("metadata", {})
    except (OSError, ValueError, AttributeError):
        metadata = None
    if not isinstance(metadata, dict) or metadata.get("generator") != GENERATOR:
        raise UltronInputError(
            out, "--out", "holds a dataset that ultron simulate did not write (an import, your"
            " own data); a simulation replaces only an earlier simulation: give a new or empty"
            " directory",
        )  # fmt: skip
    if imported := metadata.get("imports"):
        raise UltronInputError(
            out, "--out", f"holds a simulation with imported sweeps ({', '.join(imported)}),"
            " which a new simulation would replace or drop: give a new or empty directory",
        )  # fmt: skip


def simulate_to(
    config: SimulationConfig,
    out: str | Path,
    preview: bool = False,
    progress: Progress | None = None,
) -> SimulatedDataset:
    """Simulate ``config``'s dataset into ``out`` (a new or empty directory, or an earlier
    simulation's, which it replaces; a file, a folder of other files, a dataset no simulation
    wrote or a simulation with an imported sweep is an error naming ``--out``), then
    ``out/preview.png`` when ``preview``. ``progress(what, done, total)`` is told how the
    simulation advances."""
    out = check_dataset_out(out)
    _check_replaces_a_simulation(out)
    start = time.perf_counter()
    dataset = simulate_dataset(config, out=out, progress=progress)
    seconds = time.perf_counter() - start
    path = write_preview(dataset, out / "preview.png") if preview else None
    return SimulatedDataset(dataset, out, seconds, path)
