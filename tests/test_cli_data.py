"""``ultron import-ultranerf`` and ``ultron info`` end to end."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ultron.cli.main import app

runner = CliRunner()


@pytest.mark.parametrize(
    "command", [[], *([c.name] for c in app.registered_commands)], ids=lambda c: " ".join(c)
)
def test_help(command):
    result = runner.invoke(app, [*command, "--help"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output and "Traceback" not in result.output


def test_every_command_is_listed_demo_first():
    from ultron.cli.main import COMMANDS

    names = [name for name, _ in COMMANDS]
    assert names[0] == "demo" and len(set(names)) == len(names) == 13
    assert [c.name for c in app.registered_commands] == names
    listing = runner.invoke(app, ["--help"], terminal_width=200).output
    rows = [line.split()[0] for line in listing.splitlines() if re.match(r"  \S", line)]
    assert [row for row in rows if row in names] == names  # --help lists them in that order


def test_version():
    from ultron import __version__

    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"ultron {__version__}"


def _import(src: Path, out: Path, name: str, kind: str):
    args = ["import-ultranerf", str(src), "--width-mm", "80", "--depth-mm", "140"]
    return runner.invoke(app, [*args, "--out", str(out), "--sweep-name", name, "--kind", kind])


def test_import_and_info_on_l2(tmp_path: Path, l2_sample: Path):
    out = tmp_path / "l2"
    result = _import(l2_sample, out, "l2", "other")
    assert result.exit_code == 0, result.output
    assert "imported 200 frames of 512×256" in result.output
    result = runner.invoke(app, ["info", str(out)], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "frames: 200" in result.output
    assert "512 rows (depth) × 256 columns" in result.output
    assert "0.3125 mm lateral × 0.2734 mm axial" in result.output
    assert "labelled frames: 0" in result.output
    assert "reference: none" in result.output
    assert "bounding box (mm): x [" in result.output
    # a second import with another name adds a sweep
    result = _import(l2_sample, out, "again", "row")
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["info", str(out)], terminal_width=200)
    assert "sweeps: 2   frames: 400" in result.output


def test_import_bad_probe_size_is_clear(tmp_path: Path, l2_sample: Path):
    result = runner.invoke(
        app,
        [
            "import-ultranerf",
            str(l2_sample),
            "--width-mm",
            "-80",
            "--depth-mm",
            "140",
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert result.exit_code == 2
    assert "--width-mm" in result.stderr
    assert not (tmp_path / "x").exists()


def test_console_script_exit_code(tmp_path: Path):
    # the installed entry point, not just the typer app, exits 2 with one line
    result = subprocess.run(
        [sys.executable, "-m", "ultron.cli.main", "info", str(tmp_path / "nothing")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "no such directory" in result.stderr and "Traceback" not in result.stderr


THREADED = ("reconstruct", "finetune", "demo", "render", "simulate", "compound", "label",
            "fit-field")  # fmt: skip


@pytest.mark.parametrize("command", THREADED)
def test_heavy_commands_take_threads(command, tmp_path):
    help_text = runner.invoke(app, [command, "--help"], terminal_width=200).output
    assert "--threads" in help_text
    positional = {"reconstruct": 1, "finetune": 2, "render": 1, "compound": 1, "label": 1,
                  "fit-field": 1}.get(command, 0)  # fmt: skip
    args = [command, *[str(tmp_path)] * positional, "--threads", "0"]
    out = [] if command == "label" else ["--out", str(tmp_path / "o")]  # label writes in place
    result = runner.invoke(app, [*args, *out])
    assert result.exit_code == 2 and "--threads" in result.output, result.output
    assert not (tmp_path / "o").exists()


def test_field_progress_prints_plain_lines_off_a_terminal(capsys):
    from ultron.cli.reconstruct_cmds import _field_progress

    with _field_progress() as update:
        for step in range(1, 101):
            update({"step": step, "iterations": 100, "loss": 0.5, "psnr": 20.0})
    lines = [line for line in capsys.readouterr().out.splitlines() if "step " in line]
    assert len(lines) == 20  # every 5 %
    assert lines[0].startswith("fitting acoustic field: step 5/100 (5 %)")
    assert lines[-1].startswith("fitting acoustic field: step 100/100 (100 %)")
    assert "3001" not in " ".join(lines) and "101/100" not in " ".join(lines)
