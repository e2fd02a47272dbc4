"""The ``grid`` backend (default): multi-resolution factorised planes + a tiny decoder.

Features at a unit-cube point u = (x, y, z) are read by bilinear interpolation from three
axis-aligned feature planes per level and combined by a Hadamard product (as in K-planes),

    f_ℓ(u) = P_ℓ^{xy}(x, y) ⊙ P_ℓ^{xz}(x, z) ⊙ P_ℓ^{yz}(y, z),

which is a rank-limited trilinear-like 3D feature at the memory cost of 2D planes. Beside them a
coarse dense volume V (``volume_cell_mm``, C_V features per node) is read trilinearly,

    f(u) = [f_1(u), …, f_L(u), V(u)],

and the concatenation is decoded by a small ReLU MLP into the raw θ outputs. The volume holds
what a product of projections cannot: a thin curved wall oblique to every axis makes each
plane's projection of it a band, and their product fills the bands' bounding region with
wall-like features — beside and behind a real bone wall (docs/decisions.md, "the dense
volume"; off by default). The finest level's cell is at most the data's pixel size (``cell_mm``),
so the field can hold pixel-scale detail; the volume's is coarse (e.g. 2 mm), so it stays small.

For a box far from a cube the planes span the data's box, not the whole cube: axis a covers
[−e_a, e_a] of the unit cube (``axis_extent``, e = 1 on the box's longest axis) with nodes at
the same spacing on every axis, so plane P^{xy} has n_y × n_x nodes, n_a = round((R − 1)·e_a)
+ 1. They are used where the square planes would hold more than :data:`PER_AXIS_SAVING` times
their values: a long bone's recording then needs far fewer values and a faster fit step (the
planes' gradient and Adam's update dominate it); a compact box (a vertebra) keeps square
planes, whose one batched read is faster (figures in
docs/decisions.md#grid-field-per-axis-planes-fieldsgridpy). Fields fitted before (no
``axis_extent``) have square planes.
A dense 3D grid at that cell size would need (2·half_extent/cell)³ voxels (≈ 2·10⁸ for the l2
sweep), which does not fit a CPU budget; planes need 3·R² per level.

Smoothness prior: the mean squared difference between neighbouring plane cells (total
variation, squared), and the volume's over its three axes, weighted by ``smoothness_weight``.
Without it the pixel-scale planes memorise each training frame's speckle and render a noisy
texture between frames. The default (1.0) was chosen among {1e-3, 1e-2, 0.1, 1, 10} by the
held-out frames of the default simulated phantom (best SSIM; bone edges stay sharp), never on
the l2 benchmark frames.
Defaults (8 features per plane at the finest level, 4 at the coarser one, 2 levels ÷4, a
16-wide one-layer decoder) were chosen for step time (grid_sample's backward, then the
decoder, dominate it), checking on the simulated phantom's held-out frames that the fit stays
comparable to a larger grid and decoder while smaller ones fit worse (figures in
docs/decisions.md#grid-field-default-size-fieldsgridpy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from ultron.errors import argument_error
from ultron.fields.base import AcousticField
from ultron.fields.properties import HeadConfig, initial_raw_bias, n_raw_channels

#: Upper bound on a plane's side (memory guard: 3 planes × C × R² floats per level).
MAX_RESOLUTION = 2048
#: Per-axis planes replace the square ones when the square ones would hold more than this many
#: times their values (a box far from a cube, e.g. a long bone's recording); for a compact box
#: one batched read of square planes is faster (timings in
#: docs/decisions.md#grid-field-per-axis-planes-fieldsgridpy).
PER_AXIS_SAVING = 2.0
#: The dense volume's default cell (mm) for a long box (:attr:`GridFieldConfig.long_box_volume_mm`).
LONG_BOX_VOLUME_MM = 2.0
#: Side of the random window on which the smoothness prior is evaluated each step.
TV_WINDOW = 96
#: Side of the random window on which the prior is evaluated on the dense volume each step.
VOLUME_TV_WINDOW = 32
#: Probability of evaluating the prior on a plane larger than the window in a given step.
TV_LARGE_PLANE_PROBABILITY = 0.25


@dataclass(frozen=True)
class GridFieldConfig:
    """Plane resolutions (finest first) or how to derive them, features and decoder size.

    ``resolutions`` is filled in by :meth:`resolved` from ``cell_mm`` (default: the data's
    smallest pixel spacing) and the unit cube's size: the finest level has
    R = ⌈2·half_extent_mm / cell_mm⌉ + 1 nodes, each coarser level ``level_factor`` fewer.
    """

    resolutions: tuple[int, ...] | None = None
    cell_mm: float | None = None
    #: Half-extent of the planes per axis in unit-cube units (x, y, z), each in (0, 1];
    #: None: the whole cube on every axis (square planes, fields fitted before it existed).
    axis_extent: tuple[float, float, float] | None = None
    n_levels: int = 2
    level_factor: float = 4.0
    features: int = 8
    coarse_features: int = 4
    decoder_width: int = 16
    decoder_depth: int = 1
    smoothness_weight: float = 1.0
    #: Cell (mm) of the dense feature volume read trilinearly beside the planes (None: none, the
    #: default; docs/decisions.md#grid-field-the-dense-volume-an-option-fieldsgridpy).
    volume_cell_mm: float | None = None
    volume_features: int = 4
    #: Nodes (n_x, n_y, n_z) of that grid, filled in by :meth:`resolved`.
    volume_nodes: tuple[int, int, int] | None = None
    #: The volume's cell (mm) for a long box — one given per-axis planes (:meth:`resolved`) —
    #: where ``volume_cell_mm`` is not set; None: no volume there either (fields saved before
    #: it existed). Why: docs/decisions.md#grid-field-the-dense-volume-for-a-long-box-fieldsgridpy.
    long_box_volume_mm: float | None = LONG_BOX_VOLUME_MM

    def __post_init__(self) -> None:
        if self.resolutions is not None:
            resolutions = tuple(int(r) for r in self.resolutions)
            if not resolutions or any(r < 2 or r > MAX_RESOLUTION for r in resolutions):
                raise argument_error(
                    "grid.resolutions",
                    f"expected sides in [2, {MAX_RESOLUTION}], got {resolutions}",
                )
            object.__setattr__(self, "resolutions", resolutions)
        if self.axis_extent is not None:
            extent = tuple(float(e) for e in self.axis_extent)
            if len(extent) != 3 or not all(0 < e <= 1 for e in extent):
                raise argument_error(
                    "grid.axis_extent", f"expected three values in (0, 1], got {self.axis_extent}"
                )
            object.__setattr__(self, "axis_extent", extent)
        if self.cell_mm is not None and not self.cell_mm > 0:
            raise argument_error("grid.cell_mm", f"expected > 0, got {self.cell_mm}")
        if not isinstance(self.n_levels, int) or self.n_levels < 1:
            raise argument_error("grid.n_levels", f"expected ≥ 1, got {self.n_levels!r}")
        if not self.level_factor > 1:
            raise argument_error("grid.level_factor", f"expected > 1, got {self.level_factor}")
        for name in ("features", "coarse_features", "decoder_width", "decoder_depth"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise argument_error(f"grid.{name}", f"expected a positive integer, got {value!r}")
        if self.smoothness_weight < 0:
            raise argument_error("grid.smoothness_weight", "expected ≥ 0")
        if self.volume_cell_mm is not None and not (
            math.isfinite(self.volume_cell_mm) and self.volume_cell_mm > 0
        ):
            raise argument_error(
                "grid.volume_cell_mm", f"expected > 0 mm or None, got {self.volume_cell_mm!r}"
            )
        if self.long_box_volume_mm is not None and not (
            math.isfinite(self.long_box_volume_mm) and self.long_box_volume_mm > 0
        ):
            raise argument_error(
                "grid.long_box_volume_mm",
                f"expected > 0 mm or None, got {self.long_box_volume_mm!r}",
            )
        if not isinstance(self.volume_features, int) or self.volume_features < 1:
            raise argument_error(
                "grid.volume_features", f"expected a positive integer, got {self.volume_features!r}"
            )
        if self.volume_nodes is not None:
            nodes = tuple(int(n) for n in self.volume_nodes)
            if len(nodes) != 3 or not all(2 <= n <= MAX_RESOLUTION for n in nodes):
                raise argument_error(
                    "grid.volume_nodes",
                    f"expected three sides in [2, {MAX_RESOLUTION}], got {nodes}",
                )
            object.__setattr__(self, "volume_nodes", nodes)

    def resolved(
        self,
        half_extent_mm: float,
        pixel_mm: float,
        axis_extent: tuple[float, float, float] | None = None,
    ) -> GridFieldConfig:
        """This config with ``resolutions`` computed for a cube of ``half_extent_mm`` and, where
        not set, the planes' ``axis_extent`` (the data's box in unit-cube units)."""
        if self.resolutions is not None:
            return self
        if self.volume_cell_mm is not None and self.volume_nodes is None:
            planes = replace(self, volume_cell_mm=None, long_box_volume_mm=None).resolved(
                half_extent_mm, pixel_mm, axis_extent
            )
            box = planes.axis_extent or (1.0, 1.0, 1.0)
            nodes = tuple(math.ceil(2 * half_extent_mm * e / self.volume_cell_mm) + 1 for e in box)
            return replace(planes, volume_cell_mm=self.volume_cell_mm, volume_nodes=nodes)
        cell = self.cell_mm if self.cell_mm is not None else pixel_mm
        finest = math.ceil(2 * half_extent_mm / cell) + 1
        if finest > MAX_RESOLUTION:
            raise argument_error(
                "grid.cell_mm",
                f"a {cell:.3g} mm cell over {2 * half_extent_mm:.1f} mm needs {finest} nodes"
                f" per side (max {MAX_RESOLUTION}); choose a larger cell",
            )
        sides = [max(2, round(finest / self.level_factor**i)) for i in range(self.n_levels)]
        square = replace(self, resolutions=tuple(sides))
        extent = self.axis_extent if self.axis_extent is not None else axis_extent
        if extent is None:
            return square
        per_axis = replace(square, axis_extent=extent)
        if self.axis_extent is None and square.n_values() <= PER_AXIS_SAVING * per_axis.n_values():
            return square  # a compact box: one batched read of square planes is faster
        if self.long_box_volume_mm is not None and self.volume_cell_mm is None:  # a long box
            volume = replace(self, volume_cell_mm=self.long_box_volume_mm, axis_extent=extent)
            return volume.resolved(half_extent_mm, pixel_mm, axis_extent)
        return per_axis

    def axis_nodes(self) -> list[tuple[int, int, int]]:
        """Per level the nodes (n_x, n_y, n_z) along each axis (module doc)."""
        if self.resolutions is None:
            raise argument_error("config", "call GridFieldConfig.resolved(...) first")
        extent = self.axis_extent or (1.0, 1.0, 1.0)
        return [
            tuple(max(2, round((r - 1) * e) + 1) for e in extent)  # type: ignore[misc]
            for r in self.resolutions
        ]

    def plane_shapes(self) -> list[tuple[tuple[int, int], ...]]:
        """Per level the (rows, columns) of the xy, xz and yz planes."""
        return [((ny, nx), (nz, nx), (nz, ny)) for nx, ny, nz in self.axis_nodes()]

    def n_values(self) -> int:
        """The planes' values (features × nodes) over every level, and the volume's."""
        channels = [self.features] + [self.coarse_features] * (len(self.resolutions or ()) - 1)
        planes = sum(
            c * sum(rows * cols for rows, cols in shapes)
            for c, shapes in zip(channels, self.plane_shapes(), strict=True)
        )
        volume = self.volume_features * math.prod(self.volume_nodes or (0,))
        return planes + volume


class GridField(AcousticField):
    """Multi-resolution factorised planes read bilinearly + a tiny ReLU decoder.

    Square planes over the whole cube (no ``axis_extent``) are one (3, C, R, R) tensor per
    level, read with one ``grid_sample`` call (the layout of every field fitted before the
    per-axis planes); per-axis planes are three tensors of their own shapes per level."""

    def __init__(
        self,
        config: GridFieldConfig,
        learn_density: bool = False,
        generator: torch.Generator | None = None,
        heads: HeadConfig | None = None,
    ) -> None:
        super().__init__(learn_density, heads)
        if config.resolutions is None:
            raise argument_error("config", "call GridFieldConfig.resolved(...) first")
        self.config = config
        channels = [config.features] + [config.coarse_features] * (len(config.resolutions) - 1)
        self.per_axis = config.axis_extent is not None
        if self.per_axis:
            self.planes = nn.ModuleList(
                nn.ParameterList(
                    nn.Parameter(1.0 + 0.1 * torch.randn(c, *shape, generator=generator))
                    for shape in shapes
                )
                for c, shapes in zip(channels, config.plane_shapes(), strict=True)
            )
        else:
            self.planes = nn.ParameterList(
                nn.Parameter(1.0 + 0.1 * torch.randn(3, c, r, r, generator=generator))
                for c, r in zip(channels, config.resolutions, strict=True)
            )
        self.volume = None
        if config.volume_nodes is not None:
            nx, ny, nz = config.volume_nodes
            shape = (1, config.volume_features, nz, ny, nx)
            self.volume = nn.Parameter(0.1 * torch.randn(*shape, generator=generator))
            channels = [*channels, config.volume_features]
        extent = config.axis_extent or (1.0, 1.0, 1.0)
        self.register_buffer("_axis_scale", torch.tensor([1.0 / e for e in extent]), False)
        layers: list[nn.Module] = []
        fan_in = sum(channels)
        for _ in range(config.decoder_depth):
            layers += [nn.Linear(fan_in, config.decoder_width), nn.ReLU()]
            fan_in = config.decoder_width
        last = nn.Linear(fan_in, n_raw_channels(learn_density))
        with torch.no_grad():
            last.weight.mul_(0.1)
            last.bias.copy_(initial_raw_bias(learn_density, self.head_config))
        self.decoder = nn.Sequential(*layers, last)

    def features(self, points_unit: torch.Tensor) -> torch.Tensor:
        """Concatenated plane-product features (…, Σ_levels C_level)."""
        shape = points_unit.shape[:-1]
        u = points_unit.reshape(-1, 3).to(torch.float32)
        if self.per_axis:
            u = u * self._axis_scale
        # grid_sample reads (x → last axis, y → second-last axis) of each plane.
        x, y, z = u.unbind(-1)
        parts = []
        if self.per_axis:
            coords = [torch.stack(pair, dim=-1)[None, None] for pair in ((x, y), (x, z), (y, z))]
            for level in self.planes:
                xy, xz, yz = (
                    threaded_read(plane[None], where)[0, :, 0]
                    for plane, where in zip(level, coords, strict=True)
                )  # (C, N) each
                parts.append(xy * xz * yz)
        else:
            coords = torch.stack([x, y, x, z, y, z], dim=-1).view(-1, 3, 2).transpose(0, 1)[:, None]
            for plane in self.planes:
                sampled = threaded_read(plane, coords)  # (3, C, 1, N): one call
                parts.append(sampled[0, :, 0] * sampled[1, :, 0] * sampled[2, :, 0])  # (C, N)
        if self.volume is not None:
            where = torch.stack([x, y, z], dim=-1)[None, None, None]
            parts.append(threaded_read(self.volume, where)[0, :, 0, 0])
        feats = torch.cat(parts, dim=0).transpose(0, 1)
        return feats.reshape(*shape, feats.shape[-1])

    def raw(self, points_unit: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.features(points_unit))

    def regularization(
        self, generator: torch.Generator | None = None, draws: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Squared total variation of the planes, × ``smoothness_weight``.

            TV = Σ_levels mean_window[(P[i+1, j] − P[i, j])² + (P[i, j+1] − P[i, j])²]

        (the mean over a level's three planes). A stochastic, unbiased estimate of the
        whole-plane means (``generator`` draws it): a plane larger than ``TV_WINDOW`` is
        evaluated on one random window, and only with probability
        ``TV_LARGE_PLANE_PROBABILITY`` (then scaled by its inverse), because the gradient of a
        window still costs a pass over the whole plane. The dense volume's squared TV (the mean
        over its three axes) is added, on one random ``VOLUME_TV_WINDOW``³ window every step when
        the volume is larger (:func:`_volume_tv_drawn`). The draws are made on ``generator``'s
        device (the fit's CPU generator), the penalty on the planes'.

        ``draws`` (instead of ``generator``): :meth:`regularization_draws`' table, moved to the
        planes' device — the same estimate with no draw and no synchronisation (a skipped
        window is weighted by 0 instead of not evaluated), so a CUDA graph can capture it.
        """
        total = torch.zeros((), device=self._axis_scale.device)
        if self.config.smoothness_weight == 0:
            return total
        if draws is None:
            draws = self.regularization_draws(generator)
        rows = iter(() if draws is None else draws)
        for planes in self._tv_levels():
            total = total + sum(_plane_tv_drawn(plane, rows) for plane in planes) / len(planes)
        if self.volume is not None:
            total = total + _volume_tv_drawn(self.volume, rows)
        return self.config.smoothness_weight * total

    def regularization_draws(self, generator: torch.Generator | None) -> torch.Tensor | None:
        """The random windows :meth:`regularization` draws from ``generator``, in its order: one
        row (first row, first column, kept ∈ {0, 1}) per plane larger than ``TV_WINDOW``, then
        one (first z, first y, first x) for a volume larger than ``VOLUME_TV_WINDOW``; int64 on
        the generator's device; None when nothing needs a draw."""
        if self.config.smoothness_weight == 0:
            return None
        shapes = [plane.shape[-2:] for planes in self._tv_levels() for plane in planes]
        windows = [_window_draw(rows, cols, generator) for rows, cols in shapes]
        table = [(i, j, int(keep)) for i, j, keep in filter(None, windows)]
        if self.volume is not None and max(self.volume.shape[2:]) > VOLUME_TV_WINDOW:
            table.append(
                tuple(
                    int(torch.randint(0, max(1, n - VOLUME_TV_WINDOW + 1), (), generator=generator))
                    for n in self.volume.shape[2:]
                )
            )
        return torch.tensor(table, dtype=torch.int64) if table else None

    def _tv_levels(self) -> list[list[torch.Tensor]]:
        """Each level's planes as the TV takes them: its three per-axis planes, or its one
        (3, C, R, R) tensor of square planes."""
        return [list(level) if self.per_axis else [level] for level in self.planes]


def threaded_read(values: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    """``grid_sample`` (bilinear, border, ``align_corners``) of ``values`` (B, C, *grid) at
    ``where`` (B, 1, [1,] N, d); a single grid (B = 1) is read on every torch CPU thread when
    nothing needs a gradient.

    torch's CPU kernels share one call's work out over its batch: a single plane or volume
    (batch 1) is read on one thread, and more slowly with two threads than with one (figures
    in docs/decisions.md, "Reading the grid field on every thread"). So without autograd, on
    the CPU, with more than one thread and enough points, the N points are cut into one run
    per thread and read as a batch of that many views of ``values`` (``expand``: no copy),
    then put back in their order. Each point is computed by the same arithmetic as in one
    call, so the result is the same bit for bit. Otherwise (a fit's forward, whose backward
    would sum the runs' gradients in another order; an accelerator; one thread; few points; a
    batch of several grids) it is one plain call."""
    threads = torch.get_num_threads()
    n, dims = where.shape[-2], where.shape[-1]
    if (
        threads < 2
        or values.shape[0] != 1
        or values.device.type != "cpu"
        or n < _POINTS_PER_THREAD * threads
        or (torch.is_grad_enabled() and (values.requires_grad or where.requires_grad))
    ):
        return F.grid_sample(
            values, where, mode="bilinear", padding_mode="border", align_corners=True
        )
    run = -(-n // threads)
    flat = where.reshape(n, dims)
    if run * threads != n:  # pad with the grid's centre, read and dropped
        flat = torch.cat([flat, flat.new_zeros(run * threads - n, dims)])
    ones = (1,) * (where.ndim - 3)
    grids = values.expand(threads, *values.shape[1:])
    read = F.grid_sample(
        grids, flat.reshape(threads, *ones, run, dims), mode="bilinear", padding_mode="border",
        align_corners=True,
    )  # fmt: skip
    # (threads, C, *ones, run) → (1, C, *ones, threads · run), the points in their order
    read = read.movedim(0, -2).reshape(1, values.shape[1], *ones, run * threads)
    return read[..., :n]


#: Points a thread reads at least before :func:`threaded_read` shares a read out.
_POINTS_PER_THREAD = 4096


def _window_draw(
    rows: int, cols: int, generator: torch.Generator | None
) -> tuple[int, int, bool] | None:
    """The random window of a (rows, cols) plane (:func:`_window_tv`): (first row, first column,
    kept), or None for a plane no larger than ``TV_WINDOW`` (no draw)."""
    if max(rows, cols) <= TV_WINDOW:
        return None
    draw = torch.rand((), generator=generator)
    if rows == cols:
        i, j = torch.randint(0, rows - TV_WINDOW + 1, (2,), generator=generator).tolist()
    else:
        i, j = (
            int(torch.randint(0, max(1, n - TV_WINDOW + 1), (), generator=generator))
            for n in (rows, cols)
        )
    return i, j, float(draw) < TV_LARGE_PLANE_PROBABILITY


def _window_tv(plane: torch.Tensor, window: tuple[int, int, bool] | None) -> torch.Tensor:
    """Squared TV of a plane (…, rows, cols) — for square planes a level's (3, C, R, R)
    tensor, whose mean is the three planes' — on its drawn ``TV_WINDOW`` window
    (:func:`_window_draw`), sliced, scaled by 1 / ``TV_LARGE_PLANE_PROBABILITY`` when kept and 0
    when not; on the whole plane when no window was drawn (:meth:`GridField.regularization`)."""
    scale = 1.0
    if window is not None:
        i, j, keep = window
        if not keep:
            return torch.zeros((), device=plane.device)
        plane = plane[..., i : i + TV_WINDOW, j : j + TV_WINDOW]
        scale = 1.0 / TV_LARGE_PLANE_PROBABILITY
    return scale * _squared_tv(plane)


def _plane_tv_drawn(plane: torch.Tensor, draws) -> torch.Tensor:
    """The plane's squared TV on the window in the next row of ``draws`` (an iterator over the
    table of :meth:`GridField.regularization_draws`; a plane no larger than ``TV_WINDOW`` takes
    no row). On the CPU the window is sliced (:func:`_window_tv`); on another device it is
    gathered by index and a skipped window weighted by 0 — no value leaves the device, so a
    CUDA graph can capture it."""
    rows, cols = plane.shape[-2:]
    if max(rows, cols) <= TV_WINDOW:
        return _squared_tv(plane)
    row = next(draws)
    if row.device.type == "cpu":
        first_row, first_col, kept = row.tolist()
        return _window_tv(plane, (first_row, first_col, bool(kept)))
    return _indexed_window_tv(plane, row)


def _volume_tv_drawn(volume: torch.Tensor, draws) -> torch.Tensor:
    """Squared TV of the (1, C, n_z, n_y, n_x) volume, the mean over its three axes' squared
    neighbour differences — on a ``VOLUME_TV_WINDOW``³ window whose first corner is the next row
    of ``draws`` when the volume is larger (an unbiased estimate of the whole volume's mean, at
    a window's cost), else on the whole volume."""
    if max(volume.shape[2:]) > VOLUME_TV_WINDOW:
        row = next(draws)
        for axis, start in zip((2, 3, 4), row, strict=True):
            size = min(volume.shape[axis], VOLUME_TV_WINDOW)
            if row.device.type == "cpu":
                volume = volume.narrow(axis, int(start), size)
            else:
                index = start + torch.arange(size, device=volume.device)
                volume = volume.index_select(axis, index)
    return (
        sum(
            (volume.narrow(a, 1, volume.shape[a] - 1) - volume.narrow(a, 0, volume.shape[a] - 1))
            .pow(2)
            .mean()
            for a in (2, 3, 4)
        )
        / 3
    )


def _indexed_window_tv(plane: torch.Tensor, row: torch.Tensor) -> torch.Tensor:
    """:func:`_window_tv` of the window in ``row`` = (first row, first column, kept), a
    tensor on the plane's device: gathered by index, weighted by kept / p (0 when skipped)."""
    rows, cols = plane.shape[-2:]
    offsets = torch.arange(TV_WINDOW, device=plane.device)
    window = plane.index_select(-2, row[0] + offsets[: min(rows, TV_WINDOW)])
    window = window.index_select(-1, row[1] + offsets[: min(cols, TV_WINDOW)])
    return (row[2].to(plane.dtype) / TV_LARGE_PLANE_PROBABILITY) * _squared_tv(window)


def _squared_tv(plane: torch.Tensor) -> torch.Tensor:
    """mean[(P[i+1, j] − P[i, j])²] + mean[(P[i, j+1] − P[i, j])²] over the last two axes."""
    dy = plane[..., 1:, :] - plane[..., :-1, :]
    dx = plane[..., :, 1:] - plane[..., :, :-1]
    return dy.pow(2).mean() + dx.pow(2).mean()
