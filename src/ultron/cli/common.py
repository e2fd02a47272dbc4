"""Shared CLI plumbing: commands declared from their docstrings, one-line errors with exit
code 2, the consoles, progress lines."""

from __future__ import annotations

import ast
import functools
import gc
import importlib
import inspect
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, ParamSpec, TypeVar

import docstring_parser
import typer
from rich.console import Console

import ultron
from ultron.arguments import check_count
from ultron.errors import UltronError, UltronInputError, resource_error

P = ParamSpec("P")
R = TypeVar("R")

#: Exit code for bad input, as for a usage error.
EXIT_BAD_INPUT = 2

console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def user_errors(func: Callable[P, R], flags: Mapping[str, str] | None = None) -> Callable[P, R]:
    """Turn :class:`UltronError`, running out of memory and a full disk (or file-size limit)
    into a one-line ``error: …`` message on stderr and exit 2. An argument error about a
    parameter the command passed on under its own name names the option instead (``flags``:
    parameter → ``--flag``), so that the library's checks need no copy in the CLI."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return func(*args, **kwargs)
        except UltronError as exc:
            if isinstance(exc, UltronInputError) and exc.where == "argument":
                exc = UltronInputError(
                    "argument", (flags or {}).get(exc.field, exc.field), exc.problem
                )
            err_console.print(f"error: {exc}", markup=False, highlight=False)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except (MemoryError, RuntimeError, OSError) as exc:
            message = resource_error(exc)
            if message is None:
                raise
            err_console.print(f"error: {message}", markup=False, highlight=False)
            raise typer.Exit(EXIT_BAD_INPUT) from None

    return wrapper


#: The help of options that mean the same in every command, unless the command says otherwise:
#: what the command line resolves itself (a library function documents what it then receives).
COMMON_HELP = {
    "device": "Where networks compute: auto (CUDA when available, else the CPU), cpu, cuda,"
    " cuda:N or mps. cpu reproduces the CPU figures exactly.",
    "threads": "torch CPU threads (default: torch's choice).",
    "max_memory": "GiB the command's data and working memory may take, estimated before any"
    " work (default: the machine's memory, or the cgroup's or ulimit -v's limit).",
}


def command(
    *arguments: str,
    shared: Mapping[str, str] | None = None,
    metavars: Mapping[str, str] | None = None,
    aliases: Mapping[str, str] | None = None,
    documented_by: Iterable[str] = (),
    torch_threads: bool = True,
) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """A typer command from a documented function, as tyro (nerfstudio's CLI) reads one.

    Each parameter's help is its entry in the docstring's Google-style ``Args:`` section, else
    in ``shared``, else in :data:`COMMON_HELP`, else in the ``Args:`` of a library function or
    the ``Attributes:`` of a config class in ``documented_by`` (``"module:name"``) that takes
    it, under its name or, through ``aliases``, another: an option the library documents is
    documented once. The parameters named in ``arguments`` are positional, shown in upper case
    as help texts name them (``DATASET``), the others options named after them
    (``label_fraction`` → ``--label-fraction``), a bool that defaults to False a plain flag and
    an optional bool a ``--x/--no-x`` pair; ``metavars`` names the values of some. The
    command's help is the docstring above ``Args:``, each paragraph on one line.

    At the boundary, before the function runs: ``device`` is resolved (:func:`check_device`)
    and ``threads`` sets torch's CPU threads (:func:`apply_threads`; not with
    ``torch_threads=False``, where the command hands its threads on). Bad input is one line and
    exit 2 (:func:`user_errors`): the library checks the values, and its error about a
    parameter names the option, the parameter's own or, through ``aliases`` (the library's
    name → the parameter), one the command passes on under another name. A parameter left
    without help, or help or an argument naming no parameter, is a TypeError when the command
    is declared."""

    def declare(func: Callable[P, R]) -> Callable[P, R]:
        text = func.__doc__ or ""
        helps: dict[str, str] = {}
        for library in documented_by:
            for name, entry in _library_args(library).items():
                helps[(aliases or {}).get(name, name)] = entry
        helps.update(COMMON_HELP)  # what the command line resolves itself
        helps.update(shared or {})
        own = _documented(text)
        helps.update(own)
        signature = inspect.signature(func, eval_str=True)
        unknown = (set(own) | set(arguments)) - set(signature.parameters)
        if unknown:
            raise TypeError(f"{func.__name__}: no parameter named {', '.join(sorted(unknown))}")
        parameters = []
        for parameter in signature.parameters.values():
            if parameter.name not in helps:
                raise TypeError(f"{func.__name__}: parameter {parameter.name!r} has no help")
            info = _parameter_info(
                parameter, helps[parameter.name], parameter.name in arguments, metavars or {}
            )
            parameters.append(parameter.replace(annotation=Annotated[parameter.annotation, info]))
        options = [p.name for p in signature.parameters.values() if p.name not in arguments]
        flags = {name: _flag(name) for name in options}
        flags.update((name, _flag(parameter)) for name, parameter in (aliases or {}).items())
        wrapper = user_errors(_at_boundary(func, torch_threads), flags)
        wrapper.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
        wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
        wrapper.__doc__ = _paragraphs(re.split(r"\n[ \t]*Args:[ \t]*\n", text, maxsplit=1)[0])
        return wrapper

    return declare


def _documented(text: str) -> dict[str, str]:
    """The ``Args:`` entries of a Google-style docstring, each on one line."""
    documented = docstring_parser.parse(text, docstring_parser.DocstringStyle.GOOGLE)
    return {p.arg_name: " ".join(p.description.split()) for p in documented.params}


def _library_args(target: str) -> dict[str, str]:
    """The ``Args:`` (or a class's ``Attributes:``) entries of ``"module:name"``, read from the
    module's source without importing it: a command is declared at start-up, before torch
    loads."""
    module, name = target.split(":")
    package, *parts = module.split(".")  # not find_spec: it would import the parent packages
    if package != "ultron":
        raise TypeError(f"{target}: not an ultron module")
    path = Path(ultron.__file__).parent.joinpath(*parts).with_suffix(".py")
    if not path.is_file():  # an install without sources (byte code only): import it instead
        found = getattr(importlib.import_module(module), name, None)
        if found is None:
            raise TypeError(f"{target}: no such function or class")
        return _documented(inspect.getdoc(found) or "")
    for node in ast.parse(path.read_text("utf-8")).body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef) and node.name == name:
            return _documented(ast.get_docstring(node) or "")
    raise TypeError(f"{target}: no such function or class")


def _at_boundary(func: Callable[P, R], torch_threads: bool) -> Callable[P, R]:
    """``func`` with its ``device`` resolved and its ``threads`` applied (:func:`command`),
    run with the objects then alive frozen out of the garbage collector (:func:`settled`)."""

    @functools.wraps(func)
    def resolved(*args: P.args, **kwargs: P.kwargs) -> R:
        with collector_paused():  # resolving the device imports torch
            if torch_threads and "threads" in kwargs:
                apply_threads(kwargs["threads"])  # type: ignore[arg-type]
            if "device" in kwargs:
                kwargs["device"] = check_device(kwargs["device"])  # type: ignore[arg-type]
        with settled():
            return func(*args, **kwargs)

    return resolved


@contextmanager
def collector_paused() -> Iterator[None]:
    """The cyclic garbage collector off for the block (:func:`gc.disable`), as it was after.
    Importing torch allocates ≈ 10⁵ objects that live as long as the process, and triggers
    full collections that walk them all (docs/decisions.md, "The command's garbage
    collections")."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


@contextmanager
def settled() -> Iterator[None]:
    """The objects alive on entry (the modules loaded, torch's among them) moved out of the
    garbage collector's reach for the block (:func:`gc.freeze`), and back on exit
    (:func:`gc.unfreeze`, so that a process running many commands, as the tests do, collects
    them again). A full collection during the command then walks only the command's own
    objects; reference counting frees what it frees, as before. Objects a caller froze before
    entry stay frozen: ``gc.unfreeze`` cannot tell them apart, so nothing is unfrozen then."""
    frozen_before = gc.get_freeze_count()
    gc.freeze()
    try:
        yield
    finally:
        if frozen_before == 0:
            gc.unfreeze()


def _paragraphs(text: str) -> str:
    """``text``'s paragraphs (split at blank lines), each on one line: typer's help keeps a
    docstring's line breaks, which at any terminal width but the source's break a sentence."""
    paragraphs = re.split(r"\n[ \t]*\n", text.strip())
    return "\n\n".join(" ".join(p.split()) for p in paragraphs if p.strip())


def _parameter_info(
    parameter: inspect.Parameter, help: str, argument: bool, metavars: Mapping[str, str]
):
    """The typer Argument or Option of :func:`command`'s ``parameter``."""
    metavar = metavars.get(parameter.name)
    if argument:
        return typer.Argument(help=help, metavar=metavar or parameter.name.upper())
    flag = _flag(parameter.name)
    if parameter.annotation == bool | None:
        flag = f"{flag}/--no-{flag[2:]}"
    return typer.Option(flag, help=help, metavar=metavar)


def _flag(name: str) -> str:
    """The option a parameter is declared as: ``label_fraction`` → ``--label-fraction``."""
    return "--" + name.replace("_", "-")


def warning_line(line: str) -> None:
    """One ``warning: …`` line on stderr."""
    err_console.print(f"warning: {line}", markup=False, highlight=False)


def print_lines(lines: Iterable[str], warnings: Iterable[str] = ()) -> None:
    """A library's report of a command: ``lines`` on stdout, then each of ``warnings`` as a
    ``warning: …`` line on stderr."""
    for line in lines:
        console.print(line, highlight=False, soft_wrap=True)
    for line in warnings:
        warning_line(line)


@contextmanager
def stage_progress(
    first: str, unit: str = "", width: int = 18
) -> Iterator[Callable[[str, int, int], None]]:
    """A transient progress bar; yields ``report(stage, done, total)`` for a library's
    ``progress`` callback (the bar shows the stage's name and ``done/total unit``). Off a
    terminal (a log), where the bar stays silent, a line as each stage starts (``first``
    and the stage's name) and one as it passes each tenth of its work once 5 s have passed
    (:class:`StageLines`) instead."""
    if not console.is_terminal:
        lines, current = StageLines(), [None]

        def logged(stage: str, done: int, total: int) -> None:
            if stage != current[0] and not 0 < total <= done:  # not the closing report
                current[0] = stage
                lines(f"{first} {stage}", None)
            lines.advance(f"{first} {stage}", done, total, unit)

        yield logged
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    counter = "{task.completed}/{task.total}" + (f" {unit}" if unit else "")
    columns = (TextColumn(f"{{task.description:<{width}}}"), BarColumn(), TextColumn(counter))
    with Progress(*columns, TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task(first, total=None)

        def report(stage: str, done: int, total: int) -> None:
            bar.update(task, description=stage, completed=done, total=total)

        yield report


def check_device(value: str) -> str:
    """``--device``'s value resolved to an available device (``auto`` → cuda or cpu), as the
    string the library takes; a malformed or unavailable one is a one-line error."""
    from ultron.device import resolve_device

    return str(resolve_device(value, "--device"))


def apply_threads(threads: int | None) -> None:
    """Check ``--threads`` and, when given, set torch's CPU thread count."""
    if threads is not None:
        check_count("--threads", threads)
        import torch

        torch.set_num_threads(threads)


class _FitReporter:
    """A fit's progress callback (per-update dicts) with a ``stage(name, done, total)``
    method for its preparation (:func:`fit_progress`)."""

    def __init__(self, title: str, bar, task) -> None:
        self.title, self.bar, self.task = title, bar, task

    def stage(self, name: str, done: int, total: int) -> None:
        """A line at the preparation's start, every 10 % and at its end."""
        if done in (0, total) or done % max(1, total // 10) == 0:
            console.print(f"{self.title}: {name} {done}/{total}", highlight=False)

    def __call__(self, entry: dict) -> None:
        status = f"loss {entry.get('loss', float('nan')):.4f}"
        if "psnr" in entry:
            status += f"  PSNR {entry['psnr']:.2f} dB"
        if "holdout_psnr" in entry:
            status += (
                f"  held-out {entry['holdout_psnr']:.2f} dB / SSIM {entry['holdout_ssim']:.3f}"
            )
        step, total = entry.get("step", 0), entry.get("iterations", 1)  # step: updates done
        self.bar.update(self.task, total=total, completed=step, status=status)
        if not console.is_terminal and (step % max(1, total // 20) == 0 or step == total):
            line = f"{self.title}: step {step}/{total} ({100 * step / total:.0f} %), "
            console.print(line + status, highlight=False)


@contextmanager
def fit_progress(title: str) -> Iterator[Callable[[dict], None]]:
    """A progress bar fed by a fit's per-update dicts (``step``, ``iterations``, ``loss``,
    optionally ``psnr`` and the held-out check); yields the callback. Off a terminal (a log
    file, a batch job) the bar stays silent, so a plain line is printed every 5 % of the steps
    instead. Its ``stage(name, done, total)`` prints a line as a preparation (the confidence
    maps) starts, every 10 % and as it ends."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(
        TextColumn(f"[bold]{title}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TextColumn("{task.fields[status]}"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )
    task = bar.add_task(title, total=1, status="")
    with bar:
        yield _FitReporter(title, bar, task)


class StageLines:
    """A :class:`~ultron.timing.StageTimer`'s ``announce`` and ``advance``: one line as each
    stage of a run starts (``mesh_evaluate …``) and one with its time as it ends, and within a
    stage a line as it passes each tenth of its work (``mesh_evaluate: 130/260 tiles (50 %)``)
    once ``min_gap_s`` have passed since the stage's last line, so that a log shows what runs
    and a stage of minutes is not silent while a short one prints only its start and end."""

    def __init__(self, min_gap_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        self.min_gap_s, self.clock = min_gap_s, clock
        self._last, self._tenth, self._unit = clock(), 0, ""

    def __call__(self, name: str, seconds: float | None) -> None:
        text = f"{name} …" if seconds is None else f"{name}: {seconds:.1f} s"
        console.print(text, highlight=False)
        self._last, self._tenth = self.clock(), 0

    def advance(self, name: str, done: int, total: int, unit: str = "") -> None:
        if unit != self._unit:  # a new part of the stage (another view's fit) counts afresh
            self._unit, self._tenth = unit, 0
        tenth = 10 * done // total if total > 0 else 0
        now = self.clock()
        if tenth > self._tenth and now - self._last >= self.min_gap_s:
            what = f" {unit}" if unit else ""
            text = f"{name}: {done}/{total}{what} ({100 * done / total:.0f} %)"
            console.print(text, highlight=False)
            self._last, self._tenth = now, tenth
