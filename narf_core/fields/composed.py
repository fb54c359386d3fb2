"""The articulated object as a configuration-conditioned field built from its part fields.

Composition in ``volumetric`` mode (DESIGN §4.2): a sample ``x`` in the object frame is moved into
every part's frame by the forward kinematics at its own ``θ``; densities add and colour is the
density-weighted mean. This is exact and differentiable in ``x``, ``d`` and ``θ``, and it has the
same call signature as the distilled configuration field, so one renderer serves both.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from narf_core.geometry import invert_pose, rotate_vectors, transform_points
from narf_core.render import OccupancyGrid


class ComposedField(nn.Module):
    """``(x [n,3], d [n,3], θ [n,k] | [k]) -> (σ [n], rgb [n,3])`` from rigid part fields.

    ``part_poses(θ [..., k]) -> T_obj_part [..., n_parts, 4, 4]`` is the object's forward
    kinematics; ``part_grids`` (optional) skip the samples that fall in a part's empty space.
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
        n = x.shape[0]
        if n == 0:
            return x.new_zeros(0), x.new_zeros(0, 3)
        shared = theta is None or theta.dim() == 1 or (theta.shape[0] > 0 and bool((theta == theta[:1]).all()))
        theta_one = theta if theta is None or theta.dim() == 1 else theta[0]
        T_part_obj = invert_pose(self.part_poses(theta_one if shared else theta).to(x.dtype))
        sigma = x.new_zeros(n)
        weighted_rgb = x.new_zeros(n, 3)
        for i, (part, grid) in enumerate(zip(self.parts, self.grids)):
            T = T_part_obj[..., i, :, :]
            xp = transform_points(T, x)
            dp = rotate_vectors(T, d)
            keep = grid.occupied(xp) if grid is not None else _inside(xp, part.aabb)
            idx = keep.nonzero().squeeze(-1)
            if idx.numel() == 0:
                continue
            s, c = part(xp[idx], dp[idx], None)
            sigma = sigma.index_add(0, idx, s)
            weighted_rgb = weighted_rgb.index_add(0, idx, s[:, None] * c)
        rgb = weighted_rgb / sigma.clamp_min(1e-10)[:, None]
        return sigma, rgb.clamp(0, 1)


def _inside(x: Tensor, aabb: Tensor) -> Tensor:
    """``x [n,3]`` inside the box ``aabb [2,3]`` -> ``[n]`` bool."""
    return ((x >= aabb[0]) & (x <= aabb[1])).all(-1)


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

    Each axis of the joint box ``[lower, upper] [k]`` is split into ``bins``; for each bin, every
    occupied part cell (its centre and eight corners) is moved rigidly by the part poses at
    ``samples_per_bin`` configurations per axis spanning the bin (edges included; dense enough
    that no part moves more than a cell between neighbours, as the caller ensures) and splatted
    into the object grid, which is then dilated by one cell. Cheaper and tighter than probing the
    composed density, and a renderer at a given ``θ`` only marches the cells of its bin.
    ``part_poses(θ [m, k]) -> T_obj_part [m, n_parts, 4, 4]`` is the forward kinematics.
    """
    k = len(lower)
    bins = bins if k <= 1 else max(2, int(64 ** (1 / k)))
    cells = OccupancyGrid.full(aabb, resolution).occupancy.shape
    res = torch.tensor(cells)
    size = (aabb[1] - aabb[0]) / res
    corners = torch.tensor([[i, j, l] for i in (0, 1) for j in (0, 1) for l in (0, 1)] + [[0.5, 0.5, 0.5]], dtype=aabb.dtype)
    points = []
    for grid in part_grids:
        idx = grid.occupancy.nonzero().to(aabb.dtype)
        points.append((grid.aabb[0] + (idx[:, None, :] + corners) * grid.cell_size).reshape(-1, 3))
    edges = [torch.linspace(float(lo), float(hi), bins + 1, dtype=torch.float64) for lo, hi in zip(lower, upper)]
    occ = torch.zeros((bins,) * k + tuple(cells), dtype=torch.bool)
    for b in itertools.product(range(bins), repeat=k):
        axes = [torch.linspace(float(e[i]), float(e[i + 1]), samples_per_bin, dtype=torch.float64) for e, i in zip(edges, b)]
        theta = torch.cartesian_prod(*axes).reshape(-1, k) if k else torch.zeros(1, 0, dtype=torch.float64)
        target = occ[b]
        for T_obj_part in part_poses(theta).to(aabb.dtype):
            for p, pts in enumerate(points):
                ijk = ((transform_points(T_obj_part[p], pts) - aabb[0]) / size).floor().long()
                ijk = ijk[((ijk >= 0) & (ijk < res)).all(-1)]
                target[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    flat = occ.reshape(-1, 1, *cells).float()
    occ = (F.max_pool3d(flat, 3, stride=1, padding=1) > 0).reshape(occ.shape)
    return OccupancyGrid(aabb, occ, torch.stack([lower, upper]).to(aabb.dtype) if k else None)
