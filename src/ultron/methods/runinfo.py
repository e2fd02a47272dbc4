"""Run bookkeeping: stage timings, peak memory, versions, and the run's output files."""

from __future__ import annotations

import platform
import resource
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ultron import __version__, atomic


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def versions() -> dict[str, str]:
    """Versions of ultron, Python and the libraries that shape the numbers."""
    import mcubes
    import numpy
    import scipy
    import torch
    import trimesh

    return {
        "ultron": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "trimesh": trimesh.__version__,
        "pymcubes": getattr(mcubes, "__version__", "unknown"),
        "torch_threads": str(torch.get_num_threads()),
    }


@dataclass
class StageTimer:
    """Wall-clock seconds per named stage, in the order they ran."""

    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start

    @property
    def total(self) -> float:
        return sum(self.seconds.values())


def write_run_json(out_dir: Path, payload: dict[str, Any], timer: StageTimer) -> Path:
    """Write DIR/run.json with the payload, timings, peak memory and versions."""
    data = {
        **payload,
        "timings_s": {**timer.seconds, "total": timer.total},
        "peak_rss_mb": peak_rss_mb(),
        "versions": versions(),
    }
    path = Path(out_dir) / "run.json"
    atomic.write_json(path, data)
    return path
