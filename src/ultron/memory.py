"""How much memory this process may use: the machine's, the cgroup's limit and what the
address-space limit (``ulimit -v``) leaves, or what the user gives (``--max-memory``).

A base module (like :mod:`ultron.device`): the readers refuse a file that would not fit before
allocating it, and :mod:`ultron.pipeline.resources` plans runs against the same limit.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ultron.arguments import check_range

_GIB = 1024**3


def machine_memory_bytes() -> int | None:
    """Physical memory, or the cgroup's memory limit where lower; None if unknown."""
    limits = []
    try:
        limits.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text(encoding="ascii").strip()
        except OSError:
            continue
        if text.isdigit() and int(text) > 0:
            limits.append(int(text))
    return min(limits) if limits else None


def address_space_left_bytes() -> int | None:
    """Under an address-space limit (``ulimit -v``, RLIMIT_AS): the limit less the address
    space this process already maps (/proc/self/status ``VmSize``: torch alone maps a few
    GiB it never touches); None without a limit or where it cannot be read."""
    try:
        import resource

        soft, _hard = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, ValueError, OSError):
        return None
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return None
    mapped = 0
    try:
        for line in Path("/proc/self/status").read_text(encoding="ascii").splitlines():
            if line.startswith("VmSize:"):
                mapped = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return max(0, soft - mapped)


def memory_limit(max_memory_gib: float | None = None) -> tuple[float, str]:
    """The memory a run may plan for, bytes (inf if unknown), and how to name it: the
    ``--max-memory`` given, else the least of the machine's memory, the cgroup's limit and what
    the address-space limit leaves (:func:`address_space_left_bytes`). A given
    ``max_memory_gib`` must be a finite number > 0 (every run plans against this limit before
    any work, so that is where it is checked)."""
    check_range("max_memory_gib", max_memory_gib, 0.0, low_open=True)
    if max_memory_gib is not None:
        return max_memory_gib * _GIB, f"--max-memory {max_memory_gib:g} GiB"
    machine = machine_memory_bytes()
    left = address_space_left_bytes()
    if left is not None and (machine is None or left < machine):
        name = f"what the address-space limit (ulimit -v) leaves ({left / _GIB:.2f} GiB)"
        return float(left), name
    if machine is None:
        return math.inf, "this machine's memory"
    return float(machine), f"this machine's memory ({machine / _GIB:.1f} GiB)"


def check_fits_in_memory(n_bytes: float, where: str | Path, field: str, what: str) -> None:
    """Refuse (one :class:`UltronInputError` naming ``where`` and ``field``) to allocate
    ``n_bytes`` for ``what`` when that exceeds the memory this process may use."""
    from ultron.errors import UltronInputError

    limit, name = memory_limit()
    if n_bytes > limit:
        raise UltronInputError(
            where, field, f"{what} would take {n_bytes / _GIB:.3g} GiB, more than {name}"
        )


#: glibc ``mallopt`` parameters (malloc.h), the heap kept free for reuse before trimming, and
#: glibc's own values restored afterwards (DEFAULT_MMAP_MAX, DEFAULT_TRIM_THRESHOLD).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_KEEP_FREE_BYTES = 256 * 2**20
_GLIBC_MMAP_MAX, _GLIBC_TRIM_BYTES = 65536, 128 * 1024


def _mallopt(mmap_max: int, trim_bytes: int) -> bool:
    """Set glibc malloc's ``M_MMAP_MAX`` and ``M_TRIM_THRESHOLD``; False off glibc."""
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_MMAP_MAX, mmap_max)) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, trim_bytes)
        )
    except (OSError, AttributeError):
        return False


@contextmanager
def freed_memory_reused() -> Iterator[bool]:
    """Within the block, glibc's malloc serves every block from its heap and keeps up to
    256 MiB of freed heap for reuse (``mallopt``: no ``mmap``'d blocks); elsewhere it maps
    each large block afresh and hands it back to the kernel when freed, so a training step
    that allocates its gradients anew faults all of it in again (figures:
    docs/decisions.md#the-allocator-freed-memory-kept-for-reuse-memorypy). The training loop
    runs in it; glibc's own limits are restored on leaving (freed heap is then returned).
    Yields whether it applied (False off glibc). A process setting: not for threads that
    train at the same time."""
    applied = _mallopt(0, _KEEP_FREE_BYTES)
    try:
        yield applied
    finally:
        if applied:
            _mallopt(_GLIBC_MMAP_MAX, _GLIBC_TRIM_BYTES)
