"""An interrupted ``reconstruct`` resumes its stage-2 fit from the checkpoint in the run's
resume directory and writes what an uninterrupted run writes."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import tiny_ultron_run
from ultron.mesh.export import load_mesh
from ultron.methods.on_method import ONConfig
from ultron.metrics.surface import MetricsConfig
from ultron.pipeline.run import CANDIDATE_CHECKPOINTS, ReconstructionRequest, reconstruct
from ultron.pipeline.rundir import resume_dir
from ultron.train.fit_checkpoint import OCCUPANCY_FIT, checkpoint_in

METRICS = MetricsConfig(n_points=2_000, repeats=1)
ON = ONConfig()
ON_REQUEST = ReconstructionRequest(
    method="on",
    label_fraction=1.0,
    method_config=replace(ON, occupancy=replace(ON.occupancy, iters=300, batch_size=1024, lr=1e-3)),
    metrics=METRICS,
)


class Killed(Exception):
    """Stands for the run's process being killed."""


def _killed_at(stage: str, step: int):
    """An ``advance`` callback that kills the run once ``stage`` reports ``step``."""

    def advance(name: str, done: int, total: int, unit: str) -> None:
        if name == stage and done >= step:
            raise Killed

    return advance


def _same_outputs(a: Path, b: Path) -> None:
    mesh_a, mesh_b = load_mesh(a / "mesh.ply"), load_mesh(b / "mesh.ply")
    assert np.array_equal(mesh_a.vertices, mesh_b.vertices)
    assert np.array_equal(mesh_a.faces, mesh_b.faces)
    runs = [json.loads((d / "run.json").read_text()) for d in (a, b)]
    logs = [[{k: v for k, v in e.items() if k != "seconds"} for e in r["occupancy_log"]]
            for r in runs]  # fmt: skip
    assert logs[0] == logs[1]
    metrics = [json.loads((d / "metrics.json").read_text())["mean"] for d in (a, b)]
    assert metrics[0] == metrics[1]


@pytest.fixture(scope="module")
def whole_on(tiny_l3: Path, tmp_path_factory) -> Path:
    """ON's uninterrupted run (:data:`ON_REQUEST`)."""
    out = tmp_path_factory.mktemp("on") / "whole"
    summary = reconstruct(tiny_l3, ON_REQUEST, out, report=False)
    assert "resumed_from_step" not in summary
    assert not resume_dir(out).exists()  # a finished run leaves none
    return out


@pytest.mark.parametrize(("stage", "step", "resumed"), [("occupancy_fit", 260, 250),
                                                        ("mesh_evaluate", 1, 300)])  # fmt: skip
def test_a_killed_run_resumes_its_fit(tiny_l3, whole_on, tmp_path: Path, stage, step, resumed):
    out = tmp_path / "run"
    with pytest.raises(Killed):
        reconstruct(tiny_l3, ON_REQUEST, out, report=False, advance=_killed_at(stage, step))
    assert not out.exists()
    candidate = resume_dir(out) / CANDIDATE_CHECKPOINTS.format(1)
    assert checkpoint_in(candidate, OCCUPANCY_FIT).path.is_file()
    again = reconstruct(tiny_l3, ON_REQUEST, out, report=False)
    assert again["resumed_from_step"] == {"occupancy": resumed}
    run = json.loads((out / "run.json").read_text())
    assert run["resumed_from_step"] == {"occupancy": resumed}
    _same_outputs(whole_on, out)
    assert not resume_dir(out).exists()


def test_another_request_does_not_resume(tiny_l3: Path, tmp_path: Path):
    out = tmp_path / "run"
    with pytest.raises(Killed):
        reconstruct(tiny_l3, ON_REQUEST, out, report=False, advance=_killed_at("mesh_evaluate", 1))
    other = replace(ON_REQUEST, seed=1)  # other labels' draw and network
    result = reconstruct(tiny_l3, other, out, report=False)
    assert "resumed_from_step" not in result
    reconstruct(tiny_l3, other, tmp_path / "whole", report=False)
    _same_outputs(tmp_path / "whole", out)


def test_ultron_resumes_each_field_candidates_fit(tiny_l3: Path, tmp_path: Path, monkeypatch):
    monkeypatch.setenv("ULTRON_CACHE", str(tmp_path / "cache"))
    request, fields = tiny_ultron_run(iters=400, field_iters=150, n_points=METRICS.n_points)
    reconstruct(tiny_l3, request, tmp_path / "whole", field_config=fields, report=False)
    field_dir = json.loads((tmp_path / "whole" / "run.json").read_text())["field_dir"]
    out = tmp_path / "run"
    with pytest.raises(Killed):
        reconstruct(tiny_l3, request, out, [field_dir, field_dir], report=False,
                    advance=_killed_at("mesh_evaluate", 1))  # fmt: skip
    saved = sorted(str(p.relative_to(resume_dir(out))) for p in resume_dir(out).glob("*/*"))
    assert saved == [f"{CANDIDATE_CHECKPOINTS.format(k)}/{OCCUPANCY_FIT}.pt" for k in (1, 2)]
    again = reconstruct(tiny_l3, request, out, [field_dir, field_dir], report=False)
    assert again["resumed_from_step"] == {"occupancy": 400}
    _same_outputs(tmp_path / "whole", out)
