"""``reconstruct``: one dataset, one method, one label fraction → DIR with mesh, volume, metrics.

Outputs: ``mesh.ply`` (with each vertex's evidence: observed or inferred, distance to the
labelled bone), ``mesh.stl``, ``mesh.obj``, ``surface_extracted.ply`` (the whole iso-surface,
when the observed crop dropped faces), ``occupancy.nii.gz`` (aligned with the mesh in 3D Slicer,
see :mod:`ultron.mesh.export`), ``metrics.json`` when the dataset has a reference surface,
and ``run.json`` (:mod:`ultron.pipeline.record`: the command, configuration, label selection,
versions, timings per stage, peak memory), written into a staging directory that replaces DIR
as a whole at the end (:mod:`ultron.pipeline.rundir`), ``report.html`` included.

Everything cheap is checked before any work: DIR (:func:`~ultron.pipeline.rundir.check_run_dir`),
the dataset, the reference meshes (read then, used only for metrics after the mesh exists), the
oracle's files, outlier poses and the grids' memory (:mod:`ultron.pipeline.resources`).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, cast

import torch

from ultron import atomic
from ultron.data.dataset import SweepDataset
from ultron.data.labels import (
    check_selection_has_bone,
    select_label_frames,
    selection_warnings,
    unused_label_warnings,
)
from ultron.data.units import units_warnings
from ultron.device import describe_device, native_bfloat16, resolve_device
from ultron.errors import argument_error
from ultron.mesh.export import load_mesh, save_mesh, save_volume_nifti
from ultron.methods.evidence import evidence_summary, reconstruction_evidence, with_observation
from ultron.methods.registry import FieldMethod, MethodInputs, get_method
from ultron.methods.request import ReconstructionRequest
from ultron.methods.ultron_method import Reconstruction
from ultron.metrics.surface import MetricsConfig, evaluate_meshes
from ultron.models.field_dir import check_field_dataset
from ultron.models.fitted import check_field_finished, load_field
from ultron.pipeline.field_cache import get_or_fit_field
from ultron.pipeline.model_io import save_network
from ultron.pipeline.record import write_run_json
from ultron.pipeline.resources import check_run_resources
from ultron.pipeline.rundir import check_run_dir, resume_dir, staged_run_dir
from ultron.report.run_report import write_run_report
from ultron.timing import Advance, Announce, StageTimer
from ultron.train.field_fit import FieldTrainConfig
from ultron.train.loop import Progress
from ultron.train.visibility import load_oracle_truth

#: The whole iso-surface with its evidence, written when the observed crop dropped faces.
EXTRACTED_MESH = "surface_extracted.ply"
#: The checkpoint directory of the method's fits on the k-th field candidate (1 without
#: candidates) in the run's resume directory (:func:`~ultron.pipeline.rundir.resume_dir`).
CANDIDATE_CHECKPOINTS = "candidate-{}"


def run_method(
    dataset: SweepDataset,
    request: ReconstructionRequest,
    fitted,
    timer: StageTimer,
    truth: dict[str, Any] | None = None,
    dataset_name: str | None = None,
    checkpoints: Path | None = None,
) -> Reconstruction:
    """Reconstruct with ``request.method`` (``fitted`` is the acoustic field, for UltrON;
    ``truth`` the oracle's true transmission per sweep, see :mod:`ultron.train.visibility`;
    ``dataset_name``, e.g. its directory, names the dataset in RoCoSDF's input errors;
    ``checkpoints`` the directory where its fits keep their checkpoints).

    Every result carries its observed / inferred split (:mod:`ultron.methods.evidence`): a
    method that computes none (ON, RoCoSDF) is flagged with T ≡ 1 and keeps its surface."""
    inputs = method_inputs(request, fitted, timer, truth, dataset_name, checkpoints)
    return with_observed_surface(get_method(request.method).fit(dataset, inputs), dataset, timer)


def method_inputs(
    request: ReconstructionRequest,
    fitted,
    timer: StageTimer,
    truth: dict[str, Any] | None = None,
    dataset_name: str | None = None,
    checkpoints: Path | None = None,
) -> MethodInputs:
    """What ``request``'s method runs with (:class:`~ultron.methods.registry.MethodInputs`)."""
    return MethodInputs(
        request.method_config, timer, request.label_fraction, request.seed, fitted, truth,
        dataset_name, resolve_device(request.device, "device"), checkpoints,
    )  # fmt: skip


def with_observed_surface(
    result: Reconstruction, dataset: SweepDataset, timer: StageTimer
) -> Reconstruction:
    """``result``, with the observed / inferred split computed (T ≡ 1) where its method did
    not compute one."""
    if result.observation is None:
        with timer.stage("mesh_observed"):
            result = with_observation(result, dataset)
    return result


#: The reference mesh and its visible part (each None when the dataset has none).
References = tuple[Any, Any]


def load_references(dataset: SweepDataset) -> References:
    """The dataset's reference and visible-reference meshes, read in full so that an unreadable
    one is a one-line error naming the file before any work (they are used only for metrics)."""
    visible = dataset.reference_visible_path
    return (
        None if dataset.reference is None else load_mesh(dataset.reference),
        None if visible is None else load_mesh(visible),
    )


def write_outputs(
    out_dir: str | Path,
    dataset: SweepDataset,
    identity: dict[str, Any],
    result: Reconstruction,
    timer: StageTimer,
    metrics_config: MetricsConfig,
    extra: dict[str, Any] | None = None,
    report: bool = True,
    references: References | None = None,
    mesh_coordinates: str = "lps",
) -> dict[str, Any]:
    """Write the mesh, volume, the trained network (``network.pt`` when the method has one, see
    :mod:`ultron.pipeline.model_io`), metrics (with a reference) and, last, run.json into a
    staging directory that then replaces ``out_dir`` as a whole
    (:func:`~ultron.pipeline.rundir.staged_run_dir`; ``out_dir`` must be new, empty or a run of
    ``identity["command"]``); return the summary. run.json therefore marks a finished run.

    Mesh files are written in ``mesh_coordinates`` (:mod:`ultron.mesh.export`), their
    coincident vertices merged and their faces without area dropped
    (:func:`~ultron.mesh.extract.weld_coincident`; metrics.json and run.json describe the
    meshes so written); mesh.ply holds each vertex's evidence (:mod:`ultron.mesh.evidence`:
    ``observed``, ``label_distance_mm``) and, when the observed crop dropped faces,
    ``surface_extracted.ply`` the whole iso-surface with its own.

    ``identity`` (command, method, label_fraction, seed, …) heads run.json and tags
    metrics.json; ``references`` are :func:`load_references`'s meshes (read here if None).
    With ``report``, ``report.html`` is built in the staging directory after run.json, so it is
    swapped in with the rest (:mod:`ultron.report.run_report`); its time is in the returned
    timings, not in run.json.
    """
    out = Path(out_dir)
    identity = {"command": "reconstruct", **identity}
    reference, visible = load_references(dataset) if references is None else references
    result, surfaces = reconstruction_evidence(result, dataset)
    mesh = surfaces["mesh"].mesh  # as written: what metrics.json and run.json describe
    with staged_run_dir(out, identity["command"]) as staging:
        with timer.stage("write"):
            for suffix in (".ply", ".stl", ".obj"):
                ply = suffix == ".ply"
                attributes = surfaces["mesh"].evidence.vertex_attributes() if ply else None
                save_mesh(mesh, staging / f"mesh{suffix}", mesh_coordinates, attributes)
            if "extracted" in surfaces:
                whole = surfaces["extracted"]
                save_mesh(whole.mesh, staging / EXTRACTED_MESH, mesh_coordinates,
                          whole.evidence.vertex_attributes())  # fmt: skip
            save_volume_nifti(result.volume, result.grid, staging / "occupancy.nii.gz")
            if result.model is not None:
                meta = {"method": identity["method"], **result.model.meta}
                save_network(staging, result.model.network, meta)
        metrics = None
        if reference is not None:
            with timer.stage("metrics"):
                metrics = evaluate_meshes(
                    mesh, reference, metrics_config, reference_visible=visible
                )
            metrics["method"] = identity["method"]
            metrics["label_fraction"] = identity.get("label_fraction")
            atomic.write_json(staging / "metrics.json", metrics)
        payload = {
            **identity,
            "mesh": {"vertices": len(mesh.vertices), "faces": len(mesh.faces),
                     "area_mm2": float(mesh.area), "coordinates": mesh_coordinates},
            "surface_evidence": evidence_summary(surfaces),
            **result.info,
            **(extra or {}),
        }  # fmt: skip
        write_run_json(staging, payload, timer)
        if report:  # in the staging copy too: a run is swapped in whole, report included
            with timer.stage("report"):
                write_run_report(staging, dataset=dataset, shown_as=out)
    return {"out": str(out), "metrics": metrics, "timings_s": dict(timer.seconds)}


def prepare_run(
    out_dir: str | Path,
    kind: str,
    dataset_dir: str | Path,
    inputs: tuple[str | Path | None, ...] = (),
    voxel_mm: float | None = None,
    mesh: bool = True,
    field_config: Any = None,
    max_memory_gib: float | None = None,
) -> tuple[SweepDataset, References]:
    """The checks every run makes before any work, cheapest first: ``out_dir`` may hold this
    ``kind`` of run (:func:`~ultron.pipeline.rundir.check_run_dir`; ``inputs`` may not lie in
    it), the dataset loads, its reference meshes are readable, no pose is an outlier and the
    grids fit the memory (:func:`~ultron.pipeline.resources.check_run_resources`). Returns the
    dataset and its references."""
    check_run_dir(out_dir, kind, (dataset_dir, *inputs))
    dataset = SweepDataset.load(dataset_dir)
    references = load_references(dataset)
    check_run_resources(dataset, dataset_dir, voxel_mm, mesh, field_config, max_memory_gib)
    return dataset, references


def reconstruct(
    dataset_dir: str | Path,
    request: ReconstructionRequest,
    out_dir: str | Path,
    field_dir: str | Path | Sequence[str | Path] | None = None,
    field_config=None,
    progress: Progress | None = None,
    report: bool = True,
    allow_other_field: bool = False,
    max_memory_gib: float | None = None,
    announce: Announce | None = None,
    warn: Callable[[str], None] | None = None,
    advance: Advance | None = None,
) -> dict[str, Any]:
    """Check everything cheap (:func:`prepare_run`), get the field (given, or fitted and
    cached), run, write DIR (with ``report.html`` unless ``report`` is false). ``warn`` is
    told each implausible length (:func:`ultron.data.units.units_warnings`).

    A given ``field_dir`` must have been fitted on this dataset (see
    :func:`load_or_fit_field`) unless ``allow_other_field``; several (a sequence) are
    candidates, of which the run keeps the one whose trained f fits the labels best
    (:func:`run_on_fields`); ``max_memory_gib`` caps the
    grids' estimated memory (default: this machine's); ``announce`` is told as each stage
    starts and ends and ``advance`` how far a long stage has come (UltrON's θ queries, the
    occupancy fit's steps, the meshing's tiles and smoothing iterations, the observed crop's
    frames: :class:`~ultron.timing.StageTimer`). The method's network fits keep checkpoints in
    the run's resume directory (:func:`~ultron.pipeline.rundir.resume_dir`), so that the same
    run started again after an interruption resumes them (run.json ``resumed_from_step``: fit
    → update, also in the summary); the directory is removed once the run is in place."""
    timer = StageTimer(announce=announce, advance=advance)
    resume = resume_dir(out_dir)
    method = get_method(request.method)
    field_dirs = field_candidates(field_dir, method.needs_field)
    with timer.stage("load"):
        dataset, references, truth = preflight(
            dataset_dir, request, out_dir, field_dirs, field_config, allow_other_field,
            max_memory_gib, warn,
        )  # fmt: skip
    device = resolve_device(request.device, "device")
    for line in precision_warnings(request.method_config, device) if warn else ():
        warn(line)  # before any work, after the pre-flight checks as preflight's own warnings
    extra: dict[str, Any] = {"device": describe_device(device)}
    if method.needs_field:
        result, field_extra = run_on_fields(
            dataset_dir, dataset, request, field_dirs or [None], timer, truth,
            lambda candidate: load_or_fit_field(
                dataset_dir, dataset, candidate, field_config, progress, allow_other_field,
                device,
            ), resume,
        )  # fmt: skip
        extra |= field_extra
    else:
        checkpoints = _checkpoints(resume, 1)
        result = run_method(dataset, request, None, timer, truth, str(dataset_dir), checkpoints)
    identity = {
        "command": "reconstruct",
        "method": request.method,
        "label_fraction": request.label_fraction,
        "seed": request.seed,
        "dataset_dir": str(Path(dataset_dir).resolve()),
    }
    summary = write_outputs(
        out_dir, dataset, identity, result, timer, request.metrics, extra, report, references,
        request.mesh_coordinates,
    )  # fmt: skip
    shutil.rmtree(resume, ignore_errors=True)  # the run is in place: nothing left to resume
    if "resumed_from_step" in result.info:
        summary["resumed_from_step"] = result.info["resumed_from_step"]
    if "field_candidates" in extra:
        summary |= {"field_dir": extra["field_dir"], "field_candidates": extra["field_candidates"]}
    return summary


def preflight(
    dataset_dir: str | Path,
    request: ReconstructionRequest,
    out_dir: str | Path,
    field_dirs: Sequence[str | Path],
    field_config: Any = None,
    allow_other_field: bool = False,
    max_memory_gib: float | None = None,
    warn: Callable[[str], None] | None = None,
) -> tuple[SweepDataset, References, dict[str, Any] | None]:
    """:func:`reconstruct`'s checks before any work (:func:`prepare_run`; labels with bone;
    the method's resources; the oracle's files; the memory of the field to fit, when none is
    given; every field candidate), then ``warn`` told the selection's and the units' warnings.
    Returns the dataset, its references and the oracle's true T per sweep (None unless the
    run uses it)."""
    method, config = get_method(request.method), request.method_config
    dataset, references = prepare_run(
        out_dir, "reconstruct", dataset_dir, tuple(field_dirs),
        method.meshing_voxel(config), method.scan_grid, None, max_memory_gib,
    )  # fmt: skip
    # labels without bone: refused before minutes of field fit and training
    selection = select_label_frames(dataset, request.label_fraction, request.seed, dataset_dir)
    check_selection_has_bone(dataset, selection, dataset_dir)
    method.check_resources(dataset, config, selection, dataset_dir, max_memory_gib)
    # the oracle's files (an input) before the field to fit (its memory and frame size)
    visibility = method.visibility(config)
    truth = None if visibility is None else load_oracle_truth(visibility, dataset_dir, dataset)
    if method.needs_field and not field_dirs:  # the field to fit: its grid too
        check_run_resources(dataset, dataset_dir, mesh=False,
                            field_config=field_config or FieldTrainConfig(),
                            max_memory_gib=max_memory_gib)  # fmt: skip
    if len(field_dirs) > 1:  # every candidate read and checked before the first one's run
        for candidate in field_dirs:
            load_or_fit_field(dataset_dir, dataset, candidate, allow_other_field=allow_other_field)
    if warn is not None:  # after the pre-flight checks: a refused run prints its error alone
        reference = references[0]
        vertices = None if reference is None else reference.vertices
        lines = selection_warnings(dataset, selection) + unused_label_warnings(dataset, selection)
        for line in lines + units_warnings(dataset, vertices):
            warn(line)
    return dataset, references, truth


def precision_warnings(config: Any, device: torch.device) -> list[str]:
    """A line when ``config``'s occupancy fit (a method config with an ``occupancy``
    :class:`~ultron.train.occupancy.OccupancyTrainConfig`) runs in bfloat16 on ``device``
    without native bfloat16 products (:func:`~ultron.device.native_bfloat16`)."""
    occupancy = getattr(config, "occupancy", None)
    if getattr(occupancy, "precision", "float32") != "bfloat16" or native_bfloat16(device):
        return []
    return [
        f"--occupancy-precision bfloat16: {device} has no native bfloat16 products "
        "(AVX512-BF16 or AMX); torch emulates them and the occupancy fit runs many times "
        "slower than in float32 (docs/reconstruct.md)"
    ]


def field_candidates(
    field_dir: str | Path | Sequence[str | Path] | None, needs_field: bool
) -> list[str | Path]:
    """``field_dir`` as a list (empty for None); several only for a method that uses a field."""
    if field_dir is None:
        return []
    dirs = [field_dir] if isinstance(field_dir, str | Path) else list(field_dir)
    if len(dirs) > 1 and not needs_field:
        raise argument_error(
            "field_dir", f"{len(dirs)} fields given, but this method uses no acoustic field"
        )
    return dirs


def run_on_fields(
    dataset_dir: str | Path,
    dataset: SweepDataset,
    request: ReconstructionRequest,
    field_dirs: Sequence[str | Path | None],
    timer: StageTimer,
    truth: dict[str, Any] | None,
    get_field: Callable[[str | Path | None], tuple[Any, dict[str, Any]]],
    resume: Path | None = None,
) -> tuple[Reconstruction, dict[str, Any]]:
    """Run ``request`` on the field, or on the best of several (``get_field`` loads or fits
    each: :func:`load_or_fit_field`). With several, the method (one that reads a field) trains
    stage 2 on each and meshes only the f with the lowest label loss
    (:func:`ultron.train.occupancy.label_loss`, run info ``occupancy_label_loss``): the loss
    stage 2 is trained on, compared across fields of one dataset and label draw (how well it
    picks: docs/stage2-transmission.md); the field info returned is the kept one's, with
    ``field_candidates`` (every field's directory and loss), the field stages are named
    ``field k/K`` and stage 2's times add up over the candidates. With ``resume`` (a
    directory) the fits on the k-th candidate keep their checkpoints there
    (:data:`CANDIDATE_CHECKPOINTS`)."""
    if not field_dirs:
        raise argument_error("field_dirs", "expected at least one field (None: fit one)")
    name = str(dataset_dir)
    if len(field_dirs) == 1:
        with timer.stage("field"):
            fitted, field_extra = get_field(field_dirs[0])
        result = run_method(dataset, request, fitted, timer, truth, name, _checkpoints(resume, 1))
        return result, field_extra
    method = cast(FieldMethod, get_method(request.method))
    if not method.needs_field:
        raise argument_error(
            "field_dirs", f"{len(field_dirs)} fields given; {request.method} uses none"
        )
    kept: tuple[Any, MethodInputs, dict[str, Any]] | None = None
    candidates: list[dict[str, Any]] = []
    for k, candidate in enumerate(field_dirs, 1):
        with timer.stage(f"field {k}/{len(field_dirs)}"):  # names the candidate in a log
            fitted, field_extra = get_field(candidate)
        inputs = method_inputs(request, fitted, timer, truth, name, _checkpoints(resume, k))
        trained = method.train(dataset, inputs)
        if kept is None or trained.label_loss < kept[0].label_loss:  # ties: the first
            kept = (trained, inputs, field_extra)
        loss = {"occupancy_label_loss": float(trained.label_loss)}
        candidates.append({"field_dir": field_extra["field_dir"], **loss})
        del fitted, trained, inputs  # a losing candidate's field and f go now
    trained, inputs, field_extra = kept  # type: ignore[misc]  # set by the first candidate
    result = with_observed_surface(method.finish(dataset, inputs, trained), dataset, timer)
    return result, {**field_extra, "field_candidates": candidates}


def _checkpoints(resume: Path | None, k: int) -> Path | None:
    """The checkpoint directory of the fits on the k-th candidate in ``resume`` (None without
    one)."""
    return None if resume is None else resume / CANDIDATE_CHECKPOINTS.format(k)


def load_or_fit_field(
    dataset_dir: str | Path,
    dataset: SweepDataset,
    field_dir: str | Path | None,
    field_config: Any = None,
    progress: Progress | None = None,
    allow_other_field: bool = False,
    device: Any = "cpu",
) -> tuple[Any, dict[str, Any]]:
    """The dataset's acoustic field on ``device`` and what run.json records of it
    (``field_dir``, ``field_cached`` and, for a given field, ``field_dataset_match``).

    A given FIELD_DIR must match the dataset's probe geometry and, where its field.json records
    one, the dataset's content hash (:func:`ultron.models.field_dir.check_field_dataset`; a
    mismatch is an error unless ``allow_other_field``, then ``field_dataset_match`` is false;
    it is null for a field without the record). Otherwise the cached fit is used, keyed by the
    dataset directory's content (:mod:`ultron.pipeline.field_cache`).
    """
    if field_dir is not None:
        fitted = load_field(field_dir, device)
        check_field_finished(fitted, field_dir)
        fitted.check_probe(dataset.probe, where=str(dataset_dir))
        match = check_field_dataset(
            field_dir, dataset.content_hash(), str(dataset_dir), allow_other_field
        )
        used_dir, cached = Path(field_dir), True
        extra: dict[str, Any] = {"field_dataset_match": match}
    else:
        config = field_config or FieldTrainConfig()
        fitted, used_dir, cached = get_or_fit_field(dataset_dir, dataset, config, progress, device)
        extra = {}
    return fitted, {"field_dir": str(Path(used_dir).resolve()), "field_cached": cached, **extra}
