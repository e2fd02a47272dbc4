"""The field fit's confidence maps kept on disk while it runs, so that a resumed fit reads them
instead of solving them again (one sparse factorisation a frame: a large share of a long
sweep's fit; figures in docs/decisions.md, "Confidence maps kept for a resumed fit").

One file in the fit's FIELD_DIR, :data:`CONFIDENCE_CACHE`, an uncompressed ``.npz`` (no
pickles) of two arrays::

    maps  float32 (N, H, W)   confidence_maps(images, config) of the fit's frames
    key   str                 JSON: FORMAT, the frames' shape and SHA-256, the config, the solver

written atomically (:mod:`ultron.atomic`) as soon as the maps are computed, and removed when the
fit ends. The key holds everything the maps are a function of — the frames' own bytes at the
fitting resolution, Karamalis et al.'s parameters and the solver (MONAI's version) — so a file
whose key is not the fit's own (another dataset, fit shape or release of MONAI, an older
format) or that cannot be read is ignored and overwritten: a stale file can never change a
result, only fail to save time.
"""

from __future__ import annotations

import contextlib
import json
import zipfile
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ultron import atomic
from ultron.errors import argument_error
from ultron.models.field_dir import CONFIDENCE_CACHE
from ultron.train.confidence import ConfidenceConfig, confidence_maps, solver_description
from ultron.train.fit_checkpoint import fit_fingerprint

#: Names the file's layout (bumped when it changes; another format is never read).
FORMAT = "ultron-confidence-maps/1"


def confidence_key(images: np.ndarray, config: ConfidenceConfig) -> str:
    """The JSON key of the maps of ``images`` (N, H, W) under ``config``: the format, the
    frames' dtype, shape and SHA-256, the config's parameters and the solver."""
    images = np.ascontiguousarray(images)
    digest = fit_fingerprint([torch.from_numpy(images)], {})  # SHA-256 of shape, dtype, bytes
    return json.dumps(
        {
            "format": FORMAT,
            "frames": {"dtype": str(images.dtype), "shape": list(images.shape), "sha256": digest},
            "confidence": asdict(config),
            "solver": solver_description(),
        },
        sort_keys=True,
    )


def read_cached_maps(path: Path, key: str, shape: tuple[int, ...]) -> np.ndarray | None:
    """The maps in ``path`` when its key is ``key`` and they are float32 of ``shape``; None
    when the file is absent, unreadable, another fit's or malformed."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as stored:
            if set(stored.files) != {"maps", "key"} or str(stored["key"]) != key:
                return None
            maps = stored["maps"]
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    if maps.dtype != np.float32 or maps.shape != tuple(shape):
        return None
    return maps


def write_cached_maps(path: Path, key: str, maps: np.ndarray) -> None:
    """Write ``maps`` with ``key`` to ``path`` atomically."""
    with atomic.atomic_open(path) as handle:
        np.savez(handle, maps=np.ascontiguousarray(maps, dtype=np.float32), key=np.array(key))


def cached_confidence_maps(
    images: np.ndarray,
    path: Path,
    config: ConfidenceConfig | None = None,
    workers: int = 1,
    report: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, bool]:
    """:func:`~ultron.train.confidence.confidence_maps` of ``images`` (N, H, W), read from
    ``path`` when it holds this very computation's result, else computed and written there.
    Returns (maps, whether they were read). ``report`` is told (N, N) when they are read. A
    file that cannot be written (a full disk) is not an error: the maps are only not kept."""
    images = np.asarray(images)
    if images.ndim != 3:
        raise argument_error("images", f"expected (N, H, W) frames, got shape {images.shape}")
    cfg = config or ConfidenceConfig()
    key = confidence_key(images, cfg)
    maps = read_cached_maps(Path(path), key, images.shape)
    if maps is not None:
        if report is not None:
            report(len(images), len(images))
        return maps, True
    maps = confidence_maps(images, cfg, workers=workers, report=report)
    # A file that cannot be written (a full disk, ``ulimit -f``) is skipped without a word:
    # the maps are only not kept, and the fit's own next write (its checkpoint) meets the
    # same limit and says so in the command's one error line.
    with contextlib.suppress(OSError):
        write_cached_maps(Path(path), key, maps)
    return maps, False


__all__ = [
    "CONFIDENCE_CACHE",
    "FORMAT",
    "cached_confidence_maps",
    "confidence_key",
    "read_cached_maps",
    "write_cached_maps",
]
