"""Entry point of the ``ultron`` command. Commands live in role modules; :data:`COMMANDS` names
them and orders them here."""

from __future__ import annotations

import gc
import sys
from typing import Annotated

import typer

from ultron import __version__
from ultron.cli import (
    EXIT_INTERRUPTED,
    benchmark_cmds,
    data_cmds,
    eval_cmds,
    field_cmds,
    interrupted,
    label_cmds,
    phantom_cmds,
    reconstruct_cmds,
    volume_cmds,
)
from ultron.cli.common import EXIT_BAD_INPUT

#: Every command under its name, in the order ``ultron --help`` lists them: the demo, then a
#: dataset's life.
COMMANDS = (
    ("demo", reconstruct_cmds.demo),
    ("simulate", phantom_cmds.simulate),
    ("import-ultranerf", data_cmds.import_ultranerf),
    ("import-plus", data_cmds.import_plus),
    ("info", data_cmds.info),
    ("label", label_cmds.label),
    ("compound", volume_cmds.compound),
    ("fit-field", field_cmds.fit_field_command),
    ("render", field_cmds.render_command),
    ("reconstruct", reconstruct_cmds.reconstruct),
    ("finetune", reconstruct_cmds.finetune),
    ("evaluate", eval_cmds.evaluate),
    ("benchmark", benchmark_cmds.benchmark),
)

app = typer.Typer(
    name="ultron",
    help="Ultrasound Occupancy Networks: 3D bone surfaces from tracked 2D ultrasound sweeps.",
    no_args_is_help=True,
    rich_markup_mode=None,  # click's plain help: readable at 80 columns, where rich's is not
    pretty_exceptions_enable=False,
    add_completion=False,
)
for _name, _function in COMMANDS:
    app.command(_name)(_function)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"ultron {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    """Ultrasound Occupancy Networks: 3D bone surfaces from tracked 2D ultrasound sweeps."""


def main() -> None:
    """Console-script entry point. An option value of the wrong type (``--frames ten``) is one
    ``error:`` line naming the option, exit 2, like every other bad input, and so is every
    other usage error (an unknown option or command, an option without its value); Ctrl-C is
    one ``error: interrupted …`` line saying how to resume, exit 130. Everything is written
    when the command returns, so the objects then alive are frozen out of the garbage
    collector (:func:`gc.freeze`): the interpreter's exit then skips collecting torch's
    objects (docs/decisions.md, "The command's exit: live objects frozen out of the
    collector")."""
    try:
        return _run()
    except KeyboardInterrupt:  # while typer builds the commands, before it catches Ctrl-C
        interrupted()
    finally:
        gc.freeze()


def _run() -> None:
    try:
        code = app(standalone_mode=False)
    except typer.BadParameter as exc:  # click's MissingParameter too, whose message is empty
        names = exc.param.opts if exc.param is not None and exc.param.opts else [exc.param_hint]
        option = "/".join(str(n) for n in names if n) or "option"
        message = exc.message or _missing(exc)
        print(f"error: argument: {option}: {message}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    except typer.Abort:
        sys.exit(1)
    except Exception as exc:  # click's other errors carry their own message and code
        if not (hasattr(exc, "show") and hasattr(exc, "exit_code")):
            raise
        if _kind(exc, "UsageError") and not _kind(exc, "NoArgsIsHelpError"):
            # an unknown option or command, an option without its value: one line
            where = _command_path(getattr(exc, "ctx", None))
            message = exc.format_message().removesuffix(".")
            line = f"error: {message[:1].lower()}{message[1:]} (usage: {where} --help)"
            print(line, file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)
        exc.show()  # ``ultron`` alone: the help
        sys.exit(exc.exit_code)
    if code == EXIT_INTERRUPTED:  # typer's answer to Ctrl-C (a KeyboardInterrupt)
        interrupted()
    sys.exit(code if isinstance(code, int) else 0)


def _command_path(ctx) -> str:
    """``ultron`` and the names of the (sub)commands down to click's context ``ctx``."""
    names = []
    while ctx is not None and ctx.parent is not None:
        names.append(ctx.info_name)
        ctx = ctx.parent
    return " ".join(["ultron", *reversed(names)])


def _kind(exc: Exception, name: str) -> bool:
    """Whether ``exc`` is click's exception class ``name`` (or a subclass): typer ships its own
    copy of click, whose classes it does not export."""
    return any(cls.__name__ == name for cls in type(exc).__mro__)


def _missing(exc: typer.BadParameter) -> str:
    """The message of a required argument or option not given (click leaves it empty)."""
    command = exc.ctx.info_name if exc.ctx is not None and exc.ctx.info_name else "COMMAND"
    return f"missing; this is required (usage: ultron {command} --help)"


if __name__ == "__main__":
    main()
