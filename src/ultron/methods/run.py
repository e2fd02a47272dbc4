"""``reconstruct``: one dataset, one method, one label fraction → DIR with mesh, volume, metrics.

Outputs (every file atomic): ``mesh.ply``, ``mesh.stl``, ``mesh.obj``, ``occupancy.nii.gz``
(aligned with the mesh in 3D Slicer, see :mod:`ultron.mesh.export`), ``metrics.json`` when the
dataset has a reference surface, and ``run.json`` (configuration, label selection, versions,
timings per stage, peak memory). The reference is read only after the mesh exists, for metrics.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ultron import atomic
from ultron.data.dataset import SweepDataset
from ultron.errors import argument_error
from ultron.mesh.compounding import CompoundingConfig, compound_labels
from ultron.mesh.export import load_mesh, save_mesh, save_volume_nifti
from ultron.mesh.extract import extract_surface
from ultron.methods.model_io import save_network
from ultron.methods.on_method import ONConfig, reconstruct_on
from ultron.methods.runinfo import StageTimer, write_run_json
from ultron.methods.ultron_method import Reconstruction, UltronConfig, reconstruct_ultron
from ultron.metrics.surface import MetricsConfig, evaluate_meshes
from ultron.train.visibility import load_oracle_truth

FIELD_METHODS = ("ultron", "ultron-noloss")
SDF_VIEWS = {"rocosdf": ("row", "column"), "unsr-row": ("row",), "unsr-col": ("column",)}
METHODS = (*FIELD_METHODS, "compounding", "on", *SDF_VIEWS)
ROCOSDF_PRESETS = ("fast", "paper")


@dataclass(frozen=True)
class ReconstructionRequest:
    """What to run: the method, its label fraction and seed, and per-stage settings."""

    method: str = "ultron"
    label_fraction: float = 0.1
    seed: int = 0
    ultron: UltronConfig = field(default_factory=UltronConfig)
    compounding: CompoundingConfig = field(default_factory=CompoundingConfig)
    on: ONConfig = field(default_factory=ONConfig)
    rocosdf_preset: str = "fast"
    metrics: MetricsConfig = field(default_factory=MetricsConfig)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise argument_error("method", f"expected one of {METHODS}, got {self.method!r}")
        if not 0 < self.label_fraction <= 1:
            raise argument_error(
                "label_fraction", f"expected a value in (0, 1], got {self.label_fraction}"
            )
        if self.rocosdf_preset not in ROCOSDF_PRESETS:
            raise argument_error(
                "preset", f"expected one of {ROCOSDF_PRESETS}, got {self.rocosdf_preset!r}"
            )
        source = self.ultron.visibility.source
        if source != "field" and self.method not in FIELD_METHODS:
            flag = "--oracle-transmission" if source == "oracle" else f"--visibility {source}"
            raise argument_error(
                "visibility", f"{flag} applies to --method ultron or ultron-noloss only, "
                f"not {self.method!r}",
            )  # fmt: skip


def run_method(
    dataset: SweepDataset,
    request: ReconstructionRequest,
    fitted,
    timer: StageTimer,
    truth: dict[str, Any] | None = None,
) -> Reconstruction:
    """Reconstruct with ``request.method`` (``fitted`` is the acoustic field, for UltrON;
    ``truth`` the oracle's true transmission per sweep, see :mod:`ultron.train.visibility`)."""
    from ultron.data.labels import select_label_frames

    if request.method in FIELD_METHODS:
        if fitted is None:
            raise argument_error(
                "field", f"method {request.method!r} needs a fitted acoustic field"
            )
        config = UltronConfig(
            **{
                **request.ultron.__dict__,
                "label_fraction": request.label_fraction,
                "seed": request.seed,
            }
        )
        return reconstruct_ultron(dataset, fitted, request.method, config, timer, truth)
    if request.method == "on":
        return reconstruct_on(dataset, request.label_fraction, request.seed, request.on, timer)
    if request.method in SDF_VIEWS:
        from ultron.methods.rocosdf import RoCoSDFConfig, reconstruct_rocosdf

        with timer.stage("labels"):
            selection = select_label_frames(dataset, request.label_fraction, request.seed)
        return reconstruct_rocosdf(
            dataset,
            selection,
            RoCoSDFConfig.preset(request.rocosdf_preset),
            request.seed,
            SDF_VIEWS[request.method],
            timer=timer,
        )
    with timer.stage("labels"):
        selection = select_label_frames(dataset, request.label_fraction, request.seed)
    with timer.stage("mesh"):
        compounded = compound_labels(dataset, selection, request.compounding)
        mesh = extract_surface(compounded.volume, compounded.grid, request.ultron.extraction)
    info = {
        "selection": selection.to_dict(),
        "n_label_frames": selection.n_frames,
        "hole_fill_radius_mm": compounded.hole_fill_radius_mm,
        "compounding_config": request.compounding.__dict__,
    }
    return Reconstruction(mesh=mesh, volume=compounded.volume, grid=compounded.grid, info=info)


def write_outputs(
    out_dir: str | Path,
    dataset: SweepDataset,
    identity: dict[str, Any],
    result: Reconstruction,
    timer: StageTimer,
    metrics_config: MetricsConfig,
    extra: dict[str, Any] | None = None,
    report: bool = True,
) -> dict[str, Any]:
    """Write the mesh, volume, the trained network (``network.pt`` when the method has one, see
    :mod:`ultron.methods.model_io`), metrics (with a reference) and, last, run.json; return the
    summary. run.json therefore marks a finished run (the report aside).

    ``identity`` (method, label_fraction, seed, …) heads run.json and tags metrics.json.
    With ``report``, ``report.html`` follows run.json (:mod:`ultron.report.run_report`); its
    time is in the returned timings, not in run.json.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with timer.stage("write"):
        for suffix in (".ply", ".stl", ".obj"):
            save_mesh(result.mesh, out / f"mesh{suffix}")
        save_volume_nifti(result.volume, result.grid, out / "occupancy.nii.gz")
        if "network" in result.info:
            meta = {"method": identity["method"], **result.info.get("model", {})}
            save_network(out, result.info["network"], meta)
    metrics = None
    if dataset.reference is not None:
        with timer.stage("metrics"):
            visible = dataset.reference_visible_path
            metrics = evaluate_meshes(
                result.mesh,
                load_mesh(dataset.reference),
                metrics_config,
                reference_visible=None if visible is None else load_mesh(visible),
            )
        metrics["method"] = identity["method"]
        metrics["label_fraction"] = identity.get("label_fraction")
        atomic.write_json(out / "metrics.json", metrics)
    info = {k: v for k, v in result.info.items() if k not in ("network", "model")}
    payload = {
        **identity,
        "mesh": {"vertices": len(result.mesh.vertices), "faces": len(result.mesh.faces),
                 "area_mm2": float(result.mesh.area)},
        **info,
        **(extra or {}),
    }  # fmt: skip
    write_run_json(out, payload, timer)
    if report:
        from ultron.report.run_report import write_run_report

        with timer.stage("report"):
            write_run_report(out, dataset=dataset)
    return {"out": str(out), "metrics": metrics, "timings_s": dict(timer.seconds)}


def reconstruct(
    dataset_dir: str | Path,
    request: ReconstructionRequest,
    out_dir: str | Path,
    field_dir: str | Path | None = None,
    field_config=None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    report: bool = True,
    allow_other_field: bool = False,
) -> dict[str, Any]:
    """Load the dataset, get the field (given, or fitted and cached), run, write DIR (with
    ``report.html`` unless ``report`` is false).

    A given ``field_dir`` must have been fitted on this dataset (see
    :func:`load_or_fit_field`) unless ``allow_other_field``."""
    timer = StageTimer()
    with timer.stage("load"):
        dataset = SweepDataset.load(dataset_dir)
        # the oracle's files are checked before any work (field fit, outputs)
        truth = load_oracle_truth(request.ultron.visibility, dataset_dir, dataset)
    fitted, extra = None, {}
    if request.method in FIELD_METHODS:
        with timer.stage("field"):
            fitted, extra = load_or_fit_field(
                dataset_dir, dataset, field_dir, field_config, progress, allow_other_field
            )
    result = run_method(dataset, request, fitted, timer, truth)
    identity = {
        "method": request.method,
        "label_fraction": request.label_fraction,
        "seed": request.seed,
        "dataset_dir": str(Path(dataset_dir).resolve()),
    }
    return write_outputs(out_dir, dataset, identity, result, timer, request.metrics, extra, report)


def load_or_fit_field(
    dataset_dir: str | Path,
    dataset: SweepDataset,
    field_dir: str | Path | None,
    field_config: Any = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    allow_other_field: bool = False,
) -> tuple[Any, dict[str, Any]]:
    """The dataset's acoustic field and what run.json records of it (``field_dir``,
    ``field_cached`` and, for a given field, ``field_dataset_match``).

    A given FIELD_DIR must match the dataset's probe geometry and, where its field.json records
    one, the dataset's content hash (:func:`ultron.fields.fitted.check_field_dataset`; a
    mismatch is an error unless ``allow_other_field``, then ``field_dataset_match`` is false;
    it is null for a field without the record). Otherwise the cached fit is used, keyed by the
    dataset directory's content (:mod:`ultron.methods.field_cache`).
    """
    from ultron.fields.fitted import check_field_dataset, load_field
    from ultron.methods.field_cache import get_or_fit_field
    from ultron.train.field_fit import FieldTrainConfig

    if field_dir is not None:
        fitted = load_field(field_dir)
        fitted.check_probe(dataset.probe, where=str(dataset_dir))
        match = check_field_dataset(
            field_dir, dataset.content_hash(), str(dataset_dir), allow_other_field
        )
        used_dir, cached = Path(field_dir), True
        extra: dict[str, Any] = {"field_dataset_match": match}
    else:
        config = field_config or FieldTrainConfig()
        fitted, used_dir, cached = get_or_fit_field(dataset_dir, dataset, config, progress)
        extra = {}
    return fitted, {"field_dir": str(Path(used_dir).resolve()), "field_cached": cached, **extra}
