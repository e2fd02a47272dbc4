"""RoCoSDF's SDF fitting (ROCOSDF.md): Neural-Pull per view, CSG fusion, refinement.

All coordinates are normalised (the data in ≈ [−0.5, 0.5]³). Notation: f the SDF network,
q a query point, p = p_nn(q) its nearest input point, n̂ = ∇f(q)/‖∇f(q)‖.

Stage 1 (:func:`fit_view_sdf`, UNSR / Neural-Pull with RoCoSDF's extra terms), per step on a
batch of queries:

    q′     = q − f(q)·n̂                                             (pull_points)
    L_pull = mean ‖q′ − p‖                  (Euclidean, not squared) (pull_loss)
    L_scc  = mean[(1 − cos(n̂, q′ − p))·exp(−100·|f(q)|)]            (sign_consistency_loss)
    L_D    = mean[(D(0) − 1)²] + mean[D(f(q))²]      (least squares; D on detached f, own Adam)
    L_G    = mean[(D(f(q)) − 1)²]
    L      = L_pull + 0.01·L_scc + 0.01·L_G

D is a 1 → 256 → 256 → 256 → 1 MLP (LeakyReLU 0.2, sigmoid): it learns to tell the ideal SDF
value on the surface (0, "real") from the network's values at the queries ("fake"), which
pushes the field to have a zero level close to the data. Per step D is updated first (on the
detached f), then the SDF network with L (D frozen). Adam (lr 1e-3) with a linear warm-up then
cosine decay to 0 (:func:`warmup_cosine_lr`); D's Adam keeps lr 1e-3. Batches are drawn
uniformly with replacement from all queries. Two exact economies: D(0) is evaluated once (the
code evaluates it on a batch of identical zeros: same loss and gradients), and the generator
term does not compute D's weight gradients (the code computes and then discards them).

Queries (:func:`make_queries`): if the cloud has more than ``max_points`` points it is replaced
by the farthest-point samples of 5k and 15k concatenated (the code's Open3D call: both FPS runs
start at point 0, so the 5k sample is the prefix of the 15k one and those points appear
twice). σ_p = distance from p to its 50th nearest point (self included, as the code's top-k
over a distance matrix); 20 queries per point q = p + N(0, σ_p²I); plus ``grid_queries``
points drawn without replacement from the union of a 70³ grid over [−0.5, 0.5]³ and a 50³ grid
over [−1, 1]³. Each query's target is its nearest input point (KD-tree).

Farthest-point sampling is a vectorised O(N·k) loop (:func:`farthest_point_sampling`): one
min-distance update and one argmax over all N points per chosen point, in float64 numpy; fast
enough at this data's size that no voxel pre-filtering is needed (timings in
docs/decisions.md#neural-pull-farthest-point-sampling-trainneural_pullpy).

Stage 2 (:func:`fuse_and_resample`): f_csg(x) = max_v f_v(x) (intersection of the views'
insides). Samples: ``grid_samples`` points drawn from the union of two ``grid_resolution``³
grids over [−0.5, 0.5]³ and [−1, 1]³, and ``surface_samples`` near-surface points: candidates
drawn the same way, jittered uniformly within their grid cell, and accepted with probability
min(1, exp(−f_csg²/2σ²)/√(2πσ)), σ = 0.01 (the code's Gaussian weight, whose prefactor
√(2πσ) — not σ√(2π) — makes every candidate with |f_csg| ≲ 0.017 certain to be accepted),
until enough are accepted. (The code instead re-filters the same accepted grid points
repeatedly, which piles duplicates onto the grid points nearest the surface; fresh, jittered
candidates give the same density without duplicates.) Option ``candidates="box"`` (the fast
preset) draws the candidates uniformly in a given box instead (the data's bounding box grown by
a margin): inside [−0.5, 0.5]³ the grids' candidate density is uniform too, so this only skips
space where f_csg is far from 0 (the data's neighbourhood holds the whole zero level unless a
view's field has spurious surfaces far from its points) and needs fewer candidates.
Targets are f_csg at every sample.

Stage 3 (:func:`fit_refined_sdf`): a fresh network regresses f_csg,

    L = mean|f(x) − f_csg(x)| + 0.4·mean|f(x)|,

same optimiser and schedule, batches drawn uniformly (with replacement) from all samples.

Randomness comes only from the ``torch.Generator`` passed in (a CPU generator; numpy
generators are seeded from it); nothing here touches global random state. The networks are
built on the CPU and train on the ``device`` given (the draws are made on the CPU and moved).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ultron.arguments import check_integer
from ultron.device import map_chunks, resolve_device
from ultron.errors import argument_error
from ultron.fields.sdf import SDFDiscriminator, SDFNetwork, SDFNetworkConfig
from ultron.train.fit_checkpoint import FitCheckpoint, FitState, fit_fingerprint, resumable
from ultron.train.loop import Objective, Progress, descend, run_training
from ultron.train.sdf_queries import (  # noqa: F401  (re-exported: the stage-1 data API)
    QuerySet,
    as_points,
    farthest_point_sampling,
    make_queries,
    neighbour_sigma,
    numpy_rng,
    subsample_points,
    two_cube_grid_points,
)

RESAMPLE_CANDIDATES = ("grids", "box")
#: Updates between the logged entries (and progress reports) of the SDF fits.
LOG_EVERY = 100
SDFFunction = Callable[[torch.Tensor], torch.Tensor]


# ----------------------------------------------------------------------------------- losses
def pull_points(queries: torch.Tensor, sdf: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """q′ = q − f(q)·∇f(q)/‖∇f(q)‖, shape (M, 3): each query moved along the normalised
    gradient by its signed distance (onto the zero level of an exact SDF)."""
    m = queries.shape[0]
    if queries.shape != (m, 3) or grad.shape != (m, 3) or sdf.shape != (m,):
        shapes = [tuple(t.shape) for t in (queries, sdf, grad)]
        raise argument_error("queries/sdf/grad", f"expected (M, 3), (M,), (M, 3), got {shapes}")
    return queries - sdf[:, None] * F.normalize(grad, dim=-1)


def pull_loss(pulled: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """L_pull = mean_q ‖q′ − p_nn(q)‖ (Euclidean distance, not squared)."""
    _same_shape("pulled/targets", pulled, targets)
    return torch.linalg.vector_norm(pulled - targets, dim=-1).mean()


def sign_consistency_loss(
    grad: torch.Tensor,
    pulled: torch.Tensor,
    targets: torch.Tensor,
    sdf: torch.Tensor,
    decay: float = 100.0,
) -> torch.Tensor:
    """L_scc = mean_q[(1 − cos(n̂, q′ − p_nn))·exp(−decay·|f(q)|)], n̂ = ∇f/‖∇f‖.

    Near the surface (small |f|) the residual q′ − p of the pull should point along the
    normal; the weight exp(−100|f|) confines the term to the zero level's neighbourhood.
    """
    _same_shape("grad/pulled/targets", grad, pulled, targets)
    cosine = F.cosine_similarity(F.normalize(grad, dim=-1), pulled - targets, dim=-1)
    return ((1.0 - cosine) * torch.exp(-decay * sdf.abs())).mean()


def discriminator_loss(d_real: torch.Tensor, d_fake: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN loss of D: mean[(D(real) − 1)²] + mean[D(fake)²]."""
    return ((d_real - 1.0) ** 2).mean() + (d_fake**2).mean()


def generator_loss(d_fake: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN loss of the SDF network: mean[(D(f(q)) − 1)²]."""
    return ((d_fake - 1.0) ** 2).mean()


def csg_intersection(values: Sequence[torch.Tensor]) -> torch.Tensor:
    """f_csg = max_v f_v (elementwise): negative only where every view's SDF is negative."""
    if len(values) == 0:
        raise argument_error("values", "expected at least one SDF value tensor")
    out = values[0]
    for other in values[1:]:
        out = torch.maximum(out, other)
    return out


def refine_loss(pred: torch.Tensor, target: torch.Tensor, zero_weight: float = 0.4) -> torch.Tensor:
    """L = mean|f − f_csg| + zero_weight·mean|f|."""
    _same_shape("pred/target", pred, target)
    return (pred - target).abs().mean() + zero_weight * pred.abs().mean()


def warmup_cosine_lr(step: int, iterations: int, warmup: int, lr: float) -> float:
    """lr·step/warmup for step < warmup, then lr·½(1 + cos(π(step − warmup)/(iterations − warmup)))."""
    if step < warmup:
        return lr * step / warmup
    span = max(iterations - warmup, 1)
    return lr * 0.5 * (1.0 + math.cos(math.pi * (step - warmup) / span))


def _same_shape(name: str, *tensors: torch.Tensor) -> None:
    if any(t.shape != tensors[0].shape for t in tensors):
        raise argument_error(name, f"shapes differ: {[tuple(t.shape) for t in tensors]}")


# ---------------------------------------------------------------------------------- configs
@dataclass(frozen=True)
class ViewFitConfig:
    """Stage 1 (one SDF per view) settings; defaults are the paper's code."""

    network: SDFNetworkConfig = field(default_factory=SDFNetworkConfig)
    iterations: int = 10_000
    batch_size: int = 5000
    lr: float = 1e-3
    warmup: int = 1000
    scc_weight: float = 0.01
    adversarial_weight: float = 0.01
    scc_decay: float = 100.0
    discriminator_hidden: int = 256
    discriminator_lr: float = 1e-3
    queries_per_point: int = 20
    sigma_neighbour: int = 50
    grid_queries: int = 30_000
    max_points: int = 20_000
    fps_sizes: tuple[int, ...] = (5000, 15_000)

    def __post_init__(self) -> None:
        _check_training(self.iterations, self.batch_size, self.lr, self.warmup)
        for name in ("queries_per_point", "sigma_neighbour", "max_points", "discriminator_hidden"):
            check_integer(name, getattr(self, name), 1)
        check_integer("grid_queries", self.grid_queries, 0)
        if not self.fps_sizes or any(not isinstance(k, int) or k < 1 for k in self.fps_sizes):
            raise argument_error("fps_sizes", f"expected positive integers, got {self.fps_sizes!r}")
        for name in ("scc_weight", "adversarial_weight", "scc_decay"):
            if not getattr(self, name) >= 0:
                raise argument_error(name, f"expected ≥ 0, got {getattr(self, name)}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ResampleConfig:
    """Stage 2 (CSG fusion and resampling) settings; defaults are the paper's code."""

    grid_samples: int = 200_000
    surface_samples: int = 150_000
    grid_resolution: int = 120
    sigma: float = 0.01
    candidate_batch: int = 200_000
    max_rounds: int = 200
    candidates: str = "grids"

    def __post_init__(self) -> None:
        if self.candidates not in RESAMPLE_CANDIDATES:
            raise argument_error(
                "candidates", f"expected one of {RESAMPLE_CANDIDATES}, got {self.candidates!r}"
            )
        for name, low in (("grid_samples", 1), ("surface_samples", 0), ("grid_resolution", 2),
                          ("candidate_batch", 1), ("max_rounds", 1)):  # fmt: skip
            check_integer(name, getattr(self, name), low)
        if not self.sigma > 0:
            raise argument_error("sigma", f"expected > 0, got {self.sigma}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class RefineConfig:
    """Stage 3 (fresh SDF regressing f_csg) settings; defaults are the paper's code."""

    network: SDFNetworkConfig = field(default_factory=SDFNetworkConfig)
    iterations: int = 10_000
    batch_size: int = 5000
    lr: float = 1e-3
    warmup: int = 1000
    zero_weight: float = 0.4

    def __post_init__(self) -> None:
        _check_training(self.iterations, self.batch_size, self.lr, self.warmup)
        if not self.zero_weight >= 0:
            raise argument_error("zero_weight", f"expected ≥ 0, got {self.zero_weight}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check_training(iterations: int, batch_size: int, lr: float, warmup: int) -> None:
    check_integer("iterations", iterations, 1)
    check_integer("batch_size", batch_size, 1)
    check_integer("warmup", warmup, 0)
    if warmup >= iterations:
        raise argument_error("warmup", f"expected < iterations={iterations}, got {warmup}")
    if not (math.isfinite(lr) and lr > 0):
        raise argument_error("lr", f"expected > 0, got {lr}")


# ---------------------------------------------------------------------------------- stage 1
@dataclass
class SDFFit:
    """A fitted SDF network and its log: final losses, counts, seconds."""

    network: SDFNetwork
    log: dict[str, Any]


def fit_view_sdf(
    points_unit: np.ndarray,
    config: ViewFitConfig,
    generator: torch.Generator,
    progress: Progress | None = None,
    name: str = "view",
    device: torch.device | str = "cpu",
    checkpoint: FitCheckpoint | None = None,
) -> SDFFit:
    """Stage 1: fit one view's SDF to its point cloud (normalised coordinates) by Neural-Pull
    with the sign-consistency and adversarial terms (module doc). ``progress`` receives a dict
    (stage, step, iterations, losses, seconds) at the first update, every 100th and the last
    (:func:`ultron.train.loop.run_training`). The networks are built on the CPU from
    ``generator`` (the CPU generator that also draws the batches) and trained on ``device``,
    where the returned network stays; with ``checkpoint`` the fit is resumable
    (:mod:`ultron.train.fit_checkpoint`)."""
    start = time.perf_counter()
    device = resolve_device(device, "device")
    data = make_queries(points_unit, config, numpy_rng(generator))
    queries_all, targets_all = data.queries.to(device), data.targets.to(device)
    network = SDFNetwork(config.network, generator).to(device)
    discriminator = SDFDiscriminator(config.discriminator_hidden, generator).to(device)
    optimiser = torch.optim.Adam(network.parameters(), lr=config.lr)
    d_optimiser = torch.optim.Adam(discriminator.parameters(), lr=config.discriminator_lr)
    n_queries = data.queries.shape[0]
    batch = min(config.batch_size, n_queries)
    real = torch.zeros(1, device=device)

    def objective(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        index = torch.randint(0, n_queries, (batch,), generator=generator).to(device)
        queries, targets = queries_all[index], targets_all[index]
        sdf, grad = network.sdf_and_gradient(queries, create_graph=True)
        pulled = pull_points(queries, sdf, grad)
        l_pull = pull_loss(pulled, targets)
        l_scc = sign_consistency_loss(grad, pulled, targets, sdf, config.scc_decay)

        # D(0) on a batch of zeros is one value repeated: evaluating it once gives the same
        # loss and gradients at a fraction of the cost
        d_loss = discriminator_loss(discriminator(real), discriminator(sdf.detach()))
        descend([d_optimiser], d_loss)  # the adversary's own step, before the generator's

        # the generator term needs ∂D/∂f only: D's own weight gradients are not computed
        discriminator.requires_grad_(False)
        g_loss = generator_loss(discriminator(sdf))
        discriminator.requires_grad_(True)
        loss = l_pull + config.scc_weight * l_scc + config.adversarial_weight * g_loss
        scalars = {"loss": loss, "pull": l_pull, "scc": l_scc, "generator": g_loss,
                   "discriminator": d_loss}  # fmt: skip
        return loss, {k: v.detach() for k, v in scalars.items()}

    fit = FitState([network, discriminator], [optimiser, d_optimiser], generator)
    tensors = (data.queries, data.targets)
    resume = _resumable(checkpoint, fit, tensors, {"config": config.to_dict(), "view": name},
                        config.iterations)  # fmt: skip
    network.train()
    entries = _train(objective, config, optimiser, progress, f"stage1_{name}", f"{name} SDF",
                     fit, resume)  # fmt: skip
    network.eval()
    log = {"iterations": config.iterations, "n_points_used": int(data.points.shape[0]),
           "n_queries": int(n_queries), "final_losses": _final_losses(entries),
           "seconds": time.perf_counter() - start}  # fmt: skip
    return SDFFit(network, log)


def _train(
    objective: Objective,
    config: ViewFitConfig | RefineConfig,
    optimiser: torch.optim.Optimizer,
    progress: Progress | None,
    stage: str,
    name: str,
    fit: FitState,
    resume: tuple[int, Callable[[int], None] | None],
) -> list[dict[str, Any]]:
    """:func:`~ultron.train.loop.run_training` with the warm-up + cosine learning rate of
    ``config`` and an entry every :data:`LOG_EVERY` updates, from ``resume`` (the update to
    start from and the checkpoint's ``after_update``: :func:`_resumable`) into ``fit``'s log."""

    def learning_rate(step: int) -> float:
        return warmup_cosine_lr(step, config.iterations, config.warmup, config.lr)

    return run_training(
        objective, config.iterations, name=name, log_every=LOG_EVERY, progress=progress,
        learning_rate=learning_rate, optimizers=[optimiser], stage={"stage": stage},
        start=resume[0], after_update=resume[1], log=fit.log,
    )  # fmt: skip


def _resumable(
    checkpoint: FitCheckpoint | None,
    fit: FitState,
    data: Sequence[torch.Tensor],
    settings: dict[str, Any],
    iterations: int,
) -> tuple[int, Callable[[int], None] | None]:
    """:func:`~ultron.train.fit_checkpoint.resumable` for an SDF fit, fingerprinted by its
    ``data``, ``settings``, initial networks and generator."""

    def fingerprint() -> str:
        modules = [t for m in fit.modules for t in m.state_dict().values()]
        return fit_fingerprint([*data, *modules, fit.generator.get_state()], settings)

    return resumable(checkpoint, fingerprint, iterations, fit)


def _final_losses(entries: list[dict[str, Any]]) -> dict[str, float]:
    """The last logged entry's losses ({} without updates)."""
    last = entries[-1] if entries else {}
    return {k: v for k, v in last.items() if k not in ("step", "seconds")}


# ---------------------------------------------------------------------------------- stage 2
@dataclass(frozen=True)
class SDFSamples:
    """Stage-2 output: points (S, 3) float32 in normalised coordinates and f_csg there (S,)."""

    points: torch.Tensor
    sdf: torch.Tensor
    n_grid: int
    n_surface: int
    rounds: int


def evaluate_sdf(
    fn: SDFFunction,
    points: torch.Tensor,
    chunk: int = 65_536,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """fn on points (M, 3) in chunks, without gradients, each chunk moved to ``device``
    (default: where it is); returns float32 (M,) on the CPU."""
    return map_chunks(lambda p: fn(p).reshape(-1).float(), points, chunk, device)


def fuse_and_resample(
    sdf_fns: Sequence[SDFFunction],
    config: ResampleConfig,
    generator: torch.Generator,
    candidate_bounds: np.ndarray | None = None,
    device: torch.device | str | None = None,
) -> SDFSamples:
    """Stage 2: f_csg = max of ``sdf_fns`` sampled on the two-cube grids and near its zero
    level (module doc). With ``config.candidates == "box"`` the near-surface candidates are
    uniform in ``candidate_bounds`` ((2, 3) normalised [min, max], required then). The
    functions are evaluated on ``device`` (their networks'); the samples are CPU tensors."""
    if len(sdf_fns) == 0:
        raise argument_error("sdf_fns", "expected at least one SDF function")
    box = None
    if config.candidates == "box":
        box = np.asarray(
            candidate_bounds if candidate_bounds is not None else np.nan, dtype=np.float64
        )
        if box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] <= box[0]).any():
            raise argument_error(
                "candidate_bounds", f"expected a (2, 3) [min, max] box, got {candidate_bounds!r}"
            )
    rng = numpy_rng(generator)

    def f_csg(points: torch.Tensor) -> torch.Tensor:
        return csg_intersection([evaluate_sdf(fn, points, device=device) for fn in sdf_fns])

    res = config.grid_resolution
    grid = torch.from_numpy(two_cube_grid_points(config.grid_samples, (res, res), rng)).float()
    grid_sdf = f_csg(grid)
    accepted: list[torch.Tensor] = []
    accepted_sdf: list[torch.Tensor] = []
    n_accepted, rounds = 0, 0
    scale = 1.0 / math.sqrt(2 * math.pi * config.sigma)
    while n_accepted < config.surface_samples and rounds < config.max_rounds:
        rounds += 1
        if box is None:
            candidates = two_cube_grid_points(config.candidate_batch, (res, res), rng, jitter=True)
        else:
            candidates = box[0] + rng.random((config.candidate_batch, 3)) * (box[1] - box[0])
        points = torch.from_numpy(candidates).float()
        values = f_csg(points)
        weight = scale * torch.exp(-(values**2) / (2 * config.sigma**2))
        keep = torch.from_numpy(rng.random(len(values))).float() < weight
        accepted.append(points[keep])
        accepted_sdf.append(values[keep])
        n_accepted += int(keep.sum())
    surface = torch.cat(accepted)[: config.surface_samples] if accepted else torch.zeros(0, 3)
    surface_sdf = torch.cat(accepted_sdf)[: config.surface_samples] if accepted else torch.zeros(0)
    return SDFSamples(torch.cat([grid, surface]), torch.cat([grid_sdf, surface_sdf]),
                      n_grid=int(grid.shape[0]), n_surface=int(surface.shape[0]), rounds=rounds)  # fmt: skip


# ---------------------------------------------------------------------------------- stage 3
def fit_refined_sdf(
    samples: SDFSamples,
    config: RefineConfig,
    generator: torch.Generator,
    progress: Progress | None = None,
    device: torch.device | str = "cpu",
    checkpoint: FitCheckpoint | None = None,
) -> SDFFit:
    """Stage 3: a fresh SDF network regressing f_csg with L = mean|f − f_csg| + 0.4·mean|f|,
    built on the CPU from ``generator`` and trained on ``device`` (where it stays); resumable
    with ``checkpoint``."""
    start = time.perf_counter()
    device = resolve_device(device, "device")
    n = samples.points.shape[0]
    if n == 0:
        raise argument_error("samples", "no samples to fit")
    points, targets = samples.points.to(device), samples.sdf.to(device)
    network = SDFNetwork(config.network, generator).to(device)
    optimiser = torch.optim.Adam(network.parameters(), lr=config.lr)
    batch = min(config.batch_size, n)

    def objective(step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        index = torch.randint(0, n, (batch,), generator=generator).to(device)
        pred = network(points[index])
        loss = refine_loss(pred, targets[index], config.zero_weight)
        return loss, {"loss": loss.detach()}

    fit = FitState([network], [optimiser], generator)
    resume = _resumable(checkpoint, fit, (samples.points, samples.sdf),
                        {"config": config.to_dict()}, config.iterations)  # fmt: skip
    network.train()
    entries = _train(objective, config, optimiser, progress, "stage3", "refined SDF", fit, resume)
    network.eval()
    log = {"iterations": config.iterations, "n_samples": int(n),
           "final_losses": _final_losses(entries),
           "seconds": time.perf_counter() - start}  # fmt: skip
    return SDFFit(network, log)
