"""Run bookkeeping shared by every stage: wall-clock seconds per named stage, peak memory."""

from __future__ import annotations

import resource
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: Told each stage's name as it starts (seconds None) and again with its seconds as it ends.
Announce = Callable[[str, "float | None"], None]
#: Told how far the running stage has come: (stage name, units done, units in all, unit).
Advance = Callable[[str, int, int, str], None]
#: What a long step of a stage calls as it proceeds: (units done, units in all).
Advanced = Callable[[int, int], None]


@dataclass
class StageTimer:
    """Wall-clock seconds per named stage, in the order they ran; ``announce`` (optional) is
    told as each stage starts and ends (e.g. to print progress lines), ``advance`` (optional)
    how far the running stage has come (:meth:`advanced`)."""

    seconds: dict[str, float] = field(default_factory=dict)
    announce: Announce | None = field(default=None, compare=False, repr=False)
    advance: Advance | None = field(default=None, compare=False, repr=False)
    _running: list[str] = field(default_factory=list, compare=False, repr=False)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        if self.announce is not None:
            self.announce(name, None)
        self._running.append(name)
        try:
            yield
        finally:
            self._running.pop()
            elapsed = time.perf_counter() - start
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed
            if self.announce is not None:
                self.announce(name, elapsed)

    def advanced(self, done: int, total: int, unit: str = "") -> None:
        """Tell ``advance`` that the running stage has done ``done`` of ``total`` ``unit``s
        (nothing outside a stage or without ``advance``)."""
        if self.advance is not None and self._running:
            self.advance(self._running[-1], int(done), int(total), unit)

    def counter(self, unit: str) -> Advanced:
        """:meth:`advanced` for one kind of unit, as a long step's ``advance`` callback."""

        def advanced(done: int, total: int) -> None:
            self.advanced(done, total, unit)

        return advanced

    def fit_progress(self, entry: Mapping[str, Any]) -> None:
        """A fit's :data:`~ultron.train.loop.Progress` callback: its updates as the units
        ("steps", or "steps of NAME" for a fit that names its part, e.g. RoCoSDF's views)."""
        part = entry.get("stage")
        unit = "steps" if part is None else f"steps of {part}"
        self.advanced(int(entry["step"]), int(entry["iterations"]), unit)

    @property
    def total(self) -> float:
        return sum(self.seconds.values())
