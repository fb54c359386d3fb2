"""The paper's baseline: a FastNeRF-style factorised MLP conditioned on the configuration.

NARF22 §IV-B: the position MLP takes the frequency-encoded position concatenated with the
frequency-encoded configuration (10 levels each); FastNeRF's factorisation splits colour into a
position part, ``D`` colour basis vectors ``(u, v, w)``, and a direction part, ``D`` weights
``beta`` from a small MLP of the encoded view direction (4 levels); ``rgb = sigmoid(sum_i beta_i
(u_i, v_i, w_i))``. The default widths are scaled for a CPU (FastNeRF used 8x384 and 4x128).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from narf_core.fields.base import RadianceField, trunc_exp
from narf_core.fields.encodings import frequency_encoding, frequency_encoding_size


def _mlp(n_in: int, width: int, layers: int, n_out: int) -> nn.Sequential:
    """``layers`` hidden ReLU layers of ``width``, then a linear output of ``n_out``."""
    mods: list[nn.Module] = []
    for _ in range(layers):
        mods += [nn.Linear(n_in, width), nn.ReLU()]
        n_in = width
    mods.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*mods)


class FastNeRFField(RadianceField):
    """FastNeRF-style field ``(x, d, theta) -> (sigma, rgb)``; a part field when no limits are given.

    Args:
        aabb: ``[2,3]`` box (metres) in the field's frame.
        theta_lower, theta_upper: ``[k]`` joint limits (None for a part field).
        pos_levels, dir_levels: frequency-encoding levels of position and theta, and of direction.
        pos_width, pos_layers: the position MLP.
        dir_width, dir_layers: the direction MLP.
        components: ``D``, the number of colour basis vectors.
    """

    def __init__(
        self,
        aabb,
        theta_lower=None,
        theta_upper=None,
        *,
        pos_levels: int = 10,
        dir_levels: int = 4,
        pos_width: int = 128,
        pos_layers: int = 6,
        dir_width: int = 64,
        dir_layers: int = 2,
        components: int = 8,
    ) -> None:
        super().__init__(aabb, theta_lower, theta_upper)
        if min(pos_width, pos_layers, dir_width, dir_layers, components) < 1 or min(pos_levels, dir_levels) < 0:
            raise ValueError("FastNeRF widths, depths and components must be >= 1 and levels >= 0")
        self.pos_levels, self.dir_levels = pos_levels, dir_levels
        self.pos_width, self.pos_layers = pos_width, pos_layers
        self.dir_width, self.dir_layers = dir_width, dir_layers
        self.components = components
        n_pos = frequency_encoding_size(3 + self.n_theta, pos_levels)
        self.position_mlp = _mlp(n_pos, pos_width, pos_layers, 1 + 3 * components)
        self.direction_mlp = _mlp(frequency_encoding_size(3, dir_levels), dir_width, dir_layers, components)
        with torch.no_grad():  # untrained: about 10% opacity across the whole box
            self.position_mlp[-1].bias[0] = math.log(0.1 / float((self.aabb[1] - self.aabb[0]).norm()))

    def density(self, x: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        z = self.normalize_positions(x)
        th = self.normalize_theta(theta, x.shape[0])
        if th is not None:
            z = torch.cat([z, th], dim=-1)
        out = self.position_mlp(frequency_encoding(z, self.pos_levels))
        return trunc_exp(out[:, 0]), out[:, 1:]

    def color(self, features: Tensor, d: Tensor) -> Tensor:
        beta = self.direction_mlp(frequency_encoding(d, self.dir_levels))  # [n, D]
        uvw = features.reshape(-1, self.components, 3)
        return torch.sigmoid((beta[:, :, None] * uvw).sum(1))

    def config(self) -> dict:
        return {
            "arch": "fastnerf",
            "aabb": self.aabb.tolist(),
            "theta_lower": None if self.theta_lower is None else self.theta_lower.tolist(),
            "theta_upper": None if self.theta_upper is None else self.theta_upper.tolist(),
            "pos_levels": self.pos_levels,
            "dir_levels": self.dir_levels,
            "pos_width": self.pos_width,
            "pos_layers": self.pos_layers,
            "dir_width": self.dir_width,
            "dir_layers": self.dir_layers,
            "components": self.components,
        }
