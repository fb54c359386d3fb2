"""K-planes: a radiance field factorised into 2D feature planes over every pair of input axes.

The axes are ``(x, y, z)`` and, for the configuration field, ``(theta_1 .. theta_k)``. There is one
plane per pair of axes (``k = 0``: xy xz yz; ``k = 1``: xy xz yz x.theta y.theta z.theta), at a few
scales. A sample's features are the Hadamard product over the planes of their bilinear lookups,
concatenated over scales, then decoded by a small MLP whose last linear layer gives the density and
the colour logits (plus, optionally, a linear term in the spherical harmonics of the view
direction), then a sigmoid. Spatial planes are sized so that cells are about cubic on an elongated box.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import combinations

import torch
from torch import Tensor, nn

from narf_core.fields.base import RadianceField, activated_jacobian, trunc_exp
from narf_core.fields.encodings import _EDGE_SHRINK, in_texel_step, sample_plane, spherical_harmonics


def total_variation(plane: Tensor) -> Tensor:
    """Mean squared difference between neighbouring texels of ``plane [H, W, F]`` (both axes)."""
    dv = plane[1:] - plane[:-1]
    du = plane[:, 1:] - plane[:, :-1]
    return (dv * dv).mean() + (du * du).mean()


class KPlanesField(RadianceField):
    """A K-planes field ``(x, d, theta) -> (sigma, rgb)``; a part field when no limits are given.

    Args:
        aabb: ``[2,3]`` box (metres) in the field's frame.
        theta_lower, theta_upper: ``[k]`` joint limits (None for a part field).
        resolution: per scale, texels along the longest box axis (other axes proportionally fewer).
        theta_resolution: per scale, texels along every configuration axis.
        features: feature channels per plane.
        hidden, layers: the decoder MLP's width and depth.
        dir_degree: spherical-harmonics bands of the view direction fed to the colour (0 = none).
        tv_weight: weight of the planes' total variation in :meth:`regularization`.
    """

    def __init__(
        self,
        aabb,
        theta_lower=None,
        theta_upper=None,
        *,
        resolution: Sequence[int] = (64, 128),
        theta_resolution: Sequence[int] = (16, 32),
        features: int = 16,
        hidden: int = 64,
        layers: int = 2,
        dir_degree: int = 0,
        tv_weight: float = 1e-4,
    ) -> None:
        super().__init__(aabb, theta_lower, theta_upper)
        resolution, theta_resolution = [int(r) for r in resolution], [int(r) for r in theta_resolution]
        if not resolution or len(resolution) != len(theta_resolution):
            raise ValueError(
                f"resolution and theta_resolution need one entry per scale, got {resolution} and {theta_resolution}"
            )
        if min(resolution + theta_resolution) < 2:
            raise ValueError(f"plane resolutions must be >= 2, got {resolution} and {theta_resolution}")
        if features < 1 or hidden < 1 or layers < 1:
            raise ValueError(f"features, hidden and layers must be >= 1, got {features}, {hidden}, {layers}")
        if not 0 <= dir_degree <= 4:
            raise ValueError(f"dir_degree must be in 0..4 (spherical-harmonics bands), got {dir_degree}")
        self.resolution, self.theta_resolution = resolution, theta_resolution
        self.features, self.hidden, self.layers = features, hidden, layers
        self.dir_degree, self.tv_weight = dir_degree, float(tv_weight)

        k = self.n_theta
        self.pairs: list[tuple[int, int]] = list(combinations(range(3 + k), 2))
        self._pair_axes = [axis for pair in self.pairs for axis in pair]
        extent = self.aabb[1] - self.aabb[0]
        planes = []
        for r, rt in zip(resolution, theta_resolution):
            sizes = [max(2, math.ceil(r * float(e / extent.max()) - 1e-6)) for e in extent] + [rt] * k
            for a, b in self.pairs:
                shape = (sizes[b], sizes[a], features)  # rows follow axis b, columns axis a
                if b < 3:  # purely spatial: K-planes' random init
                    planes.append(nn.Parameter(torch.empty(shape).uniform_(0.1, 0.5)))
                else:  # involves a configuration axis: ones, so theta starts as a no-op
                    planes.append(nn.Parameter(torch.ones(shape)))
        self.planes = nn.ParameterList(planes)

        width = features * len(resolution)
        mlp: list[nn.Module] = []
        for _ in range(layers):
            mlp += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
            width = hidden
        self.decoder = nn.Sequential(*mlp)
        self.head = nn.Linear(hidden, 4)  # raw density and the view-independent colour logits
        self.direction_head = nn.Linear(dir_degree**2, 3, bias=False) if dir_degree > 0 else None
        with torch.no_grad():  # untrained: about 10% opacity across the whole box
            self.head.bias[0] = math.log(0.1 / float(extent.norm()))

    def plane_features(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        """``x [n,3]``, ``theta [n,k] | [k] | None`` -> the decoder's input ``[n, features * scales]``.

        Computed channel-major (``[features * scales, n]`` in memory, returned transposed) so
        that every lookup and product runs on contiguous rows.
        """
        z = self.normalize_positions(x)
        th = self.normalize_theta(theta, x.shape[0])
        if th is not None:
            z = torch.cat([z, th], dim=-1)
        n_pairs = len(self.pairs)
        coords = torch.stack([z[:, a] for a in self._pair_axes], dim=-1)  # cheaper backward than z[:, list]
        coords = coords.reshape(-1, n_pairs, 2).transpose(0, 1)  # [pairs, n, 2]
        scales = []
        for s in range(len(self.resolution)):
            f = None
            for p in range(n_pairs):
                v = sample_plane(self.planes[s * n_pairs + p], coords[p]).t()  # [F, n], contiguous
                f = v if f is None else f * v
            scales.append(f)
        return torch.cat(scales, dim=0).t()

    def density(self, x: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``sigma [n]`` and, as features, the view-independent colour logits ``[n, 3]``."""
        out = self.head(self.decoder(self.plane_features(x, theta)))
        return trunc_exp(out[:, 0]), out[:, 1:]

    @property
    def supports_jacobian(self) -> bool:
        """Whether :meth:`jacobian` serves: the colour does not depend on the view direction."""
        return self.direction_head is None

    @torch.no_grad()
    def jacobian(self, x: Tensor, theta: Tensor | None) -> tuple[Tensor, Tensor]:
        """The field and its derivatives at ``x [n, 3]``, ``θ [k]`` or ``[n, k]``: ``values [n, 4]`` (``σ``,
        colour) and ``∂values/∂(x, θ) [n, 4, 3 + k]``; no graph, view-independent fields only.

        Every column is one difference along its axis that keeps every lookup between the same two texel
        centres (:func:`~narf_core.fields.encodings.in_texel_step`: there the bilinear lookup is linear, and
        the difference its derivative); a plane is looked up again only where
        the moved axis is one of its pair's (one ``grid_sample`` per plane for the point and its two moves),
        and the decoder runs once on the ``1 + 3 + k`` feature sets (see
        :meth:`~narf_core.fields.articulated.ArticulatedField.jacobian`)."""
        if not self.supports_jacobian:
            raise ValueError("a field whose colour depends on the view direction has no jacobian here")
        n, k = x.shape[0], self.n_theta
        z = self.normalize_positions(x)  # [n, 3 + k] over [-1, 1], the planes' coordinates
        per_unit = 2 / (self.aabb[1] - self.aabb[0])  # dz/dx
        if k:
            z = torch.cat([z, self.normalize_theta(theta, n)], 1)
            per_unit = torch.cat([per_unit, 2 / (self.theta_upper - self.theta_lower)])
        T, n_pairs = 4 + k, len(self.pairs)
        texels = []  # along each axis at each scale, as a plane over it holds them (rows follow a pair's second axis)
        for a in range(3 + k):
            p, pair = next((p, pair) for p, pair in enumerate(self.pairs) if a in pair)
            texels.append([self.planes[s_ * n_pairs + p].shape[1 - pair.index(a)] for s_ in range(len(self.resolution))])
        half = (torch.tensor(texels, dtype=z.dtype, device=z.device) - 1) / 2  # [3 + k, S]: grid_sample's texels per unit
        texel = (z[..., None] * _EDGE_SHRINK + 1) * half  # [n, 3 + k, S]: each axis's texel coordinate per scale
        rate = _EDGE_SHRINK * half  # its change per unit of z
        h = torch.stack([in_texel_step(texel[:, a], rate[a].expand(n, -1)) for a in range(3 + k)], 1)  # [n, 3 + k]
        scales = []
        for s_ in range(len(self.resolution)):
            f = z.new_ones(T, self.features, n)  # the point's features, then each column's moved point's
            for p, (a, b) in enumerate(self.pairs):
                c = z[:, [a, b]]
                moved_a, moved_b = c.clone(), c.clone()
                moved_a[:, 0] += h[:, a]
                moved_b[:, 1] += h[:, b]
                v = sample_plane(self.planes[s_ * n_pairs + p], torch.cat([c, moved_a, moved_b])).t().reshape(-1, 3, n)
                for t in range(T):
                    f[t] *= v[:, 1] if t == 1 + a else v[:, 2] if t == 1 + b else v[:, 0]
            scales.append(f)
        features = torch.cat(scales, 1).transpose(1, 2).reshape(T * n, -1)  # [T n, F S]
        raw = self.head(self.decoder(features)).reshape(T, n, 4)
        draw = ((raw[1:] - raw[:1]) / h.t()[..., None] * per_unit[:, None, None]).permute(1, 2, 0).to(x.dtype)
        sigma, colour, dsigma, dcolour = activated_jacobian(raw[0].to(x.dtype), draw)
        return torch.cat([sigma[:, None], colour], 1), torch.cat([dsigma[:, None], dcolour], 1)

    def color(self, features: Tensor, d: Tensor) -> Tensor:
        if self.direction_head is not None:
            features = features + self.direction_head(spherical_harmonics(d, self.dir_degree))
        return torch.sigmoid(features)

    def total_variation(self) -> Tensor:
        """Mean over the planes of :func:`total_variation` (a scalar)."""
        return torch.stack([total_variation(p) for p in self.planes]).mean()

    def regularization(self) -> Tensor:
        return self.tv_weight * self.total_variation()

    def config(self) -> dict:
        return {
            "arch": "kplanes",
            "aabb": self.aabb.tolist(),
            "theta_lower": None if self.theta_lower is None else self.theta_lower.tolist(),
            "theta_upper": None if self.theta_upper is None else self.theta_upper.tolist(),
            "resolution": self.resolution,
            "theta_resolution": self.theta_resolution,
            "features": self.features,
            "hidden": self.hidden,
            "layers": self.layers,
            "dir_degree": self.dir_degree,
            "tv_weight": self.tv_weight,
        }
