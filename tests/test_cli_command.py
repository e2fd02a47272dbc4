"""``ultron.cli.common.command``: a typer command declared by its function's docstring."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
import typer.main
from typer.testing import CliRunner

from ultron.cli.common import COMMON_HELP, command
from ultron.cli.main import app as ultron_app
from ultron.errors import argument_error

runner = CliRunner()


@command("source", shared={"count": "Shared count help.", "unused": "Not a parameter here."},
         metavars={"depth_mm": "MM"})  # fmt: skip
def _example(
    source: Path,
    out: Path,
    depth_mm: float = 1.5,
    count: int = 3,
    quiet: bool = False,
    smooth: bool | None = None,
    names: list[str] | None = None,
    threads: int | None = None,
) -> None:
    """Do the example.

    A second paragraph, written
    over two lines.

    Args:
        source: Where the input
            lives, on two lines.
        out: Output directory.
        depth_mm: Depth, mm.
        quiet: Print nothing.
        smooth: Smooth or not (default: the preset's).
        names: Names (repeat).
    """
    if count < 0:
        raise argument_error("--count", f"expected ≥ 0, got {count}")
    if depth_mm > 10:  # as a library function would name its own parameter
        raise argument_error("depth_mm" if count else "source", f"expected ≤ 10, got {depth_mm}")
    typer.echo(f"{source} {out} {depth_mm} {count} {quiet} {smooth} {names} {threads}")


def _click_command():
    app = typer.Typer()
    app.command("example")(_example)
    app.command("other")(lambda: None)  # two commands keep "example" a subcommand
    return app, typer.main.get_command(app).commands["example"]


def test_parameters_are_declared_from_the_docstring():
    _, click_command = _click_command()
    params = {p.name: p for p in click_command.params}
    assert params["source"].param_type_name == "argument"
    assert params["source"].metavar == "SOURCE"  # as the help text names it
    assert params["source"].help == "Where the input lives, on two lines."
    assert params["out"].opts == ["--out"] and params["out"].required
    assert params["depth_mm"].opts == ["--depth-mm"] and params["depth_mm"].metavar == "MM"
    assert params["count"].help == "Shared count help."  # from ``shared``
    assert params["threads"].help == COMMON_HELP["threads"]
    # a bool defaulting to False is a plain flag; an optional bool a --x/--no-x pair
    assert params["quiet"].is_flag and params["quiet"].secondary_opts == []
    assert params["smooth"].opts == ["--smooth"]
    assert params["smooth"].secondary_opts == ["--no-smooth"]
    assert params["names"].multiple
    # the command's help is the text above Args:, its paragraphs kept, each on one line
    assert click_command.help == "Do the example.\n\nA second paragraph, written over two lines."


def test_a_declared_command_parses_and_refuses_bad_input(tmp_path: Path):
    app, _ = _click_command()
    args = ["example", "src", "--out", "o", "--depth-mm", "2", "--no-smooth", "--names", "a"]
    result = runner.invoke(app, [*args, "--names", "b", "--quiet"])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == "src o 2.0 3 True False ['a', 'b'] None"
    result = runner.invoke(app, [*args, "--count", "-1"])
    assert result.exit_code == 2
    assert result.output.strip() == "error: argument: --count: expected ≥ 0, got -1"
    assert "Traceback" not in result.output


@pytest.mark.parametrize(("count", "named"), [("1", "--depth-mm"), ("0", "source")])
def test_a_library_error_about_a_parameter_names_its_option(count: str, named: str):
    """An argument error raised under an option's parameter name names the option; one about
    a positional argument keeps the name."""
    app, _ = _click_command()
    args = ["example", "src", "--out", "o", "--depth-mm", "11", "--count", count]
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.output.strip() == f"error: argument: {named}: expected ≤ 10, got 11.0"


def test_a_parameter_without_help_is_refused_when_declared():
    def no_help(value: int = 0) -> None:
        """Nothing said of value."""

    with pytest.raises(TypeError, match="'value' has no help"):
        command()(no_help)


@pytest.mark.parametrize(
    ("arguments", "entries"),
    [((), "value: The value.\n    valeu: The value, misspelt."), (("missing",), "value: V.")],
    ids=["misspelt-entry", "absent-argument"],
)
def test_help_or_an_argument_naming_no_parameter_is_refused(arguments, entries):
    def declared(value: int = 0) -> None:
        pass

    declared.__doc__ = f"A command.\n\nArgs:\n    {entries}\n"
    with pytest.raises(TypeError, match=r"no parameter named (valeu|missing)"):
        command(*arguments)(declared)


def test_every_ultron_option_has_help_and_no_command_help_shows_its_args_section():
    commands = typer.main.get_command(ultron_app).commands
    assert len(commands) == 13
    for name, click_command in commands.items():
        assert "Args:" not in (click_command.help or ""), name
        for paragraph in (click_command.help or "").split("\n\n"):  # a sentence is not broken
            assert paragraph and "\n" not in paragraph and "  " not in paragraph, name
        for param in click_command.params:
            assert param.help and "\n" not in param.help, (name, param.name)
            assert "  " not in param.help, (name, param.name)  # continuation lines joined
            assert "``" not in param.help and ":func:" not in param.help, (name, param.name)


@command(aliases={"depth": "depth_mm"}, documented_by=("ultron.pipeline.presets:preset_request",))
def _at_the_boundary(
    depth_mm: float = 1.0,
    negatives: str | None = None,
    device: str = "auto",
    threads: int | None = None,
) -> None:
    """Report what the function receives.

    Args:
        depth_mm: Depth, mm.
    """
    import torch

    if depth_mm < 0:  # the library's check of the value it takes as ``depth``
        raise argument_error("depth", f"expected ≥ 0, got {depth_mm}")
    typer.echo(f"{negatives} {device} {torch.get_num_threads()}")


def _boundary_app():
    app = typer.Typer()
    app.command("example")(_at_the_boundary)
    app.command("other")(lambda: None)
    return app


def test_device_and_threads_are_resolved_before_the_command_runs(one_thread):
    import torch

    result = runner.invoke(_boundary_app(), ["example", "--device", "auto", "--threads", "2"])
    assert result.exit_code == 0, result.output
    auto = "cuda" if torch.cuda.is_available() else "cpu"  # as --device's help promises
    assert result.output.split()[1:] == [auto, "2"]  # resolved, and torch given 2 threads
    result = runner.invoke(_boundary_app(), ["example", "--device", "tpu"])
    assert result.exit_code == 2 and result.output.startswith("error: argument: --device: ")


def test_an_aliased_library_error_names_the_option():
    result = runner.invoke(_boundary_app(), ["example", "--depth-mm", "-1"])
    assert result.exit_code == 2
    assert result.output.strip() == "error: argument: --depth-mm: expected ≥ 0, got -1.0"


def test_help_comes_from_the_library_function_that_takes_the_option():
    """An option's help is the library's own ``Args:`` entry, read without importing it, under
    the option's name or an alias; reconstruct's method options read preset_request's."""
    import docstring_parser

    from ultron.pipeline.presets import preset_request

    documented = docstring_parser.parse(preset_request.__doc__ or "")
    library = {p.arg_name: " ".join(p.description.split()) for p in documented.params}
    commands = typer.main.get_command(ultron_app).commands
    example = typer.main.get_command(_boundary_app()).commands["example"]
    assert {p.name: p.help for p in example.params}["negatives"] == library["negatives"]
    reconstruct = {p.name: p.help for p in commands["reconstruct"].params}
    assert reconstruct["negatives"] == library["negatives"]
    assert reconstruct["label_support"] == library["label_support_mm"]  # through its alias
    assert reconstruct["oracle_transmission"] == library["oracle"]
    with pytest.raises(TypeError, match="no such function or class"):
        command(documented_by=("ultron.pipeline.presets:no_such_function",))(lambda: None)


def test_declaring_the_commands_loads_no_torch():
    """The help read from library docstrings is read from their source: ``ultron --help`` and
    a bad option answer without loading torch (a second of start-up)."""
    import subprocess
    import sys

    code = (
        "import sys, typer.main, ultron.cli.main as m; typer.main.get_command(m.app);"
        " print(sorted(n for n in ('torch', 'ultron.phantom', 'ultron.pipeline.presets')"
        " if n in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_help_is_the_same_read_from_the_source_or_from_the_imported_module(monkeypatch, tmp_path):
    """Without the sources (an install of byte code only) the entries come from the imported
    object's docstring: the same help."""
    import ultron
    from ultron.cli.common import _library_args

    targets = ("ultron.pipeline.presets:preset_request", "ultron.metrics.surface:MetricsConfig")
    from_source = [_library_args(target) for target in targets]
    monkeypatch.setattr(ultron, "__file__", str(tmp_path / "__init__.py"))
    assert [_library_args(target) for target in targets] == from_source
    assert from_source[0]["negatives"].startswith("ultron: background labels")
    with pytest.raises(TypeError, match="no such function or class"):
        _library_args("ultron.pipeline.presets:no_such_function")
