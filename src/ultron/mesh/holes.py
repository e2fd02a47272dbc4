"""Hole filling of a compounded volume: PLUS's "stick" filler, vectorised.

PLUS (``vtkPlusFillHolesInVolume``, element ``Type="STICK"``) fills each empty voxel v from the
filled voxels around it along 13 directions d (the 3 axes, the 6 face diagonals and the 4 space
diagonals): along +d the first filled voxel is f steps away, along −d the first is r steps
away; the *stick* through v is usable when f + r + 1 ≤ L (``StickLengthLimit``: the stick's
length in voxels, both filled ends included) and its length is (f + r + 1)·|d|. The shortest
usable stick gives the value (ties: the mean of the tied sticks; ``NumberOfSticksToUse="1"``):
the linear interpolation between its two ends,

    v = (r·value₊ + f·value₋) / (f + r),

or, with ``plus_weights``, PLUS's own weighting ((r + 1)·value₊ + f·value₋) / (f + r + 1), which
leans half a voxel towards the +d end. A voxel with no usable stick stays a hole.

Instead of walking every stick from every voxel, the distance to the nearest filled voxel along
±d is computed for all voxels at once by one sweep per direction through the volume's slices
(each slice from the previous one, shifted by d): O(voxels) per direction, whatever L. The
sticks are then compared only at the holes a stick can reach: the nearer end of a usable stick
lies min(f, r) ≤ (f + r)/2 ≤ (L − 1)/2 steps from the hole, so a hole with no filled voxel
within Chebyshev distance ⌊(L − 1)/2⌋ (one separable maximum filter) keeps its hole.

Memory: about 20 bytes per voxel of working arrays (float32 steps and values along +d and −d)
besides the volume, and 16 bytes per reachable hole.
"""

from __future__ import annotations

import queue

import numpy as np

from ultron.errors import argument_error
from ultron.parallel import default_workers, thread_map

#: PLUS's 13 stick directions.
STICK_DIRECTIONS = (
    (1, 0, 0), (0, 1, 0), (0, 0, 1),
    (1, 1, 0), (1, 0, 1), (0, 1, 1),
    (1, -1, 0), (1, 0, -1), (0, 1, -1),
    (1, 1, 1), (-1, 1, 1), (1, -1, 1), (-1, -1, 1),
)  # fmt: skip


def _overlap(n: int, shift: int) -> tuple[slice, slice]:
    """(destination, source) slices of an axis of ``n`` voxels for out[i] = in[i − shift]."""
    return slice(max(shift, 0), n + min(shift, 0)), slice(max(-shift, 0), n + min(-shift, 0))


def nearest_back(
    volume: np.ndarray,
    filled: np.ndarray,
    direction: tuple[int, int, int],
    out: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """For every voxel v, the smallest j ≥ 1 with v − j·d filled (inf if none) and that
    voxel's value (0 if none), float32 volumes: one sweep through the slices along d's first
    non-zero axis, each slice from the previous one shifted by d's other components.

    ``out``: two float32 buffers of ``volume.size`` elements to write the steps and values
    into (then returned as views), so that a caller sweeping many directions reuses its
    memory instead of allocating two volumes per sweep."""
    d = np.asarray(direction, dtype=np.int64)
    axis = int(np.flatnonzero(d)[0])
    others = [a for a in range(3) if a != axis]
    order = range(volume.shape[axis]) if d[axis] > 0 else range(volume.shape[axis] - 1, -1, -1)
    vol = np.moveaxis(volume, axis, 0)
    fil = np.moveaxis(filled, axis, 0)
    (dst_b, src_b), (dst_c, src_c) = (_overlap(vol.shape[i + 1], int(d[a])) for i, a in
                                      enumerate(others))  # fmt: skip
    if out is None:
        out = tuple(np.empty(volume.size, dtype=np.float32) for _ in range(2))
    for buffer in out:
        if buffer.dtype != np.float32 or buffer.size != volume.size:
            raise argument_error("out", f"expected float32 buffers of {volume.size} elements")
    steps, values = (buffer.reshape(vol.shape) for buffer in out)
    steps.fill(np.inf)  # the border no shift reaches stays "none": inf steps, value 0
    values.fill(0.0)
    step = np.empty(vol.shape[1:], dtype=np.float32)
    value = np.empty(vol.shape[1:], dtype=np.float32)
    previous = None
    for x in order:
        if previous is not None:
            hit = fil[previous]  # copyto with ``where``: faster than boolean indexing
            np.add(steps[previous], 1.0, out=step)
            np.copyto(step, 1.0, where=hit)
            np.copyto(value, values[previous])
            np.copyto(value, vol[previous], where=hit)
            steps[x][dst_b, dst_c] = step[src_b, src_c]
            values[x][dst_b, dst_c] = value[src_b, src_c]
        previous = x
    return np.moveaxis(steps, 0, axis), np.moveaxis(values, 0, axis)


def fill_holes_stick(
    volume: np.ndarray, filled: np.ndarray, length: int, plus_weights: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Fill the holes (``~filled``) of ``volume`` with the stick filler (module doc) of
    maximum stick ``length`` voxels (≥ 3: a stick holds two filled ends and a hole).

    Returns the filled volume (float32, a copy) and the mask of the voxels it filled.
    """
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 3:
        raise argument_error("fill_holes", f"expected a stick length ≥ 3 voxels, got {length!r}")
    volume = np.asarray(volume, dtype=np.float32)
    filled = np.asarray(filled, dtype=bool)
    if volume.ndim != 3 or filled.shape != volume.shape:
        raise argument_error("filled", f"expected the volume's 3D shape {volume.shape}")
    out, new = volume.copy(), np.zeros(volume.shape, dtype=bool)
    box = filled_box(filled, 0)
    if box is not None:  # a stick's hole lies between its two filled ends: in their box
        at, values = _fill_sticks(volume[box], filled[box], length, plus_weights)
        out[box][at], new[box][at] = values, True
    return out, new


def _fill_sticks(
    volume: np.ndarray, filled: np.ndarray, length: int, plus_weights: bool
) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """:func:`fill_holes_stick` on validated arrays: the indices of the holes it fills and
    their values."""
    at = reachable_holes(filled, length)
    best = np.full(len(at[0]), np.inf, dtype=np.float32)
    total = np.zeros(len(at[0]), dtype=np.float32)
    count = np.zeros(len(at[0]), dtype=np.float32)

    # the holes' flat indices in nearest_back's own layout (its sweep axis first), so that
    # its arrays are read with one np.take each: much faster than indexing with ``at``
    flat = {}
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        moved = [volume.shape[axis]] + [volume.shape[a] for a in others]
        flat[axis] = np.ravel_multi_index((at[axis], *(at[a] for a in others)), moved)

    workers = default_workers()  # the sweeps release the GIL; a batch bounds the memory
    # one set of sweep buffers per thread, reused from direction to direction: fresh memory
    # costs more than the sweeps on a virtual machine that hands freed pages back to its host
    # (docs/decisions.md, "Fresh memory: the meshing's temporaries")
    spare: queue.SimpleQueue = queue.SimpleQueue()
    for _ in range(min(workers, len(STICK_DIRECTIONS))):
        spare.put([np.empty(volume.size, dtype=np.float32) for _ in range(2)])

    def sticks(direction: tuple[int, int, int]) -> list[np.ndarray]:
        """(back steps, back value, forward steps, forward value) at the reachable holes."""
        axis = int(np.flatnonzero(direction)[0])
        buffers = spare.get()
        try:
            found = []
            for sign in (1, -1):
                swept = nearest_back(volume, filled, tuple(sign * c for c in direction), buffers)
                found += [np.take(np.moveaxis(a, axis, 0), flat[axis]) for a in swept]
            return found
        finally:
            spare.put(buffers)

    batches = [STICK_DIRECTIONS[i : i + workers] for i in range(0, len(STICK_DIRECTIONS), workers)]
    swept = (
        pair
        for batch in batches
        for pair in zip(batch, thread_map(sticks, batch, workers), strict=True)
    )
    for direction, (back_steps, back_value, fwd_steps, fwd_value) in swept:
        span = fwd_steps + back_steps
        usable = span + 1 <= length
        with np.errstate(invalid="ignore", divide="ignore"):
            if plus_weights:
                value = ((back_steps + 1) * fwd_value + fwd_steps * back_value) / (span + 1)
            else:
                value = (back_steps * fwd_value + fwd_steps * back_value) / span
        norm = np.float32(np.sqrt(sum(c * c for c in direction)))
        stick = np.where(usable, (span + 1) * norm, np.float32(np.inf))
        shorter = stick < best
        tied = usable & (stick == best)
        best = np.where(shorter, stick, best)
        total = np.where(shorter, value, np.where(tied, total + value, total))
        count = np.where(shorter, 1.0, np.where(tied, count + 1.0, count)).astype(np.float32)
    found = count > 0
    return tuple(axis[found] for axis in at), total[found] / count[found]


def filled_box(filled: np.ndarray, margin: int) -> tuple[slice, ...] | None:
    """Slices of the smallest box holding every voxel of ``filled``, grown by ``margin`` voxels
    on each side within the volume; ``None`` when nothing is filled. Every hole either filler
    can fill lies in it (a stick between its two filled ends; a nearest fill within its
    distance), so they work on the box alone: on a sparse sweep it is a fraction of the grid."""
    axes = [np.flatnonzero(filled.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    if len(axes[0]) == 0:
        return None
    return tuple(
        slice(max(int(index[0]) - margin, 0), min(int(index[-1]) + 1 + margin, n))
        for index, n in zip(axes, filled.shape, strict=True)
    )


def reachable_holes(filled: np.ndarray, length: int) -> tuple[np.ndarray, ...]:
    """Indices (C order) of the holes of ``filled`` that a stick of at most ``length`` voxels
    can reach: those with a filled voxel within Chebyshev distance ⌊(length − 1)/2⌋ (module
    doc)."""
    from scipy import ndimage

    reach = min((length - 1) // 2, max(filled.shape))  # beyond the volume: the same mask
    near = ndimage.maximum_filter(filled.view(np.uint8), size=2 * reach + 1, mode="constant")
    return np.nonzero(~filled & (near > 0))


def fill_holes_nearest(
    volume: np.ndarray, filled: np.ndarray, max_distance_voxels: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fill every hole within ``max_distance_voxels`` of a filled voxel with the value of the
    nearest filled voxel (Euclidean, in voxels; PLUS's NEAREST_NEIGHBOR filler without its
    averaging of equidistant voxels). Returns the volume (float32, a copy) and the new mask."""
    from scipy import ndimage

    volume = np.asarray(volume, dtype=np.float32)
    filled = np.asarray(filled, dtype=bool)
    if not max_distance_voxels >= 0:
        raise argument_error("max_distance_voxels", f"expected ≥ 0, got {max_distance_voxels}")
    out, new = volume.copy(), np.zeros_like(filled)
    box = filled_box(filled, int(min(np.floor(max_distance_voxels), max(filled.shape))))
    if box is None:
        return out, new
    inside = filled[box]
    nearest = ndimage.distance_transform_edt(~inside, return_distances=False, return_indices=True)
    squared = _squared_offsets(nearest)
    within = min(_largest_square_within(max_distance_voxels), np.iinfo(squared.dtype).max)
    found = ~inside & (squared <= within)
    out[box][found] = volume[box][tuple(axis[found] for axis in nearest)]
    new[box] = found
    return out, new


def _squared_offsets(nearest: np.ndarray) -> np.ndarray:
    """|v − nearest(v)|² in voxels², exact integers, from a feature transform ``nearest``
    (ndim, *shape): what ``distance_transform_edt`` squares and sums in float64 (exactly, as
    these are integers under 2⁵³), without its five float64 volumes."""
    shape = nearest.shape[1:]
    dtype = (
        np.int32 if len(shape) * max(shape, default=0) ** 2 < np.iinfo(np.int32).max else np.int64
    )
    squared = np.zeros(shape, dtype=dtype)
    for axis, n in enumerate(shape):
        offset = nearest[axis].astype(dtype)
        offset -= np.arange(n, dtype=dtype).reshape(
            [n if a == axis else 1 for a in range(len(shape))]
        )
        offset *= offset
        squared += offset
    return squared


def _largest_square_within(radius: float) -> int:
    """The largest integer k with √k ≤ ``radius`` as float64 computes it (−1 when none):
    √ is monotone, so |d|² ≤ k exactly when the Euclidean distance √|d|² ≤ ``radius``."""
    square = float(radius) * float(radius)
    if not square < 2.0**62:  # beyond any distance in a grid that fits in memory
        return int(np.iinfo(np.int64).max)
    k = int(np.floor(square))
    while k >= 0 and np.sqrt(np.float64(k)) > radius:
        k -= 1
    while np.sqrt(np.float64(k + 1)) <= radius:
        k += 1
    return k
