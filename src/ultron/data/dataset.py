"""The sweep dataset format ``ultron-sweeps/1`` (see METHOD.md §1).

A dataset is a directory::

    dataset.json            {"format": "ultron-sweeps/1", "units": "mm",
                             "probe": {"width_mm": W_mm, "depth_mm": D_mm},
                             "sweeps": [{"name": "row", "kind": "row"}, ...],
                             "reference": "reference.ply" | null}
    <sweep>/images.npy      uint8 (N, H, W), row 0 at the transducer face, W scanlines
    <sweep>/poses.npy       float (N, 4, 4) probe-to-world, translation in mm
    <sweep>/labels.npy      optional uint8 (N, H, W): 1 target, 0 background, 255 not annotated
    reference.ply|.stl      optional ground-truth surface in world mm

Optional additions of ultron (readers of the plain format may ignore them): a top-level
``"metadata"`` object, and per sweep an optional ``"true_poses"`` file name
(``<sweep>/true_poses.npy``) holding the untracked-error poses of simulated data. Ground truth
of simulated data, for diagnosis only (never read by a reconstruction):

    <sweep>/transmission.npy  float16 (N, H, W) in [0, 1]: the true transmission reaching every
                              pixel (exclusive, row 0 = 1, TGC-compensated; see
                              :mod:`ultron.phantom.simulator`), read when present
    reference_visible.ply     the part of the reference some frame could image (see
                              :mod:`ultron.phantom.visibility`), named by the optional
                              top-level key ``"reference_visible"``
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ultron import atomic
from ultron.data.import_records import check_import_records
from ultron.data.validation import (
    LABEL_UNANNOTATED,
    contained_path,
    input_file,
    load_npy,
    validate_images,
    validate_labels,
    validate_mesh_file,
    validate_poses,
    validate_positive,
    validate_probe_extent,
    validate_transmission,
)
from ultron.errors import UltronInputError, argument_error, read_json_file

_T = TypeVar("_T")

FORMAT = "ultron-sweeps/1"
SWEEP_KINDS = ("row", "column", "tilted", "other")
_NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_REFERENCE_SUFFIXES = (".ply", ".stl", ".obj", ".off")
TRANSMISSION_FILE = "transmission.npy"
#: Names the definition of :meth:`SweepDataset.content_hash`; hashed first, so a change of
#: definition (a new version) changes every hash.
CONTENT_HASH_VERSION = "ultron-dataset-sha256/1"


@dataclass(frozen=True)
class ProbeGeometry:
    """A linear probe's image geometry.

    ``width_mm`` is the lateral field of view (across the ``width_px`` scanlines) and
    ``depth_mm`` the imaging depth (over the ``height_px`` samples of each scanline).
    Pixel (r, c) lies at probe point ((c − W/2)·width_mm/W, r·depth_mm/H, 0).
    """

    width_mm: float
    depth_mm: float
    height_px: int
    width_px: int

    def __post_init__(self) -> None:
        validate_positive(self.width_mm, "argument", "width_mm")
        validate_positive(self.depth_mm, "argument", "depth_mm")
        for name in ("height_px", "width_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise argument_error(name, f"expected a positive integer, got {value!r}")

    @property
    def lateral_spacing_mm(self) -> float:
        """Distance between adjacent scanlines (image columns), mm."""
        return self.width_mm / self.width_px

    @property
    def axial_spacing_mm(self) -> float:
        """Distance between adjacent samples along a scanline (image rows), mm: the step Δ."""
        return self.depth_mm / self.height_px

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of every frame."""
        return (self.height_px, self.width_px)


@dataclass
class Sweep:
    """One tracked sweep: frames, their probe-to-world poses and optional labels; for simulated
    data optionally the true poses and the true transmission (N, H, W) float16 (diagnosis only,
    ``<sweep>/transmission.npy``)."""

    name: str
    kind: str
    images: np.ndarray
    probe_to_world: np.ndarray
    labels: np.ndarray | None = None
    true_probe_to_world: np.ndarray | None = None
    true_transmission: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = f"sweep {self.name!r}"
        if not isinstance(self.name, str) or not _NAME_PATTERN.match(self.name):
            raise argument_error(
                "name", f"sweep name {self.name!r} must match {_NAME_PATTERN.pattern}"
            )
        if self.kind not in SWEEP_KINDS:
            raise UltronInputError(where, "kind", f"{self.kind!r} is not one of {SWEEP_KINDS}")
        validate_images(self.images, where, "images")
        validate_poses(self.probe_to_world, where, "poses")
        self.probe_to_world = np.asarray(self.probe_to_world, dtype=np.float64)
        n = self.images.shape[0]
        _check_count(self.probe_to_world, n, where, "poses")
        if self.labels is not None:
            validate_labels(self.labels, where, "labels")
            _check_count(self.labels, n, where, "labels")
            if self.labels.shape != self.images.shape:
                raise UltronInputError(
                    where,
                    "labels",
                    f"shape {self.labels.shape} differs from images {self.images.shape}",
                )
        if self.true_probe_to_world is not None:
            validate_poses(self.true_probe_to_world, where, "true_poses")
            self.true_probe_to_world = np.asarray(self.true_probe_to_world, dtype=np.float64)
            _check_count(self.true_probe_to_world, n, where, "true_poses")
        if self.true_transmission is not None:
            validate_transmission(self.true_transmission, where, "transmission", self.images.shape)

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def labelled_frames(self) -> np.ndarray:
        """Indices of frames with at least one annotated (non-255) pixel."""
        if self.labels is None:
            return np.zeros(0, dtype=np.int64)
        annotated = (self.labels != LABEL_UNANNOTATED).any(axis=(1, 2))
        return np.flatnonzero(annotated)


def one_sweep(names: Collection[str], option: str) -> str:
    """The one sweep of ``names`` that ``option`` (``--export``, ``--masks``) works on: more or
    fewer is an error naming ``--sweeps``."""
    if len(names) != 1:
        raise argument_error(
            "--sweeps", f"{option} works on one sweep: name it (--sweeps NAME; here {len(names)})"
        )
    return next(iter(names))


def _check_count(array: np.ndarray, n: int, where: str | Path, field_name: str) -> None:
    if array.shape[0] != n:
        raise UltronInputError(
            where, field_name, f"has {array.shape[0]} frames but images have {n} (N mismatch)"
        )


@dataclass
class SweepDataset:
    """A set of tracked sweeps sharing one probe geometry, with an optional reference surface
    and, for simulated data, its visible part (``reference_visible_path``: the faces some frame
    could image; for metrics only, never read by a reconstruction)."""

    probe: ProbeGeometry
    sweeps: list[Sweep]
    reference: Path | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    reference_visible_path: Path | None = None
    _memo: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.sweeps:
            raise argument_error("sweeps", "a dataset needs at least one sweep")
        names = [s.name for s in self.sweeps]
        if len(set(names)) != len(names):
            raise argument_error("sweeps", f"sweep names must be unique, got {names}")
        for sweep in self.sweeps:
            if sweep.images.shape[1:] != self.probe.image_shape:
                raise UltronInputError(
                    f"sweep {sweep.name!r}",
                    "images",
                    f"frame size {sweep.images.shape[1:]} differs from the probe's"
                    f" {self.probe.image_shape}",
                )

    # ----------------------------------------------------------------- queries
    @property
    def n_frames(self) -> int:
        return sum(s.n_frames for s in self.sweeps)

    def sweep(self, name: str) -> Sweep:
        """The sweep called ``name``; raises a clear error listing the available names."""
        for sweep in self.sweeps:
            if sweep.name == name:
                return sweep
        raise argument_error(
            "sweep", f"no sweep {name!r}; available: {[s.name for s in self.sweeps]}"
        )

    def memoized(self, key: str, compute: Callable[[SweepDataset], _T]) -> _T:
        """``compute(self)``, computed once per dataset object under ``key``: measurements of
        the frames that several stages ask for (the speckle's resolved shape: the field fit,
        the pre-flight checks and the meshing voxel). A dataset's frames are not changed after
        construction; :func:`dataclasses.replace` makes a new object with nothing memoized."""
        if key not in self._memo:
            self._memo[key] = compute(self)
        return self._memo[key]

    def all_poses(self) -> np.ndarray:
        """Every frame's probe-to-world pose, sweeps concatenated in order, (N_total, 4, 4)."""
        return np.concatenate([s.probe_to_world for s in self.sweeps], axis=0)

    def content_hash(self) -> str:
        """SHA-256 (64 hex digits) of what identifies this dataset's data.

        Hashed in this order: :data:`CONTENT_HASH_VERSION`; the probe geometry (width and
        depth in mm, height and width in pixels); then per sweep, in the dataset's order, its
        name and its images, poses and labels (``none`` where it has no labels), each array as
        its little-endian dtype, its shape and its C-order bytes. Sweep kinds, the reference
        mesh, metadata and the simulator's ground truth are not part of it. The same arrays
        give the same hash whether loaded or built in memory (poses are float64 either way);
        a changed pixel, pose, label, name or sweep order changes it. Fast: one pass of SHA-256
        over the arrays, no copies of contiguous little-endian ones (timing in
        docs/decisions.md#content-hash-datadatasetpy).
        """
        digest = hashlib.sha256(CONTENT_HASH_VERSION.encode())
        probe = self.probe
        size_mm = [float(probe.width_mm), float(probe.depth_mm)]
        size_px = [int(probe.height_px), int(probe.width_px)]
        digest.update(json.dumps({"probe": [*size_mm, *size_px]}).encode())
        for sweep in self.sweeps:
            digest.update(json.dumps({"sweep": sweep.name}).encode())
            for name, array in (
                ("images", sweep.images),
                ("poses", sweep.probe_to_world),
                ("labels", sweep.labels),
            ):
                _hash_array(digest, name, array)
        return digest.hexdigest()

    # ------------------------------------------------------------------- I/O
    @classmethod
    def load(cls, path: str | Path) -> SweepDataset:
        """Read and validate a dataset directory. Raises :class:`UltronInputError` on bad input."""
        root = Path(path)
        meta_path = root / "dataset.json"
        if not os.path.lexists(meta_path):
            made_by = "ultron simulate, import-plus and import-ultranerf write one"
            if not root.is_dir():
                found = "is not a directory" if root.exists() else "no such directory"
                raise UltronInputError(
                    root, "directory", f"{found}; expected a dataset's ({made_by})"
                )
            raise UltronInputError(
                root, "dataset.json", f"missing: not an ultron dataset directory ({made_by})"
            )
        input_file(meta_path, "dataset.json")
        meta = _read_json(meta_path)
        fmt = meta.get("format")
        if fmt != FORMAT:
            raise UltronInputError(
                meta_path, "format", f"unknown format {fmt!r}, expected {FORMAT!r}"
            )
        if meta.get("units", "mm") != "mm":
            raise UltronInputError(
                meta_path, "units", f"{meta.get('units')!r}; {FORMAT} holds lengths in mm"
            )
        probe_meta = meta.get("probe")
        if not isinstance(probe_meta, dict):
            raise UltronInputError(
                meta_path, "probe", "expected an object with width_mm and depth_mm"
            )
        width_mm, depth_mm = (
            validate_probe_extent(probe_meta.get(key), meta_path, f"probe.{key}")
            for key in ("width_mm", "depth_mm")
        )
        entries = meta.get("sweeps")
        if not isinstance(entries, list) or not entries:
            raise UltronInputError(meta_path, "sweeps", "expected a non-empty list of sweeps")

        sweeps = [_load_sweep(root, meta_path, i, entry) for i, entry in enumerate(entries)]
        names = [s.name for s in sweeps]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise UltronInputError(
                meta_path, "sweeps", f"sweep names must be unique; {', '.join(twice)} repeated"
            )
        shape = sweeps[0].images.shape[1:]
        for sweep in sweeps[1:]:
            if sweep.images.shape[1:] != shape:
                raise UltronInputError(
                    root / sweep.name / "images.npy",
                    "images",
                    f"frame size {sweep.images.shape[1:]} differs from sweep"
                    f" {sweeps[0].name!r} ({shape}); one probe geometry per dataset",
                )
        probe = ProbeGeometry(width_mm, depth_mm, int(shape[0]), int(shape[1]))

        reference_path = _reference_path(root, meta_path, meta, "reference")
        if reference_path is not None:
            validate_mesh_file(reference_path, "reference")
        visible_path = _reference_path(root, meta_path, meta, "reference_visible")
        if visible_path is not None:
            validate_mesh_file(visible_path, "reference_visible")
        metadata = meta.get("metadata", {})
        if not isinstance(metadata, dict):
            raise UltronInputError(meta_path, "metadata", "expected an object")
        check_import_records(metadata, {s.name: s.n_frames for s in sweeps}, meta_path)
        return cls(
            probe=probe,
            sweeps=sweeps,
            reference=reference_path,
            metadata=metadata,
            reference_visible_path=visible_path,
        )

    def save(self, path: str | Path, only_sweeps: Collection[str] | None = None) -> None:
        """Write the dataset to directory ``path`` atomically.

        A new dataset is written into a temporary sibling directory that is renamed to ``path``
        at the end, so an interrupted save leaves nothing behind. Into an existing directory,
        every file is replaced atomically, sweep arrays first and ``dataset.json`` last, so an
        interruption leaves the previous ``dataset.json`` in place. ``only_sweeps`` restricts the
        arrays written to those sweeps (the others must already be on disk there), as when a
        sweep is added to an existing dataset.
        """
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise UltronInputError(root, "out", "exists and is not a directory")
        if root.exists():
            self._write_into(root, only_sweeps)
            return
        with atomic.staged_directory(root) as staging:
            self._write_into(staging, None)

    def _write_into(self, root: Path, only_sweeps: Collection[str] | None) -> None:
        for sweep in self.sweeps:
            if only_sweeps is None or sweep.name in only_sweeps:
                self._save_sweep(root, sweep)
        reference_name = visible_name = None
        if self.reference is not None:
            reference_name = _copy_mesh(root, self.reference, "reference")
        if self.reference_visible_path is not None:
            visible_name = _copy_mesh(root, self.reference_visible_path, "reference_visible")
        atomic.write_json(root / "dataset.json", self.to_json(reference_name, visible_name))

    def to_json(
        self, reference_name: str | None, reference_visible_name: str | None = None
    ) -> dict[str, Any]:
        """The ``dataset.json`` content (``"reference_visible"`` only when there is one)."""
        sweeps = []
        for sweep in self.sweeps:
            entry: dict[str, Any] = {"name": sweep.name, "kind": sweep.kind}
            if sweep.true_probe_to_world is not None:
                entry["true_poses"] = "true_poses.npy"
            sweeps.append(entry)
        meta: dict[str, Any] = {
            "format": FORMAT,
            "units": "mm",
            "probe": {"width_mm": self.probe.width_mm, "depth_mm": self.probe.depth_mm},
            "sweeps": sweeps,
            "reference": reference_name,
        }
        if reference_visible_name is not None:
            meta["reference_visible"] = reference_visible_name
        if self.metadata:
            meta["metadata"] = self.metadata
        return meta

    @staticmethod
    def _save_sweep(root: Path, sweep: Sweep) -> None:
        folder = root / sweep.name
        atomic.save_npy(folder / "images.npy", sweep.images)
        atomic.save_npy(folder / "poses.npy", sweep.probe_to_world)
        optional = {
            "labels.npy": sweep.labels,
            "true_poses.npy": sweep.true_probe_to_world,
            TRANSMISSION_FILE: sweep.true_transmission,
        }
        for name, array in optional.items():
            if array is not None:
                atomic.save_npy(folder / name, array)
            else:  # a replaced sweep must not inherit its predecessor's files
                (folder / name).unlink(missing_ok=True)


def _hash_array(digest: Any, name: str, array: np.ndarray | None) -> None:
    """Feed ``name``, dtype (little-endian), shape and C-order bytes of ``array`` to ``digest``."""
    if array is None:
        digest.update(json.dumps({name: None}).encode())
        return
    array = np.asarray(array)
    canonical = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    header = {name: [canonical.dtype.str, list(canonical.shape)]}
    digest.update(json.dumps(header).encode())
    digest.update(canonical.reshape(-1).view(np.uint8))


def _reference_path(root: Path, meta_path: Path, meta: dict[str, Any], key: str) -> Path | None:
    """``root / meta[key]`` for a file name, None for an absent key or null."""
    name = meta.get(key)
    if name is None:
        return None
    if not isinstance(name, str) or not name:
        raise UltronInputError(meta_path, key, f"expected a file name or null, got {name!r}")
    return contained_path(root, name, meta_path, key)


def _copy_mesh(root: Path, source: str | Path, stem: str) -> str:
    """Copy the mesh ``source`` to ``root/<stem><suffix>`` atomically (unless it is that file);
    returns the file name."""
    source = Path(source)
    suffix = source.suffix.lower()
    if suffix not in _REFERENCE_SUFFIXES:
        raise UltronInputError(source, stem, f"expected one of {_REFERENCE_SUFFIXES}")
    name = f"{stem}{suffix}"
    target = root / name
    if not source.is_file():
        raise UltronInputError(source, stem, f"{stem.replace('_', ' ')} mesh file is missing")
    if not (target.exists() and target.resolve() == source.resolve()):
        tmp = target.with_name(f".{name}.tmp")
        shutil.copyfile(source, tmp)
        tmp.replace(target)
    return name


def _read_json(path: Path) -> dict[str, Any]:
    meta = read_json_file(path, "dataset.json")
    if not isinstance(meta, dict):
        raise UltronInputError(path, "dataset.json", "expected a JSON object")
    return meta


def _load_sweep(root: Path, meta_path: Path, index: int, entry: Any) -> Sweep:
    if not isinstance(entry, dict):
        raise UltronInputError(
            meta_path, f"sweeps[{index}]", "expected an object with name and kind"
        )
    name = entry.get("name")
    kind = entry.get("kind", "other")
    if not isinstance(name, str) or not _NAME_PATTERN.match(name):
        raise UltronInputError(meta_path, f"sweeps[{index}].name", f"invalid sweep name {name!r}")
    if kind not in SWEEP_KINDS:
        raise UltronInputError(
            meta_path, f"sweeps[{index}].kind", f"{kind!r} is not one of {SWEEP_KINDS}"
        )
    folder = contained_path(root, name, meta_path, f"sweeps[{index}].name")
    if not folder.is_dir():
        raise UltronInputError(
            folder, f"sweep {name!r}", "listed in dataset.json but the folder is missing"
        )

    images_path, poses_path = folder / "images.npy", folder / "poses.npy"
    images = load_npy(images_path, "images")
    validate_images(images, images_path)
    poses = load_npy(poses_path, "poses")
    validate_poses(poses, poses_path)
    _check_count(poses, images.shape[0], poses_path, "poses")

    labels = None
    labels_path = folder / "labels.npy"
    if input_file(labels_path, "labels", required=False):
        labels = load_npy(labels_path, "labels")
        validate_labels(labels, labels_path)
        _check_count(labels, images.shape[0], labels_path, "labels")
        if labels.shape != images.shape:
            raise UltronInputError(
                labels_path, "labels", f"shape {labels.shape} differs from images {images.shape}"
            )
    true_poses = None
    true_name = entry.get("true_poses")
    if true_name is not None:
        true_path = contained_path(folder, true_name, meta_path, f"sweeps[{index}].true_poses")
        true_poses = load_npy(true_path, "true_poses")
        validate_poses(true_poses, true_path, "true_poses")
        _check_count(true_poses, images.shape[0], true_path, "true_poses")
    transmission = None
    transmission_path = folder / TRANSMISSION_FILE
    if input_file(transmission_path, "transmission", required=False):
        transmission = load_npy(transmission_path, "transmission")
        validate_transmission(transmission, transmission_path, "transmission", images.shape)
    return Sweep(
        name=name,
        kind=kind,
        images=images,
        probe_to_world=poses,
        labels=labels,
        true_probe_to_world=true_poses,
        true_transmission=transmission,
    )
