"""Entry point of the ``ultron`` command. Commands live in role modules and register here."""

from __future__ import annotations

from typing import Annotated

import typer

from ultron import __version__
from ultron.cli import (
    benchmark_cmds,
    data_cmds,
    eval_cmds,
    field_cmds,
    label_cmds,
    phantom_cmds,
    reconstruct_cmds,
    volume_cmds,
)

app = typer.Typer(
    name="ultron",
    help="Ultrasound Occupancy Networks: 3D bone surfaces from tracked 2D ultrasound sweeps.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

data_cmds.register(app)
eval_cmds.register(app)
field_cmds.register(app)
label_cmds.register(app)
phantom_cmds.register(app)
reconstruct_cmds.register(app)
volume_cmds.register(app)
benchmark_cmds.register(app)

#: The order ``ultron --help`` lists the commands in: the demo, then a dataset's life.
COMMAND_ORDER = (
    "demo", "simulate", "import-ultranerf", "import-plus", "info", "label", "compound",
    "fit-field", "render", "reconstruct", "finetune", "evaluate", "benchmark",
)  # fmt: skip
app.registered_commands.sort(
    key=lambda c: COMMAND_ORDER.index(c.name) if c.name in COMMAND_ORDER else len(COMMAND_ORDER)
)


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
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
