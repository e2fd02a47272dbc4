"""A field knows its dataset: fit-field resumes only its own dataset's checkpoint (and a raised
--iters follows the new total's learning-rate schedule); reconstruct / render --field refuse a
field fitted on another dataset unless --allow-other-field."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from torch.optim.optimizer import register_optimizer_step_pre_hook
from typer.testing import CliRunner

from field_configs import quick_field_config
from ultron.cli.main import app
from ultron.data.dataset import ProbeGeometry, Sweep, SweepDataset
from ultron.errors import UltronInputError
from ultron.metrics.surface import MetricsConfig
from ultron.models.field_dir import check_field_dataset
from ultron.parallel import torch_threads
from ultron.pipeline import run as run_module
from ultron.pipeline.run import ReconstructionRequest, load_or_fit_field, reconstruct
from ultron.train.field_fit import FieldTrainConfig, fit_field, learning_rate_at

PROBE = ProbeGeometry(width_mm=8.0, depth_mm=9.0, height_px=24, width_px=16)
MISMATCH = "checkpoint was fitted on another dataset; use a new --out or --no-resume"


pytestmark = pytest.mark.usefixtures("one_thread")


def make_dataset(seed: int = 0, n: int = 10) -> SweepDataset:
    """Random frames along elevation, labelled bone below row 12 (enough for compounding)."""
    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = np.linspace(0.0, 4.0, n)
    images = rng.integers(0, 256, size=(n, 24, 16), dtype=np.uint8)
    labels = np.zeros((n, 24, 16), dtype=np.uint8)
    labels[:, 12:18] = 1
    return SweepDataset(PROBE, [Sweep("row", "row", images, poses, labels)])


def quick_config(**overrides) -> FieldTrainConfig:
    return quick_field_config(**overrides)


def one_line_error(result, *needles: str) -> str:
    """The one stderr line of a CLI run refused with exit code 2 (checked to name ``needles``)."""
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    assert "Traceback" not in result.output
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# ----------------------------------------------------------------- fit-field resume
def test_resume_refuses_another_dataset(tmp_path: Path) -> None:
    data, other = make_dataset(0), make_dataset(1)
    out = tmp_path / "f"
    fit_field(data, quick_config(iterations=4), out)
    meta = json.loads((out / "field.json").read_text())
    assert meta["dataset_sha256"] == data.content_hash() != other.content_hash()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(UltronInputError, match=r"field\.json: dataset_sha256: " + MISMATCH):
        fit_field(other, quick_config(iterations=8), out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing touched
    # the same dataset resumes; without resume another dataset starts afresh
    fit_field(data, quick_config(iterations=6), out)
    assert json.loads((out / "field.json").read_text())["step"] == 6
    fit_field(other, quick_config(iterations=3), out, resume=False)
    meta = json.loads((out / "field.json").read_text())
    assert meta["step"] == 3 and meta["dataset_sha256"] == other.content_hash()
    steps = [
        json.loads(line)["step"] for line in (out / "train_log.jsonl").read_text().splitlines()
    ]
    assert steps == [1, 3]  # not the previous run's log (1 … 6)


def test_field_without_recorded_hash_resumes(tmp_path: Path) -> None:
    out = tmp_path / "f"
    fit_field(make_dataset(0), quick_config(iterations=4), out)
    meta = json.loads((out / "field.json").read_text())
    del meta["dataset_sha256"]  # as written before the hash was recorded
    (out / "field.json").write_text(json.dumps(meta))
    fit_field(make_dataset(1), quick_config(iterations=6), out)  # not checked: resumes
    assert json.loads((out / "field.json").read_text())["step"] == 6


def test_cli_fit_field_other_dataset_and_no_resume(tmp_path: Path) -> None:
    runner = CliRunner()
    make_dataset(0).save(tmp_path / "a")
    make_dataset(1).save(tmp_path / "b")
    base = ["fit-field", "--out", str(tmp_path / "f"), "--iters", "2", "--check-every", "5"]
    assert runner.invoke(app, [*base, str(tmp_path / "a")]).exit_code == 0
    before = (tmp_path / "f" / "checkpoint.pt").read_bytes()
    refused = runner.invoke(app, [*base, str(tmp_path / "b")])
    one_line_error(refused, "field.json", "dataset_sha256", MISMATCH)
    assert "fit-field" not in refused.stdout  # refused before any progress bar
    assert (tmp_path / "f" / "checkpoint.pt").read_bytes() == before
    result = runner.invoke(app, [*base, str(tmp_path / "b"), "--no-resume"])
    assert result.exit_code == 0, result.output
    meta = json.loads((tmp_path / "f" / "field.json").read_text())
    assert meta["dataset_sha256"] == SweepDataset.load(tmp_path / "b").content_hash()


# ----------------------------------------------------------------- learning-rate schedule
@pytest.fixture
def rates() -> list[float]:
    """The learning rate every optimiser step actually runs with, in order (a global
    step pre-hook of torch's optimisers, removed after the test)."""
    seen: list[float] = []
    handle = register_optimizer_step_pre_hook(
        lambda optimizer, args, kwargs: seen.append(optimizer.param_groups[0]["lr"])
    )
    yield seen
    handle.remove()


def test_raised_iters_follow_the_new_totals_schedule(tmp_path: Path, rates: list[float]) -> None:
    data = make_dataset(0)
    logged: dict[str, dict[int, float]] = {"fresh": {}, "resumed": {}}

    def log_into(name: str):
        return lambda entry: logged[name].__setitem__(entry["step"], entry["lr"])

    fit_field(data, quick_config(iterations=60), tmp_path / "fresh", log_into("fresh"))
    fresh = list(rates)
    rates.clear()
    fit_field(data, quick_config(iterations=20), tmp_path / "resumed", log_into("resumed"))
    fit_field(data, quick_config(iterations=60), tmp_path / "resumed", log_into("resumed"))
    resumed = list(rates)
    assert len(fresh) == len(resumed) == 60
    lr0 = quick_config().lr
    # the first 20 steps decayed towards 0.1·lr at step 20, the rest follow the 60-step schedule
    assert resumed[19] == pytest.approx(lr0 * 0.1 ** (19 / 20), rel=1e-12)
    assert resumed[20] == pytest.approx(lr0 * 0.1 ** (20 / 60), rel=1e-12)
    np.testing.assert_allclose(resumed[20:], fresh[20:], rtol=1e-12, atol=0)
    np.testing.assert_allclose(
        [logged["resumed"][k] for k in range(21, 61)],
        [logged["fresh"][k] for k in range(21, 61)],
        rtol=1e-12,
        atol=0,
    )
    # at the end: the 60-step schedule's final rate, lr0·0.1 (the old schedule gave lr0·1e-3)
    assert logged["resumed"][60] == pytest.approx(logged["fresh"][60], rel=1e-12)
    assert logged["resumed"][60] == pytest.approx(lr0 * 0.1, rel=1e-12)
    assert learning_rate_at(quick_config(iterations=60), 60) == pytest.approx(lr0 * 0.1)
    log = [json.loads(line) for line in (tmp_path / "resumed" / "train_log.jsonl").open()]
    assert log[-1]["step"] == 60 and log[-1]["lr"] == pytest.approx(lr0 * 0.1, rel=1e-12)


def test_explicit_decay_horizon_does_not_follow_iterations() -> None:
    config = quick_config(iterations=60, lr_decay_steps=30)
    assert learning_rate_at(config, 30) == pytest.approx(config.lr * 0.1, rel=1e-12)
    assert learning_rate_at(replace(config, iterations=600), 30) == learning_rate_at(config, 30)


# ----------------------------------------------------------------- a given field's dataset
@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory) -> dict[str, Path]:
    """Dataset ``a`` with its field, and ``b``: ``a`` with one pixel changed."""
    root = tmp_path_factory.mktemp("provenance")
    make_dataset(0).save(root / "a")
    shutil.copytree(root / "a", root / "b")
    images = np.load(root / "b" / "row" / "images.npy")
    images[3, 4, 5] ^= 1
    np.save(root / "b" / "row" / "images.npy", images)
    with torch_threads(1):
        fit_field(SweepDataset.load(root / "a"), quick_config(iterations=2), root / "field")
    return {"a": root / "a", "b": root / "b", "field": root / "field"}


def test_given_field_is_checked_against_the_dataset(two_datasets, tmp_path: Path) -> None:
    a, b, field = two_datasets["a"], two_datasets["b"], two_datasets["field"]
    data_a, data_b = SweepDataset.load(a), SweepDataset.load(b)
    _, extra = load_or_fit_field(a, data_a, field)
    assert extra["field_dataset_match"] is True and extra["field_cached"] is True
    with pytest.raises(UltronInputError, match=r"field\.json: dataset_sha256: .*another dataset"):
        load_or_fit_field(b, data_b, field)
    _, extra = load_or_fit_field(b, data_b, field, allow_other_field=True)
    assert extra["field_dataset_match"] is False
    legacy = tmp_path / "legacy"
    shutil.copytree(field, legacy)
    meta = json.loads((legacy / "field.json").read_text())
    del meta["dataset_sha256"]
    (legacy / "field.json").write_text(json.dumps(meta))
    assert check_field_dataset(legacy, data_b.content_hash()) is None  # accepted, unknown
    _, extra = load_or_fit_field(b, data_b, legacy)
    assert extra["field_dataset_match"] is None


def test_cli_refuses_another_datasets_field(two_datasets, tmp_path: Path) -> None:
    runner = CliRunner()
    b, field = str(two_datasets["b"]), str(two_datasets["field"])
    out = tmp_path / "out"
    result = runner.invoke(app, ["reconstruct", b, "--field", field, "--out", str(out)])
    one_line_error(result, str(Path(field) / "field.json"), "dataset_sha256", "--allow-other")
    assert not out.exists()
    frames = tmp_path / "frames.npy"
    render = ["render", field, "--dataset", b, "--sweep", "row", "--out", str(frames)]
    one_line_error(runner.invoke(app, render), "field.json", "dataset_sha256")
    assert not frames.exists()
    result = runner.invoke(app, [*render, "--allow-other-field", "--expected"])
    assert result.exit_code == 0, result.output
    assert np.load(frames).shape == (10, 24, 16)


def test_allowed_other_field_is_recorded_in_run_json(
    two_datasets, tmp_path: Path, monkeypatch
) -> None:
    # UltrON's own stages are tested elsewhere; here the cheap compounding stands in for them,
    # so that only the field's path to run.json is exercised
    original = run_module.run_method

    def compounding(
        dataset, request, fitted, timer, truth=None, dataset_name=None, checkpoint=None
    ):
        assert fitted is not None  # the other dataset's field was loaded
        return original(
            dataset, replace(request, method="compounding", method_config=None), None, timer
        )

    monkeypatch.setattr(run_module, "run_method", compounding)
    request = ReconstructionRequest(label_fraction=1.0, metrics=MetricsConfig(n_points=500))
    b, field = two_datasets["b"], two_datasets["field"]
    with pytest.raises(UltronInputError, match="dataset_sha256"):
        reconstruct(b, request, tmp_path / "refused", field, report=False)
    assert not (tmp_path / "refused").exists()
    reconstruct(b, request, tmp_path / "out", field, report=False, allow_other_field=True)
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["field_dataset_match"] is False
    assert run["field_dir"] == str(field.resolve())


def test_interrupted_cached_fit_of_a_relabelled_dataset_restarts(tmp_path: Path, monkeypatch):
    from ultron.pipeline.field_cache import get_or_fit_field

    monkeypatch.setenv("ULTRON_CACHE", str(tmp_path / "cache"))
    make_dataset(0).save(tmp_path / "d")
    config = quick_config(iterations=6, checkpoint_every=2)

    def interrupt(entry: dict) -> None:
        if entry["step"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        get_or_fit_field(tmp_path / "d", SweepDataset.load(tmp_path / "d"), config, interrupt)
    labels = np.load(tmp_path / "d" / "row" / "labels.npy")
    labels[0, 0, 0] = 1  # the cache key ignores labels, the dataset hash does not
    np.save(tmp_path / "d" / "row" / "labels.npy", labels)
    relabelled = SweepDataset.load(tmp_path / "d")
    steps: list[int] = []
    _, field_dir, cached = get_or_fit_field(
        tmp_path / "d", relabelled, config, lambda e: steps.append(e["step"])
    )
    assert not cached and steps == [1, 2, 3, 4, 5, 6]  # started afresh, not at step 2
    meta = json.loads((field_dir / "field.json").read_text())
    assert meta["dataset_sha256"] == relabelled.content_hash()
