"""The ``ultron`` console script, also ``python -m ultron``.

It imports only :mod:`sys` and :mod:`ultron.cli`'s constants before it can catch Ctrl-C, so
that an interrupt while typer and the commands load is the same one line
and exit code as an interrupt later, not a traceback of the import machinery. (An interrupt
during Python's own start-up, before this module runs, is beyond any program's reach.)
"""

from __future__ import annotations

from ultron.cli import interrupted


def main() -> None:
    """Load the commands, then run :func:`ultron.cli.main.main`. Ctrl-C at any moment after
    this function starts prints ``error: interrupted …`` and exits with
    :data:`ultron.cli.EXIT_INTERRUPTED`."""
    try:
        from ultron.cli.main import main as run_command
    except KeyboardInterrupt:
        interrupted()
    try:
        run_command()
    finally:
        _ignore_interrupts()


def _ignore_interrupts() -> None:
    """Ignore Ctrl-C from now on: the command is over, its outputs written and its line
    printed, and an interrupt could only land in the interpreter's exit (its atexit
    callbacks), which prints Python's "Exception ignored … KeyboardInterrupt" traceback."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


if __name__ == "__main__":
    main()
