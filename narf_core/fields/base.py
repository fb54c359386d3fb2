"""The radiance-field base class: density and colour split, normalisation by the box and joint limits.

A field is any callable ``(x [n,3], d [n,3], theta [n,k] | None) -> (sigma [n], rgb [n,3])``
(docs/design.md §5); :class:`RadianceField` is the trainable kind. Positions are in the field's own frame
(object or part frame, metres) and are normalised by the box ``aabb`` to [-1, 1]; the
configuration ``theta`` (radians or metres) by its limits to [-1, 1]. A part field has ``k = 0``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor, nn

SIGMA_MAX_LOG = 15.0  # densities saturate at e^15 ~ 3.3e6 per metre


def trunc_exp(raw: Tensor) -> Tensor:
    """Density activation: ``exp(min(raw, 15))`` whose gradient is that same value everywhere.

    Finite for any input (never inf, never NaN for finite ``raw``) and, unlike a plain clamp,
    still pushes down an overshooting raw value.
    """
    return torch.exp(raw - (raw - raw.clamp(max=SIGMA_MAX_LOG)).detach())


def activated_jacobian(raw: Tensor, draw: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``σ [m]`` and colour ``[m, 3]`` of a decoder's raw outputs ``raw [m, 4]`` (as :func:`trunc_exp` and the
    sigmoid give them), with their derivatives ``[m, c]``, ``[m, 3, c]`` from the raw outputs' ``draw [m, 4, c]``:
    ``trunc_exp``'s derivative is its value, the sigmoid's ``c (1 - c)``."""
    sigma = raw[:, 0].clamp(max=SIGMA_MAX_LOG).exp()
    colour = torch.sigmoid(raw[:, 1:])
    return sigma, colour, sigma[:, None] * draw[:, 0], (colour * (1 - colour))[..., None] * draw[:, 1:]


def _as_box(aabb) -> Tensor:
    box = torch.as_tensor(aabb, dtype=torch.float32)
    if tuple(box.shape) != (2, 3):
        raise ValueError(f"aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got shape {tuple(box.shape)}")
    if not bool(torch.isfinite(box).all()) or not bool((box[1] > box[0]).all()):
        raise ValueError(f"aabb must be finite with max > min on every axis, got {box.tolist()}")
    return box


def _as_limits(lower, upper) -> tuple[Tensor, Tensor] | None:
    if lower is None and upper is None:
        return None
    if lower is None or upper is None:
        raise ValueError("theta_lower and theta_upper must be given together")
    lo = torch.as_tensor(lower, dtype=torch.float32).reshape(-1)
    hi = torch.as_tensor(upper, dtype=torch.float32).reshape(-1)
    if lo.shape != hi.shape:
        raise ValueError(f"theta_lower has {lo.numel()} values but theta_upper has {hi.numel()}")
    if lo.numel() == 0:
        return None
    if not bool(torch.isfinite(lo).all() & torch.isfinite(hi).all()) or not bool((hi > lo).all()):
        raise ValueError(f"joint limits must be finite with upper > lower, got {lo.tolist()} .. {hi.tolist()}")
    return lo, hi


class RadianceField(nn.Module, ABC):
    """A radiance field over a box, optionally conditioned on a configuration ``theta [k]``.

    Buffers: ``aabb [2,3]`` (metres, the field's frame) and, for ``k > 0``, ``theta_lower`` and
    ``theta_upper [k]``. Subclasses implement :meth:`density`, :meth:`color` and :meth:`config`.
    """

    theta_lower: Tensor | None
    theta_upper: Tensor | None

    def __init__(self, aabb, theta_lower=None, theta_upper=None) -> None:
        super().__init__()
        self.register_buffer("aabb", _as_box(aabb))
        limits = _as_limits(theta_lower, theta_upper)
        self.register_buffer("theta_lower", None if limits is None else limits[0])
        self.register_buffer("theta_upper", None if limits is None else limits[1])

    @property
    def n_theta(self) -> int:
        """``k``, the number of configuration inputs (0 for a part field)."""
        return 0 if self.theta_lower is None else self.theta_lower.numel()

    def normalize_positions(self, x: Tensor) -> Tensor:
        """``x [n,3]`` (metres, any float dtype) -> ``[n,3]`` in [-1, 1] over the box, field dtype."""
        lo, hi = self.aabb[0], self.aabb[1]
        return (x.to(lo.dtype) - lo) * (2 / (hi - lo)) - 1

    def normalize_theta(self, theta: Tensor | None, n: int) -> Tensor | None:
        """``theta [n,k]`` or ``[k]`` -> ``[n,k]`` in [-1, 1] over the limits (``None`` when ``k = 0``)."""
        k = self.n_theta
        if k == 0:
            if theta is not None and theta.numel() > 0:
                raise ValueError(f"this field takes no configuration, got theta of shape {tuple(theta.shape)}")
            return None
        if theta is None:
            raise ValueError(f"this field needs a configuration theta with {k} values, got None")
        if theta.shape not in ((k,), (n, k)):
            raise ValueError(f"theta must be [{k}] or [{n}, {k}], got shape {tuple(theta.shape)}")
        lo, hi = self.theta_lower, self.theta_upper
        return ((theta.to(lo.dtype) - lo) * (2 / (hi - lo)) - 1).expand(n, k)

    @abstractmethod
    def density(self, x: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``x [n,3]``, ``theta [n,k] | [k] | None`` -> ``sigma [n]`` (1/m, >= 0), ``features [n,f]``."""

    @abstractmethod
    def color(self, features: Tensor, d: Tensor) -> Tensor:
        """``features [n,f]`` (from :meth:`density`), unit ``d [n,3]`` -> ``rgb [n,3]`` in (0, 1)."""

    @abstractmethod
    def config(self) -> dict:
        """JSON-able hyper-parameters; ``narf_core.fields.make_field(config)`` rebuilds the field."""

    def forward(self, x: Tensor, d: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(x [n,3], d [n,3], theta [n,k] | [k] | None) -> (sigma [n], rgb [n,3])``, field dtype."""
        sigma, features = self.density(x, theta)
        return sigma, self.color(features, d.to(features.dtype))

    def density_only(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        """``sigma [n]`` alone (occupancy grids, silhouettes, depth)."""
        return self.density(x, theta)[0]

    def regularization(self) -> Tensor:
        """A scalar penalty the trainers add to the loss (0 unless the architecture defines one)."""
        return self.aabb.new_zeros(())
