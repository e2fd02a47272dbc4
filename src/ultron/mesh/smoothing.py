"""Constrained smoothing of a binary volume's 0.5 level set (Lempitsky, CVPR 2010).

This is PyMCubes' ``smooth_constrained`` (the method ``mcubes.smooth`` picks for volumes under
500³) with its sparse system assembled by vectorised numpy instead of PyMCubes' Python loop over
voxels into a ``lil_matrix``, which is slow and memory-hungry on the demo's crop (figures in
docs/decisions.md#constrained-smoothing-pymcubes-matrix-meshsmoothingpy). The energy,
constraints, band, Jacobi iteration and stopping rule are PyMCubes' own, and
``tests/test_mesh.py`` checks that both give the same embedding.

Energy: with u the embedding on the band B = {|d| ≤ band_radius} around the 0.5 level set (d the
signed Euclidean distance, positive inside, ±0.5 at the border voxels) and D_a the second
difference along axis a (a missing neighbour contributes the voxel itself, i.e. a Neumann
boundary), minimise

    E(u) = ½ Σ_a ‖D_a u‖² = ½ uᵀ Q u,   Q = Σ_a D_aᵀ D_a,

subject to u ≥ d where d > 0 (inside stays inside), u ≤ d where d < 0, with bounds of magnitude
< 1 relaxed to 0, by damped Jacobi (weight ½) with the bounds projected after every step, until
the energy improves by less than ``rel_tol`` per iteration (checked every 10) or ``max_iters``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import torch
from scipy import sparse

from ultron.errors import argument_error


def second_difference_system(band: np.ndarray) -> sparse.csr_matrix:
    """Q = Σ_a D_aᵀ D_a over the voxels of ``band`` (in C order), D_a as in the module doc."""
    band = np.asarray(band, dtype=bool)
    if band.ndim != 3:
        raise argument_error("band", f"expected a 3D boolean array, got shape {band.shape}")
    return band_second_differences(np.flatnonzero(band), np.asarray(band.shape))


def band_second_differences(keys: np.ndarray, shape: np.ndarray) -> sparse.csr_matrix:
    """Q = Σ_a D_aᵀ D_a (module doc) over the band whose voxels have the sorted C-order
    ``keys`` in a box of ``shape``: the band need not be held densely (the tiled extraction).

    Q's entries are written out rather than multiplied: with p(i), n(i) voxel i's band
    neighbours along axis a and s_i = −2 + [no p(i)] + [no n(i)] its row's centre in D_a,

        Q_ii += s_i² + [p(i)] + [n(i)],   Q_{i,n(i)} += s_i + s_{n(i)},   Q_{i,n(n(i))} += 1,

    and the same towards p (every entry a small integer, so exactly DᵀD's)."""
    n = len(keys)
    coords = np.unravel_index(keys, tuple(shape))
    strides = (shape[1] * shape[2], shape[2], 1)
    # 13 slots a row (the diagonal; per axis and side the neighbour and the one beyond), in the
    # order of their keys' offsets; an absent one keeps column −1. The entries are integers in
    # [−4, 18]: int8 slots, and int32 columns where they fit, take a fifth of the memory of
    # float64 and int64 ones (docs/decisions.md, "Fresh memory: the meshing's temporaries")
    index = np.int32 if 13 * n < np.iinfo(np.int32).max else np.int64
    cols = np.full((n, 13), -1, dtype=index)
    vals = np.zeros((n, 13), dtype=np.int8)
    cols[:, 6] = np.arange(n)
    for axis in range(3):
        neighbours = []
        for offset in (-1, 1):
            along = coords[axis] + offset
            target = keys + offset * strides[axis]
            found = np.minimum(np.searchsorted(keys, target), max(n - 1, 0))
            present = (along >= 0) & (along < shape[axis])
            if n:
                present &= keys[found] == target
            neighbours.append(np.where(present, found, -1))
        centre = (neighbours[0] < 0).astype(np.int8) + (neighbours[1] < 0) - 2
        vals[:, 6] += centre**2 + (neighbours[0] >= 0) + (neighbours[1] >= 0)
        for side, near in zip((-1, 1), neighbours, strict=True):
            slot = (1, 3, 5)[axis] if side < 0 else (11, 9, 7)[axis]  # the beyond: slot + side
            i = np.flatnonzero(near >= 0)
            j = near[i]
            cols[i, slot], vals[i, slot] = j, centre[i] + centre[j]
            beyond = near[j] >= 0
            cols[i[beyond], slot + side], vals[i[beyond], slot + side] = near[j[beyond]], 1
    kept = vals != 0  # an isolated voxel's zero diagonal is left out, as DᵀD leaves it
    indptr = np.zeros(n + 1, dtype=index)
    np.cumsum(np.count_nonzero(kept, axis=1), out=indptr[1:])
    q = sparse.csr_matrix(
        (vals[kept].astype(np.float64), cols[kept], indptr), shape=(n, n), copy=False
    )
    q.sort_indices()  # in key order already unless the box is under 3 voxels along an axis
    return q


def smooth_constrained(
    binary: np.ndarray, band_radius: int = 4, max_iters: int = 500, rel_tol: float = 1e-6
) -> np.ndarray:
    """Smooth embedding (float64, positive inside, zero level on the smoothed surface).

    Same result as ``mcubes.smooth_constrained(binary, band_radius, max_iters, rel_tol)``.
    """
    from mcubes.smoothing import signed_distance_function

    binary = np.asarray(binary)
    if binary.ndim != 3:
        raise argument_error("binary", f"expected a 3D array, got shape {binary.shape}")
    if band_radius < 1:
        raise argument_error("band_radius", f"expected ≥ 1, got {band_radius}")
    distance, _, band = signed_distance_function(binary, band_radius)
    q = second_difference_system(band)
    result = np.asarray(distance, dtype=np.float64)
    x = result[band]
    upper = np.where(x < 0, x, np.inf)
    lower = np.where(x > 0, x, -np.inf)
    upper[np.abs(upper) < 1] = 0
    lower[np.abs(lower) < 1] = 0
    result[band] = projected_jacobi(q, x, lower, upper, max_iters, rel_tol, overwrite_q=True)
    return result


def projected_jacobi(
    q: sparse.csr_matrix,
    x: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    max_iters: int,
    rel_tol: float,
    weight: float = 0.5,
    advance: Callable[[int, int], None] | None = None,
    overwrite_q: bool = False,
) -> np.ndarray:
    """x ← clip(w·(−D⁻¹(Q − D)x) + (1 − w)·x, lower, upper), D = diag(Q).

    The step is one sparse product with J = (1 − w)·I − w·D⁻¹(Q − D), assembled once (the
    same non-zeros as Q), so an iteration reads the matrix once and allocates nothing; the
    result equals the step written out to rounding (docs/decisions.md, "Constrained
    smoothing"). The product runs on torch's threads (a CSR tensor with 32-bit indices; scipy's is
    single-threaded), in float64. The energy ½ xᵀQx checked every ``check_each`` steps reuses
    that step's product y = Jx, since Qx = D(x − y)/w: no second product. ``advance``, when
    given, is told (iterations done, ``max_iters``) at every energy check. ``overwrite_q``:
    J is assembled in Q's own arrays (:func:`jacobi_step_matrix`), when the caller is done
    with Q."""
    diagonal = q.diagonal()
    matrix = _torch_csr(jacobi_step_matrix(q, weight, overwrite_q))
    x = torch.from_numpy(np.array(x, dtype=np.float64))
    y = torch.empty_like(x)
    bounds = [torch.from_numpy(np.asarray(b, dtype=np.float64)) for b in (lower, upper)]
    diagonal = torch.from_numpy(diagonal)
    check_each = 10
    cumulative_tol = 1 - (1 - rel_tol) ** check_each
    energy = None
    for i in range(max_iters + 1):
        torch.mv(matrix, x, out=y)
        if i % check_each == 0:  # the energy of x, the iterate after i steps
            if advance is not None:
                advance(i, max_iters)
            previous, energy = energy, float(x @ (diagonal * (x - y))) / (2 * weight)
            if previous is not None and (
                previous <= 0 or (previous - energy) / previous < cumulative_tol
            ):
                break
        if i == max_iters:
            break
        torch.clamp(y, *bounds, out=y)
        x, y = y, x
    return x.numpy()


def jacobi_step_matrix(
    q: sparse.csr_matrix, weight: float, overwrite_q: bool = False
) -> sparse.csr_matrix:
    """J = (1 − w)·I − w·D⁻¹(Q − D), D = diag(Q), with sorted indices: J_ij = (−w / Q_ii)·Q_ij
    off the diagonal, 1 − w on it. Scaled on Q's own entries (the same products, so the same
    bits, as the sparse expression) when Q holds every diagonal entry, a run of rows at a time
    so that the temporaries stay small; otherwise (an isolated voxel's empty row) by the sparse
    expression. ``overwrite_q`` (as scipy.linalg's ``overwrite_a``): J is written into Q's
    arrays, which it then shares, instead of a copy of them (a band of 10⁶ voxels: 0.1 GB)."""
    diagonal = q.diagonal()
    q = q.tocsr()
    q.sort_indices()
    chunks = [(a, min(a + _ROWS_AT_ONCE, q.shape[0])) for a in range(0, q.shape[0], _ROWS_AT_ONCE)]
    on_diagonal = [_on_diagonal(q, a, b) for a, b in chunks]
    if sum(np.count_nonzero(on) for on in on_diagonal) == q.shape[0]:
        scale = -weight / diagonal
        data = q.data if overwrite_q else np.empty_like(q.data)
        for (a, b), on in zip(chunks, on_diagonal, strict=True):
            lo, hi = q.indptr[a], q.indptr[b]
            part = data[lo:hi]
            np.multiply(
                np.repeat(scale[a:b], np.diff(q.indptr[a : b + 1])), q.data[lo:hi], out=part
            )
            part[on] = 1 - weight
        arrays = (q.indices, q.indptr) if overwrite_q else (q.indices.copy(), q.indptr.copy())
        return sparse.csr_matrix((data, *arrays), shape=q.shape, copy=False)
    step = sparse.diags(-weight / diagonal) @ (q - sparse.diags(diagonal))
    step = (step + sparse.identity(len(diagonal)) * (1 - weight)).tocsr()
    step.sort_indices()
    return step


#: Rows of Q scaled at once by :func:`jacobi_step_matrix`.
_ROWS_AT_ONCE = 1 << 16


def _on_diagonal(q: sparse.csr_matrix, a: int, b: int) -> np.ndarray:
    """Which stored entries of rows [a, b) of the CSR ``q`` lie on its diagonal."""
    rows = np.repeat(np.arange(a, b, dtype=q.indices.dtype), np.diff(q.indptr[a : b + 1]))
    return q.indices[q.indptr[a] : q.indptr[b]] == rows


def _torch_csr(matrix: sparse.csr_matrix) -> torch.Tensor:
    """``matrix`` as a torch CSR tensor (32-bit indices where they fit: the faster kernel)."""
    index = np.int32 if matrix.nnz < np.iinfo(np.int32).max else np.int64
    with warnings.catch_warnings():  # "… is in beta state"; "Sparse invariant checks are
        # implicitly disabled" (torch 2.11, although check_invariants is given)
        for message in ("Sparse CSR tensor support", "Sparse invariant checks"):
            warnings.filterwarnings("ignore", message=message, category=UserWarning)
        return torch.sparse_csr_tensor(
            torch.from_numpy(matrix.indptr.astype(index, copy=False)),
            torch.from_numpy(matrix.indices.astype(index, copy=False)),
            torch.from_numpy(matrix.data),
            size=matrix.shape,
            check_invariants=False,
        )
