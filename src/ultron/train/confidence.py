"""Ultrasound confidence maps (Karamalis et al. 2012): the ``confidence`` source of stage 2's
transmission T (:mod:`ultron.train.visibility`) and the field fit's confidence prior
(:mod:`ultron.train.frames`), computed with MONAI's port of the authors' code and a symmetric
sparse solve (docs/decisions.md#confidence-maps-threads-trainconfidencepy)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ultron.arguments import check_finite
from ultron.errors import UltronError, argument_error


@dataclass(frozen=True)
class ConfidenceConfig:
    """Karamalis et al. 2012's parameters (their B-mode defaults, also MONAI's): ``alpha`` the
    attenuation weighting, ``beta`` the edge-weight sensitivity, ``gamma`` the horizontal
    penalty."""

    alpha: float = 2.0
    beta: float = 90.0
    gamma: float = 0.05

    def __post_init__(self) -> None:
        check_finite("confidence.alpha", self.alpha, 0.0, strict=False)
        check_finite("confidence.beta", self.beta, 0.0, strict=True)
        check_finite("confidence.gamma", self.gamma, 0.0, strict=False)


def solver_description() -> str:
    """What computes :func:`confidence_map`: MONAI's release and the solve (for records)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"monai {version('monai')} UltrasoundConfidenceMap, SuperLU symmetric mode"
    except PackageNotFoundError:
        return "monai (not installed)"


def confidence_map(image: np.ndarray, config: ConfidenceConfig | None = None) -> np.ndarray:
    """Ultrasound confidence map C (H, W) float32 ∈ [0, 1] of one B-mode frame (row 0 at the
    transducer): Karamalis, Wein, Klein, Navab, "Ultrasound confidence maps using random walks",
    Med. Image Anal. 16 (2012) 1101–1112, computed with MONAI's port of the authors' code.

    The frame c (normalised to [0, 1], times the depth weighting 1 − exp(−α·r/(H − 1)) of the
    authors' code) is a graph of 8-connected pixels with edge weights
        w_ij = exp(−β·g_ij) + ε,   g_ij = |c_i − c_j| normalised to [0, 1], + γ on the edges
                                   that are not vertical (the horizontal penalty), renormalised,
    and L = D − W its weighted graph Laplacian (D the weighted degrees). C_i is the probability
    that a random walker starting at pixel i reaches the transducer row before the bottom row:
    the Dirichlet problem with C = 1 on row 0 and C = 0 on row H − 1,
        L_U C_U = −B^T C_M
    (U the unmarked pixels, M the marked ones, B the U × M block of L), solved exactly by a
    sparse LU factorisation. L_U is symmetric positive definite, so the factorisation takes
    SuperLU's symmetric mode (minimum-degree ordering of L_U + L_Uᵀ, diagonal pivots) instead
    of MONAI's general one: the same solution to ≈ 1e-12 in less time (docs/decisions.md).
    A bright reflector (a bone surface) is a strong barrier to the walk, so C drops under it:
    acoustic shadow.
    """
    cfg = config or ConfidenceConfig()
    image = np.asarray(image)
    if image.ndim != 2 or min(image.shape) < 3:
        raise argument_error("image", f"expected an (H, W) frame with H, W ≥ 3, got {image.shape}")
    if not np.isfinite(image).all():
        raise argument_error("image", "contains NaN or infinite values")
    solver = _symmetric_confidence_map()(
        alpha=cfg.alpha, beta=cfg.beta, gamma=cfg.gamma, mode="B", sink_mode="all"
    )
    result = np.asarray(solver(image.astype(np.float64)), dtype=np.float64)
    return np.clip(result.reshape(image.shape), 0.0, 1.0).astype(np.float32)


@functools.cache
def _symmetric_confidence_map() -> type:
    """MONAI's ``UltrasoundConfidenceMap`` with its linear solve L_U x = r done by SuperLU in
    symmetric mode (:func:`confidence_map`); everything else, the Laplacian included, MONAI's."""
    try:
        from monai.data.ultrasound_confidence_map import UltrasoundConfidenceMap
    except ImportError:
        raise UltronError(
            "the 'confidence' visibility needs MONAI: pip install 'monai>=1.6'"
        ) from None
    from scipy.sparse.linalg import splu

    class SymmetricConfidenceMap(UltrasoundConfidenceMap):
        def _solve_linear_system(self, lap: Any, rhs: Any) -> np.ndarray:
            factor = splu(
                lap.tocsc(),
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
            return factor.solve(np.asarray(rhs, dtype=np.float64).reshape(-1))

    return SymmetricConfidenceMap


def confidence_maps(
    images: np.ndarray,
    config: ConfidenceConfig | None = None,
    workers: int = 1,
    report: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """:func:`confidence_map` of every frame (N, H, W) → float32 (N, H, W), ``workers`` frames
    at a time on threads (the sparse solve releases the GIL, so the threads run in parallel;
    the maps are the same; timings in docs/decisions.md#confidence-maps-threads-trainconfidencepy);
    ``report`` is told (done, N) as frames finish, in order."""
    from concurrent.futures import ThreadPoolExecutor

    cfg = config or ConfidenceConfig()
    images = np.asarray(images)
    if images.ndim != 3:
        raise argument_error("images", f"expected (N, H, W) frames, got shape {images.shape}")
    total = len(images)
    out = np.empty(images.shape, dtype=np.float32)
    if report is not None:
        report(0, total)
    with ThreadPoolExecutor(max(1, int(workers))) as pool:
        maps = pool.map(lambda image: confidence_map(image, cfg), images)
        for index, value in enumerate(maps):
            out[index] = value
            if report is not None:
                report(index + 1, total)
    return out
