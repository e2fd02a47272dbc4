"""Ground truth a simulator can add to a dataset, for diagnostics only (never to reconstruct).

``<dataset_dir>/<sweep>/transmission.npy`` (optional, written by ``ultron simulate`` only):
float16 (N, H, W), the true exclusive transmission T ∈ [0, 1] reaching each pixel of each
frame along its own scanline — the share of the transmitted pulse that arrives there,
T = 1 at the transducer face and T ≈ 0 in acoustic shadow — with the time-gain compensation
taken out (the gel's own attenuation is compensated, as in the displayed image), on the same
pixel grid as ``images.npy``. ``ultron reconstruct --oracle-transmission`` trains UltrON's
attenuation-compensated loss with it instead of the fitted field's T: an upper bound on what a
perfect visibility estimate could give. (:meth:`SweepDataset.load
<ultron.data.dataset.SweepDataset.load>` also reads the file, when present, into
``Sweep.true_transmission``.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ultron.data.dataset import TRANSMISSION_FILE
from ultron.data.validation import load_npy, validate_transmission
from ultron.errors import UltronInputError, argument_error


def true_transmission_path(dataset_dir: str | Path, sweep_name: str) -> Path:
    """``<dataset_dir>/<sweep_name>/transmission.npy`` (the sweep name must be a plain name)."""
    plain = isinstance(sweep_name, str) and Path(sweep_name).name == sweep_name
    if not plain or sweep_name in ("", ".", ".."):
        raise argument_error("sweep_name", f"expected a sweep's folder name, got {sweep_name!r}")
    return Path(dataset_dir) / sweep_name / TRANSMISSION_FILE


def load_true_transmission(
    dataset_dir: str | Path,
    sweep_name: str,
    expected_shape: tuple[int, ...] | None = None,
) -> np.ndarray:
    """The simulator's true transmission T (N, H, W) of one sweep, float16 in [0, 1].

    ``expected_shape`` (the sweep's ``images.shape``) is checked when given. A missing file
    (datasets not simulated by ``ultron simulate``, or simulated before it wrote the file) and a
    malformed one raise :class:`UltronInputError` naming the file.
    """
    path = true_transmission_path(dataset_dir, sweep_name)
    if not path.is_file():
        raise UltronInputError(
            path,
            TRANSMISSION_FILE,
            "file is missing: the true transmission is written by `ultron simulate` only "
            "(a simulated dataset; re-simulate it with a version that writes it)",
        )
    array = load_npy(path, TRANSMISSION_FILE)
    validate_transmission(array, path, TRANSMISSION_FILE, expected_shape)
    return array
