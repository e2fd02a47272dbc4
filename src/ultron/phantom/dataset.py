"""The full simulated experiment: phantom → sweeps → B-mode, labels, tracked poses → dataset.

``simulate_dataset`` reproduces the paper's acquisition in software: a vertebra phantom in
gelatin scanned by a robot-held linear probe with row, column and ±10° tilted row sweeps,
segmented by hand. Defaults (sized for CPU work, one L3):

* probe: 38 mm linear array at 5 MHz, 96 scanlines × 128 samples over 70 mm depth
  (0.40 mm lateral × 0.55 mm axial pixels). The probe face lies on the gel surface 10 mm
  posterior of the spinous process tip, so the image spans the posterior elements and the
  vertebral body's posterior wall with the posterior ≈ 10 mm of the body (for L3: depths
  10–40 mm spinous process and laminae, ≈ 60 mm posterior wall, 70 mm ≈ 10 mm into the body).
* sweeps: ``row``, ``column``, ``tilt_p10``, ``tilt_m10``, 60 frames each, spread over the
  bone's extent plus a 4 mm margin.
* tracking error: 0.3 mm and 0.2° per axis (half per-sweep bias, half per-frame jitter), see
  ``protocols.py``; images and labels come from the true poses, the dataset stores the
  tracked ones and keeps the true ones as ``true_probe_to_world``.
* annotation noise: 0.3 mm edge jitter, 2 % coarse frames (``annotation.py``).
* ground truth for diagnosis (never read by a reconstruction): per sweep the true
  transmission of every pixel, ``<sweep>/transmission.npy`` (float16, see ``simulator.py``),
  and ``reference_visible.ply``, the part of ``reference.ply`` some frame could image
  (``visibility.py``; its criterion goes to ``phantom.json``'s ``"reference_visible"``).

Every random draw comes from the seed: the scatterers from a hash of (seed, lattice node), the
image noise, the tracking error and the annotation noise from independent streams spawned from
it, so the same seed gives byte-identical files. The simulation runs on one torch thread (and
restores the caller's setting): float reductions then give the same bits whatever the machine's
thread count, and on a shared 2-core machine one thread is also the fastest (the work is
element-wise on modest tensors; a second OpenMP thread mostly spins).
"""

from __future__ import annotations

import dataclasses
import io
import math
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ultron import atomic
from ultron.arguments import check_count, check_seed
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.data.geometry import field_of_view_bounds_mm
from ultron.errors import argument_error
from ultron.memory import check_fits_in_memory
from ultron.parallel import torch_threads
from ultron.phantom.annotation import AnnotationConfig, annotate
from ultron.phantom.protocols import (
    DEFAULT_SWEEPS,
    ScanConfig,
    TrackingNoise,
    perturb_poses,
    plan_sweep,
    sweep_spec,
)
from ultron.phantom.shapes import DEFAULT_VOXEL_MM, get_phantom
from ultron.phantom.simulator import BModeConfig, simulate_frames
from ultron.phantom.speckle import scatterer_field
from ultron.phantom.tissue import Tissue
from ultron.phantom.visibility import reference_visibility

#: Progress callback: (what is being done, units done, units in total).
Progress = Callable[[str, int, int], None]

PHANTOM_JSON_FORMAT = "ultron-phantom/1"
#: ``dataset.json``'s ``metadata.generator`` of a simulated dataset: the only kind of dataset
#: a simulation replaces (:func:`ultron.pipeline.simulate.simulate_to`).
GENERATOR = "ultron simulate"
VISIBLE_REFERENCE = "reference_visible.ply"


#: The coarsest SDF grid / reference-mesh voxel, mm.
MAX_VOXEL_MM = 2.0


#: Bytes a simulated frame keeps per pixel: the B-mode and labels (uint8), the true T
#: (float16) and the float32 rendering it is made from.
FRAME_BYTES_PER_PIXEL = 8


@dataclass(frozen=True)
class SimulationConfig:
    """Every parameter of a simulated dataset (immutable; derive variants with ``replace``).

    Attributes:
        phantom: Phantom: vertebrae L2, L3, L3b, L4; condyle (end of a long bone); femur (44
            cm, long sweeps).
        seed: Random seed (same seed → same files).
        sweeps: Sweeps by name: row, column, tilt_p<deg>, tilt_m<deg>.
        probe_width_mm: Linear probe width (lateral FOV), mm.
        depth_mm: Imaging depth, mm.
        height_px: Samples per scanline.
        width_px: Scanlines per frame.
        voxel_mm: SDF grid / reference mesh voxel, mm.
    """

    phantom: str = "L3"
    seed: int = 0
    sweeps: tuple[str, ...] = DEFAULT_SWEEPS
    probe_width_mm: float = 38.0
    depth_mm: float = 70.0
    height_px: int = 128
    width_px: int = 96
    voxel_mm: float = DEFAULT_VOXEL_MM  # SDF grid and reference mesh
    scan: ScanConfig = field(default_factory=ScanConfig)
    tracking: TrackingNoise = field(default_factory=TrackingNoise)
    annotation: AnnotationConfig = field(default_factory=AnnotationConfig)
    bmode: BModeConfig = field(default_factory=BModeConfig)

    def __post_init__(self) -> None:
        get_phantom(self.phantom)
        check_seed("seed", self.seed)
        if isinstance(self.sweeps, str) or not self.sweeps:
            raise argument_error(
                "sweeps", f"expected a non-empty tuple of names, got {self.sweeps!r}"
            )
        specs = [sweep_spec(name) for name in self.sweeps]
        if len({s.name for s in specs}) != len(specs):
            raise argument_error("sweeps", f"sweep names must be unique, got {list(self.sweeps)}")
        check_count("height_px", self.height_px)
        check_count("width_px", self.width_px)
        self.probe()  # validates the geometry
        if not (math.isfinite(self.voxel_mm) and 0 < self.voxel_mm <= MAX_VOXEL_MM):
            raise argument_error(
                "voxel_mm", f"expected a voxel in (0, {MAX_VOXEL_MM:g}] mm, got {self.voxel_mm}"
            )

    def probe(self) -> ProbeGeometry:
        return ProbeGeometry(self.probe_width_mm, self.depth_mm, self.height_px, self.width_px)

    def replace(self, **changes: Any) -> SimulationConfig:
        """A copy with ``changes`` (nested configs are replaced whole)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able nested dict of every parameter (``phantom.json``'s ``config``)."""
        data = dataclasses.asdict(self)
        data["sweeps"] = list(self.sweeps)
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SimulationConfig:
        """Inverse of :meth:`to_dict` (missing keys take their defaults), e.g. to re-run the
        configuration stored in a dataset's ``phantom.json``."""
        return _from_dict(cls, data, "config")


_NESTED: dict[str, type] = {
    "scan": ScanConfig,
    "tracking": TrackingNoise,
    "annotation": AnnotationConfig,
    "bmode": BModeConfig,
    "gel": Tissue,
    "bone": Tissue,
}


def _from_dict(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, Mapping):
        raise argument_error(where, f"expected an object, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise argument_error(
            where, f"unknown parameter(s) {unknown}; expected some of {sorted(names)}"
        )
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        if name in _NESTED:
            value = _from_dict(_NESTED[name], value, f"{where}.{name}")
        elif name == "sweeps" and isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise argument_error(where, str(exc)) from None


def _streams(seed: int) -> dict[str, torch.Generator]:
    """Independent generators for image noise, tracking error and annotation, from ``seed``."""
    children = np.random.SeedSequence(seed).spawn(3)
    names = ("images", "tracking", "annotation")
    return {
        name: torch.Generator().manual_seed(int(child.generate_state(1, dtype=np.uint64)[0] >> 1))
        for name, child in zip(names, children, strict=True)
    }


def simulate_dataset(
    config: SimulationConfig, out: Path | str | None = None, progress: Progress | None = None
) -> SweepDataset:
    """Simulate the whole ``ultron-sweeps/1`` dataset of ``config``.

    With ``out``, the dataset (with each sweep's ``transmission.npy``), ``reference.ply``,
    ``reference_visible.ply`` and ``phantom.json`` (every parameter) are written there
    atomically (``dataset.json`` last); without, the reference meshes go to a new temporary
    directory (the returned dataset points at them) and nothing else is written.
    ``progress(what, done, total)`` is called as the work advances.
    """
    if not isinstance(config, SimulationConfig):
        raise argument_error("config", f"expected a SimulationConfig, got {type(config).__name__}")
    with torch_threads(1):
        return _simulate(config, out, progress)


def _simulate(
    config: SimulationConfig, out: Path | str | None, progress: Progress | None
) -> SweepDataset:
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        raise argument_error("out", f"{out} exists and is not a directory")
    report = progress or (lambda what, done, total: None)
    phantom = get_phantom(config.phantom)
    probe = config.probe()
    specs = [sweep_spec(name) for name in config.sweeps]
    n_frames = config.scan.frames_per_sweep
    total = len(specs) * n_frames + 2
    check_fits_in_memory(
        float(len(specs) * n_frames) * probe.height_px * probe.width_px * FRAME_BYTES_PER_PIXEL,
        "argument", "frames (--frames)", f"{len(specs)} sweeps of {n_frames} frames",
    )  # fmt: skip

    report("phantom SDF grid", 0, total)
    volume = phantom.sdf_volume(config.voxel_mm)
    bounds = phantom.bounds_mm
    true_poses = [plan_sweep(s, bounds, phantom.surface_y_mm, config.scan) for s in specs]
    box = field_of_view_bounds_mm(true_poses, probe).numpy()
    pad = config.bmode.elevation_span_mm + 2 * config.bmode.speckle_voxel_mm
    field_ = scatterer_field(
        np.stack([box[0] - pad, box[1] + pad]),
        config.bmode.speckle_voxel_mm,
        config.bmode.gel,
        config.bmode.bone,
        config.seed,
    )
    report("phantom SDF grid", 1, total)

    streams = _streams(config.seed)
    sweeps = []
    for i, (spec, poses) in enumerate(zip(specs, true_poses, strict=True)):
        report(f"sweep {spec.name}", 1 + i * n_frames, total)
        frames = simulate_frames(
            torch.from_numpy(poses), probe, volume, field_, config.bmode, streams["images"]
        )
        labels = annotate(frames.interfaces, probe, config.annotation, streams["annotation"])
        tracked = (
            perturb_poses(poses, config.tracking, streams["tracking"])
            if config.tracking.enabled
            else poses
        )
        sweeps.append(
            Sweep(
                name=spec.name,
                kind=spec.kind,
                images=frames.images.numpy(),
                probe_to_world=tracked,
                labels=labels.numpy(),
                true_probe_to_world=poses if config.tracking.enabled else None,
                true_transmission=frames.transmission.numpy().astype(np.float16),
            )
        )
    report("reference mesh", 1 + len(specs) * n_frames, total)
    reference_ply = volume.mesh().export(file_type="ply")
    report("visible reference", 1 + len(specs) * n_frames, total)
    if out is not None and not Path(out).exists():  # written whole or not at all
        with atomic.staged_directory(out) as staging:
            _write_simulation(staging, reference_ply, sweeps, true_poses, config, phantom, probe)
        report("done", total, total)
        return SweepDataset.load(out)
    root = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="ultron-phantom-"))
    dataset = _write_simulation(
        root, reference_ply, sweeps, true_poses, config, phantom, probe, save=out is not None
    )
    report("done", total, total)
    return dataset


def _write_simulation(
    root: Path,
    reference_ply: bytes,
    sweeps: list[Sweep],
    true_poses: list[np.ndarray],
    config: SimulationConfig,
    phantom: Any,
    probe: ProbeGeometry,
    save: bool = True,
) -> SweepDataset:
    """Write the reference meshes into ``root`` and, with ``save``, the simulated dataset and
    phantom.json (dataset.json last)."""
    reference = root / "reference.ply"
    atomic.write_bytes(reference, reference_ply)
    visible_path, visibility = _write_visible_reference(
        reference_ply, sweeps, true_poses, config, root
    )
    metadata = {
        "generator": GENERATOR,
        "phantom": phantom.name,
        "seed": config.seed,
        "world_frame": "x lateral (left-right), y posterior->anterior (beam), z caudal->cranial; mm",
    }
    dataset = SweepDataset(
        probe=probe,
        sweeps=sweeps,
        reference=reference,
        metadata=metadata,
        reference_visible_path=visible_path,
    )
    if save:
        atomic.write_json(root / "phantom.json", phantom_json(config, visibility))
        dataset.save(root)
    return dataset


def _write_visible_reference(
    reference_ply: bytes,
    sweeps: list[Sweep],
    true_poses: list[np.ndarray],
    config: SimulationConfig,
    root: Path,
) -> tuple[Path | None, dict[str, Any]]:
    """Write ``root/reference_visible.ply`` (when some face is visible) from the reference as
    stored (float32 vertices and normals, read back) and the sweeps' true poses and
    transmission; returns its path and the criterion for ``phantom.json``."""
    import trimesh

    mesh = trimesh.load(io.BytesIO(reference_ply), file_type="ply", process=False)
    visible, visibility = reference_visibility(
        mesh,
        [(s.name, poses, s.true_transmission) for s, poses in zip(sweeps, true_poses, strict=True)],
        config.probe(),
        config.bmode.elevation_span_mm,
    )
    path = None
    if visible is not None:
        path = root / VISIBLE_REFERENCE
        atomic.write_bytes(path, visible.export(file_type="ply"))
    visibility["file"] = None if path is None else path.name
    return path, visibility


def phantom_json(
    config: SimulationConfig, visibility: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The ``phantom.json`` content: the full configuration and the phantom's description, and
    with ``visibility`` the visible reference's criterion (:mod:`ultron.phantom.visibility`:
    incidence limit, T threshold, slab half-thickness per sweep, counts, file)."""
    phantom = get_phantom(config.phantom)
    bmode = config.bmode
    content = {
        "format": PHANTOM_JSON_FORMAT,
        "config": config.to_dict(),
        "phantom": phantom.to_dict(),
        "derived": {
            "reflection_gel_bone": bmode.reflection,
            "gel_impedance_mrayl": bmode.gel.impedance_mrayl,
            "bone_impedance_mrayl": bmode.bone.impedance_mrayl,
            "gel_attenuation_db_per_mm": bmode.gel.attenuation_db_per_mm(bmode.frequency_mhz),
            "bone_attenuation_db_per_mm": bmode.bone.attenuation_db_per_mm(bmode.frequency_mhz),
            "lateral_spacing_mm": config.probe().lateral_spacing_mm,
            "axial_spacing_mm": config.probe().axial_spacing_mm,
        },
        "world_frame": {
            "origin": "centre of the vertebral body",
            "x": "lateral (patient left-right)",
            "y": "posterior -> anterior; the beam (probe +y) points along +y",
            "z": "caudal -> cranial",
            "gel_surface_y_mm": phantom.surface_y_mm,
        },
    }
    if visibility is not None:
        content["reference_visible"] = dict(visibility)
    return content
