"""A FIELD_DIR on disk, written and read here (``fit-field`` writes it, every user reads it).

Files: ``field.json`` (format ``ultron-field/1``: the field, render and training
configurations, the probe geometry it was fitted at, the world ↔ unit-cube transform, the
held-out frames, the step reached, the dataset's content hash and where it was fitted),
``checkpoint.pt`` (model, optimiser and batch-generator state, step and iterations; CPU
tensors, so it loads on any device), ``train_log.jsonl`` (one JSON object per logged update)
and ``theta_stats.json`` (θ's per-channel statistics, written when the fit ends), and on a
simulated dataset ``transmission_check.json`` (the fitted T against the true one); while a fit
runs, ``confidence_maps.npz`` (:mod:`ultron.train.confidence_cache`; removed when it ends).
Every write is atomic; the log is written before the checkpoint and field.json, so it may run
ahead of a checkpoint after a kill, never behind (:func:`read_train_log` drops what runs
ahead).
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import torch

from ultron import atomic
from ultron.device import cpu_state
from ultron.errors import UltronInputError, read_json_file
from ultron.outputs import check_not_inside_output, check_output_dir, is_inside

FIELD_FORMAT = "ultron-field/1"
FIELD_JSON = "field.json"
CHECKPOINT = "checkpoint.pt"
THETA_STATS = "theta_stats.json"
TRAIN_LOG = "train_log.jsonl"
#: The fit's confidence maps while it runs (:mod:`ultron.train.confidence_cache`).
CONFIDENCE_CACHE = "confidence_maps.npz"
#: Written at the end of a fit on a dataset with the simulator's true transmission (every
#: annotated sweep has ``transmission.npy``): the fitted field's T against it
#: (:mod:`ultron.train.transmission_check`). Diagnostic only; no reader of a field needs it.
TRANSMISSION_CHECK = "transmission_check.json"
#: Written last by a fit that ran to its end (θ statistics and transmission check included)
#: and removed when a fit starts or continues, so that a fit asked again for the same steps
#: loads the field instead of preparing its frames afresh (:func:`fit_is_done`).
FIT_DONE = "done"


def read_field_json(field_dir: Path) -> dict[str, Any]:
    """FIELD_DIR's field.json, checked to be a JSON object of this format."""
    path = field_dir / FIELD_JSON
    if not path.is_file():
        raise UltronInputError(path, FIELD_JSON, "file is missing (not a fitted field directory)")
    meta = read_json_file(path, FIELD_JSON)
    if not isinstance(meta, dict) or meta.get("format") != FIELD_FORMAT:
        raise UltronInputError(path, "format", f"expected {FIELD_FORMAT!r}")
    return meta


def check_field_dataset(
    field_dir: str | Path, dataset_sha256: str, where: str = "dataset", allow_other: bool = False
) -> bool | None:
    """Whether FIELD_DIR was fitted on the dataset whose content hash is ``dataset_sha256``
    (:meth:`SweepDataset.content_hash`, recorded as field.json's ``dataset_sha256``).

    Returns True on a match and None for a field.json without the record (fitted before it
    was kept). A mismatch raises a one-line :class:`UltronInputError` naming field.json and
    ``dataset_sha256`` (``where`` names the dataset) unless ``allow_other``, then returns False.
    """
    root = Path(field_dir)
    recorded = read_field_json(root).get("dataset_sha256")
    if recorded is None:
        return None
    if recorded == dataset_sha256:
        return True
    if allow_other:
        return False
    raise UltronInputError(
        root / FIELD_JSON,
        "dataset_sha256",
        f"the field was fitted on another dataset than {where} (recorded {str(recorded)[:12]}…,"
        f" {where} has {dataset_sha256[:12]}…); pass --allow-other-field to use it anyway",
    )


def read_checkpoint(field_dir: Path) -> dict[str, Any]:
    """FIELD_DIR's checkpoint.pt (plain data only), read onto the CPU."""
    path = field_dir / CHECKPOINT
    if not path.is_file():
        raise UltronInputError(path, CHECKPOINT, "checkpoint file is missing")
    try:
        return torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt or foreign file
        raise UltronInputError(path, CHECKPOINT, f"cannot be read ({type(exc).__name__})") from None


def save_checkpoint(
    out_dir: Path,
    module: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    step: int,
    iterations: int,
) -> None:
    """Write ``checkpoint.pt`` atomically: the model, optimiser and batch generator's state
    after ``step`` of ``iterations`` updates, as CPU tensors."""
    state = {  # CPU copies, so that the checkpoint loads on any device
        "model": cpu_state(module.state_dict()),
        "optimizer": cpu_state(optimizer.state_dict()),
        "generator": generator.get_state(),
        "step": step,
        "iterations": iterations,
    }
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic.write_bytes(out_dir / CHECKPOINT, buffer.getvalue())


def write_train_log(out_dir: Path, entries: list[dict[str, Any]]) -> None:
    """Write ``train_log.jsonl`` atomically, one entry per line."""
    atomic.write_text(out_dir / TRAIN_LOG, "".join(json.dumps(e) + "\n" for e in entries))


def read_train_log(out: Path, step: int) -> list[dict[str, Any]]:
    """FIELD_DIR ``out``'s training log up to ``step``: the log is saved before the checkpoint
    (:func:`ultron.train.field_fit.fit_field`), so after a kill between the two it may hold entries beyond the
    checkpoint, which the resumed run computes again."""
    path = out / TRAIN_LOG
    if not path.is_file():
        return []
    entries = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
        except json.JSONDecodeError as exc:
            raise UltronInputError(path, f"line {number}", f"not valid JSON ({exc})") from None
        if not isinstance(entry, dict) or not isinstance(entry.get("step"), int):
            raise UltronInputError(path, f"line {number}", "expected an object with a step")
        if entry["step"] <= step:
            entries.append(entry)
    return entries


def check_field_out(out: str | Path, dataset_dir: str | Path, option: str = "--out") -> Path:
    """Refuse (one line naming ``out``) a FIELD_DIR to write that is not new, empty or an
    earlier fit's (it holds field.json, checkpoint.pt, train_log.jsonl or, from a fit stopped
    before its first checkpoint, confidence_maps.npz), or that is or holds
    the dataset; creates nothing. A subdirectory of the dataset is fine (its sweeps are listed
    by name). The rule of :func:`ultron.pipeline.rundir.check_run_dir`: an output directory
    belongs to one kind of output."""
    out = check_output_dir(out, option)
    check_not_inside_output(out, option)
    if is_inside(dataset_dir, out):
        raise UltronInputError(
            out, option, f"holds the dataset {dataset_dir}; write the field into its own directory"
        )
    if not out.is_dir() or not any(out.iterdir()):
        return out
    if any((out / n).exists() for n in (FIELD_JSON, CHECKPOINT, TRAIN_LOG, CONFIDENCE_CACHE)):
        return out
    what = (
        "an ultron run (run.json)" if (out / "run.json").exists() else "no field of an earlier fit"
    )
    raise UltronInputError(
        out, option, f"is not empty and holds {what}; give a new or empty directory"
    )


def clear_field_dir(out: Path) -> None:
    """Remove a previous fit's files from ``out`` (only FIELD_DIR's own file names), so that
    an interrupted fresh run never leaves a mix of two runs (or an old checkpoint to resume)."""
    for name in (FIT_DONE, CHECKPOINT, FIELD_JSON, THETA_STATS, TRAIN_LOG, TRANSMISSION_CHECK):
        (out / name).unlink(missing_ok=True)


def fit_is_done(out: Path, iterations: int) -> bool:
    """Whether FIELD_DIR ``out`` holds a fit that ran to its end at ``iterations`` steps: its
    :data:`FIT_DONE` marker, field.json and checkpoint, and field.json's ``step`` equal to
    ``iterations`` (a fit continued to more steps removes the marker first)."""
    if not all((out / n).is_file() for n in (FIT_DONE, FIELD_JSON, CHECKPOINT)):
        return False
    return read_field_json(out).get("step") == iterations


def write_transmission_check(out_dir: Path, check: dict[str, Any]) -> None:
    """Write ``transmission_check.json`` atomically (see :data:`TRANSMISSION_CHECK`)."""
    atomic.write_json(out_dir / TRANSMISSION_CHECK, check)


def read_transmission_check(field_dir: Path) -> dict[str, Any] | None:
    """FIELD_DIR's ``transmission_check.json``, or None when the field has none (a dataset
    without ground truth, or a field fitted before the check existed)."""
    path = Path(field_dir) / TRANSMISSION_CHECK
    if not path.is_file():
        return None
    data = read_json_file(path, TRANSMISSION_CHECK)
    if not isinstance(data, dict):
        raise UltronInputError(path, TRANSMISSION_CHECK, "expected a JSON object")
    return data
