"""A fitted acoustic field (FIELD_DIR, read and written by :mod:`ultron.models.field_dir`)
joined to the renderer: :class:`FittedField` and :func:`load_field`.

FIELD_DIR layout (written by :func:`ultron.train.fit_field`, every file atomically)::

    field.json        format, the dataset's content hash (``dataset_sha256``, see
                      :meth:`SweepDataset.content_hash`; absent in fields fitted before it was
                      recorded), field config (sizes resolved), render config, probe geometry
                      the field was fitted at, world ↔ unit-cube transform, training config, step
    checkpoint.pt     {"model", "optimizer", "step", "iterations", "generator"} (torch.save;
                      "iterations" is the configured total, absent in older ones, which may
                      also hold an unused "scheduler")
    theta_stats.json  per-channel mean / std of θ over the training frames (stage 2 normalises θ)
    train_log.jsonl   one JSON object per logged step, every one up to the checkpoint's step
                      (written before the checkpoint, so it may run ahead of it by one
                      checkpoint interval after a kill; a resumed fit drops those entries)

A fit saves its files in the order train_log.jsonl, checkpoint.pt, field.json: the checkpoint
is the commit point, and its ``step`` is the authority on the progress (:class:`FitProgress`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ultron.data.dataset import ProbeGeometry
from ultron.data.geometry import UnitCube, as_pose_tensor
from ultron.device import evaluation_chunk, map_chunks, module_device, resolve_device
from ultron.errors import UltronInputError, argument_error, malformed_entries, read_json_file
from ultron.fields.base import AcousticField
from ultron.fields.factory import FieldConfig, build_field
from ultron.fields.properties import CHANNELS, CHANNELS_WITH_DENSITY, AcousticProperties
from ultron.models.field_dir import (
    CHECKPOINT,
    FIELD_JSON,
    THETA_STATS,
    read_checkpoint,
    read_field_json,
)
from ultron.render.renderer import RenderConfig, RenderedFrames, render_field

#: Frames rendered at once by :meth:`FittedField.render` / :meth:`FittedField.render_maps`.
RENDER_CHUNK_FRAMES = 8


@dataclass(frozen=True)
class FitProgress:
    """How far a field's fit got: the checkpoint's ``step`` of ``iterations`` configured."""

    step: int
    iterations: int

    @property
    def finished(self) -> bool:
        return self.step >= self.iterations


def check_field_finished(fitted: FittedField, field_dir: str | Path) -> None:
    """Refuse a field whose fit did not finish (no θ statistics: it was interrupted), naming
    FIELD_DIR's field.json, how far the fit got and how to finish it."""
    if fitted.theta_stats is not None:
        return
    progress = fitted.fit_progress
    at = "" if progress is None else f" at step {progress.step} of {progress.iterations}"
    raise UltronInputError(
        Path(field_dir) / "field.json", "theta_stats", f"the field's fit stopped{at} before it"
        " wrote its θ statistics (interrupted?); run `ultron fit-field` again with the same"
        " --out to finish it",
    )  # fmt: skip


@dataclass(frozen=True)
class ThetaStatistics:
    """Per-channel mean and standard deviation of θ, in the named channel order."""

    channels: tuple[str, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.channels)
        if not n or not all(isinstance(c, str) for c in self.channels):
            raise argument_error("channels", f"expected channel names, got {self.channels!r}")
        for name in ("mean", "std"):
            values = getattr(self, name)
            numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
            if len(values) != n or not numbers or not all(math.isfinite(v) for v in values):
                raise argument_error(name, f"expected {n} finite numbers, got {values!r:.80}")
        if not all(s > 0 for s in self.std):
            raise argument_error("std", f"expected positive values, got {self.std!r}")

    def normalise(self, theta: torch.Tensor) -> torch.Tensor:
        """(θ − mean) / std for a (…, C) tensor in :attr:`channels` order."""
        if theta.shape[-1] != len(self.channels):
            raise argument_error("theta", f"expected {len(self.channels)} channels")
        mean = torch.tensor(self.mean, dtype=theta.dtype, device=theta.device)
        std = torch.tensor(self.std, dtype=theta.dtype, device=theta.device)
        return (theta - mean) / std

    def to_dict(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "mean": list(self.mean), "std": list(self.std)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ThetaStatistics:
        return cls(tuple(data["channels"]), tuple(data["mean"]), tuple(data["std"]))


@dataclass(frozen=True)
class FieldMaps:
    """Per-pixel maps of rendered frames, numpy float32 (N, H, W) each.

    ``theta`` is (N, H, W, C) in ``channels`` order; ``transmission`` is T along each frame's
    own scanlines (exclusive, T = 1 at the transducer face).
    """

    bmode: np.ndarray
    theta: np.ndarray
    channels: tuple[str, ...]
    transmission: np.ndarray


def probe_to_dict(probe: ProbeGeometry) -> dict[str, Any]:
    return {
        "width_mm": probe.width_mm,
        "depth_mm": probe.depth_mm,
        "height_px": probe.height_px,
        "width_px": probe.width_px,
    }


class FittedField:
    """A trained acoustic field with its geometry: query θ, render B-mode, θ and T maps.

    The field computes on its device (:func:`load_field`'s ``device``); every method takes
    inputs on any device (or numpy) and returns CPU tensors or numpy arrays.
    """

    def __init__(
        self,
        field: AcousticField,
        field_config: FieldConfig,
        unit_cube: UnitCube,
        probe: ProbeGeometry,
        render_config: RenderConfig,
        theta_stats: ThetaStatistics | None = None,
        fit_progress: FitProgress | None = None,
    ) -> None:
        self.field = field.eval()
        self.field_config = field_config
        self.unit_cube = unit_cube
        self.probe = probe
        self.render_config = render_config
        self.theta_stats = theta_stats
        #: the fit's progress where known (:func:`load_field` reads it from the checkpoint)
        self.fit_progress = fit_progress

    @property
    def device(self) -> torch.device:
        """Where the field computes."""
        return module_device(self.field)

    @property
    def channels(self) -> tuple[str, ...]:
        return CHANNELS_WITH_DENSITY if self.field.learn_density else CHANNELS

    def check_probe(self, probe: ProbeGeometry, where: str = "dataset") -> None:
        """Raise unless ``probe`` has this field's physical width and depth (mm)."""
        for name in ("width_mm", "depth_mm"):
            mine, theirs = getattr(self.probe, name), getattr(probe, name)
            if abs(mine - theirs) > 1e-6 * max(1.0, abs(mine)):
                raise UltronInputError(
                    where, f"probe.{name}", f"{theirs:g} differs from the field's {mine:g}"
                )

    @torch.no_grad()
    def query(
        self, points_mm: np.ndarray | torch.Tensor, chunk: int | None = None
    ) -> AcousticProperties:
        """θ at world points (…, 3) in mm, float32 tensors of shape (…), evaluated ``chunk``
        points at a time (default 2¹⁷ on the CPU, more on an accelerator)."""
        chunk = chunk or evaluation_chunk(self.device, 1 << 17)
        points = torch.as_tensor(
            np.asarray(points_mm) if not torch.is_tensor(points_mm) else points_mm
        )
        if points.ndim < 1 or points.shape[-1] != 3:
            raise argument_error("points_mm", f"expected (..., 3), got {tuple(points.shape)}")
        if not torch.isfinite(points).all():
            raise argument_error("points_mm", "contains NaN or infinite values")
        flat = self.unit_cube.to_unit(points.reshape(-1, 3).cpu().to(torch.float64), torch.float32)
        empty = torch.zeros(0, len(self.channels))
        stacked = map_chunks(lambda u: self.field(u).stack(), flat, chunk, self.device, empty)
        return AcousticProperties.unstack(
            stacked.reshape(*points.shape[:-1], len(self.channels)), self.channels
        )

    def _poses(self, probe_to_world: np.ndarray | torch.Tensor) -> torch.Tensor:
        poses = as_pose_tensor(probe_to_world, "probe_to_world").cpu().to(torch.float64)
        if not torch.isfinite(poses).all():
            raise argument_error("probe_to_world", "contains NaN or infinite values")
        return poses

    @torch.no_grad()
    def _render_chunks(
        self, poses: torch.Tensor, seed: int, expected: bool, chunk_frames: int
    ) -> list[RenderedFrames]:
        if chunk_frames < 1:
            raise argument_error("chunk_frames", f"expected ≥ 1, got {chunk_frames}")
        generator = torch.Generator().manual_seed(int(seed))
        return [
            render_field(
                self.field,
                self.unit_cube,
                self.probe,
                poses[i : i + chunk_frames],
                self.render_config,
                generator=generator,
                expected=expected,
            )
            for i in range(0, poses.shape[0], chunk_frames)
        ]

    def render(
        self,
        probe_to_world: np.ndarray | torch.Tensor,
        seed: int = 0,
        expected: bool = False,
        chunk_frames: int = RENDER_CHUNK_FRAMES,
    ) -> np.ndarray:
        """B-mode frames (N, H, W) float32 in [0, 1] at the field's probe geometry.

        Scatterers are drawn from a generator seeded by ``seed`` (deterministic), or replaced
        by their expectation when ``expected`` (the speckle-free mean image).
        """
        poses = self._poses(probe_to_world)
        chunks = self._render_chunks(poses, seed, expected, chunk_frames)
        if not chunks:
            return np.zeros((0, *self.probe.image_shape), dtype=np.float32)
        return torch.cat([c.intensity.cpu() for c in chunks]).clamp(0, 1).numpy().astype(np.float32)

    def render_maps(
        self,
        probe_to_world: np.ndarray | torch.Tensor,
        seed: int = 0,
        expected: bool = False,
        chunk_frames: int = RENDER_CHUNK_FRAMES,
    ) -> FieldMaps:
        """B-mode plus θ maps (N, H, W, C) and the transmission T (N, H, W) per frame."""
        poses = self._poses(probe_to_world)
        chunks = self._render_chunks(poses, seed, expected, chunk_frames)
        shape = (0, *self.probe.image_shape)
        if not chunks:
            empty = np.zeros(shape, dtype=np.float32)
            return FieldMaps(
                empty, empty[..., None].repeat(len(self.channels), -1), self.channels, empty
            )
        return FieldMaps(
            bmode=torch.cat([c.intensity.cpu() for c in chunks]).clamp(0, 1).numpy(),
            theta=torch.cat([c.properties.stack().cpu() for c in chunks]).numpy(),
            channels=self.channels,
            transmission=torch.cat([c.transmission.cpu() for c in chunks]).numpy(),
        )

    @torch.no_grad()
    def pixel_theta_transmission(
        self,
        probe_to_world: np.ndarray | torch.Tensor,
        frame_index: np.ndarray | torch.Tensor,
        rows: np.ndarray | torch.Tensor,
        cols: np.ndarray | torch.Tensor,
        chunk_frames: int = 8,
        probe: ProbeGeometry | None = None,
        on_frames: Callable[[np.ndarray, torch.Tensor], None] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """θ (P, C) and T (P,) at pixels (frame_index, rows, cols) of frames ``probe_to_world``.

        T is the exclusive transmission along that frame's own scanline, computed from the
        fitted field without gradient (stage 2's attenuation compensation). Frames are
        processed ``chunk_frames`` at a time, only those that hold requested pixels.

        ``probe`` (default: the field's) gives the pixel grid of ``rows``/``cols``, e.g. the
        dataset's native grid when the field was fitted at a reduced ``fit_shape``; it must have
        the field's width and depth in mm. T is then accumulated at that grid's step Δ (α is per
        mm; β is per sample, as in Ultra-NeRF, so a much finer grid counts a reflector more often).
        ``on_frames``, when given, is told (frame indices (k,), T (k, H, W) on the field's
        device) of every chunk of whole frames rendered (:class:`TransmissionMaps` keeps them).
        """
        poses = self._poses(probe_to_world)
        grid = self.probe if probe is None else probe
        if probe is not None:
            self.check_probe(probe, "argument")
        idx = [
            torch.as_tensor(a.cpu() if torch.is_tensor(a) else np.asarray(a), dtype=torch.int64)
            for a in (frame_index, rows, cols)
        ]
        frame_idx, row_idx, col_idx = torch.broadcast_tensors(*idx)
        frame_idx, row_idx, col_idx = (
            frame_idx.reshape(-1),
            row_idx.reshape(-1),
            col_idx.reshape(-1),
        )
        height, width = grid.image_shape
        for name, values, bound in (
            ("frame_index", frame_idx, poses.shape[0]),
            ("rows", row_idx, height),
            ("cols", col_idx, width),
        ):
            if values.numel() and (values.min() < 0 or values.max() >= bound):
                raise argument_error(name, f"indices must lie in [0, {bound})")
        theta = torch.zeros(frame_idx.shape[0], len(self.channels))
        transmission = torch.zeros(frame_idx.shape[0])
        # the pixels in frame order, once: each chunk of frames takes one contiguous run
        by_frame = torch.argsort(frame_idx, stable=True)
        sorted_frames = frame_idx[by_frame]
        needed = torch.unique_consecutive(sorted_frames)
        for start in range(0, needed.shape[0], chunk_frames):
            frames = needed[start : start + chunk_frames]
            rendered = render_field(
                self.field,
                self.unit_cube,
                grid,
                poses[frames],
                self.render_config,
                expected=True,
            )
            lo = int(torch.searchsorted(sorted_frames, frames[0]))
            hi = int(torch.searchsorted(sorted_frames, frames[-1], right=True))
            sel = by_frame[lo:hi]
            local = torch.searchsorted(frames, sorted_frames[lo:hi])
            f, r, c = (i.to(self.device) for i in (local, row_idx[sel], col_idx[sel]))
            theta[sel] = rendered.properties.stack()[f, r, c].cpu()
            transmission[sel] = rendered.transmission[f, r, c].cpu()
            if on_frames is not None:
                on_frames(frames.numpy(), rendered.transmission)
        return theta, transmission


@dataclass
class TransmissionMaps:
    """A fitted field's T of whole frames (H, W) float32, kept per sweep as a stage renders them
    (:meth:`FittedField.pixel_theta_transmission`'s ``on_frames``), so that a later stage on the
    same field and pixel grid reads them instead of rendering them again (stage 2 renders its
    labelled frames; the observed crop needs every frame's T).

    Each sweep's maps live in one (n_frames, H, W) array, made at its first frame: its pages are
    backed only as frames are written, and one block, unlike a small array per frame, never
    holds the allocator's heap above the stages' large temporaries (docs/decisions.md)."""

    maps: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    kept: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def add(
        self, sweep: str, frames: Sequence[int], transmission: torch.Tensor, n_frames: int
    ) -> None:
        """Keep ``transmission`` (k, H, W) of ``frames`` (k,) of ``sweep`` (of ``n_frames``)."""
        values = transmission.detach().cpu().numpy()
        index = np.asarray(frames, dtype=np.int64)
        if values.ndim != 3 or values.shape[0] != index.size:
            raise argument_error(
                "transmission", f"expected ({index.size}, H, W), got {values.shape}"
            )
        if index.size and (index.min() < 0 or index.max() >= n_frames):
            raise argument_error("frames", f"indices must lie in [0, {n_frames})")
        if sweep not in self.maps:
            self.maps[sweep] = np.empty((n_frames, *values.shape[1:]), dtype=np.float32)
            self.kept[sweep] = np.zeros(n_frames, dtype=bool)
        self.maps[sweep][index] = values
        self.kept[sweep][index] = True

    def get(self, sweep: str, frame: int) -> np.ndarray | None:
        """The kept T of ``frame`` of ``sweep``, or None."""
        kept = self.kept.get(sweep)
        if kept is None or not 0 <= frame < kept.size or not kept[frame]:
            return None
        return self.maps[sweep][frame]

    @property
    def n_frames(self) -> int:
        """How many frames are kept, over every sweep."""
        return int(sum(np.count_nonzero(kept) for kept in self.kept.values()))


def check_finite_weights(module: torch.nn.Module, where: str | Path, field: str) -> None:
    """Refuse a network any of whose weights is NaN or infinite (a diverged or damaged fit:
    everything it renders or meshes would be NaN), naming the file and the first tensor."""
    for name, tensor in module.state_dict().items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise UltronInputError(
                where, field, f"weights {name!r} hold NaN or inf (a diverged fit); fit again"
            )


def load_field(field_dir: str | Path, device: torch.device | str = "cpu") -> FittedField:
    """Load a fitted field from FIELD_DIR (field.json + checkpoint.pt [+ theta_stats.json])
    onto ``device`` (the checkpoint's tensors are read onto the CPU, then moved: a field
    fitted on any device loads on any other)."""
    device = resolve_device(device, "device")
    root = Path(field_dir)
    if not root.is_dir():
        raise UltronInputError(root, "field_dir", "is not a directory")
    meta = read_field_json(root)
    where = root / FIELD_JSON
    for key in ("field", "render", "probe", "unit_cube"):
        if not isinstance(meta.get(key), dict):
            raise UltronInputError(where, key, f"expected an object, got {meta.get(key)!r:.60}")
    with malformed_entries(where, "field"):
        field_config = FieldConfig.from_dict(meta["field"])
    with malformed_entries(where, "render"):
        render_config = RenderConfig.from_dict(meta["render"])
    with malformed_entries(where, "probe"):
        probe = ProbeGeometry(**meta["probe"])
    with malformed_entries(where, "unit_cube"):
        unit_cube = UnitCube.from_dict(meta["unit_cube"])
    checkpoint = read_checkpoint(root)
    module, _ = build_field(
        field_config,
        unit_cube.half_extent_mm,
        min(probe.axial_spacing_mm, probe.lateral_spacing_mm),
    )
    try:
        module.load_state_dict(checkpoint["model"])
    except (KeyError, RuntimeError) as exc:
        raise UltronInputError(
            root / CHECKPOINT, "model", f"does not match field.json ({str(exc).splitlines()[0]})"
        ) from None
    check_finite_weights(module, root / CHECKPOINT, "model")
    stats = None
    stats_path = root / THETA_STATS
    if stats_path.is_file():
        with malformed_entries(stats_path, THETA_STATS):
            stats = ThetaStatistics.from_dict(read_json_file(stats_path, THETA_STATS))
    progress = fit_progress(meta, checkpoint)
    module.to(device)
    return FittedField(module, field_config, unit_cube, probe, render_config, stats, progress)


def fit_progress(meta: dict[str, Any], checkpoint: dict[str, Any]) -> FitProgress | None:
    """The fit's progress: the checkpoint's ``step`` of its ``iterations`` (field.json's
    ``train.iterations`` for a checkpoint from before it was saved); None if either is
    missing or not an integer."""
    step = checkpoint.get("step")
    iterations = checkpoint.get("iterations")
    if iterations is None:
        train = meta.get("train")
        iterations = train.get("iterations") if isinstance(train, dict) else None
    values = (step, iterations)
    if any(isinstance(v, bool) or not isinstance(v, int) for v in values):
        return None
    return FitProgress(int(step), int(iterations))
