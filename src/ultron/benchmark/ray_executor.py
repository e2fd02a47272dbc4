"""``ultron benchmark --executor ray``: the benchmark's tasks as Ray tasks.

Each task of the plan (simulate, field, auto-label, every cell) becomes one Ray task that asks
for ``threads`` CPUs and runs the same worker as the local executor
(:func:`ultron.benchmark.runner.execute`) with torch set to that many threads, so a cell's
outputs are the local executor's, file for file; resume works as locally (a finished cell is
skipped by the worker). Tasks are submitted as soon as their dependencies have finished; Ray
places them where CPUs are free, so ``--jobs`` does not cap them (it only sets the default
``--threads``: cores // jobs).

With no ``address`` a local Ray cluster is started on this machine with its CPU count and shut
down at the end (so the same command runs on a laptop); with an address (``auto``, or
``ray://host:10001``) the running cluster is joined and left running. On a cluster every node
must see the output directory at the same path (a shared filesystem): tasks read their inputs
from it and write their run directories into it.

Ray is optional (``pip install -e ".[ray]"``); without it ``--executor ray`` is a one-line
error saying so.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from typing import Any

from ultron.errors import argument_error

EXECUTORS = ("local", "ray")
RAY_INSTALL_HINT = 'Ray is not installed: pip install -e ".[ray]" (or pip install ray)'


def import_ray() -> Any:
    """The ``ray`` module, or a one-line :class:`UltronInputError` naming ``--executor``."""
    try:
        import ray
    except ImportError:
        raise argument_error("--executor", RAY_INSTALL_HINT) from None
    return ray


def check_executor(executor: str, address: str | None) -> None:
    """Validate ``executor`` / ``address`` before any work (Ray importable when asked for)."""
    if executor not in EXECUTORS:
        raise argument_error(
            "--executor", f"expected one of {', '.join(EXECUTORS)}, got {executor!r}"
        )
    if address is not None and executor != "ray":
        raise argument_error("--address", "only used with --executor ray")
    if address is not None and not address.strip():
        raise argument_error("--address", "expected a Ray address (auto, or ray://host:port)")
    if executor == "ray":
        import_ray()


def ray_error_line(exc: BaseException) -> str:
    """The last informative line of a Ray error (its text spans many lines with colour
    codes): ``RayTaskError: … ModuleNotFoundError: No module named 'x'`` → that last line."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc))
    lines = [line.strip() for line in text.splitlines() if line.strip().strip("^")]
    return f"{type(exc).__name__}: {lines[-1] if lines else 'no message'}"


def _run_with_threads(worker: Callable[[Any], dict], task: Any, threads: int) -> dict:
    """Body of one Ray task: torch on ``threads`` threads, then the local worker."""
    import torch

    torch.set_num_threads(threads)
    return worker(task)


def run_graph_on_ray(
    graph: Any,
    threads: int,
    worker: Callable[[Any], dict],
    address: str | None,
    crash: Callable[[BaseException], dict],
    gpus: float = 0.0,
) -> None:
    """Run ``graph``'s tasks (:class:`ultron.benchmark.runner._Graph`) on Ray (module doc),
    each reserving ``threads`` CPUs and ``gpus`` GPUs (Ray then sets CUDA_VISIBLE_DEVICES,
    so ``cuda`` in a task is the GPU it was given); a task whose Ray worker died finishes
    with ``crash(exc)``'s outcome."""
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        if address is None:
            ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=threads, num_gpus=gpus, max_retries=0)(_run_with_threads)
        running: dict[Any, Any] = {}

        def submit_ready() -> None:
            for task in graph.take_ready():
                running[remote.remote(worker, task, threads)] = task

        submit_ready()
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            task = running.pop(done[0])
            try:
                outcome = ray.get(done[0])
            except Exception as exc:  # the worker died (e.g. out of memory) or Ray failed
                outcome = crash(RuntimeError(ray_error_line(exc)))
            graph.finish(task, outcome)
            submit_ready()
    finally:
        if started:
            ray.shutdown()
