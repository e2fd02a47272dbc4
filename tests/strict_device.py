"""A dispatch mode that refuses, as CUDA does, an operation mixing tensors of two devices.

PyTorch's ``meta`` device alone lets many kernels (matmul, gather, …) take CPU operands, so
running a compute path on ``meta`` does not prove it device-correct. Under
:class:`StrictDevices` every aten operation checks its tensor arguments: all of one device,
except 0-dim CPU tensors (which CUDA accepts too), the copies that move data between
devices, and the CPU index tensors of advanced indexing (which CUDA moves itself).
"""

from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

aten = torch.ops.aten
#: Operations that may legitimately see two devices.
CROSS_DEVICE_OPS = {
    aten._to_copy.default,
    aten.copy_.default,
    aten.index.Tensor,
    aten.index_put_.default,
    aten.index_put.default,
    aten._index_put_impl_.default,
    aten.lift_fresh.default,
    aten._local_scalar_dense.default,
}


class StrictDevices(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func not in CROSS_DEVICE_OPS:
            flat, _ = tree_flatten((args, kwargs))
            devices = {
                t.device
                for t in flat
                if isinstance(t, torch.Tensor) and not (t.dim() == 0 and t.device.type == "cpu")
            }
            if len(devices) > 1:
                raise RuntimeError(f"{func} mixes devices {sorted(map(str, devices))}")
        return func(*args, **kwargs)
