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
INTERRUPTED = "interrupted; nothing half-written. Run the same command again"
#: What running again resumes, for the commands whose fits keep checkpoints.
RESUMES = {
    "fit-field": "the field fit continues from its last checkpoint",
    **dict.fromkeys(
        ("reconstruct", "finetune", "demo", "benchmark"),
        "a field fit and the network fits continue from their last checkpoint",
    ),
}


def interrupted_line(argv: list[str]) -> str:
    """:data:`INTERRUPTED`, and what running again resumes where the command ``argv[1]`` (the
    command line) keeps checkpoints (:data:`RESUMES`)."""
    resumes = RESUMES.get(argv[1] if len(argv) > 1 else "")
    return INTERRUPTED + (f" to resume: {resumes}" if resumes else "")


def interrupted() -> None:
    """Print the interrupted line and exit with :data:`EXIT_INTERRUPTED`."""
    print(f"error: {interrupted_line(sys.argv)}", file=sys.stderr)
    sys.exit(EXIT_INTERRUPTED)
