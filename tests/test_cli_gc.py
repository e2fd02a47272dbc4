"""The CLI's boundary: the collector paused while torch loads, the heap frozen while a command
runs, and both undone after it (a process running many commands, as the tests do)."""

from __future__ import annotations

import gc

import pytest

from ultron.cli.common import collector_paused, command, settled


@pytest.fixture(autouse=True)
def nothing_frozen():
    """Start from an unfrozen heap: a test that ran ``ultron.cli.main.main`` in this worker
    left its exit's ``gc.freeze`` behind."""
    gc.unfreeze()


def test_settled_freezes_then_unfreezes():
    before = gc.get_freeze_count()
    with settled():
        assert gc.get_freeze_count() > before
    assert gc.get_freeze_count() == 0


def test_settled_unfreezes_on_error():
    with pytest.raises(ValueError), settled():
        raise ValueError("boom")
    assert gc.get_freeze_count() == 0


def test_collector_paused_restores_state():
    assert gc.isenabled()
    with collector_paused():
        assert not gc.isenabled()
    assert gc.isenabled()
    gc.disable()
    try:
        with collector_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()  # was off before: stays off
    finally:
        gc.enable()


def test_settled_leaves_a_callers_freeze():
    gc.freeze()
    try:
        with settled():
            pass
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_a_command_runs_frozen_and_leaves_nothing_frozen():
    seen = []

    @command()
    def probe() -> None:
        """Record the collector's state."""
        seen.append((gc.get_freeze_count(), gc.isenabled()))

    probe()
    assert seen[0][0] > 0 and seen[0][1]
    assert gc.get_freeze_count() == 0 and gc.isenabled()
