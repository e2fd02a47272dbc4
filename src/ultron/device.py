"""Where a run computes: ``--device auto|cpu|cuda|cuda:N|mps``.

The rule of the code base: a network or field lives on one device (the run's); public
functions that evaluate it take inputs on any device and return results on the CPU (numpy or
CPU tensors), so that data handling, meshing and metrics never see a device. Training loops
move their data to the module's device once; their random draws (batches, scatterer noise,
minibatch orders) come from seeded CPU generators and are moved after drawing, so a run draws
the same batches on every device and a checkpointed generator resumes on any device. On the
CPU every such move is a no-op, so ``--device cpu`` reproduces the figures of a build without
this option exactly.

Modules are always *built* on the CPU (the same seed gives the same initial weights on every
device) and then moved; checkpoints are written from CPU copies and loaded with
``map_location``, so a model saved on one device loads on any other.
"""

from __future__ import annotations

import itertools
import platform
from collections.abc import Callable
from typing import Any

import torch

from ultron.arguments import check_integer
from ultron.errors import UltronInputError

CPU = torch.device("cpu")


def _mps_available() -> bool:
    backend = getattr(torch.backends, "mps", None)
    return bool(backend is not None and backend.is_available())


def resolve_device(
    spec: str | torch.device | None = "auto", option: str = "--device"
) -> torch.device:
    """The torch device of ``spec``: ``auto`` (CUDA when available, else the CPU),
    ``cpu``, ``cuda``, ``cuda:N`` or ``mps``; a device object passes through (checked the same
    way). A malformed or unavailable device is a one-line :class:`UltronInputError` naming
    ``option``."""
    if isinstance(spec, torch.device):
        text = str(spec)
    elif spec is None:
        text = "auto"
    elif isinstance(spec, str):
        text = spec.strip().lower()
    else:
        raise UltronInputError("argument", option, f"expected a device name, got {spec!r}")
    if text == "auto":  # MPS only when asked: it has no float64, and is less tested
        return torch.device("cuda") if torch.cuda.is_available() else CPU
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda", "mps"):
        raise UltronInputError(
            "argument", option, f"expected auto, cpu, cuda, cuda:N or mps, got {spec!r}"
        )
    if device.type == "cpu":
        return CPU
    if device.type == "mps":
        if not _mps_available():
            raise UltronInputError("argument", option, "mps is not available on this machine")
        return device
    if not torch.cuda.is_available():
        raise UltronInputError(
            "argument",
            option,
            f"{text} is not available: this torch build ({torch.__version__}) sees no CUDA"
            " device; use --device cpu",
        )
    index = 0 if device.index is None else device.index
    count = torch.cuda.device_count()
    if index >= count:
        raise UltronInputError(
            "argument", option, f"{text} is not available: this machine has {count} CUDA device(s)"
        )
    return device


def describe_device(device: torch.device) -> dict[str, Any]:
    """What run.json and field.json record of ``device``: its name (``cpu``, ``cuda:0``, …),
    the accelerator's model where there is one, and the torch version."""
    record: dict[str, Any] = {"device": str(device), "torch": torch.__version__}
    if device.type == "cuda":
        index = torch.cuda.current_device() if device.index is None else device.index
        record["device"] = f"cuda:{index}"
        record["accelerator"] = torch.cuda.get_device_name(index)
    elif device.type == "cpu":
        record["accelerator"] = platform.processor() or platform.machine()
    else:
        record["accelerator"] = device.type
    return record


def native_bfloat16(device: torch.device) -> bool:
    """Whether ``device`` multiplies bfloat16 natively. On a CPU this is oneDNN's own test
    (AVX512-BF16 or AMX, and not capped by ``ONEDNN_MAX_CPU_ISA``; False where this torch
    lacks the test); on CUDA :func:`torch.cuda.is_bf16_supported`; elsewhere True. Without
    native products torch emulates them, far more slowly than float32."""
    if device.type == "cpu":
        test = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
        return bool(test()) if test is not None else False
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    return True


def module_device(module: torch.nn.Module) -> torch.device:
    """The device of ``module``'s first parameter or buffer (the CPU for one without any)."""
    first = next(itertools.chain(module.parameters(), module.buffers()), None)
    return CPU if first is None else first.device


#: How many times larger an evaluation chunk is on an accelerator than on the CPU: the CPU
#: chunks are sized for its caches and memory, a GPU wants far more points per kernel launch.
ACCELERATOR_CHUNK_FACTOR = 16


def evaluation_chunk(device: torch.device | None, cpu_chunk: int) -> int:
    """Points per chunk when evaluating a network on ``device``: ``cpu_chunk`` on the CPU (and
    for None), ×:data:`ACCELERATOR_CHUNK_FACTOR` elsewhere. Chunking never changes a result
    beyond float reassociation (every point is evaluated independently)."""
    if device is None or device.type == "cpu":
        return cpu_chunk
    return cpu_chunk * ACCELERATOR_CHUNK_FACTOR


def map_chunks(
    fn: Callable[[torch.Tensor], torch.Tensor],
    inputs: torch.Tensor,
    chunk: int,
    device: torch.device | str | None = None,
    empty: torch.Tensor | None = None,
    gradients: bool = False,
) -> torch.Tensor:
    """``fn`` over consecutive row chunks of ``inputs`` (at most ``chunk`` rows each), without
    gradients unless ``gradients`` — the one chunked evaluator of the code base. Each chunk is
    moved to ``device`` (None: left where it is), each result to the CPU, and the results are
    concatenated along their first axis; ``inputs`` without rows give ``empty`` (default: a
    float32 (0,))."""
    check_integer("chunk", chunk, 1)
    parts = []
    with torch.set_grad_enabled(gradients and torch.is_grad_enabled()):
        for start in range(0, inputs.shape[0], chunk):
            part = inputs[start : start + chunk]
            parts.append(fn(part if device is None else part.to(device)).cpu())
    if not parts:
        return torch.zeros(0) if empty is None else empty
    return torch.cat(parts)


def cpu_state(state: Any) -> Any:
    """``state`` (a state dict, possibly nested) with every tensor copied to the CPU, for a
    checkpoint that loads anywhere."""
    if torch.is_tensor(state):
        return state.detach().cpu()
    if isinstance(state, dict):
        return {k: cpu_state(v) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(cpu_state(v) for v in state)
    return state


__all__ = [
    "CPU",
    "cpu_state",
    "describe_device",
    "evaluation_chunk",
    "map_chunks",
    "module_device",
    "resolve_device",
]
