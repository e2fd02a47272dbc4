"""CPU threads for numpy / scipy work that releases the GIL (EDT, sparse products)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from ultron.errors import argument_error

T = TypeVar("T")
R = TypeVar("R")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` elsewhere), ≥ 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch on ``n`` CPU threads within the block; the previous count is restored after it,
    also when the block fails."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def default_workers() -> int:
    """Threads for numpy / scipy work: torch's thread count (what ``--threads`` or a benchmark
    worker's share of the cores set), at most the available cores."""
    import torch

    return max(1, min(available_cores(), torch.get_num_threads()))


def thread_map(
    function: Callable[[T], R], items: Iterable[T], workers: int | None = None
) -> list[R]:
    """``[function(item) for item in items]``, in order, on ``workers`` threads (``None``:
    :func:`default_workers`; 1: in this thread). Worth it only where ``function`` releases the
    GIL."""
    if workers is None:
        workers = default_workers()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise argument_error("workers", f"expected a positive integer or None, got {workers!r}")
    items = list(items)
    if workers == 1 or len(items) < 2:
        return [function(item) for item in items]
    with ThreadPoolExecutor(min(workers, len(items))) as pool:
        return list(pool.map(function, items))
