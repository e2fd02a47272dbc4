"""Acoustic fields cached by dataset content: one fit per dataset and field configuration.

The key is a SHA-256 over the dataset's ``dataset.json`` and every sweep's images and poses
(labels and the reference do not affect stage 1) plus the field-training configuration. The
cache lives in ``$ULTRON_CACHE`` (default ``~/.cache/ultron``) under ``fields/<key>``; a fit
interrupted there resumes from its checkpoint on the next call.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from ultron.device import resolve_device
from ultron.errors import UltronInputError
from ultron.models.field_dir import CHECKPOINT, FIELD_JSON, FIT_DONE
from ultron.models.fitted import load_field
from ultron.train.field_fit import fit_field
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.loop import Progress

CHUNK = 1 << 20


def cache_root() -> Path:
    return Path(os.environ.get("ULTRON_CACHE", Path.home() / ".cache" / "ultron"))


def dataset_hash(dataset_dir: str | Path, extra: dict[str, Any] | None = None) -> str:
    """Content hash of a dataset directory's stage-1 inputs (and ``extra``, e.g. a config)."""
    root = Path(dataset_dir)
    digest = hashlib.sha256()
    meta = json.loads((root / "dataset.json").read_text(encoding="utf-8"))
    digest.update(
        json.dumps({k: meta.get(k) for k in ("format", "probe", "sweeps")}, sort_keys=True).encode()
    )
    for sweep in meta["sweeps"]:
        for name in ("images.npy", "poses.npy"):
            with open(root / sweep["name"] / name, "rb") as handle:
                while block := handle.read(CHUNK):
                    digest.update(block)
    if extra is not None:
        digest.update(json.dumps(extra, sort_keys=True, default=str).encode())
    return digest.hexdigest()[:20]


def cached_field_dir(
    dataset_dir: str | Path, config_dict: dict[str, Any], device_type: str = "cpu"
) -> Path:
    """The cache directory of a fit of this dataset and configuration on a device of
    ``device_type``: fields fitted on an accelerator are kept apart (their float arithmetic
    differs), while CPU fits keep the keys they had before devices existed."""
    extra = config_dict if device_type == "cpu" else {**config_dict, "device": device_type}
    return cache_root() / "fields" / dataset_hash(dataset_dir, extra)


def get_or_fit_field(
    dataset_dir: str | Path,
    dataset,
    config,
    progress: Progress | None = None,
    device: Any = "cpu",
):
    """Load the cached field for this dataset and configuration onto ``device``, fitting it
    there first if needed (see :func:`cached_field_dir` for the key).

    An interrupted fit resumes, unless its field.json records another dataset content hash
    (:meth:`SweepDataset.content_hash`, which covers the labels too, while the cache key does
    not): then the fit starts afresh, so that field.json names the dataset it is used with."""
    device = resolve_device(device, "device")
    config = resolve_fit_shape(config, dataset)  # the key holds the shape the fit uses
    field_dir = cached_field_dir(dataset_dir, config.to_dict(), device.type)
    if all((field_dir / n).is_file() for n in (FIT_DONE, FIELD_JSON, CHECKPOINT)):
        return load_field(field_dir, device), field_dir, True
    try:
        fitted = fit_field(dataset, config, field_dir, progress, resume=True, device=device)
    except UltronInputError as exc:
        if exc.field != "dataset_sha256":
            raise
        fitted = fit_field(dataset, config, field_dir, progress, resume=False, device=device)
    return fitted, field_dir, False
