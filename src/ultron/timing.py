"""Run bookkeeping shared by every stage: wall-clock seconds per named stage, peak memory."""

from __future__ import annotations

import resource
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: Told each stage's name as it starts (seconds None) and again with its seconds as it ends.
Announce = Callable[[str, "float | None"], None]


@dataclass
class StageTimer:
    """Wall-clock seconds per named stage, in the order they ran; ``announce`` (optional) is
    told as each stage starts and ends (e.g. to print progress lines)."""

    seconds: dict[str, float] = field(default_factory=dict)
    announce: Announce | None = field(default=None, compare=False, repr=False)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        if self.announce is not None:
            self.announce(name, None)
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            self.seconds[name] = self.seconds.get(name, 0.0) + elapsed
            if self.announce is not None:
                self.announce(name, elapsed)

    @property
    def total(self) -> float:
        return sum(self.seconds.values())
