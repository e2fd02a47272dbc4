"""ultron.parallel: thread_map keeps the order and the results; bad worker counts are refused."""

from __future__ import annotations

import threading

import pytest
import torch

from ultron.errors import UltronInputError
from ultron.parallel import available_cores, default_workers, thread_map


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


def test_default_workers_follow_torch_threads():
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # --threads 1: numpy work on one thread too
        assert default_workers() == 1
        torch.set_num_threads(available_cores() + 3)  # never more than the cores
        assert default_workers() == available_cores()
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize("workers", [0, -1, 1.5, True, "2"])
def test_thread_map_refuses_bad_worker_counts(workers):
    with pytest.raises(UltronInputError, match="workers"):
        thread_map(lambda x: x, [1, 2], workers=workers)
