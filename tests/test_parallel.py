"""ultron.parallel: thread_map keeps the order and the results; bad worker counts are refused."""

from __future__ import annotations

import threading

import pytest

from ultron.errors import UltronInputError
from ultron.parallel import available_cores, thread_map


def test_thread_map_keeps_order_and_runs_on_threads():
    seen: set[int] = set()
    barrier = threading.Barrier(2, timeout=10)

    def work(item: int) -> int:
        seen.add(threading.get_ident())
        if item < 2:
            barrier.wait()  # both first items run at once, on two threads, or this times out
        return item * item

    assert thread_map(work, range(7), workers=2) == [i * i for i in range(7)]
    assert len(seen) == 2


def test_thread_map_one_worker_runs_here_and_empty_input():
    here = threading.get_ident()
    assert thread_map(lambda _: threading.get_ident(), [1, 2, 3], workers=1) == [here] * 3
    assert thread_map(lambda x: x, [], workers=3) == []
    assert available_cores() >= 1


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_thread_map_refuses_bad_worker_counts(workers):
    with pytest.raises(UltronInputError, match="workers"):
        thread_map(lambda x: x, [1, 2], workers=workers)
