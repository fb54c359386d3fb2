"""Occupancy: which points of a box may hold density, so that the marcher skips the rest.

The marcher (:mod:`narf_core.sampling`) asks an :class:`Occupancy` three things: a box outside which
nothing is occupied (:meth:`~Occupancy.bounds`, to clip the rays), and, along a batch of rays, which
sample positions ``t`` are occupied (:meth:`~Occupancy.along`, prepared once per march and asked
once per marching round); :meth:`~Occupancy.occupied` answers for single points. Two kinds implement
it: the :class:`OccupancyGrid` (a boolean voxel grid, optionally one per bin of the configuration
θ, looked up in cell units along the rays) and the part composition
(:class:`~narf_core.fields.composed.PosedComposition`, the union of its parts' grids, through
:class:`PointwiseRays`).

A *field* is any callable ``(x [n,3], d [n,3], theta [n,k] | None) -> (sigma [n], rgb [n,3])``
(docs/design.md §5); :meth:`OccupancyGrid.from_field` probes its density, through ``density_only(x,
theta) -> sigma [n]`` where the field has it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

Field = Callable[[Tensor, Tensor, "Tensor | None"], tuple[Tensor, Tensor]]


class RayOccupancy(Protocol):
    """Occupancy along ``m`` rays, prepared by :meth:`Occupancy.along` for one march."""

    def __call__(self, t: Tensor) -> Tensor:
        """``t [m, w]`` distances along each ray -> ``[m, w]`` bool: the point ``o + t d`` may hold density."""
        ...

    def select(self, keep: Tensor) -> RayOccupancy:
        """The same for the rays ``keep [m']`` (indices) only, as the marcher retires rays."""
        ...

    # Optional: ``span() -> (near [m], far [m])``, distances along each ray outside which nothing is
    # occupied (``near > far``: nothing at all); the marcher then marches each ray only there.


class Occupancy(Protocol):
    """Which points may hold density, for a configuration ``theta`` (``[k]``, ``[n,k]`` or ``None``: any).

    An answer may err on the side of "occupied", never the other way: the marcher skips what is not.
    """

    def occupied(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        """``x [n,3]`` (metres), ``theta [k] | [n,k] | None`` -> ``[n]`` bool."""
        ...

    def bounds(self, theta: Tensor | None = None) -> Tensor | None:
        """``[2,3]``: a box outside which nothing is occupied at ``theta [k]`` (any ``theta`` if
        ``None``); ``None`` when nothing is occupied at all."""
        ...

    def along(self, origins: Tensor, directions: Tensor, theta: Tensor | None = None) -> RayOccupancy:
        """Occupancy along the rays ``origins``, ``directions [m,3]`` at ``theta [k] | [m,k] | None``."""
        ...


@dataclass
class PointwiseRays:
    """:class:`RayOccupancy` from a pointwise ``occupied(x [n,3], theta) -> [n]``: for an
    :class:`Occupancy` with nothing faster along rays. ``theta``: ``[k]`` shared, ``[m,k]`` per ray, or ``None``."""

    occupied: Callable[[Tensor, Tensor | None], Tensor]
    origins: Tensor
    directions: Tensor
    theta: Tensor | None = None

    def __call__(self, t: Tensor) -> Tensor:
        x = (self.origins[:, None, :] + t[..., None] * self.directions[:, None, :]).reshape(-1, 3)
        theta = self.theta
        if theta is not None and theta.dim() == 2:
            theta = theta.repeat_interleave(t.shape[1], 0)
        return self.occupied(x, theta).reshape(t.shape)

    def select(self, keep: Tensor) -> PointwiseRays:
        theta = self.theta[keep] if self.theta is not None and self.theta.dim() == 2 else self.theta
        return PointwiseRays(self.occupied, self.origins[keep], self.directions[keep], theta)


def needs_theta_grad(theta: Tensor) -> bool:
    """Whether a field must carry the gradient of ``theta`` (grad mode on, ``theta`` requiring it)."""
    return torch.is_grad_enabled() and theta.requires_grad


def one_configuration(theta: Tensor) -> bool:
    """Whether a field may take the rows of ``theta [n, k]`` as one configuration (its kinematics once): an
    expanded θ (one tensor, whose rows' gradients sum into it), or rows equal in value none of which needs a
    gradient of its own (a Gauss-Newton Jacobian's per-ray θ leaves each need theirs). True for no rows."""
    if theta.shape[0] == 0 or theta.stride(0) == 0:
        return True
    return not needs_theta_grad(theta) and bool((theta == theta[:1]).all())


def density_fn(field) -> Callable[[Tensor, Tensor | None], Tensor]:
    """``(x [n,3], theta) -> sigma [n]`` of ``field``: its ``density_only`` if it has one, else its
    density at ``d = 0``."""
    density_only = getattr(field, "density_only", None)
    if density_only is not None:
        return density_only
    return lambda x, theta: field(x, torch.zeros_like(x), theta)[0]


def _cells_for(aabb: Tensor, resolution: int | Sequence[int]) -> tuple[int, int, int]:
    """Cells per axis: ``resolution`` along the longest axis and about cubic cells, or 3 given counts."""
    if isinstance(resolution, int):
        if resolution < 1:
            raise ValueError(f"grid resolution must be >= 1, got {resolution}")
        extent = (aabb[1] - aabb[0]).double()
        cells = [max(1, math.ceil(resolution * float(e / extent.max()) - 1e-6)) for e in extent]
        return cells[0], cells[1], cells[2]
    cells = [int(r) for r in resolution]
    if len(cells) != 3 or min(cells) < 1:
        raise ValueError(f"grid resolution must be an int or 3 positive ints, got {resolution}")
    return cells[0], cells[1], cells[2]




def _configurations(
    field, theta_samples: Tensor | None, theta_bins: int | None
) -> tuple[list[Tensor | None], int, tuple[int, ...], Tensor | None]:
    """The configurations :meth:`OccupancyGrid.from_field` evaluates.

    Returns the distinct configurations (each ``[k]``, or ``None`` for a part field), the
    samples per bin and axis, the bins per axis (empty for a single union grid) and the
    ``theta_range [2,k]`` of a binned grid. Binned: a per-axis ``linspace`` over the limits with
    ``per_bin - 1`` steps per bin, in row-major product order.
    """
    lower, upper = getattr(field, "theta_lower", None), getattr(field, "theta_upper", None)
    if theta_samples is not None:
        return list(theta_samples.to(torch.float32)), 0, (), None
    if lower is None or lower.numel() == 0:
        return [None], 0, (), None
    k = lower.numel()
    bins = theta_bins if theta_bins is not None else max(1, round(8 ** (1.0 / k)))
    if bins < 1:
        raise ValueError(f"theta_bins must be >= 1, got {bins}")
    per_bin = max(2, round(4 ** (1.0 / k)))
    steps = bins * (per_bin - 1) + 1
    axes = [torch.linspace(float(lo), float(hi), steps) for lo, hi in zip(lower, upper)]
    thetas = torch.cartesian_prod(*axes).reshape(-1, k).to(lower.device, torch.float32)
    return list(thetas), per_bin, (bins,) * k, torch.stack([lower, upper]).float()


def _dilate(occ: Tensor, cells: int) -> Tensor:
    """Grow the occupied set of ``occ [..., Rx, Ry, Rz]`` (bool) by ``cells`` cells (a cube)."""
    if cells <= 0:
        return occ
    lead = occ.shape[:-3]
    v = occ.reshape(-1, 1, *occ.shape[-3:]).float()
    v = F.max_pool3d(v, 2 * cells + 1, stride=1, padding=cells)
    return (v > 0).reshape(*lead, *occ.shape[-3:])


def _tight_box(aabb: Tensor, occ: Tensor) -> Tensor | None:
    """``[2,3]`` around the occupied cells of ``occ [Rx, Ry, Rz]``, or ``None`` if there are none."""
    nz = occ.nonzero()
    if nz.shape[0] == 0:
        return None
    size = (aabb[1] - aabb[0]) / torch.tensor(occ.shape, dtype=aabb.dtype, device=aabb.device)
    return torch.stack([aabb[0] + nz.amin(0) * size, aabb[0] + (nz.amax(0) + 1) * size])


@dataclass(frozen=True)
class OccupancyGrid:
    """Which cells of a box may hold density, optionally per bin of the configuration.

    ``occupancy``: bool ``[Rx, Ry, Rz]`` over ``aabb [2,3]``, or ``[B, .., B, Rx, Ry, Rz]`` with
    ``k`` leading axes of ``B`` bins each that split ``theta_range [2,k]`` (lower, upper) evenly:
    then each 3D grid holds for every ``theta`` in its bin, and :attr:`union` for every ``theta``
    in the limits. Cell ``(i, j, l)`` covers ``aabb[0] + ([i, j, l] + [0, 1)) * cell_size``.
    Immutable (lookup tables are derived once); ``aabb`` and ``theta_range`` are kept as float32.
    In a model bundle: ``occupancy`` as uint8, ``aabb`` and ``theta_range`` as lists.
    """

    aabb: Tensor
    occupancy: Tensor
    theta_range: Tensor | None = None

    def __post_init__(self) -> None:
        aabb = self.aabb.to(torch.float32)
        if tuple(aabb.shape) != (2, 3) or not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"grid aabb must be [2,3] with max > min, got {aabb.tolist()}")
        occupancy = self.occupancy.bool()
        k = occupancy.dim() - 3
        if k < 0:
            raise ValueError(f"occupancy must be [Rx, Ry, Rz] or [bins.., Rx, Ry, Rz], got shape {tuple(occupancy.shape)}")
        theta_range = None if self.theta_range is None else self.theta_range.to(torch.float32)
        if k > 0:
            if theta_range is None or tuple(theta_range.shape) != (2, k):
                raise ValueError(f"an occupancy with {k} configuration axes needs theta_range [2, {k}]")
            if len(set(occupancy.shape[:k])) != 1:
                raise ValueError(f"every configuration axis needs the same number of bins, got {tuple(occupancy.shape[:k])}")
            if not bool((theta_range[1] > theta_range[0]).all()):
                raise ValueError(f"theta_range must have upper > lower, got {theta_range.tolist()}")
        elif theta_range is not None:
            raise ValueError("theta_range is only for an occupancy with configuration bins")
        cells = tuple(occupancy.shape[k:])
        per_bin = occupancy.reshape(-1, *cells)
        union = per_bin.any(0)
        if union.numel() >= 1 << 24:
            raise ValueError(f"at most 2^24 cells per grid, got {cells}")
        derived = {
            "aabb": aabb,
            "occupancy": occupancy,
            "theta_range": theta_range,
            "union": union,  # [Rx, Ry, Rz]: valid for every theta
            "_k": k,
            "_bins": occupancy.shape[0] if k else 1,
            "_cells": cells,
            "_flat": occupancy.reshape(-1),
            "_union_flat": union.reshape(-1),
            "_scale": torch.tensor(cells, dtype=torch.float32, device=aabb.device) / (aabb[1] - aabb[0]),
            "_bounds": _tight_box(aabb, union),
            "_bin_bounds": [_tight_box(aabb, g) for g in per_bin] if k else [],
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)

    @property
    def resolution(self) -> tuple[int, int, int]:
        """Cells per spatial axis."""
        return tuple(self._cells)  # type: ignore[return-value]

    @property
    def cell_size(self) -> Tensor:
        """``[3]`` cell edge lengths (metres)."""
        return (self.aabb[1] - self.aabb[0]) / torch.tensor(self.resolution, dtype=self.aabb.dtype, device=self.aabb.device)

    @property
    def fraction(self) -> float:
        """The mean share of occupied cells (over the bins)."""
        return float(self._flat.float().mean())

    @classmethod
    def full(cls, aabb: Tensor, resolution: int | Sequence[int] = 64) -> OccupancyGrid:
        """Every cell occupied (before a field is trained)."""
        return cls(aabb, torch.ones(_cells_for(aabb, resolution), dtype=torch.bool, device=aabb.device))

    @classmethod
    def from_points(cls, aabb: Tensor, resolution: int | Sequence[int], points: Tensor, dilate: int = 0) -> OccupancyGrid:
        """The cells (``resolution`` as in :meth:`full`) that hold one of ``points [n,3]`` (those outside
        ``aabb`` left out), grown by ``dilate`` cells."""
        shape = _cells_for(aabb, resolution)
        grid = cls(aabb, torch.zeros(shape, dtype=torch.bool, device=aabb.device))
        inside = ((points >= aabb[0]) & (points <= aabb[1])).all(-1)
        top = torch.tensor(shape, device=aabb.device) - 1
        cell = torch.minimum(grid._cell_units(points[inside]).floor().long(), top)
        occ = grid.occupancy.clone()
        occ[cell[:, 0], cell[:, 1], cell[:, 2]] = True
        return cls(aabb, _dilate(occ, dilate))

    @classmethod
    @torch.no_grad()
    def from_field(
        cls,
        field,
        aabb: Tensor,
        resolution: int | Sequence[int] = 128,
        *,
        theta_samples: Tensor | None = None,
        theta_bins: int | None = None,
        threshold: float | None = None,
        passes: int = 3,
        dilate: int = 1,
        chunk: int = 1 << 16,
        generator: torch.Generator | None = None,
    ) -> OccupancyGrid:
        """The cells where ``field``'s density exceeds ``threshold`` somewhere, dilated by ``dilate`` cells.

        Density is evaluated at every cell centre and at ``passes - 1`` random points per cell, and
        the maximum over the configurations is kept. Configurations: the rows of ``theta_samples
        [m, k]`` if given (one grid, their union); otherwise, for a field with joint limits
        (``theta_lower``/``theta_upper``), ``theta_bins`` bins per axis (default 8 for one joint,
        fewer for more; ignored with ``theta_samples``), each sampled at 4 (k = 1) evenly spaced
        points, its edges included.
        ``threshold`` (1/m) defaults to the density that gives 1% opacity across one cell's
        diagonal. ``resolution``: cells along the longest axis (cubic cells), or three counts.
        From 16 cells per axis up, only the cells under a (generously thresholded, dilated) grid
        of twice the cell size are evaluated.
        """
        aabb = aabb.to(torch.float32)
        cells = _cells_for(aabb, resolution)
        size = (aabb[1] - aabb[0]) / torch.tensor(cells, dtype=torch.float32, device=aabb.device)
        if threshold is None:
            threshold = -math.log1p(-0.01) / float(size.norm())
        thetas, per_bin, bins, theta_range = _configurations(field, theta_samples, theta_bins)

        axes = [torch.arange(c, dtype=torch.float32, device=aabb.device) for c in cells]
        index = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # [cells, 3]
        if min(cells) >= 16:  # coarse-to-fine: skip the cells under an empty coarse cell
            coarse_cells = [(c + 1) // 2 for c in cells]
            coarse_box = torch.stack([aabb[0], aabb[0] + 2 * size * torch.tensor(coarse_cells, device=aabb.device)])
            coarse = cls.from_field(
                field, coarse_box, coarse_cells, theta_samples=theta_samples, theta_bins=theta_bins,
                threshold=threshold / 4, passes=passes, dilate=1, chunk=chunk, generator=generator,
            )
            parent = (index / 2).long()
            index = index[coarse.union[parent[:, 0], parent[:, 1], parent[:, 2]]]

        density = density_fn(field)
        best = torch.zeros(len(thetas), index.shape[0], device=aabb.device)  # per configuration
        for p in range(max(1, passes)):
            offset = torch.full_like(index, 0.5) if p == 0 else torch.rand(index.shape, generator=generator).to(aabb.device)
            x = aabb[0] + (index + offset) * size
            for i, theta in enumerate(thetas):
                for s in range(0, x.shape[0], chunk):
                    xs = x[s : s + chunk]
                    th = None if theta is None else theta.expand(xs.shape[0], -1)
                    best[i, s : s + chunk] = torch.maximum(best[i, s : s + chunk], density(xs, th).float())
        if bins:  # the maximum over each bin's configurations (bins share their edge samples)
            k = len(bins)
            best = best.reshape(*[bins[0] * (per_bin - 1) + 1] * k, -1)
            for axis in range(k):
                best = best.unfold(axis, per_bin, per_bin - 1).amax(-1)
        else:
            best = best.amax(0)
        occ = torch.zeros(*best.shape[:-1], *cells, dtype=torch.bool, device=aabb.device)
        occ[..., index[:, 0].long(), index[:, 1].long(), index[:, 2].long()] = best > threshold
        return cls(aabb, _dilate(occ, dilate), theta_range)


    def _bin_offset(self, theta: Tensor) -> Tensor:
        """Flat offset of the bin of ``theta [k]`` or ``[n,k]`` (clamped into the range)."""
        lo, hi = self.theta_range[0].to(theta.dtype), self.theta_range[1].to(theta.dtype)
        b = ((theta - lo) * (self._bins / (hi - lo))).long().clamp(0, self._bins - 1)
        flat = b[..., 0]
        for i in range(1, self._k):
            flat = flat * self._bins + b[..., i]
        return (flat * self._union_flat.numel()).int()

    def _table_offset(self, theta: Tensor | None) -> Tensor | int:
        """The offset :meth:`_lookup` takes for ``theta [k]`` (an int) or ``[m,k]`` (``[m,1]``);
        ``-1`` (the union) without ``theta`` or for a grid without bins."""
        if self._k == 0 or theta is None:
            return -1
        offset = self._bin_offset(theta)
        return int(offset) if theta.dim() == 1 else offset[:, None]

    def _cell_units(self, x: Tensor) -> Tensor:
        """``x [m,3]`` (metres, object frame) in cell units: ``(x - aabb[0]) * cells / extent`` (float32)."""
        return (x.float() - self.aabb[0]) * self._scale

    def _lookup(self, cell_o: Tensor, cell_d: Tensor, t: Tensor, offset: Tensor | int) -> Tensor:
        """Occupancy at ``t [m, w]`` along rays in cell units (``cell_o``, ``cell_d [m,3]``) -> ``[m, w]``.

        One contiguous ``[m, w]`` pass per axis; points outside the box read the nearest cell.
        ``offset``: :meth:`_table_offset` of the configuration(s).
        """
        t = t.float()
        flat = None
        for axis, r in enumerate(self._cells):
            c = torch.addcmul(cell_o[:, axis : axis + 1].float(), t, cell_d[:, axis : axis + 1].float())
            c = c.floor_().clamp_(0, r - 1)
            flat = c if flat is None else flat.mul_(r).add_(c)  # exact: fewer than 2^24 cells per bin
        index = flat.int()  # int32: faster to convert and to gather with than int64
        if isinstance(offset, int) and offset < 0:
            return self._union_flat[index]
        return self._flat[index + offset]

    def occupied(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        """``x [n,3]`` (metres) -> ``[n]`` bool: inside the box (faces included) and in an occupied cell.

        ``theta`` (``[k]`` or ``[n,k]``) picks the configuration bin; without it, or for a grid
        without bins, the union over the configurations is used.
        """
        x = x.float()
        inside = ((x >= self.aabb[0]) & (x <= self.aabb[1])).all(-1)
        cells = self._cell_units(x)
        hit = self._lookup(cells, torch.zeros_like(cells), x.new_zeros(x.shape[0], 1), self._table_offset(theta))
        return hit[:, 0] & inside

    def along(self, origins: Tensor, directions: Tensor, theta: Tensor | None = None) -> GridRays:
        """Occupancy along rays (the marcher's fast path): the rays are moved into cell units once."""
        return GridRays(self, self._cell_units(origins), directions.float() * self._scale, self._table_offset(theta))

    def bounds(self, theta: Tensor | None = None) -> Tensor | None:
        """``[2,3]`` the tight box around the occupied cells (of ``theta [k]``'s bin), ``None`` if none."""
        if self._k == 0 or theta is None:
            return self._bounds
        return self._bin_bounds[int(self._bin_offset(theta)) // self._union_flat.numel()]

    def to(self, device: torch.device | str) -> OccupancyGrid:
        return OccupancyGrid(
            self.aabb.to(device), self.occupancy.to(device), None if self.theta_range is None else self.theta_range.to(device)
        )


@dataclass
class GridRays:
    """:class:`RayOccupancy` of an :class:`OccupancyGrid`: the rays in cell units (``cell_o``, ``cell_d
    [m,3]``) and the table offset of their configuration bin (one int, or ``[m,1]`` per ray)."""

    grid: OccupancyGrid
    cell_o: Tensor
    cell_d: Tensor
    offset: Tensor | int

    def __call__(self, t: Tensor) -> Tensor:
        return self.grid._lookup(self.cell_o, self.cell_d, t, self.offset)

    def select(self, keep: Tensor) -> GridRays:
        offset = self.offset if isinstance(self.offset, int) else self.offset[keep]
        return GridRays(self.grid, self.cell_o[keep], self.cell_d[keep], offset)
