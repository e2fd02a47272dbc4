"""Entry point of the ``ultron`` command. Commands live in role modules and register here."""

from __future__ import annotations

import typer

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


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
