"""``finetune``: adapt a trained UltrON network to a new shape and write a run directory.

The algorithm (which layers are frozen, the loss, the settings) is
:mod:`ultron.methods.finetune`; this module checks the inputs as ``reconstruct`` does, loads
MODEL_DIR's network (:mod:`ultron.pipeline.model_io`) and the new dataset's field, and writes
the same outputs as ``reconstruct`` (:func:`ultron.pipeline.run.write_outputs`), plus the
fine-tuned ``network.pt`` (itself a valid MODEL_DIR).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ultron.data.labels import check_selection_has_bone, select_label_frames, selection_warnings
from ultron.device import describe_device, resolve_device
from ultron.methods.catalog import FINETUNE_METHOD
from ultron.methods.finetune import FinetuneConfig, check_theta_model, finetune_ultron
from ultron.pipeline.model_io import NETWORK_FILE, load_network
from ultron.pipeline.run import load_or_fit_field, prepare_run, write_outputs
from ultron.timing import Advance, Announce, StageTimer
from ultron.train.field_fit import FieldTrainConfig
from ultron.train.loop import Progress
from ultron.train.visibility import VisibilityConfig, load_oracle_truth


def finetune(
    model_dir: str | Path,
    dataset_dir: str | Path,
    config: FinetuneConfig,
    out_dir: str | Path,
    field_dir: str | Path | None = None,
    field_config=None,
    progress: Progress | None = None,
    report: bool = True,
    allow_other_field: bool = False,
    max_memory_gib: float | None = None,
    warn: Callable[[str], None] | None = None,
    announce: Announce | None = None,
    advance: Advance | None = None,
) -> dict[str, Any]:
    """Check everything cheap as ``reconstruct`` does (:func:`~ultron.pipeline.run.prepare_run`;
    DIR must be new, empty or an earlier ``finetune`` run), load MODEL_DIR's network and the
    new dataset's field, fine-tune, write DIR as ``reconstruct`` does; returns the same summary
    (``out``, ``metrics``, ``timings_s``).

    A given ``field_dir`` must have been fitted on the new dataset unless
    ``allow_other_field`` (see :func:`~ultron.pipeline.run.load_or_fit_field`); ``warn`` is
    told the label selection's warnings (:func:`~ultron.data.labels.selection_warnings`);
    ``announce`` and ``advance`` the stages and how far a long one has come, as
    :func:`~ultron.pipeline.run.reconstruct` tells them."""
    timer = StageTimer(announce=announce, advance=advance)
    where = str(Path(model_dir) / NETWORK_FILE)
    to_fit = (field_config or FieldTrainConfig()) if field_dir is None else None
    with timer.stage("load"):
        dataset, references = prepare_run(
            out_dir, "finetune", dataset_dir, (model_dir, field_dir), config.meshing.voxel_mm,
            True, to_fit, max_memory_gib,
        )  # fmt: skip
        network, meta = load_network(model_dir)
        # the source the model was trained with (``field`` if not recorded)
        visibility = config.visibility or VisibilityConfig.from_dict(meta, where)
        truth = None
        if config.iters > 0:  # labels to fine-tune on, before any field is fitted
            selection = select_label_frames(
                dataset, config.label_fraction, config.seed, dataset_dir
            )
            check_selection_has_bone(dataset, selection, dataset_dir)
            truth = load_oracle_truth(visibility, dataset_dir, dataset)
            # after the pre-flight checks: a refused run prints its error alone
            if warn is not None:
                for line in selection_warnings(dataset, selection):
                    warn(line)
    device = resolve_device(config.device, "device")
    with timer.stage("field"):
        fitted, extra = load_or_fit_field(
            dataset_dir, dataset, field_dir, field_config, progress, allow_other_field, device
        )
    extra = {"device": describe_device(device), **extra}
    spec = check_theta_model(network, meta, fitted, where)
    result = finetune_ultron(
        dataset, fitted, network, spec, config, timer, visibility=visibility, truth=truth
    )
    identity = {
        "command": "finetune",
        "method": FINETUNE_METHOD,
        "label_fraction": config.label_fraction if config.iters > 0 else 0.0,
        "seed": config.seed,
        "dataset_dir": str(Path(dataset_dir).resolve()),
        "model_dir": str(Path(model_dir).resolve()),
        "model_method": meta.get("method"),
    }
    return write_outputs(
        out_dir, dataset, identity, result, timer, config.metrics, extra, report, references,
        config.mesh_coordinates,
    )  # fmt: skip
