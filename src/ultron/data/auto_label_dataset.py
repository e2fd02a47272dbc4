"""Write automatic bone labels (:mod:`ultron.data.auto_labels`) into a dataset's sweeps.

:func:`auto_label_dataset` labels the chosen sweeps of a dataset directory and records under
``metadata.auto_labels.<sweep>`` of ``dataset.json`` that the sweep's labels are automatic::

    {"method": "ultron-auto-labels/2", "config": {...AutoLabelConfig...}, "frames": N,
     "shares": {"bone": …, "background": …, "unsure": …},
     "frames_without_bone": …, "frames_to_check": [...], "labels_digest": "…"}

``labels_digest`` (:func:`labels_digest`) ties a record to the labels it describes, so that
every write is atomic and any interruption leaves a dataset that tells the truth: the records
are written first (``dataset.json``), then each sweep's ``labels.npy``, then ``dataset.json``
again without the sweeps' earlier mask records. A record whose digest is not that of the
sweep's labels (the run was stopped before it wrote them) is stale and ignored
(:func:`auto_label_records`), and a rerun of the same ``label --auto`` relabels the sweeps
whose labels are automatic labels of the same settings without ``--replace``: it resumes.

and writing, per sweep, ``auto_labels_quality.csv``: one row per frame (``frame``,
``bone_scanlines``: the share of its scanlines with a surface, ``evidence``: the mean bone
score along it, ``unsure``: the share of unsure pixels, ``check``: 1 where the surface dropped
out while the neighbouring frames see one, :func:`~ultron.data.auto_labels.frames_to_check`;
for a sweep imported from PLUS also ``recording_frame``: the frame's number in the recording's
file, as Slicer and ``label --export``'s masks number it), so that a user sees which frames to
look at before trusting them.

Existing labels — a person's, or automatic labels of other settings — are never overwritten
unless ``replace`` is true.
Everything that can be checked (sweep names, existing labels, writable folders) is checked
before any frame is labelled, so a refused call writes nothing.
"""

from __future__ import annotations

import hashlib
import math
import os
import shlex
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ultron import atomic
from ultron.data.auto_labels import (
    AUTO_LABELS_METHOD,
    AutoLabelConfig,
    FrameQuality,
    auto_label_frames,
    frames_to_check,
)
from ultron.data.dataset import SweepDataset, one_sweep
from ultron.data.validation import (
    LABEL_BACKGROUND,
    LABEL_TARGET,
    LABEL_UNANNOTATED,
    validate_labels,
)
from ultron.errors import UltronInputError, argument_error

#: ``dataset.json`` metadata key holding, per sweep, the record of its automatic labels.
METADATA_KEY = "auto_labels"
#: ``dataset.json``'s metadata key of the sweeps whose labels came from a person's masks
#: (:mod:`ultron.data.label_import`): replaced by automatic labels, a sweep leaves it.
MASKS_KEY = "label_imports"
#: The per-frame quality summary written into each labelled sweep's folder.
QUALITY_FILE = "auto_labels_quality.csv"
#: How many frames to check a record and the CLI name at most.
MAX_LISTED = 20

#: Progress callback: (sweep name, frames done, frames of the sweep).
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class SweepLabelSummary:
    """What :func:`auto_label_dataset` wrote for one sweep: frames, the share of bone (1),
    background (0) and unsure (255) pixels, whether labels were replaced, and the time taken."""

    name: str
    frames: int
    bone: float
    background: float
    unsure: float
    replaced: bool
    seconds: float
    #: Frames without any detected bone, and those to check (:func:`frames_to_check`).
    frames_without_bone: int = 0
    frames_to_check: tuple[int, ...] = ()
    #: For a sweep imported from PLUS: each frame's number in the recording's file, and the file
    #: (its path where the import read it and it still is, else its name).
    recording_frames: tuple[int, ...] | None = None
    recording: str | None = None

    def shares(self) -> dict[str, float]:
        return {"bone": self.bone, "background": self.background, "unsure": self.unsure}

    def lines(self, dataset_dir: str | Path) -> tuple[list[str], list[str]]:
        """What ``label --auto`` prints for the sweep (lines, warnings): the label shares, the
        frames without bone and those to check (:data:`MAX_LISTED` at most), and a warning
        when no frame shows bone."""
        where = Path(dataset_dir) / self.name
        listed = self.frames_to_check[:MAX_LISTED]
        more = " …" if len(self.frames_to_check) > MAX_LISTED else ""
        check = ", ".join(str(i) for i in listed) + more
        if listed and self.recording_frames is not None:
            in_file = [self.recording_frames[i] for i in listed]
            if in_file != list(listed):
                check += f" (the recording's {', '.join(str(i) for i in in_file)}{more})"
        lines = [
            f"{self.name}: {self.frames} frames, bone {100 * self.bone:.2f} %, background"
            f" {100 * self.background:.1f} %, unsure {100 * self.unsure:.1f} %"
            f" ({'replaced' if self.replaced else 'wrote'} labels.npy, {self.seconds:.1f} s)",
            f"  {self.frames_without_bone} frames without bone; {len(self.frames_to_check)} where"
            f" the surface dropped out{': check ' + check if listed else ''}"
            f" (per frame: {where / QUALITY_FILE})",
        ]
        if listed and self.recording is not None:
            nrrd = self.recording.lower().endswith((".nrrd", ".nhdr"))  # a twin of its format
            command = ["ultron", "label", str(dataset_dir), "--export",
                       f"{self.name}_labels.seq.{'nrrd' if nrrd else 'mha'}", "--sweeps",
                       self.name]  # fmt: skip
            if not Path(self.recording).is_absolute():  # not where the import read it
                command += ["--recording", self.recording]
            lines.append(f"  to correct them over the recording: {shlex.join(command)}")
        warnings = []
        if self.frames and self.frames_without_bone == self.frames:
            warnings.append(
                f"{where}: no bone found in any of its {self.frames} frames (a recording without"
                " bone, or frames the detector does not suit): its labels are background and"
                " unsure only, nothing to reconstruct from"
            )
        return lines, warnings


def quality_csv(
    qualities: Sequence[FrameQuality], recording_frames: Sequence[int] | None = None
) -> str:
    """The per-frame quality summary (module docstring) as CSV text; ``recording_frames``:
    each frame's number in a PLUS recording's file (the last column), None for another sweep."""
    lines = ["frame,bone_scanlines,evidence,unsure,check"]
    if recording_frames is not None:
        lines[0] += ",recording_frame"
    check = frames_to_check(list(qualities))
    for i, q in enumerate(qualities):
        evidence = "" if math.isnan(q.evidence) else f"{q.evidence:.4f}"  # no surface
        line = f"{i},{q.bone_scanlines:.4f},{evidence},{q.unsure:.4f},{int(check[i])}"
        lines.append(line if recording_frames is None else f"{line},{recording_frames[i]}")
    return "\n".join(lines) + "\n"


def label_shares(labels: np.ndarray) -> dict[str, float]:
    """The share of bone (1), background (0) and unsure / not annotated (255) pixels."""
    labels = np.asarray(labels)
    total = max(1, labels.size)
    return {
        "bone": float(np.count_nonzero(labels == LABEL_TARGET) / total),
        "background": float(np.count_nonzero(labels == LABEL_BACKGROUND) / total),
        "unsure": float(np.count_nonzero(labels == LABEL_UNANNOTATED) / total),
    }


def _chosen_sweeps(
    dataset: SweepDataset, root: Path, sweeps: Sequence[str] | None, option: str
) -> list[str]:
    names = [s.name for s in dataset.sweeps]
    if sweeps is None:
        return names
    if isinstance(sweeps, str) or not all(isinstance(n, str) for n in sweeps):
        raise argument_error(option, f"expected a list of sweep names, got {sweeps!r}")
    if not sweeps:
        raise argument_error(option, "expected at least one sweep name")
    for name in sweeps:
        if name not in names:
            raise argument_error(
                option, f"no sweep {name!r} in dataset {root}; available: {', '.join(names)}"
            )
    return list(dict.fromkeys(sweeps))


def _check_writable(root: Path, names: Sequence[str]) -> None:
    for folder in (root, *(root / name for name in names)):
        if not os.access(folder, os.W_OK | os.X_OK):
            raise UltronInputError(folder, "labels", "directory is not writable")


def check_labelling(
    root: str | Path,
    sweeps: Sequence[str] | None = None,
    replace: bool = False,
    option: str = "sweeps",
    what: str = "automatic labels",
    one: str | None = None,
    min_frame_px: int = 3,
    relabel: AutoLabelConfig | None = None,
) -> tuple[SweepDataset, list[str]]:
    """Load the dataset at ``root`` and check that the chosen ``sweeps`` (default: all) exist,
    have no labels unless ``replace``, and can be written; returns the dataset and the names.
    A sweep that already has labels is an error naming it, ``--replace`` and ``what`` would
    overwrite them; an unknown sweep one naming it and ``option`` (the argument that chose
    it); with ``one`` (the option that works on one sweep), other than one sweep chosen; frames
    of fewer than ``min_frame_px`` rows or columns (the detector needs rows about an echo).
    With ``relabel``, labels that are automatic labels of those settings (their record's
    digest matching) count as no labels: labelling them again reproduces them, and the rerun
    of an interrupted ``label --auto`` resumes without ``--replace``."""
    root = Path(root)
    dataset = SweepDataset.load(root)
    if min(dataset.probe.image_shape) < min_frame_px:
        raise UltronInputError(
            root / "dataset.json", "probe", f"frames of {dataset.probe.height_px} ×"
            f" {dataset.probe.width_px} pixels; {what} need at least {min_frame_px} ×"
            f" {min_frame_px}",
        )  # fmt: skip
    names = _chosen_sweeps(dataset, root, sweeps, option)
    if one is not None:
        names = [one_sweep(names, one)]
    if not replace:
        same = _same_auto_labels(dataset, relabel)
        for name in names:
            if dataset.sweep(name).labels is not None and name not in same:
                raise UltronInputError(
                    root / name / "labels.npy",
                    "labels",
                    f"sweep {name!r} already has labels; pass --replace to overwrite them"
                    f" with {what}",
                )
    _check_writable(root, names)
    return dataset, names


def _same_auto_labels(dataset: SweepDataset, config: AutoLabelConfig | None) -> set[str]:
    """The sweeps whose labels are automatic labels of ``config`` (none without one)."""
    if config is None:
        return set()
    wanted = config.to_dict()
    records = auto_label_records(dataset).items()
    return {name for name, record in records if record.get("config") == wanted}


def labels_digest(labels: np.ndarray) -> str:
    """A digest of a sweep's label array (its shape, dtype and bytes): BLAKE2b, 16 bytes, hex.
    ``dataset.json``'s label records carry it, so that a record names the labels it was
    written with (module docstring)."""
    labels = np.ascontiguousarray(labels)
    digest = hashlib.blake2b(f"{labels.shape}{labels.dtype.str}".encode(), digest_size=16)
    digest.update(memoryview(labels).cast("B"))
    return digest.hexdigest()


def record_matches(record: dict[str, Any], labels: np.ndarray | None) -> bool:
    """Whether a label record describes ``labels``: there are labels, and the record's
    ``labels_digest`` is theirs (a record written before digests existed matches any)."""
    if labels is None:
        return False
    digest = record.get("labels_digest")
    return digest is None or digest == labels_digest(labels)


def _record(config: AutoLabelConfig, summary: SweepLabelSummary) -> dict[str, Any]:
    return {
        "method": AUTO_LABELS_METHOD,
        "config": config.to_dict(),
        "frames": summary.frames,
        "shares": summary.shares(),
        "frames_without_bone": summary.frames_without_bone,
        "frames_to_check": list(summary.frames_to_check[:MAX_LISTED]),
        "quality": QUALITY_FILE,
    }


def auto_label_dataset(
    root: str | Path,
    sweeps: Sequence[str] | None = None,
    replace: bool = False,
    config: AutoLabelConfig | None = None,
    progress: Progress | None = None,
) -> list[SweepLabelSummary]:
    """Label the chosen ``sweeps`` (default: all) of the dataset at ``root`` automatically
    (:func:`~ultron.data.auto_labels.auto_label_frames`) and write them (module docstring):
    every sweep is labelled first, then the labels are written, ``dataset.json`` last. Returns
    one summary per sweep, in the order given."""
    cfg = _checked_config(config)
    dataset, names = check_labelling(root, sweeps, replace, relabel=cfg)
    return label_checked_sweeps(root, dataset, names, cfg, progress)


def _checked_config(config: AutoLabelConfig | None) -> AutoLabelConfig:
    cfg = config or AutoLabelConfig()
    if not isinstance(cfg, AutoLabelConfig):
        raise argument_error("config", f"expected an AutoLabelConfig, got {type(cfg).__name__}")
    return cfg


def label_checked_sweeps(
    root: str | Path,
    dataset: SweepDataset,
    names: Sequence[str],
    config: AutoLabelConfig | None = None,
    progress: Progress | None = None,
) -> list[SweepLabelSummary]:
    """:func:`auto_label_dataset`'s work once :func:`check_labelling` has passed: ``dataset``
    and ``names`` are what it returned for ``root``. A caller that checks first (to refuse bad
    input before it shows any progress) thus reads the dataset once."""
    cfg = _checked_config(config)
    root = Path(root)
    computed: dict[str, tuple[np.ndarray, list[FrameQuality]]] = {}
    summaries = []
    for name in names:  # every sweep is labelled before anything is written
        sweep = dataset.sweep(name)
        start = time.perf_counter()
        report = None if progress is None else (lambda d, t, n=name: progress(n, d, t))
        labels, qualities = auto_label_frames(sweep.images, dataset.probe, cfg, progress=report)
        validate_labels(labels, f"sweep {name!r}", "labels")
        computed[name] = labels, qualities
        summary = SweepLabelSummary(
            name,
            sweep.n_frames,
            **label_shares(labels),
            replaced=sweep.labels is not None,
            seconds=time.perf_counter() - start,
            frames_without_bone=sum(q.bone_scanlines == 0 for q in qualities),
            frames_to_check=tuple(int(i) for i in np.flatnonzero(frames_to_check(qualities))),
            **_recording_of(dataset, name),
        )
        summaries.append(summary)
    records = dict(dataset.metadata.get(METADATA_KEY) or {})
    for summary in summaries:
        records[summary.name] = _record(cfg, summary)
        csv = quality_csv(computed[summary.name][1], summary.recording_frames)
        atomic.write_text(root / summary.name / QUALITY_FILE, csv)
    write_labels(root, dataset, {n: computed[n][0] for n in names}, METADATA_KEY, records,
                 MASKS_KEY)  # fmt: skip
    return summaries


def write_labels(
    root: Path,
    dataset: SweepDataset,
    labels: dict[str, np.ndarray],
    key: str,
    records: dict[str, Any],
    other_key: str,
) -> None:
    """Write new ``labels`` (sweep name → array) into the dataset at ``root`` with their
    records (``metadata[key]``, each given its labels' :func:`labels_digest` here), so that an
    interruption at any point leaves records that tell the truth: ``dataset.json`` with the new records,
    then each ``labels.npy``, then ``dataset.json`` without the sweeps' records under
    ``other_key`` (the other source of labels; a record of it written before digests existed
    first gets the digest of the labels it describes, so that it goes stale with them).
    ``dataset`` is updated to match."""
    others = dict(dataset.metadata.get(other_key) or {})
    for name in labels:
        record, current = others.get(name), dataset.sweep(name).labels
        if isinstance(record, dict) and "labels_digest" not in record and current is not None:
            others[name] = {**record, "labels_digest": labels_digest(current)}
    records = dict(records)
    for name, array in labels.items():
        records[name] = {**records[name], "labels_digest": labels_digest(array)}
    dataset.metadata = {**dataset.metadata, key: records}
    if others:
        dataset.metadata[other_key] = others
    save_dataset_json(root, dataset)
    for name, array in labels.items():
        atomic.save_npy(root / name / "labels.npy", array)
        dataset.sweep(name).labels = array
    dataset.metadata = without_sweeps(dataset.metadata, other_key, list(labels))
    save_dataset_json(root, dataset)


def _recording_of(dataset: SweepDataset, name: str) -> dict[str, Any]:
    """A PLUS sweep's frame numbers in its recording's file and the file's name (the import's
    record, ``metadata.imports.<name>``); nothing for another sweep."""
    record = (dataset.metadata.get("imports") or {}).get(name)
    if not (isinstance(record, dict) and record.get("source") == "plus"):
        return {}
    frames = record.get("frames")
    if not isinstance(frames, list) or len(frames) != dataset.sweep(name).n_frames:
        return {}
    path = record.get("sequence_path")
    found = isinstance(path, str) and Path(path).is_file()  # then label --export finds it
    recording = path if found else record.get("sequence")
    return {"recording_frames": tuple(int(f) for f in frames), "recording": recording}


def without_sweeps(metadata: dict[str, Any], key: str, names: Sequence[str]) -> dict[str, Any]:
    """``metadata`` with the sweeps ``names`` left out of its per-sweep record ``key`` (the
    record itself left out once it holds no sweep); ``metadata`` is not changed."""
    kept = {k: v for k, v in (metadata.get(key) or {}).items() if k not in names}
    out = {k: v for k, v in metadata.items() if k != key}
    if kept:
        out[key] = kept
    return out


def save_dataset_json(root: Path, dataset: SweepDataset) -> None:
    """Write ``root/dataset.json`` of ``dataset`` (its metadata changed), atomically, after the
    sweeps' files it names."""
    reference = dataset.reference.name if dataset.reference is not None else None
    visible = dataset.reference_visible_path
    meta = dataset.to_json(reference, visible.name if visible is not None else None)
    atomic.write_json(root / "dataset.json", meta)


def auto_label_records(dataset: SweepDataset) -> dict[str, dict[str, Any]]:
    """``metadata.auto_labels`` of a loaded dataset: sweep name → record, for the sweeps that
    have the labels it records (an entry of a sweep without ``labels.npy``, or whose digest is
    not that of its labels, is stale and left out: :func:`record_matches`); {} for a dataset
    without automatic labels (every dataset written before they existed)."""
    records = dataset.metadata.get(METADATA_KEY)
    if not isinstance(records, dict):
        return {}
    labels = {s.name: s.labels for s in dataset.sweeps}
    return {
        k: v
        for k, v in records.items()
        if k in labels and isinstance(v, dict) and record_matches(v, labels[k])
    }
