"""The ``ultron`` command line: thin wrappers that parse, call the library and print.

Each command imports the library inside its function, after its options are checked, so that
``ultron --help`` and a refused option answer in a fraction of a second instead of waiting
for torch (these are the only imports of ultron inside functions besides the phantom ↔ SDF
volume pair, :mod:`ultron.report`'s entry points, and optional or heavy third-party
libraries).

:mod:`ultron.__main__` is the console script; this package's own module imports only
:mod:`sys`, so that it can catch Ctrl-C before typer and the commands load.
"""

from __future__ import annotations

import sys

#: Exit code of an interrupted command (128 + SIGINT, as a shell reports one).
EXIT_INTERRUPTED = 130
#: The line an interrupted command prints.
INTERRUPTED = (
    "interrupted; nothing half-written. Run the same command again to resume: a field fit and"
    " reconstruct's network fits continue from their last checkpoint"
)


def interrupted() -> None:
    """Print the interrupted line and exit with :data:`EXIT_INTERRUPTED`."""
    print(f"error: {INTERRUPTED}", file=sys.stderr)
    sys.exit(EXIT_INTERRUPTED)
