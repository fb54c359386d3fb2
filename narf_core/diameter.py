"""The diameter of a point set: the object's size (ADD < 10 % of the diameter, the uncertainty floor).

Inputs are numpy arrays or torch tensors ``[n, 3]`` (metres), computed in float64 on the CPU; kept
apart from :mod:`narf_core.metrics` so that the model bundle, which states its object's diameter,
does not depend on the evaluation layer.
"""

from __future__ import annotations

import math

import numpy as np
import torch

PAIRWISE_BLOCK = 1 << 21
"""Pairwise distances computed at once by brute-force searches (16 MiB of float64)."""
_EXACT_DIAMETER_MAX = 4096  # up to this many points the diameter is computed over all pairs
_DIAMETER_DIRECTIONS = 1024  # extreme points along this many directions stand in for larger sets


def as_points(x, name: str) -> np.ndarray:
    """``x`` (array-like or tensor) as float64 ``[n, 3]``; a ValueError naming ``name`` otherwise."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    try:
        p = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be numeric, got {type(x).__name__}") from e
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape [n, 3], got {list(p.shape)}")
    return p


def object_diameter(points) -> float:
    """The largest distance (m) between two of ``points [n, 3]``.

    Exact when there are at most 4096 points or, with scipy installed, at most 4096 vertices on their
    convex hull (the diameter joins two hull vertices). Otherwise the pair is searched among the
    extreme points along 1024 evenly spread directions; the diameter's direction lies within 0.078
    rad of one of them, so the result is at least ``cos(0.078) = 0.997`` of the true value.
    """
    p = as_points(points, "points")
    if len(p) == 0:
        raise ValueError("points is empty")
    if len(p) > _EXACT_DIAMETER_MAX:
        p = _hull_vertices(p)
    if len(p) > _EXACT_DIAMETER_MAX:
        p = _extreme_points(p, _sphere_directions(_DIAMETER_DIRECTIONS))
    p = p - p.mean(0)  # centred, |a - b|^2 = |a|^2 + |b|^2 - 2 a.b loses nothing that matters to the max
    sq = (p * p).sum(1)
    block = max(1, PAIRWISE_BLOCK // len(p))
    best = 0.0
    for start in range(0, len(p), block):
        d2 = sq[start : start + block, None] + sq[None] - 2 * p[start : start + block] @ p.T
        best = max(best, float(d2.max()))
    return math.sqrt(max(best, 0.0))


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """The vertices of the convex hull of ``points [n, 3]``; all points without scipy or for flat sets."""
    try:
        from scipy.spatial import ConvexHull, QhullError
    except ImportError:
        return points
    try:
        return points[ConvexHull(points).vertices]
    except QhullError:  # coplanar or collinear points
        return points


def _extreme_points(points: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The points ``[<= 2 d, 3]`` lowest and highest along each of ``directions [d, 3]``."""
    block = max(1, PAIRWISE_BLOCK // len(directions))
    low = np.full(len(directions), np.inf)
    high = np.full(len(directions), -np.inf)
    arg_low = np.zeros(len(directions), dtype=np.int64)
    arg_high = np.zeros(len(directions), dtype=np.int64)
    columns = np.arange(len(directions))
    for start in range(0, len(points), block):
        proj = directions @ points[start : start + block].T  # [d, block]
        i_low, i_high = proj.argmin(1), proj.argmax(1)
        v_low, v_high = proj[columns, i_low], proj[columns, i_high]
        arg_low = np.where(v_low < low, start + i_low, arg_low)
        arg_high = np.where(v_high > high, start + i_high, arg_high)
        low, high = np.minimum(low, v_low), np.maximum(high, v_high)
    return points[np.unique(np.concatenate([arg_low, arg_high]))]


def _sphere_directions(n: int) -> np.ndarray:
    """``[n, 3]`` unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + math.sqrt(5)) * i
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
