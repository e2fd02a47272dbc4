"""A field fit's progress on disk: checkpoints every --checkpoint-every steps, a training log that
survives a kill at any point with every step exactly once, no resume to fewer --iters than the
checkpoint's step, and a warning when rendering from an unfinished fit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from field_configs import quick_field_config, random_sweep
from ultron import atomic
from ultron.cli.main import app
from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.models import load_field
from ultron.models.fitted import FitProgress, fit_progress
from ultron.train import field_fit
from ultron.train.field_fit import FieldTrainConfig, fit_field

runner = CliRunner()


pytestmark = pytest.mark.usefixtures("one_thread")


def make_dataset(n: int = 10) -> SweepDataset:
    return random_sweep(n)


def quick_config(**overrides) -> FieldTrainConfig:
    return quick_field_config(**{"iterations": 30, **overrides})


def snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def read_log(field_dir: Path) -> list[tuple]:
    """(step, loss, psnr, lr) of every log entry (seconds differ between runs)."""
    lines = (field_dir / "train_log.jsonl").read_text().splitlines()
    return [tuple(json.loads(line)[k] for k in ("step", "loss", "psnr", "lr")) for line in lines]


def one_line(result, stream: str, prefix: str, *needles: str) -> str:
    lines = [line for line in getattr(result, stream).splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(prefix), lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert "Traceback" not in result.output
    return lines[0]


# ----------------------------------------------------------------- --checkpoint-every
def test_cli_checkpoint_every_sets_the_save_steps(tmp_path: Path, monkeypatch) -> None:
    make_dataset().save(tmp_path / "d")
    saved: list[int] = []
    original = field_fit.save_checkpoint

    def spy(out, module, optimizer, generator, step, iterations):
        saved.append(step)
        original(out, module, optimizer, generator, step, iterations)

    monkeypatch.setattr(field_fit, "save_checkpoint", spy)
    base = ["fit-field", str(tmp_path / "d"), "--iters", "7", "--holdout-every", "0"]
    result = runner.invoke(app, [*base, "--out", str(tmp_path / "a"), "--checkpoint-every", "3"])
    assert result.exit_code == 0, result.output
    assert saved == [3, 6, 7]
    assert json.loads((tmp_path / "a" / "field.json").read_text())["train"]["checkpoint_every"] == 3
    saved.clear()  # default: the preset's 500 steps, so only the last one here
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "b")]).exit_code == 0
    assert saved == [7]
    assert "--checkpoint-every" in runner.invoke(app, ["fit-field", "--help"]).output


# ----------------------------------------------------------------- the log after a kill
@pytest.mark.parametrize(
    "killed_at", ["progress", "train_log.jsonl", "checkpoint.pt", "field.json"]
)
def test_log_holds_every_step_once_after_a_kill(tmp_path: Path, monkeypatch, killed_at: str):
    """Killed between saves (a progress callback raising at step 13) or while the save at step
    20 writes one of its files; the resumed log equals that of an uninterrupted fit."""
    data = make_dataset()
    fit_field(data, quick_config(), tmp_path / "full")
    expected = read_log(tmp_path / "full")
    assert [entry[0] for entry in expected] == [1, 5, 10, 15, 20, 25, 30]

    progress = None
    if killed_at == "progress":

        def progress(entry: dict) -> None:
            if entry["step"] == 13:
                raise KeyboardInterrupt

    else:
        writes = {"n": 0}
        write_bytes = atomic.write_bytes

        def killing_write(path, payload: bytes) -> None:
            if Path(path).name == killed_at:
                writes["n"] += 1
                if writes["n"] == 2:  # the second save, at step 20
                    raise KeyboardInterrupt
            write_bytes(path, payload)

        monkeypatch.setattr(atomic, "write_bytes", killing_write)
    with pytest.raises(KeyboardInterrupt):
        fit_field(data, quick_config(), tmp_path / "killed", progress=progress)
    monkeypatch.undo()
    fit_field(data, quick_config(), tmp_path / "killed")
    assert read_log(tmp_path / "killed") == expected


# ----------------------------------------------------------------- a fit asked again
def test_a_finished_fit_asked_again_is_loaded_not_prepared(tmp_path: Path, monkeypatch) -> None:
    """The end of a fit writes its ``done`` marker last; asked again for the same steps it loads
    the field (the frames' preparation, confidence maps included, is not redone); continued to
    more steps, the marker is gone until that fit ends; a fit stopped after its last save but
    before its end prepares again and writes what its end writes."""
    from ultron.models.field_dir import FIT_DONE, THETA_STATS

    data, out = make_dataset(), tmp_path / "f"
    first = fit_field(data, quick_config(iterations=6), out)
    assert (out / FIT_DONE).is_file()
    prepared: list[bool] = []
    original = field_fit._prepare

    def spy(*args, **kwargs):
        prepared.append((out / FIT_DONE).exists())
        return original(*args, **kwargs)

    monkeypatch.setattr(field_fit, "_prepare", spy)
    again = fit_field(data, quick_config(iterations=6), out)
    assert prepared == []
    weights = zip(first.field.state_dict().items(), again.field.state_dict().values(), strict=True)
    for (name, x), y in weights:
        assert torch.equal(x, y), name
    assert again.theta_stats == first.theta_stats
    longer = fit_field(data, quick_config(iterations=8), out)
    assert prepared == [False] and (out / FIT_DONE).is_file()
    assert json.loads((out / "field.json").read_text())["step"] == 8
    assert longer.theta_stats != first.theta_stats
    (out / FIT_DONE).unlink()  # stopped after the last save, before the statistics
    (out / THETA_STATS).unlink()
    fit_field(data, quick_config(iterations=8), out)
    assert prepared == [False, False] and (out / FIT_DONE).is_file()
    assert (out / THETA_STATS).is_file()


# ----------------------------------------------------------------- fewer --iters than done
def test_resume_below_the_checkpoint_step_is_an_error(tmp_path: Path, monkeypatch) -> None:
    data, out = make_dataset(), tmp_path / "f"
    fit_field(data, quick_config(iterations=20), out)
    before = snapshot(out)
    with pytest.raises(UltronInputError, match=r"field.json: step: the checkpoint is at step 20,"):
        fit_field(data, quick_config(iterations=10), out)
    assert snapshot(out) == before
    # field.json behind its checkpoint (killed between the two writes): the checkpoint's step
    # is checked too, before anything is written
    write_bytes = atomic.write_bytes

    def killing_write(path, payload: bytes) -> None:
        if Path(path).name == "field.json" and b'"step": 40' in payload:
            raise KeyboardInterrupt
        write_bytes(path, payload)

    monkeypatch.setattr(atomic, "write_bytes", killing_write)
    with pytest.raises(KeyboardInterrupt):
        fit_field(data, quick_config(iterations=40), out)
    monkeypatch.undo()
    assert json.loads((out / "field.json").read_text())["step"] == 30
    before = snapshot(out)
    with pytest.raises(UltronInputError, match=r"at step 40, beyond --iters 35; pass --no-resume"):
        fit_field(data, quick_config(iterations=35), out)
    assert snapshot(out) == before
    fit_field(data, quick_config(iterations=35), out, resume=False)  # afresh, as told
    assert json.loads((out / "field.json").read_text())["step"] == 35


def test_cli_resume_below_the_checkpoint_step(tmp_path: Path) -> None:
    make_dataset().save(tmp_path / "d")
    base = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--holdout-every", "0"]
    assert runner.invoke(app, [*base, "--iters", "6"]).exit_code == 0
    before = snapshot(tmp_path)
    result = runner.invoke(app, [*base, "--iters", "3"])
    assert result.exit_code == 2
    one_line(result, "stderr", "error: ", "field.json", "--iters 3", "--no-resume")
    assert snapshot(tmp_path) == before
    assert runner.invoke(app, [*base, "--iters", "3", "--no-resume"]).exit_code == 0
    assert json.loads((tmp_path / "f" / "field.json").read_text())["step"] == 3


# ----------------------------------------------------------------- render an unfinished fit
def test_render_warns_when_the_fit_did_not_finish(tmp_path: Path) -> None:
    data = make_dataset()

    def interrupt(entry: dict) -> None:
        if entry["step"] == 11:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_field(data, quick_config(iterations=20), tmp_path / "f", progress=interrupt)
    assert load_field(tmp_path / "f").fit_progress == FitProgress(10, 20)
    np.save(tmp_path / "p.npy", data.all_poses()[:2])
    args = ["render", str(tmp_path / "f"), "--poses", str(tmp_path / "p.npy"), "--out"]
    result = runner.invoke(app, [*args, str(tmp_path / "a.npy")])
    assert result.exit_code == 0, result.output
    one_line(result, "stderr", "warning: ", "field.json", "step 10 of 20", "fit-field")
    assert np.load(tmp_path / "a.npy").shape == (2, 24, 16)
    fit_field(data, quick_config(iterations=20), tmp_path / "f")  # finish it: no warning
    result = runner.invoke(app, [*args, str(tmp_path / "b.npy")])
    assert result.exit_code == 0 and result.stderr.strip() == ""


def test_reconstruct_refuses_an_unfinished_field_saying_how_to_finish_it(tmp_path: Path) -> None:
    data = make_dataset()
    labels = np.full(data.sweeps[0].images.shape, 255, dtype=np.uint8)
    labels[:, :12], labels[:, 12] = 0, 1
    data.sweeps[0].labels = labels
    data.save(tmp_path / "d")

    def interrupt(entry: dict) -> None:
        if entry["step"] == 11:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_field(data, quick_config(iterations=20), tmp_path / "f", progress=interrupt)
    args = ["reconstruct", str(tmp_path / "d"), "--field", str(tmp_path / "f")]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "o")])
    assert result.exit_code == 2, result.output
    one_line(result, "stderr", "error: ", "f/field.json", "step 10 of 20", "run `ultron fit-field`")
    assert not (tmp_path / "o").exists()


def test_fit_field_says_when_it_resumed_and_from_which_step(tmp_path: Path) -> None:
    make_dataset().save(tmp_path / "d")
    base = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--holdout-every", "0"]
    first = runner.invoke(app, [*base, "--iters", "4"])
    assert first.exit_code == 0 and "resumed" not in first.stdout
    more = runner.invoke(app, [*base, "--iters", "6"])
    assert more.exit_code == 0, more.output
    assert f"resumed the fit in {tmp_path / 'f'} from its checkpoint at step 4 of 6" in more.stdout
    again = runner.invoke(app, [*base, "--iters", "6"])
    assert again.exit_code == 0 and "had finished its 6 steps; loaded it" in again.stdout


def test_fit_progress_of_older_checkpoints() -> None:
    # a checkpoint without "iterations" (from before it was saved): field.json's total
    assert fit_progress({"train": {"iterations": 20}}, {"step": 10}) == FitProgress(10, 20)
    assert fit_progress({}, {"step": 5, "iterations": 5}).finished
    assert fit_progress({}, {"step": 5}) is None


# ------------------------------------------------------------ progress lines off a terminal
class _Recorder:
    """A fit's progress with a ``stage`` method: what a fit tells it, in order."""

    def __init__(self) -> None:
        self.events: list[tuple] = []

    def stage(self, name: str, done: int, total: int) -> None:
        self.events.append(("stage", name, done, total))

    def __call__(self, entry: dict) -> None:
        self.events.append(("step", entry["step"]))


def test_the_fit_reports_its_confidence_maps_before_its_steps(tmp_path: Path) -> None:
    recorder = _Recorder()
    fit_field(make_dataset(), quick_config(iterations=3), tmp_path / "f", recorder)
    stages = [e for e in recorder.events if e[0] == "stage"]
    assert stages[0] == ("stage", "confidence maps", 0, 10)
    assert stages[-1] == ("stage", "confidence maps", 10, 10) and len(stages) == 11
    first_step = recorder.events.index(("step", 1))
    assert first_step == len(stages)  # every map before the first update
    plain = []  # a progress callable without ``stage`` gets the update dicts only
    fit_field(make_dataset(), quick_config(iterations=3), tmp_path / "g", plain.append, False)
    assert [e["step"] for e in plain] == [1, 2, 3]


def test_cli_prints_a_line_per_stage_and_preparation_into_a_log(tmp_path: Path) -> None:
    """Off a terminal (CliRunner is not one) fit-field prints the confidence maps' advance and
    its steps, and reconstruct one line as each stage starts and one with its time."""
    make_dataset().save(tmp_path / "d")
    base = ["fit-field", str(tmp_path / "d"), "--out", str(tmp_path / "f"), "--iters", "4"]
    result = runner.invoke(app, [*base, "--holdout-every", "0"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "fit-field: confidence maps 0/10" in result.output
    assert "fit-field: confidence maps 10/10" in result.output
    assert "fit-field: step 4/4 (100 %)" in result.output


def test_demo_prints_each_reconstruction_stage_into_a_log(tmp_path: Path, monkeypatch) -> None:
    """Off a terminal the demo names each method and prints its stages as reconstruct does (a
    spinner prints nothing into a log, where stage 2 runs for minutes). The field fit and the
    reconstruction are stand-ins that tell what the real ones tell."""
    from ultron.pipeline import demo

    monkeypatch.chdir(tmp_path)  # short paths: the console wraps at 80 columns
    make_dataset().save(Path("d") / "dataset")
    told = []

    def reconstruct(dataset_dir, request, out_dir, field_dir, announce=None, advance=None):
        told.append((request.method, str(out_dir), callable(advance)))
        announce("occupancy_fit", None)
        announce("occupancy_fit", 12.0)
        return {"metrics": {}, "timings_s": {"occupancy_fit": 12.0}}

    monkeypatch.setattr(demo, "fit_field", lambda *a, **k: None)
    monkeypatch.setattr(demo, "reconstruct", reconstruct)
    result = runner.invoke(app, ["demo", "--out", "d"])
    assert result.exit_code == 0, result.output
    assert told == [("ultron", str(Path("d", "ultron")), True),
                    ("ultron-noloss", str(Path("d", "ultron-noloss")), True)]  # fmt: skip
    lines = result.output.splitlines()
    for method, label in demo.DEMO_METHODS.items():  # the method named, then its stages
        named = lines.index(f"{label} → {Path('d', method)}")
        assert lines[named + 1 : named + 3] == ["occupancy_fit …", "occupancy_fit: 12.0 s"]


def test_stage_lines_print_each_tenth_once_a_gap_has_passed() -> None:
    """A stage's advance prints at a new tenth only ``min_gap_s`` after the stage's last line:
    a fast stage prints its start and end alone, a slow one its tenths."""
    from ultron.cli.common import StageLines, console
    from ultron.timing import StageTimer

    now = [0.0]
    lines = StageLines(min_gap_s=5.0, clock=lambda: now[0])
    timer = StageTimer(announce=lines, advance=lines.advance)
    timer.advanced(1, 2, "tiles")  # outside a stage: nothing
    with console.capture() as captured:
        with timer.stage("fast"):
            for done in range(1, 11):
                now[0] += 0.1
                timer.advanced(done, 10, "tiles")
        with timer.stage("slow"):
            for done in range(1, 101):
                now[0] += 1.0  # 100 s in all: a tenth every 10 s
                timer.advanced(done, 100, "steps")
            now[0] += 2.0
            timer.counter("frames")(3, 4)  # a tenth passed, but 2 s after the last line
    text = captured.get().splitlines()
    assert text[0] == "fast …" and text[1].startswith("fast: ") and text[1].endswith(" s")
    assert text[2] == "slow …" and text[-1].startswith("slow: ") and text[-1].endswith(" s")
    slow = [t for t in text if t.startswith("slow: ") and t.endswith("%)")]
    assert slow == [f"slow: {k}/100 steps ({k} %)" for k in range(10, 101, 10)]


def test_a_stage_progress_bar_prints_lines_into_a_log() -> None:
    """Off a terminal (simulate, label --auto into a log) the bar is silent: each stage's start
    is a line, named after the work; a closing report starts nothing."""
    from ultron.cli.common import console, stage_progress

    assert not console.is_terminal
    with console.capture() as captured:
        with stage_progress("labelling", unit="frames") as report:
            report("row", 0, 10)
            report("row", 5, 10)
            report("column", 0, 3)
            report("done", 3, 3)
    assert captured.get().splitlines() == ["labelling row …", "labelling column …"]


def test_stage_timer_tells_the_running_stage() -> None:
    from ultron.timing import StageTimer

    told: list[tuple] = []
    timer = StageTimer(advance=lambda *e: told.append(e))
    with timer.stage("outer"):
        timer.fit_progress({"step": 3, "iterations": 9, "loss": 0.5})
        timer.fit_progress({"step": 2, "iterations": 9, "stage": "stage1_row"})
        with timer.stage("inner"):
            timer.counter("tiles")(1, 2)
        timer.advanced(4, 9)
    timer.advanced(5, 9)
    assert told == [("outer", 3, 9, "steps"), ("outer", 2, 9, "steps of stage1_row"),
                    ("inner", 1, 2, "tiles"), ("outer", 4, 9, "")]  # fmt: skip
    assert StageTimer().advanced(1, 2) is None  # without ``advance``: nothing to tell
