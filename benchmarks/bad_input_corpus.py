"""The bad-input corpus in one run: its size and how many cases ended in a traceback (0).

Runs every case of the three corpora in the tests — broken datasets through ``ultron info``
(``tests/test_bad_input.py``), out-of-range numeric options (``tests/test_cli_numeric.py``)
and bad outputs, references, importer input and resources (``tests/test_bad_input_corpus.py``)
— each in a fresh temporary directory holding the tests' tiny dataset, and counts the cases,
the tracebacks (an exception other than the CLI's exit, or "Traceback" in the output) and the
cases that broke another rule (exit code 2, one ``error:`` line naming the file or option,
nothing written). Exits 1 unless both counts are 0.

Usage::

    python benchmarks/bad_input_corpus.py
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "tests"
sys.path.insert(0, str(TESTS))

import test_bad_input  # noqa: E402
import test_bad_input_corpus as corpus  # noqa: E402
import test_cli_numeric  # noqa: E402
from conftest import build_tiny_dataset  # noqa: E402

#: build(tmp, dataset) → (CLI arguments, hints the one error line must hold).
Builder = Callable[[Path, Path], tuple[list[str], tuple[str, ...]]]
#: A case: (corpus name, case name, builder).
Case = tuple[str, str, Builder]


def _info_case(name: str) -> Builder:
    mutate, file_hint, field_hint = test_bad_input.CASES[name]

    def build(tmp: Path, data: Path) -> tuple[list[str], tuple[str, ...]]:
        mutate(data)
        return ["info", str(data)], (file_hint, field_hint)

    return build


def _numeric_case(command: str, option: str, value: str) -> Builder:
    def build(tmp: Path, data: Path) -> tuple[list[str], tuple[str, ...]]:
        template = test_cli_numeric.COMMANDS[command]
        args = [a.format(data=data, out=tmp / "out") for a in template]
        return [*args, option, value], (f"argument: {option}: expected ",)

    return build


def _command_case(name: str) -> Builder:
    build, hints = corpus.CASES[name]
    return lambda tmp, data: (build(tmp, data), hints)


# --- import-plus: bad PLUS / Slicer recordings (tests/test_import_plus.py's BAD_CASES), a
# fourth corpus kept in its own block ----------------------------------------------------------
def _plus_case(name: str) -> Builder:
    import test_import_plus

    build, hints = test_import_plus.BAD_CASES[name]
    return lambda tmp, data: (build(tmp), hints)


def plus_cases() -> Iterator[Case]:
    """The bad PLUS recordings and configurations of ``ultron import-plus``."""
    import test_import_plus

    for name in sorted(test_import_plus.BAD_CASES):
        yield "import-plus", name, _plus_case(name)


# --- compound: bad options, outputs and datasets of ``ultron compound``
# (tests/test_compound.py's BAD_CASES), a block of its own ------------------------------------
def _compound_case(name: str) -> Builder:
    import test_compound

    build, hints = test_compound.BAD_CASES[name]
    return lambda tmp, data: (build(tmp, data), hints)


def compound_cases() -> Iterator[Case]:
    """The bad options, outputs and datasets of ``ultron compound``."""
    import test_compound

    for name in sorted(test_compound.BAD_CASES):
        yield "compound", name, _compound_case(name)


def cases() -> Iterator[Case]:
    """Every case of the three corpora."""
    for name in sorted(test_bad_input.CASES):
        yield "info", name, _info_case(name)
    for command, option, value in test_cli_numeric.CASES:
        yield "numeric", f"{command} {option} {value}", _numeric_case(command, option, value)
    for name in sorted(corpus.CASES):
        yield "commands", name, _command_case(name)
    yield from plus_cases()
    yield from compound_cases()


def run_case(build: Builder) -> tuple[bool, str | None]:
    """(ended in a traceback, the broken rule or None) of one case."""
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        data = tmp / "tiny"
        build_tiny_dataset().save(data)
        os.environ["ULTRON_CACHE"] = str(tmp / "cache")
        args, hints = build(tmp, data)
        before = corpus.snapshot(tmp)
        result = corpus.runner.invoke(corpus.app, args)
        traceback = "Traceback" in result.output or not isinstance(result.exception, SystemExit)
        try:
            corpus.check_refused(result, hints)
            assert corpus.snapshot(tmp) == before, "something was written"
        except AssertionError as exc:
            return traceback, str(exc) or "assertion failed"
        return traceback, None


def main() -> int:
    """Run the corpus, print its size and the tracebacks; 1 if any case failed."""
    counts: dict[str, int] = {}
    tracebacks, broken = [], []
    for group, name, build in cases():
        counts[group] = counts.get(group, 0) + 1
        traceback, problem = run_case(build)
        if traceback:
            tracebacks.append(f"{group}/{name}")
        if problem:
            broken.append(f"{group}/{name}: {problem}")
    parts = ", ".join(f"{group} {n}" for group, n in counts.items())
    print(f"bad-input corpus: {sum(counts.values())} cases ({parts})")
    print(f"tracebacks: {len(tracebacks)}" + (f" ({', '.join(tracebacks)})" if tracebacks else ""))
    print(f"cases breaking another rule: {len(broken)}")
    for line in broken:
        print(f"  {line}")
    return 1 if tracebacks or broken else 0


if __name__ == "__main__":
    sys.exit(main())
