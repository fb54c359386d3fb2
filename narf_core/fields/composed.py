"""The articulated object as one field composed of its rigid part fields (docs/design.md §4.2, ``volumetric``).

A sample ``x`` in the object frame is moved into every part's frame (``x_part = T_part_obj x``, ``d``
rotated); a part is evaluated only where the sample lies in its box (in its occupied cells when it has
a grid); densities add and the colour is the density-weighted mean (0 where no part has density).
This is exact and differentiable in ``x``, ``d`` and the part poses (so in ``θ`` through the forward
kinematics), and it has the same call signature as the distilled configuration field, so one
renderer serves both.

One composition (:func:`compose`), posed two ways: :class:`ComposedField` runs the forward kinematics
for every ``θ`` it is given (per sample, or once for a shared ``θ``); :class:`PosedComposition` holds
the parts at fixed poses (:func:`compose_parts`, e.g. one render at one ``θ``) and is also an
:class:`~narf_core.occupancy.Occupancy` (the union of its parts' grids), so a render can skip its
empty space. :func:`union_occupancy` builds the object-frame grid over every ``θ`` from the part grids.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from narf_core.geometry import box_corners, invert_pose, rotate_vectors, transform_points
from narf_core.occupancy import Field, Occupancy, OccupancyGrid, PointwiseRays, one_configuration


def compose(
    part_fields: Sequence[Field], part_grids: Sequence[Occupancy | None], T_part_obj: Tensor, x: Tensor, d: Tensor
) -> tuple[Tensor, Tensor]:
    """``(sigma [n], rgb [n,3])`` of the parts at ``x``, ``d [n,3]`` (object frame, any float dtype).

    ``T_part_obj``: ``[p,4,4]`` (one pose per part) or ``[n,p,4,4]`` (per sample). A part without a
    grid counts as occupied inside its box (its ``aabb`` attribute). Results are in ``x``'s dtype.
    """
    sigma = x.new_zeros(x.shape[0])
    weighted = x.new_zeros(x.shape[0], 3)
    for i, (idx, xp) in enumerate(_part_samples(part_fields, part_grids, T_part_obj, x)):
        if idx.numel() == 0:
            continue
        T = T_part_obj[..., i, :, :].to(d.dtype)
        dp = rotate_vectors(T if T.dim() == 2 else T[idx], d[idx])
        s, c = part_fields[i](xp, dp, None)
        s = s.to(x.dtype)
        sigma = sigma.index_add(0, idx, s)
        weighted = weighted.index_add(0, idx, s[:, None] * c.to(x.dtype))
    rgb = torch.where(sigma[:, None] > 0, weighted / sigma.clamp_min(1e-30)[:, None], 0.0)
    return sigma, rgb


def _part_samples(
    part_fields: Sequence[Field], part_grids: Sequence[Occupancy | None], T_part_obj: Tensor, x: Tensor
) -> list[tuple[Tensor, Tensor]]:
    """Per part: the indices of the samples ``x [n,3]`` it covers and their positions in its frame."""
    out = []
    for i, grid in enumerate(part_grids):
        xp = transform_points(T_part_obj[..., i, :, :].to(x.dtype), x)
        inside = grid.occupied(xp) if grid is not None else _inside(xp, part_fields[i].aabb.to(x.dtype))
        idx = inside.nonzero().squeeze(-1)
        out.append((idx, xp[idx]))
    return out


def _inside(x: Tensor, aabb: Tensor) -> Tensor:
    """``x [n,3]`` inside the box ``aabb [2,3]`` (faces included) -> ``[n]`` bool."""
    return ((x >= aabb[0]) & (x <= aabb[1])).all(-1)


def composed_aabb(part_aabbs: Tensor, T_obj_part: Tensor) -> Tensor:
    """``[2,3]``: the object-frame box around part boxes ``part_aabbs [p,2,3]`` posed by ``T_obj_part [p,4,4]``."""
    corners = torch.stack([box_corners(b) for b in part_aabbs.to(T_obj_part.dtype)])  # [p, 8, 3]
    moved = transform_points(T_obj_part[:, None], corners).reshape(-1, 3)
    return torch.stack([moved.amin(0), moved.amax(0)])


class ComposedField(nn.Module):
    """``(x [n,3], d [n,3], θ [n,k] | [k]) -> (σ [n], rgb [n,3])`` from rigid part fields (:func:`compose`).

    ``part_poses(θ [..., k]) -> T_obj_part [..., n_parts, 4, 4]`` is the object's forward
    kinematics; ``part_grids`` (optional) skip the samples that fall in a part's empty space. A
    ``θ`` shared by all samples (``[k]``, or rows that are one: :func:`~narf_core.occupancy.one_configuration`)
    runs the kinematics once; rows that are leaves of their own get each their own ``∂/∂θ``.
    """

    def __init__(
        self,
        part_fields: Sequence[nn.Module],
        part_grids: Sequence | None,
        part_poses: Callable[[Tensor], Tensor],
    ) -> None:
        super().__init__()
        self.parts = nn.ModuleList(part_fields)
        self.grids = list(part_grids) if part_grids is not None else [None] * len(part_fields)
        self.part_poses = part_poses

    def forward(self, x: Tensor, d: Tensor, theta: Tensor | None) -> tuple[Tensor, Tensor]:
        if x.shape[0] == 0:
            return x.new_zeros(0), x.new_zeros(0, 3)
        shared = theta is None or theta.dim() == 1 or one_configuration(theta)
        theta_one = theta if theta is None or theta.dim() == 1 else theta[0]
        T_part_obj = invert_pose(self.part_poses(theta_one if shared else theta).to(x.dtype))
        return compose(self.parts, self.grids, T_part_obj, x, d)


class PosedComposition:
    """The parts at fixed poses ``T_obj_part [p,4,4]``: a field (``θ`` is ignored) and an occupancy.

    As a field, :func:`compose` (differentiable in the poses). As an
    :class:`~narf_core.occupancy.Occupancy`: ``occupied(x)`` is the union of the parts' occupancy
    (their grids, or their boxes), ``bounds()`` is :attr:`aabb`, the object-frame box around the
    posed part boxes, so the composition can be passed as its own ``grid``.
    """

    def __init__(self, part_fields: Sequence[Field], part_grids: Sequence[Occupancy | None], T_obj_part: Tensor) -> None:
        if not (len(part_fields) == len(part_grids) == T_obj_part.shape[0]) or T_obj_part.shape[1:] != (4, 4):
            raise ValueError(
                f"need one grid (or None) and one pose [4,4] per part: got {len(part_fields)} fields, "
                f"{len(part_grids)} grids and poses of shape {tuple(T_obj_part.shape)}"
            )
        self.fields, self.grids = list(part_fields), list(part_grids)
        self.T_obj_part = T_obj_part
        self.T_part_obj = invert_pose(T_obj_part)
        self.part_aabbs = torch.stack([f.aabb.to(T_obj_part.dtype) for f in self.fields])
        self.aabb = composed_aabb(self.part_aabbs, T_obj_part)

    def __call__(self, x: Tensor, d: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        return compose(self.fields, self.grids, self.T_part_obj, x, d)

    def occupied(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        hit = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        for idx, _ in _part_samples(self.fields, self.grids, self.T_part_obj, x):
            hit[idx] = True
        return hit

    def bounds(self, theta: Tensor | None = None) -> Tensor:
        return self.aabb

    def along(self, origins: Tensor, directions: Tensor, theta: Tensor | None = None) -> PointwiseRays:
        return PointwiseRays(self.occupied, origins, directions)


def compose_parts(
    part_fields: Sequence[Field], part_grids: Sequence[Occupancy | None], T_obj_part: Tensor
) -> PosedComposition:
    """The composition of ``part_fields`` posed by ``T_obj_part [p,4,4]`` (see :class:`PosedComposition`)."""
    return PosedComposition(part_fields, part_grids, T_obj_part)


def union_occupancy(
    part_grids: Sequence,
    part_poses: Callable[[Tensor], Tensor],
    lower: Tensor,
    upper: Tensor,
    aabb: Tensor,
    resolution: int,
    *,
    bins: int = 8,
    samples_per_bin: int = 8,
) -> OccupancyGrid:
    """The object-frame occupancy of the composition, per bin of the configuration.

    Each axis of the joint box ``[lower, upper] [k]`` is split into ``bins``. Every occupied part
    cell is moved rigidly by the part poses at ``samples_per_bin`` configurations per axis spanning
    each bin (edges included; dense enough that no part moves more than a cell between neighbours,
    as the caller ensures), and every object cell its moved box's bounding box touches is marked
    (cells of a part grid finer than the object grid are merged into blocks no larger than an
    object cell first). The cells of parts that move are then dilated by one cell to cover the
    motion between samples; a part that keeps one pose (the root's) is splatted once, undilated.
    Cheaper and tighter than probing the composed density, and a renderer at a given ``θ`` only
    marches the cells of its bin. ``part_poses(θ [m, k]) -> T_obj_part [m, n_parts, 4, 4]`` is the
    forward kinematics.
    """
    k = len(lower)
    cells = OccupancyGrid.full(aabb, resolution).occupancy.shape
    size = (aabb[1] - aabb[0]) / torch.tensor(cells)
    edges = [torch.linspace(float(lo), float(hi), bins + 1, dtype=torch.float64) for lo, hi in zip(lower, upper)]
    thetas, bin_of = [], []  # every configuration sampled, and the flat index of its bin
    for flat_bin, b in enumerate(itertools.product(range(bins), repeat=k)):
        axes = [torch.linspace(float(e[i]), float(e[i + 1]), samples_per_bin, dtype=torch.float64) for e, i in zip(edges, b)]
        theta = torch.cartesian_prod(*axes).reshape(-1, k) if k else torch.zeros(1, 0, dtype=torch.float64)
        thetas.append(theta)
        bin_of.append(torch.full((theta.shape[0],), flat_bin))
    poses = part_poses(torch.cat(thetas)).to(aabb.dtype)  # [m, n_parts, 4, 4]
    bin_of = torch.cat(bin_of)
    moving = torch.zeros(bins**k, *cells, dtype=torch.bool)
    still = torch.zeros(cells, dtype=torch.bool)
    n_bins, per_bin = moving.shape[0], moving[0].numel()
    for p, grid in enumerate(part_grids):
        centres, half = _cell_boxes(grid, float(size.min()))
        unique, which = torch.unique(poses[:, p].reshape(-1, 16), dim=0, return_inverse=True)
        unique = unique.reshape(-1, 4, 4)
        if unique.shape[0] == 1:  # no dilation will cover rounding for a part that stays still: grow its boxes a little
            still.view(-1)[_touched_cells(transform_points(unique[:, None], centres), unique[:, :3, :3].abs() @ half,
                                          aabb[0], size, cells, 1e-4, torch.zeros(1, dtype=torch.long))] = True
            continue
        # each distinct pose once, into every bin it occurs in: (pose, bin) pairs, a chunk of poses at a time
        pairs = torch.unique(which * n_bins + bin_of)
        pose_of, bin_of_pair = pairs // n_bins, pairs % n_bins
        chunk = max(1, _SPLAT_CHUNK // max(len(centres), 1))
        for first in range(0, len(pairs), chunk):
            T = unique[pose_of[first:first + chunk]]  # [c, 4, 4]
            moving.view(-1)[_touched_cells(transform_points(T[:, None], centres), T[:, :3, :3].abs() @ half, aabb[0],
                                           size, cells, 0.0, bin_of_pair[first:first + chunk] * per_bin)] = True
    moving = F.max_pool3d(moving[:, None].float(), 3, stride=1, padding=1)[:, 0] > 0
    occ = (moving | still).reshape((bins,) * k + tuple(cells))
    return OccupancyGrid(aabb, occ, torch.stack([lower, upper]).to(aabb.dtype) if k else None)


def _cell_boxes(grid: OccupancyGrid, max_size: float) -> tuple[Tensor, Tensor]:
    """Centres ``[n,3]`` and half-size ``[3]`` of the occupied cells of ``grid``, merged into blocks of
    at most ``max_size`` metres where the grid is finer than that."""
    occupancy, cell = grid.occupancy, grid.cell_size
    factor = max(1, int(max_size // float(cell.max())))
    if factor > 1:
        occupancy = F.max_pool3d(occupancy[None, None].float(), factor, ceil_mode=True)[0, 0] > 0
        cell = cell * factor
    return grid.aabb[0] + (occupancy.nonzero() + 0.5) * cell, cell / 2


_SPLAT_CHUNK = 1 << 17  # boxes moved at once (poses times a part's boxes) while the union is splatted


def _touched_cells(centres: Tensor, half: Tensor, origin: Tensor, size: Tensor, cells, grow: float, base: Tensor
                   ) -> Tensor:
    """The flat indices (row-major, ``[m]``) of every cell of a grid ``cells`` (from ``origin``, cells of
    ``size [3]``) touched by an axis-aligned box ``centres [c, n, 3] ± half [c, 3]`` (``c`` poses of the same
    ``n`` boxes) grown by ``grow`` cells on every side, each pose's offset by ``base [c]`` (its grid's start in
    a stack of grids). Per axis, a box touches the cells from its low end's to its high end's."""
    lo = ((centres - half[:, None] - origin) / size - grow).floor().long()
    hi = ((centres + half[:, None] - origin) / size + grow).floor().long()
    span = int((hi - lo).max()) + 1 if centres.numel() else 0
    strides = (cells[1] * cells[2], cells[2], 1)
    axes = []  # per axis, per offset along it: (the cell's share of the flat index, whether the box reaches it)
    for a in range(3):
        at = [lo[..., a] + o for o in range(span)]
        axes.append([(x * strides[a] + (base[:, None] if a == 0 else 0), (x <= hi[..., a]) & (x >= 0) & (x < cells[a]))
                     for x in at])
    touched = [(fx + fy + fz)[vx & vy & vz] for (fx, vx), (fy, vy), (fz, vz) in itertools.product(*axes)]
    return torch.cat(touched) if touched else torch.zeros(0, dtype=torch.long)
