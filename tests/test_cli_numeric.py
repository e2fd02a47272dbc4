"""Every numeric CLI option refuses negative, NaN, infinite and out-of-range values at once: one
line on stderr naming the option, exit code 2, no traceback, nothing written."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from ultron.arguments import MAX_SEED, check_range
from ultron.cli.main import app
from ultron.errors import UltronInputError

runner = CliRunner()

SIZE = ["--width-mm", "80", "--depth-mm", "140"]
#: command → (arguments before the options, with {data} / {out} placeholders)
COMMANDS = {
    "fit-field": ["fit-field", "{data}", "--out", "{out}"],
    "render": ["render", "{data}", "--dataset", "{data}", "--sweep", "row", "--out", "{out}.npy"],
    "reconstruct": ["reconstruct", "{data}", "--out", "{out}"],
    "finetune": ["finetune", "{data}", "{data}", "--out", "{out}"],
    "demo": ["demo", "--out", "{out}"],
    "evaluate": ["evaluate", "{data}/a.ply", "{data}/b.ply", "--out", "{out}.json"],
    "import-ultranerf": ["import-ultranerf", "{data}", "--out", "{out}", *SIZE],
    "simulate": ["simulate", "--out", "{out}"],
    "benchmark": ["benchmark", "--out", "{out}"],
}

SEED_VALUES = ["-1", str(MAX_SEED + 1)]
CASES = [
    *[("fit-field", "--seed", v) for v in SEED_VALUES],
    ("fit-field", "--holdout-every", "-1"),
    ("fit-field", "--holdout-every", "1"),
    ("fit-field", "--iters", "0"),
    ("fit-field", "--iters", "-5"),
    ("fit-field", "--iters", "99999999999999999999"),
    ("fit-field", "--fit-shape", "coarse"),
    ("fit-field", "--scattering-floor", "nan"),
    ("fit-field", "--scattering-floor", "1"),
    ("fit-field", "--volume-cell", "-1"),
    ("fit-field", "--volume-cell", "nan"),
    ("fit-field", "--scattering-floor", "-0.1"),
    ("fit-field", "--scattering-floor", "0.9"),  # at or above the initial φ (0.5)
    ("fit-field", "--scattering-warmup", "-1"),
    ("fit-field", "--check-every", "0"),
    ("fit-field", "--threads", "0"),
    ("fit-field", "--checkpoint-every", "0"),
    ("fit-field", "--max-memory", "0"),
    ("fit-field", "--max-memory", "nan"),
    ("render", "--seed", "-1"),
    *[("reconstruct", "--seed", v) for v in SEED_VALUES],
    ("reconstruct", "--label-fraction", "nan"),
    ("reconstruct", "--label-fraction", "inf"),
    ("reconstruct", "--label-fraction", "0"),
    ("reconstruct", "--label-fraction", "1.5"),
    ("reconstruct", "--field-iters", "0"),
    ("reconstruct", "--occupancy-iters", "-1"),
    ("reconstruct", "--points", "0"),
    ("reconstruct", "--occupancy-iters", "0"),
    ("reconstruct", "--max-memory", "0"),
    ("reconstruct", "--max-memory", "nan"),
    ("finetune", "--max-memory", "-1"),
    ("finetune", "--iters", "-1"),
    ("finetune", "--anchor-weight", "-1"),
    ("finetune", "--anchor-weight", "nan"),
    ("finetune", "--label-fraction", "nan"),
    ("finetune", "--seed", "-2"),
    ("finetune", "--points", "-1"),
    ("finetune", "--field-iters", "-1"),
    ("demo", "--seed", "-1"),
    ("evaluate", "--points", "0"),
    ("evaluate", "--repeats", "-1"),
    ("evaluate", "--seed", "-1"),
    ("import-ultranerf", "--width-mm", "nan"),
    ("import-ultranerf", "--width-mm", "-80"),
    ("import-ultranerf", "--depth-mm", "inf"),
    ("import-ultranerf", "--depth-mm", "0"),
    ("import-ultranerf", "--orthonormalize-tol", "nan"),
    ("import-ultranerf", "--orthonormalize-tol", "inf"),
    ("import-ultranerf", "--orthonormalize-tol", "-0.1"),
    ("import-ultranerf", "--orthonormalize-tol", "1"),
    ("simulate", "--seed", "-1"),
    ("simulate", "--frames", "0"),
    ("simulate", "--step-mm", "nan"),
    ("simulate", "--step-mm", "-1"),
    ("simulate", "--probe-width-mm", "inf"),
    ("simulate", "--depth-mm", "0"),
    ("simulate", "--height-px", "0"),
    ("simulate", "--width-px", "-1"),
    ("simulate", "--pose-noise-mm", "nan"),
    ("simulate", "--pose-noise-deg", "inf"),
    ("simulate", "--label-noise-mm", "-1"),
    ("simulate", "--label-missing", "nan"),
    ("simulate", "--label-errors", "1.5"),
    ("simulate", "--voxel-mm", "nan"),
    ("simulate", "--voxel-mm", "3"),
    ("benchmark", "--seeds", "0"),
    ("benchmark", "--jobs", "0"),
    ("benchmark", "--threads", "-1"),
    # counts above MAX_COUNT, refused by the library's check_count
    *[
        (command, option, str(10**10))
        for command, option in [
            ("simulate", "--frames"),
            ("simulate", "--height-px"),
            ("reconstruct", "--occupancy-iters"),
            ("fit-field", "--scattering-warmup"),
            ("fit-field", "--holdout-every"),
            ("benchmark", "--seeds"),
            ("benchmark", "--jobs"),
        ]
    ],
]


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.parametrize(("command", "option", "value"), CASES)
def test_bad_numeric_option_is_refused(
    tmp_path: Path, tiny_dataset_dir: Path, command: str, option: str, value: str
) -> None:
    out = tmp_path / "out"
    args = [a.format(data=tiny_dataset_dir, out=out) for a in COMMANDS[command]]
    before = _snapshot(tmp_path)
    result = runner.invoke(app, [*args, option, value])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"error: argument: {option}: expected "), lines[0]
    assert "Traceback" not in result.output and isinstance(result.exception, SystemExit)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny"]  # no output created
    assert _snapshot(tmp_path) == before  # nothing written


def test_check_range_messages() -> None:
    with pytest.raises(UltronInputError, match=r"^argument: --x: expected an integer ≥ 1, got 0$"):
        check_range("--x", 0, 1)
    with pytest.raises(UltronInputError, match=r"expected a finite number in \(0, 1\], got nan"):
        check_range("--f", float("nan"), 0.0, 1.0, low_open=True)
    with pytest.raises(UltronInputError, match=r"expected a finite number ≥ 0, got inf"):
        check_range("--f", float("inf"), 0.0)
    for ok in (None, 1.0, 0.5):  # None: the option was not given
        check_range("--f", ok, 0.0, 1.0, low_open=True)
    with pytest.raises(UltronInputError, match=r"in \[0, 4294967295\], got -1$"):
        check_range("--seed", -1, 0, MAX_SEED)


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (["simulate", "--frames", "ten"], "--frames"),
        (["fit-field", "X", "--iters", "1.5"], "--iters"),
    ],
)
def test_an_option_of_the_wrong_type_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, args, option
) -> None:
    import sys

    from ultron.cli.main import main

    monkeypatch.setattr(sys, "argv", ["ultron", *args, "--out", str(tmp_path / "out")])
    with pytest.raises(SystemExit) as caught:
        main()
    assert caught.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: argument: {option}: "), lines
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["label", "--atuo", "D"], "error: no such option: --atuo (Possible options: --auto)"
         " (usage: ultron label --help)"),
        (["labl"], "error: no such command 'labl'. Did you mean 'label'? (usage: ultron --help)"),
        (["reconstruct", "A", "B", "--out", "O"], "error: got unexpected extra argument(s) (B)"
         " (usage: ultron reconstruct --help)"),
    ],
)  # fmt: skip
def test_every_other_usage_error_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, args, expected
) -> None:
    """An unknown option or command is one line and exit 2, as every other bad input, not
    click's usage block."""
    import sys

    from ultron.cli.main import main

    monkeypatch.setattr(sys, "argv", ["ultron", *args])
    with pytest.raises(SystemExit) as caught:
        main()
    assert caught.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [expected]


def test_ultron_alone_prints_the_help(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    import sys

    from ultron.cli.main import main

    monkeypatch.setattr(sys, "argv", ["ultron"])
    with pytest.raises(SystemExit):
        main()
    captured = capsys.readouterr()
    assert "reconstruct" in captured.out + captured.err and "error:" not in captured.err


@pytest.mark.parametrize(
    ("args", "option", "command"),
    [
        (["info"], "dataset", "ultron info"),
        (["compound", "D"], "--out", "ultron compound"),
        (["import-ultranerf", "U", "--out", "O"], "--width-mm", "ultron import-ultranerf"),
    ],
)
def test_a_missing_argument_is_one_line_naming_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, args, option, command
) -> None:
    """click leaves a missing parameter's message empty: the line still says what is wrong."""
    import sys

    from ultron.cli.main import main

    monkeypatch.setattr(sys, "argv", ["ultron", *args])
    with pytest.raises(SystemExit) as caught:
        main()
    assert caught.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [
        f"error: argument: {option}: missing; this is required (usage: {command} --help)"
    ]


def test_an_interrupted_command_says_how_to_resume(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    import sys

    import ultron.pipeline.run as run_module
    from ultron.cli.main import EXIT_INTERRUPTED, main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "reconstruct", interrupted)
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["ultron", "reconstruct", str(tmp_path), "--out", str(out)])
    with pytest.raises(SystemExit) as caught:
        main()
    assert caught.value.code == EXIT_INTERRUPTED == 130
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: interrupted"), lines
    assert "run the same command again to resume" in lines[0].lower()


def test_an_interrupt_while_the_commands_load_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    """Ctrl-C while the console script imports typer and the commands (its first ≈ 0.2 s)
    is the same line and exit code as one during a command, not an import traceback."""
    import sys

    import ultron.__main__ as entry
    import ultron.cli as cli

    class InterruptedImport:
        def find_spec(self, name, path=None, target=None):
            if name == "ultron.cli.main":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "ultron.cli.main", raising=False)
    monkeypatch.setattr(sys, "meta_path", [InterruptedImport(), *sys.meta_path])
    with pytest.raises(SystemExit) as caught:
        entry.main()
    assert caught.value.code == cli.EXIT_INTERRUPTED == 130
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert lines == [f"error: {cli.interrupted_line(sys.argv)}"]
    assert cli.interrupted_line(["ultron", "label", "d", "--auto"]) == cli.INTERRUPTED
    assert "field fit continues" in cli.interrupted_line(["ultron", "fit-field", "d"])


def test_the_console_script_ignores_ctrl_c_once_the_command_is_over(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """After the command returns only the interpreter's exit is left; a Ctrl-C there would
    print Python's atexit traceback and exit 0, so the console script ignores it."""
    import signal
    import sys

    import ultron.__main__ as entry

    before = signal.getsignal(signal.SIGINT)
    monkeypatch.setattr(sys, "argv", ["ultron", "--version"])
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a shell (not xdist's)
        with pytest.raises(SystemExit) as caught:
            entry.main()
        assert caught.value.code == 0
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_the_console_script_is_the_interrupt_safe_entry_point() -> None:
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "ultron"]
    assert script.value == "ultron.__main__:main"


def _field_config(**changes):
    from ultron.train.field_config import FieldTrainConfig

    return FieldTrainConfig(**changes)


def _request(**changes):
    from ultron.methods.request import ReconstructionRequest

    return ReconstructionRequest(**changes)


def _memory(gib):
    from ultron.memory import memory_limit

    return memory_limit(gib)


def _metrics(**changes):
    from ultron.metrics.surface import MetricsConfig

    return MetricsConfig(**changes)


def _read_ultranerf(tolerance):
    from ultron.data.importers import read_ultranerf

    return read_ultranerf("/nonexistent", 80.0, 140.0, orthonormalize_tolerance=tolerance)


@pytest.mark.parametrize(
    ("make", "name"),
    [
        (lambda: _field_config(holdout_every=1), "holdout_every"),
        (lambda: _field_config(seed=MAX_SEED + 1), "seed"),
        (lambda: _field_config(iterations=10**9 + 1), "iterations"),
        (lambda: _field_config(check_every=True), "check_every"),
        (lambda: _request(seed=-1), "seed"),
        (lambda: _request(seed=MAX_SEED + 1), "seed"),
        (lambda: _memory(0.0), "max_memory_gib"),
        (lambda: _memory(float("nan")), "max_memory_gib"),
        (lambda: _metrics(seed=-1), "seed"),
        (lambda: _metrics(n_points=0), "n_points"),
        (lambda: _read_ultranerf(float("nan")), "orthonormalize_tolerance"),  # before the files
    ],
)
def test_the_library_checks_what_the_cli_hands_on(make, name: str) -> None:
    """The commands pass these values on unchecked: the library refuses them, naming its
    parameter (which the CLI maps onto the option)."""
    with pytest.raises(UltronInputError, match=rf"^argument: {name}: expected "):
        make()
