"""The field fit's confidence maps kept on disk (ultron.train.confidence_cache): read back only
when they are this very computation's result, recomputed otherwise, never an error."""

from __future__ import annotations

import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ultron.errors import UltronInputError
from ultron.train import confidence_cache
from ultron.train.confidence import ConfidenceConfig, confidence_maps
from ultron.train.confidence_cache import (
    FORMAT,
    cached_confidence_maps,
    confidence_key,
    read_cached_maps,
    write_cached_maps,
)


def frames(n: int = 3, seed: int = 0) -> np.ndarray:
    """Small B-mode-like frames: speckle over a bright band (a reflector) at row 12."""
    rng = np.random.default_rng(seed)
    images = rng.uniform(0.1, 0.4, size=(n, 24, 16)).astype(np.float32)
    images[:, 12:14] = 0.95
    return images


def refuse_to_compute(monkeypatch) -> None:
    def fail(*args, **kwargs):
        raise AssertionError("the maps were computed again")

    monkeypatch.setattr(confidence_cache, "confidence_maps", fail)


def test_computed_once_then_read(tmp_path: Path, monkeypatch) -> None:
    images, path = frames(), tmp_path / "c.npz"
    maps, read = cached_confidence_maps(images, path, workers=2)
    assert not read and path.is_file()
    np.testing.assert_array_equal(maps, confidence_maps(images))
    assert maps[:, 20].mean() < maps[:, 5].mean()  # the shadow under the band
    refuse_to_compute(monkeypatch)
    told = []
    again, read = cached_confidence_maps(images, path, report=lambda d, n: told.append((d, n)))
    assert read and told == [(3, 3)]
    np.testing.assert_array_equal(again, maps)
    assert again.dtype == np.float32


@pytest.mark.parametrize(
    "change",
    ["pixel", "config", "frames"],
)
def test_another_computation_recomputes_and_overwrites(tmp_path: Path, change: str) -> None:
    images, config, path = frames(), ConfidenceConfig(), tmp_path / "c.npz"
    cached_confidence_maps(images, path, config)
    if change == "pixel":
        images = images.copy()
        images[1, 3, 4] += 0.25
    elif change == "config":
        config = ConfidenceConfig(beta=60.0)
    else:
        images = frames(4)
    maps, read = cached_confidence_maps(images, path, config)
    assert not read
    np.testing.assert_array_equal(maps, confidence_maps(images, config))
    assert read_cached_maps(path, confidence_key(images, config), images.shape) is not None


def test_the_key_names_what_the_maps_depend_on() -> None:
    images = frames()
    key = json.loads(confidence_key(images, ConfidenceConfig(gamma=0.1)))
    assert key["format"] == FORMAT
    assert key["frames"]["shape"] == [3, 24, 16] and key["frames"]["dtype"] == "float32"
    assert key["confidence"] == {"alpha": 2.0, "beta": 90.0, "gamma": 0.1}
    assert key["solver"].startswith("monai ")
    other = images.copy()
    other[0, 0, 0] = 0.5
    assert confidence_key(other, ConfidenceConfig()) != confidence_key(images, ConfidenceConfig())


def malformed(path: Path, kind: str, key: str, images: np.ndarray) -> None:
    if kind == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif kind == "truncated":
        write_cached_maps(path, key, confidence_maps(images))
        path.write_bytes(path.read_bytes()[:200])
    elif kind == "wrong shape":
        write_cached_maps(path, key, np.zeros((3, 24, 15), np.float32))
    elif kind == "wrong dtype":
        with open(path, "wb") as handle:
            np.savez(handle, maps=np.zeros(images.shape), key=np.array(key))
    elif kind == "missing key":
        with open(path, "wb") as handle:
            np.savez(handle, maps=np.zeros(images.shape, np.float32))
    elif kind == "pickled":
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("maps.npy", b"\x93NUMPY")


@pytest.mark.parametrize(
    "kind", ["garbage", "truncated", "wrong shape", "wrong dtype", "missing key", "pickled"]
)
def test_an_unreadable_or_malformed_file_is_recomputed(tmp_path: Path, kind: str) -> None:
    images, path = frames(), tmp_path / "c.npz"
    key = confidence_key(images, ConfidenceConfig())
    malformed(path, kind, key, images)
    assert read_cached_maps(path, key, images.shape) is None
    maps, read = cached_confidence_maps(images, path)
    assert not read
    np.testing.assert_array_equal(maps, confidence_maps(images))
    np.testing.assert_array_equal(read_cached_maps(path, key, images.shape), maps)


def test_invalid_frames_name_the_argument(tmp_path: Path) -> None:
    with pytest.raises(UltronInputError, match="images"):
        cached_confidence_maps(np.zeros((24, 16), np.float32), tmp_path / "c.npz")
    assert not (tmp_path / "c.npz").exists()


def test_a_file_that_cannot_be_written_is_skipped(tmp_path: Path, monkeypatch) -> None:
    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(confidence_cache, "write_cached_maps", full_disk)
    images, path = frames(), tmp_path / "c.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even a warning: the fit's next write says it
        maps, read = cached_confidence_maps(images, path)
    assert not read and not path.exists()
    np.testing.assert_array_equal(maps, confidence_maps(images))
