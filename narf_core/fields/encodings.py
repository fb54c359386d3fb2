"""Input encodings: NeRF's frequency encoding, real spherical harmonics and bilinear feature planes.

Pure functions on tensors. :func:`sample_plane` is the K-planes lookup: ``grid_sample`` on a
channels-last plane (about 3x faster on CPU than channels-first), with coordinates kept off the
exact border so that a joint at its limit still gets a gradient.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def frequency_encoding(x: Tensor, n_levels: int, include_input: bool = True) -> Tensor:
    """NeRF's positional encoding of ``x [n, c]`` (values in about [-1, 1]).

    Returns ``[n, c * (2 * n_levels + include_input)]``: ``x`` itself (optional), then
    ``sin(2^l pi x)`` for ``l < n_levels`` (channel-major), then the matching cosines.
    """
    if n_levels < 0:
        raise ValueError(f"n_levels must be >= 0, got {n_levels}")
    freqs = math.pi * 2.0 ** torch.arange(n_levels, dtype=x.dtype, device=x.device)
    xb = (x[..., None] * freqs).flatten(-2)  # [n, c * L]
    parts = [x] if include_input else []
    return torch.cat(parts + [torch.sin(xb), torch.cos(xb)], dim=-1)


def frequency_encoding_size(n_channels: int, n_levels: int, include_input: bool = True) -> int:
    """The width of :func:`frequency_encoding`'s output."""
    return n_channels * (2 * n_levels + int(include_input))


_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def spherical_harmonics(d: Tensor, degree: int) -> Tensor:
    """Real spherical harmonics of unit directions ``d [n, 3]``: ``[n, degree**2]``.

    ``degree`` counts bands (nerfstudio's convention): 1 gives the constant, 2 adds the three
    linear terms, up to 4 (16 coefficients). ``degree = 0`` gives ``[n, 0]``.
    """
    if not 0 <= degree <= 4:
        raise ValueError(f"spherical harmonics degree must be in 0..4, got {degree}")
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _SH_C0)] if degree >= 1 else []
    if degree >= 2:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree >= 3:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            _SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * xz, _SH_C2[4] * (xx - yy),
        ]
    if degree >= 4:
        out += [
            _SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * xy * z, _SH_C3[2] * y * (4 * zz - xx - yy),
            _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
            _SH_C3[5] * z * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1) if out else d.new_zeros(d.shape[0], 0)


_EDGE_SHRINK = 1 - 1e-6  # pulls coordinates off the exact border (see sample_plane)


def sample_plane(plane: Tensor, coords: Tensor) -> Tensor:
    """Bilinear lookup in a feature plane: ``plane [H, W, F]`` at ``coords [n, 2]`` -> ``[n, F]``.

    ``coords = (u, v)`` are normalised: ``u = -1`` is the centre of column 0 and ``u = 1`` that of
    column ``W - 1`` (``align_corners=True``); ``v`` likewise indexes rows. Outside [-1, 1] the
    value is clamped to the border (and its coordinate gradient is 0). ``grid_sample`` also gives
    a zero coordinate gradient *on* the border, which would freeze a configuration pinned at its
    joint limit; so coordinates are first scaled by ``1 - 1e-6`` (a shift of at most 1e-6 of the
    plane, about 1e-4 texel), and a value at a limit gets the one-sided slope of the edge cell.
    The plane is read channels-last (the fast ``grid_sample`` path on CPU). The result is the
    transpose of a contiguous ``[F, n]`` tensor (``.t()`` gives it back for free). ``H, W >= 2``.
    """
    if plane.dim() != 3 or plane.shape[0] < 2 or plane.shape[1] < 2:
        raise ValueError(f"plane must be [H, W, F] with H, W >= 2, got shape {tuple(plane.shape)}")
    if coords.dim() != 2 or coords.shape[-1] != 2:
        raise ValueError(f"coords must be [n, 2], got shape {tuple(coords.shape)}")
    grid = (coords.to(plane.dtype) * _EDGE_SHRINK)[None, None]
    out = F.grid_sample(plane.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, :, 0].t()


def in_texel_step(texel: Tensor, rate: Tensor, cap: float = 0.003, least: float = 0.001) -> Tensor:
    """Signed steps ``[m]`` for forward differences of bilinear lookups, each kept inside its cells where it can.

    ``texel [m, P]``: lookup coordinates in texel units (texel centres at the integers, as
    ``align_corners=True`` places them); ``rate [m, P]``: their change per unit step. A lookup is linear
    between two texel centres, so a difference that keeps every coordinate between the same two is the
    derivative itself, up to float rounding, which a longer step makes smaller: each row steps half the
    room left before its first cell edge, forward or backward, whichever has more, at most ``cap`` and at
    least ``least`` texels in its fastest coordinate (where the edges of two grids lie close together the
    room is small, and rounding would swamp a shorter step). A row whose coordinates do not move steps 1."""
    moving = rate != 0
    frac = texel - texel.floor()
    speed = rate.abs().where(moving, torch.ones_like(rate))
    inf = torch.full_like(texel, math.inf)
    ahead = torch.where(moving, torch.where(rate > 0, 1 - frac, frac) / speed, inf).amin(1)
    behind = torch.where(moving, torch.where(rate > 0, frac, 1 - frac) / speed, inf).amin(1)
    fastest = rate.abs().amax(1).clamp_min(1e-30)
    forward = ahead >= behind
    size = (0.5 * torch.where(forward, ahead, behind)).clamp(least / fastest, cap / fastest)
    size = torch.where(moving.any(1), size, torch.ones_like(size))
    return torch.where(forward, size, -size)
