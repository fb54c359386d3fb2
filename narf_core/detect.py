"""Detection: an object's pose and configuration from one masked view, without an initial pose.

The refiner (:func:`~narf_core.estimate.refine`) is local: from a pose tens of degrees or a
silhouette's width off it ends in a wrong minimum. After a long absence (the object left the view,
the camera moved) or at a first frame with no pose, :func:`detect` searches globally:

1. Orientations: ``options.views`` directions from which the camera may see the object (a
   Fibonacci sphere in the object's frame) times ``options.rolls`` turns about the line of sight,
   each with ``options.theta_starts`` configurations (the given one, then spread over the joint box).
2. Placement, per candidate, without rendering (:func:`_place`): the model's surface points turned
   by it, those in front kept (a z-buffer on a coarse grid), their centre put on the ray through
   the mask's centroid, then moved along the line of sight by the median difference between the
   observed and the points' depth on the mask (RGB only: scaled so that the points spread like the
   mask's pixels) and across it so that the points' projected centroid is the mask's, a few times.
   Points are weighed by the area they stand for (:func:`area_weights`): a link has as many points
   however large it is, and an unweighted centroid leans towards the small ones.
3. Score (:func:`_scores`): ``explained * covered``, where ``explained`` is the share of the
   projected points inside the image that land on the mask, or (with depth) behind an observed
   surface nearer than theirs (an occluder), and ``covered`` the share of mask pixels near a
   projected point; with depth, times the share of points on the mask whose depth agrees with the
   observed one.
4. The ``options.climb`` best distinct candidates each move to their best-scored neighbour (turns
   by ``options.climb_deg`` about a camera axis, then half that; joint steps) while one scores
   higher, ``options.climb_rounds`` times per step size.
5. Of the ``options.keep`` best whose orientations differ by ``options.separation_deg``, those
   scoring at least ``options.refine_share`` of the best's are refined (``options.preset``,
   ``options.iterations``); the lowest final loss wins. Several survive where the silhouette and
   depth cannot tell (a flat object seen from either side): the colour in the refiner's loss can.

Without depth the distance comes from the silhouette's size alone, and a partial mask (an
occluder, the image's border) makes it wrong: the tracker detects only with depth
(docs/benchmarks.md, "Re-detection after a long absence").

Conventions as in docs/design.md §2 (OpenCV camera, ``T_cam_obj``, metres).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from narf_core.checks import check_option_types, check_pose, option_rule
from narf_core.estimate import (
    MIN_MASK_PIXELS,
    PRESETS,
    EstimateInputError,
    EstimateOptions,
    EstimateResult,
    _check_call,
    _check_observation,
    _Parameterisation,
    _theta_starts,
    refine,
)
from narf_core.geometry import Pinhole, so3_exp
from narf_core.observation import dilate

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel

_GRID = 48  # the z-buffer's cells across the object's diameter (visibility of the surface points)


class DetectInputError(EstimateInputError):
    """Unusable input to :func:`detect`; the message names the argument."""


@dataclass
class DetectOptions:
    """Detector settings (plain JSON-able fields).

    ``views * rolls`` orientations, each with ``theta_starts`` configurations, are scored; the
    ``keep`` best that differ by ``separation_deg`` are refined with ``preset`` for ``iterations``
    (``refine_theta_starts`` configuration starts each). ``visible_m``: a surface point within this
    of the nearest one in its z-buffer cell is visible; ``depth_tolerance_m``: a point agrees with
    the observed depth within this; ``occluder_m``: an observed surface this far in front of a point
    hides it.
    """

    views: int = 48
    rolls: int = 12
    theta_starts: int = 3
    keep: int = 4
    refine_share: float = 0.8
    climb: int = 16
    climb_deg: float = 12.0
    climb_rounds: int = 2
    separation_deg: float = 30.0
    preset: str = "robust"
    iterations: int = 40
    refine_theta_starts: int = 2
    visible_m: float = 0.01
    depth_tolerance_m: float = 0.02
    occluder_m: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        check_option_types(self, DetectInputError)
        need = option_rule(self, DetectInputError)
        need(1 <= self.views <= 1024, "views", "must be in [1, 1024]")
        need(1 <= self.rolls <= 360, "rolls", "must be in [1, 360]")
        need(1 <= self.theta_starts <= 16, "theta_starts", "must be in [1, 16]")
        need(1 <= self.keep <= 32, "keep", "must be in [1, 32]")
        need(0 <= self.refine_share <= 1, "refine_share", "must be in [0, 1]")
        need(0 <= self.climb <= 256, "climb", "must be in [0, 256]")
        need(0 < self.climb_deg <= 90, "climb_deg", "must be in (0, 90] degrees")
        need(0 <= self.climb_rounds <= 16, "climb_rounds", "must be in [0, 16]")
        need(0 <= self.separation_deg <= 180, "separation_deg", "must be in [0, 180] degrees")
        need(self.preset in PRESETS, "preset", f"must be one of {', '.join(PRESETS)}")
        need(self.iterations >= 1, "iterations", "must be >= 1")
        need(1 <= self.refine_theta_starts <= 64, "refine_theta_starts", "must be in [1, 64]")
        for name in ("visible_m", "depth_tolerance_m", "occluder_m"):
            need(getattr(self, name) > 0, name, "must be > 0 metres")

    def refine_options(self, **overrides) -> EstimateOptions:
        """The refiner's options for one kept candidate (its θ is the refinement's first start; every
        orientation was scored already, so no pose starts)."""
        return EstimateOptions.preset(self.preset, **{"iterations": self.iterations,
                                                      "theta_starts": self.refine_theta_starts,
                                                      "seed": self.seed, "refinements": 0, "rgb_refinements": 0,
                                                      "rgb_polish": 0,
                                                      "pose_starts": 1, **overrides})


# --------------------------------------------------------------------------------------------
# orientations


def fibonacci_directions(count: int) -> np.ndarray:
    """``[count, 3]`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r = np.sqrt(np.clip(1 - z**2, 0, 1))
    phi = math.pi * (3 - math.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def facing_to_R_cam_obj(direction_obj: np.ndarray) -> np.ndarray:
    """``[n, 3, 3]`` rotations that turn each object-frame unit direction ``[n, 3]`` onto the camera's
    -z axis (that side of the object faces the camera), by the shortest turn."""
    target = np.array([0.0, 0.0, -1.0])
    v = direction_obj / np.linalg.norm(direction_obj, axis=-1, keepdims=True)
    axis = np.cross(v, target)
    s, c = np.linalg.norm(axis, axis=-1), v @ target
    # Facing away (c = -1): any axis normal to v turns it half round; the x axis is normal to ±z.
    axis = np.where((s < 1e-9)[:, None], np.array([1.0, 0.0, 0.0]), axis / np.maximum(s, 1e-12)[:, None])
    return so3_exp(torch.from_numpy(axis * np.arctan2(s, c)[:, None])).numpy()


def orientations(views: int, rolls: int) -> np.ndarray:
    """``[views * rolls, 3, 3]`` rotations ``R_cam_obj``: each of ``views`` Fibonacci directions of the
    object turned to face the camera, then turned about the camera's z axis by ``rolls`` equal steps."""
    facing = facing_to_R_cam_obj(fibonacci_directions(views))
    psi = 2 * math.pi * np.arange(rolls) / rolls
    roll = np.zeros((rolls, 3, 3))
    roll[:, 0, 0], roll[:, 0, 1], roll[:, 1, 0], roll[:, 1, 1], roll[:, 2, 2] = (
        np.cos(psi), -np.sin(psi), np.sin(psi), np.cos(psi), 1.0)
    return (roll[None] @ facing[:, None]).reshape(-1, 3, 3)


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angles (radians) between rotations ``Ra [..., 3, 3]`` and ``Rb [..., 3, 3]``."""
    trace = np.einsum("...ij,...ij->...", Ra, Rb)
    return np.arccos(np.clip((trace - 1) / 2, -1, 1))


# --------------------------------------------------------------------------------------------
# candidates: placed and scored without rendering


def _link_points(model: NarfModel) -> list[tuple[int, np.ndarray]]:
    """``(link index, surface points [n, 3] in the link's frame)`` of every link that has points."""
    return [(i, np.asarray(p, dtype=np.float64)) for i, name in enumerate(model.links)
            if len(p := model.sample_points.get(name, ())) > 0]


def points_obj(model: NarfModel, theta: torch.Tensor) -> np.ndarray:
    """The model's surface points ``[N, 3]`` in the object frame at ``θ [k]``, link after link."""
    links = model.kinematics.link_poses(theta).double().numpy()
    out = [p @ links[i, :3, :3].T + links[i, :3, 3] for i, p in _link_points(model)]
    return np.concatenate(out) if out else np.zeros((0, 3))


def _visible(x: np.ndarray, cell: float, margin: float) -> np.ndarray:
    """``[M, N]`` bool: of each candidate's points ``x [M, N, 3]`` (camera axes, about the object's
    centre), those within ``margin`` of the nearest point of their ``cell``-sized column along z
    (an orthographic z-buffer: the object is small against its distance)."""
    m, n = x.shape[:2]
    ij = np.floor(x[..., :2] / cell).astype(np.int64)
    ij -= ij.min(axis=(0, 1))
    width = int(ij[..., 1].max()) + 1
    key = (np.arange(m)[:, None] * (int(ij[..., 0].max()) + 1) + ij[..., 0]) * width + ij[..., 1]
    nearest = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(nearest, key.ravel(), x[..., 2].ravel())
    return x[..., 2] <= nearest[key] + margin


@dataclass
class _View:
    """The observation as the scorer reads it: the mask, its centroid and pixels, and the depth."""

    mask: np.ndarray  # [H, W] bool
    depth: np.ndarray | None  # [H, W] metres, 0 = none
    K: np.ndarray  # [3, 3]
    centroid: np.ndarray  # [2] pixel (u, v) of the mask's centroid, pixel centres at +0.5
    spread: float  # RMS distance of the mask's pixels from it
    median_depth: float | None  # of the mask's pixels with a return


def _view(mask: np.ndarray, depth: np.ndarray | None, camera: Pinhole) -> _View:
    v, u = np.nonzero(mask)
    if len(u) < MIN_MASK_PIXELS:
        raise DetectInputError(f"mask has {len(u)} object pixel(s); at least {MIN_MASK_PIXELS} are needed")
    uv = np.stack([u, v], -1) + 0.5
    centroid = uv.mean(0)
    seen = None if depth is None else depth[v, u]
    seen = None if seen is None or not (seen > 0).any() else float(np.median(seen[seen > 0]))
    spread = float(np.sqrt(((uv - centroid) ** 2).sum(-1).mean()))
    return _View(mask, depth, camera.K.detach().double().cpu().numpy(), centroid, max(spread, 0.5), seen)


def area_weights(q: np.ndarray, radius: float) -> np.ndarray:
    """``[N]`` weights of surface points ``q [N, 3]`` proportional to the area each stands for: one
    over the number of points within ``radius`` (the points are not spread evenly over the
    surface: each part has as many, however large)."""
    near = np.zeros(len(q))
    for chunk in np.array_split(np.arange(len(q)), max(1, len(q) // 512)):
        near[chunk] = (((q[chunk, None] - q[None]) ** 2).sum(-1) < radius**2).sum(1)
    return 1.0 / near.clip(min=1)


def _place(x: np.ndarray, visible: np.ndarray, area: np.ndarray, view: _View, rounds: int = 3) -> np.ndarray:
    """``[M, 3]`` positions of the object's centre for the candidates' points ``x [M, N, 3]`` (camera
    axes, about the centre) with their ``visible [M, N]`` ones and area weights ``area [N]``. First
    on the mask centroid's ray, at the distance where the visible points' median depth is the
    mask's (RGB only: where their spread projects to the mask's); then ``rounds`` times: moved along
    the line of sight by the median difference between the observed depth and the points' on the
    mask (RGB only: scaled so that the projected points spread like the mask's pixels), and across
    it so that the projected points' centroid is the mask's (both weighted by area: the image's
    pixels are spread evenly over the silhouette)."""
    K = view.K
    h, w = view.mask.shape
    if view.median_depth is not None:
        with warnings.catch_warnings():  # (a candidate with no visible point: nan, then the floor below)
            warnings.simplefilter("ignore", RuntimeWarning)
            z = view.median_depth - np.nanmedian(np.where(visible, x[..., 2], np.nan), axis=1)
    else:
        z = K[0, 0] * _spread(x[..., :2], visible * area) / view.spread
    front = np.max(np.where(visible, -x[..., 2], -np.inf), axis=1).clip(min=0) + 0.01
    centre = np.linalg.solve(K, np.array([*view.centroid, 1.0]))[None] * np.nan_to_num(np.maximum(z, front))[:, None]
    for _ in range(rounds):
        p = x + centre[:, None]
        uv = _project(p, K)
        px = np.floor(uv).astype(np.int64)
        inside = visible & (px[..., 0] >= 0) & (px[..., 0] < w) & (px[..., 1] >= 0) & (px[..., 1] < h)
        weight = inside * area
        if view.depth is not None:
            d = view.depth[np.clip(px[..., 1], 0, h - 1), np.clip(px[..., 0], 0, w - 1)]
            on = inside & view.mask[np.clip(px[..., 1], 0, h - 1), np.clip(px[..., 0], 0, w - 1)] & (d > 0)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                shift = np.nan_to_num(np.nanmedian(np.where(on, d - p[..., 2], np.nan), axis=1))
            scale = (centre[:, 2] + shift) / centre[:, 2]
        else:
            scale = _spread(uv, weight) / view.spread
        centre = centre * np.maximum(scale, front / centre[:, 2])[:, None]  # along the line of sight
        total = weight.sum(1)
        mean = (uv * weight[..., None]).sum(1) / total.clip(min=1e-12)[:, None]
        offset = np.where((total > 0)[:, None], view.centroid - mean, 0.0)
        centre[:, :2] += offset / np.array([K[0, 0], K[1, 1]]) * centre[:, 2:3]  # (projection: near enough)
    return centre


def _project(p: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``[..., 2]`` of camera-frame points ``p [..., 3]`` in front of the camera."""
    uv = p @ K.T
    return uv[..., :2] / uv[..., 2:3].clip(min=1e-6)


def _spread(a: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``[M]`` weighted RMS distance of the 2-D points ``a [M, N, 2]`` from their weighted centroid."""
    total = weight.sum(1).clip(min=1e-12)
    mean = (a * weight[..., None]).sum(1) / total[:, None]
    return np.sqrt((((a - mean[:, None]) ** 2).sum(-1) * weight).sum(1) / total).clip(min=1e-9)


def _scores(x: np.ndarray, visible: np.ndarray, view: _View, options: DetectOptions) -> np.ndarray:
    """``[M]`` scores in [0, 1] of the candidates' visible points ``x [M, N, 3]`` (camera frame)
    against the view (the module docstring, step 3)."""
    h, w = view.mask.shape
    px = np.floor(_project(x, view.K)).astype(np.int64)
    inside = visible & (x[..., 2] > 1e-3) & (px[..., 0] >= 0) & (px[..., 0] < w) & (px[..., 1] >= 0) & (px[..., 1] < h)
    u, v = np.clip(px[..., 0], 0, w - 1), np.clip(px[..., 1], 0, h - 1)
    n_mask = int(view.mask.sum())
    n_in = inside.sum(1).clip(min=1)
    spacing = np.clip(np.ceil(np.sqrt(n_mask / n_in)), 1, 8).astype(np.int64)  # pixels between points
    grown = dilate(view.mask, 1)
    on_mask = inside & grown[v, u]
    explained = on_mask.copy()
    agree = np.ones(len(x))
    if view.depth is not None:
        d = view.depth[v, u]
        explained |= inside & (d > 0) & (d < x[..., 2] - options.occluder_m)
        measured = on_mask & (d > 0)
        close = measured & (np.abs(d - x[..., 2]) < options.depth_tolerance_m)
        agree = (close.sum(1) + 1) / (measured.sum(1) + 1)
    covered = _covered(view.mask, inside, u, v, spacing)
    return explained.sum(1) / n_in * covered * agree * (inside.sum(1) > 0)


def _covered(mask: np.ndarray, inside: np.ndarray, u: np.ndarray, v: np.ndarray, spacing: np.ndarray,
             chunk: int = 128) -> np.ndarray:
    """``[M]``: the share of ``mask``'s pixels within ``spacing [M]`` pixels of one of a candidate's
    points ``inside [M, N]`` at pixels ``(u, v) [M, N]``; computed on the mask's box (grown by the
    largest spacing), ``chunk`` candidates at a time."""
    rows_, cols_ = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    grow = int(spacing.max())
    v0, u0 = max(0, rows_[0] - grow), max(0, cols_[0] - grow)
    v1, u1 = min(mask.shape[0], rows_[-1] + 1 + grow), min(mask.shape[1], cols_[-1] + 1 + grow)
    crop = mask[v0:v1, u0:u1]
    h, w = crop.shape
    keep = inside & (u >= u0) & (u < u1) & (v >= v0) & (v < v1)
    out = np.zeros(len(inside))
    for r in np.unique(spacing):
        for rows in np.array_split(np.flatnonzero(spacing == r), max(1, int(np.sum(spacing == r)) // chunk)):
            hits = np.zeros((len(rows), h, w), dtype=bool)
            m, i = np.nonzero(keep[rows])
            hits[m, v[rows][m, i] - v0, u[rows][m, i] - u0] = True
            out[rows] = (dilate(hits, int(r)) & crop).sum((1, 2)) / max(int(crop.sum()), 1)
    return out


@dataclass
class Candidate:
    """A scored start: ``T_cam_obj [4, 4]``, ``joints`` and its ``score`` in [0, 1]."""

    T_cam_obj: np.ndarray
    joints: dict[str, float]
    score: float


@dataclass
class _Scored:
    """A placed candidate: its score, ``R_cam_obj [3, 3]``, box centre ``[3]`` (camera frame) and ``θ [k]``."""

    score: float
    R: np.ndarray
    centre: np.ndarray
    theta: torch.Tensor


class _Scorer:
    """Places and scores candidates of one view: the model's points per configuration, the view."""

    def __init__(self, model: NarfModel, view: _View, options: DetectOptions) -> None:
        box = model.aabb.double().cpu().numpy()
        self.model, self.view, self.options = model, view, options
        self.centre_obj = (box[0] + box[1]) / 2
        self.cell = max(model.diameter, 1e-3) / _GRID
        # Each link's points weighed in its own frame: θ moves links, never a link's points.
        self.area = np.concatenate([area_weights(p, 2 * self.cell) for _, p in _link_points(model)] or [np.zeros(0)])
        lower, upper = model.kinematics.lower.double(), model.kinematics.upper.double()
        self.lower, self.upper = lower, upper

    def __call__(self, R: np.ndarray, theta: torch.Tensor) -> list[_Scored]:
        """Each rotation ``R [M, 3, 3]`` at ``θ [k]``, placed on the view and scored."""
        q = points_obj(self.model, theta) - self.centre_obj
        x = q[None] @ R.transpose(0, 2, 1)  # [M, N, 3] camera axes, about the centre
        visible = _visible(x, self.cell, self.options.visible_m)
        centre = _place(x, visible, self.area, self.view)
        score = _scores(x + centre[:, None], visible, self.view, self.options)
        return [_Scored(float(value), R[i], centre[i], theta) for i, value in enumerate(score)]

    def climb(self, start: _Scored, turn: float, joint_step: torch.Tensor) -> _Scored:
        """``start`` or the best of its neighbours (turned by ``turn`` radians about a camera axis either
        way; each joint moved by ``joint_step [k]`` either way, within its limits), if better."""
        axes = np.concatenate([np.eye(3), -np.eye(3)]) * turn
        turned = _rotations(axes) @ start.R
        found = self(turned, start.theta)
        for j in range(len(joint_step)):
            for sign in (1.0, -1.0):
                theta = start.theta.clone()
                theta[j] = (theta[j] + sign * joint_step[j]).clamp(self.lower[j], self.upper[j])
                found += self(start.R[None], theta)
        return max([start, *found], key=lambda c: c.score)

    def pose(self, c: _Scored) -> np.ndarray:
        """``T_cam_obj [4, 4]`` of a candidate."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = c.R, c.centre - c.R @ self.centre_obj
        return T


def _rotations(rotvec: np.ndarray) -> np.ndarray:
    """``[n, 3, 3]`` rotation matrices of rotation vectors ``[n, 3]`` (radians)."""
    from narf_core.geometry import so3_exp

    return so3_exp(torch.from_numpy(np.asarray(rotvec, dtype=np.float64))).numpy()


def _distinct(found: Sequence[_Scored], count: int, separation: float) -> list[_Scored]:
    """The best ``count`` of ``found`` whose rotations are at least ``separation`` radians apart."""
    kept: list[_Scored] = []
    for c in sorted(found, key=lambda c: -c.score):
        if all(rotation_angle(c.R, k.R) >= separation for k in kept):
            kept.append(c)
            if len(kept) == count:
                break
    return kept


def candidates(
    model: NarfModel,
    camera: Pinhole,
    mask: np.ndarray,
    depth: np.ndarray | None = None,
    joints: Mapping[str, float] | None = None,
    options: DetectOptions | None = None,
    hints: Sequence[tuple[np.ndarray, Mapping[str, float]]] = (),
) -> list[Candidate]:
    """The ``options.keep`` best-scored distinct starts for ``mask [H, W]`` bool (and ``depth [H, W]``
    metres, 0 = none), best first: the grid of orientations and configurations scored, then the
    ``options.climb`` best distinct ones each moved to its best-scored neighbour (turns of
    ``options.climb_deg``, then half that, and joint steps) while one scores higher. ``joints``: the
    first configuration tried (mid-range if None); ``hints``: poses also scored (e.g. a tracker's
    last estimate), placed on the mask like the others. Inputs as :func:`detect` checks them."""
    opts = options or DetectOptions()
    scorer = _Scorer(model, _view(mask, depth, camera), opts)
    theta0 = model.kinematics.joint_vector(joints, field="joints", error=DetectInputError).double()
    R = orientations(opts.views, opts.rolls)
    found: list[_Scored] = []
    for theta in _theta_grid(model, theta0, opts.theta_starts):
        found += scorer(R, theta)
    for i, (T, hint_joints) in enumerate(hints):
        theta = model.kinematics.joint_vector(hint_joints, field=f"hints[{i}].joints", error=DetectInputError).double()
        found += scorer(np.asarray(T, dtype=np.float64)[None, :3, :3], theta)
    separation = math.radians(opts.separation_deg)
    tops = _distinct(found, opts.climb, separation / 2)
    joint_step = (scorer.upper - scorer.lower) / (2 * opts.theta_starts)
    for turn in (math.radians(opts.climb_deg), math.radians(opts.climb_deg) / 2):
        for _ in range(opts.climb_rounds):
            tops = [scorer.climb(c, turn, joint_step) for c in tops]
        joint_step = joint_step / 2
    return [Candidate(scorer.pose(c), model.kinematics.joint_dict(c.theta), c.score)
            for c in _distinct(tops, opts.keep, separation)]


def _theta_grid(model: NarfModel, theta0: torch.Tensor, count: int) -> list[torch.Tensor]:
    """``count`` configurations: ``theta0``, then others spread over the joint box (the refiner's starts)."""
    if theta0.shape[0] == 0:
        return [theta0]
    param = _Parameterisation.around(torch.eye(4, dtype=torch.float64), model)  # (only its joint box is read)
    return list(_theta_starts(theta0, param, count))


# --------------------------------------------------------------------------------------------
# detection


def detect(
    model: NarfModel,
    camera: Pinhole,
    image: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray | None = None,
    *,
    joints: Mapping[str, float] | None = None,
    options: DetectOptions | None = None,
    hints: Sequence[tuple[np.ndarray, Mapping[str, float]]] = (),
    refine_options: EstimateOptions | None = None,
) -> EstimateResult:
    """The object's pose and configuration in ``image [H, W, 3]`` uint8 where ``mask [H, W]`` marks it
    (``depth [H, W]`` metres, 0 or NaN = no return, optional), with no initial pose: the best of
    the ``options.keep`` best-scored candidates (:func:`candidates`) after refinement, by the
    refiner's final loss. ``joints``: a configuration to try first (mid-range if None); ``hints``:
    ``(T_cam_obj, joints)`` pairs scored beside the grid (a tracker's last estimate);
    ``refine_options``: the refiner's for each candidate refined (those scoring at least
    ``options.refine_share`` of the best's; default :meth:`DetectOptions.refine_options`).
    ``seconds`` is the whole detection's.

    Raises:
        DetectInputError: an empty or tiny mask, sizes that do not match, bad options or joints.
    """
    start = time.perf_counter()
    opts = _check_call(options, DetectOptions, camera, DetectInputError)
    image, mask, depth = _check_observation(image, mask, depth, camera, DetectInputError)
    for i, (T, _) in enumerate(hints):
        check_pose(T, f"hints[{i}].T_cam_obj", error=DetectInputError)
    found = candidates(model, camera, mask, depth, joints, opts, hints)
    refine_opts = refine_options if refine_options is not None else opts.refine_options()
    best: EstimateResult | None = None
    for c in found:
        if c.score < opts.refine_share * found[0].score:
            continue
        result = refine(model, image, mask, camera, c.T_cam_obj, joints_init=c.joints, depth=depth, options=refine_opts)
        if best is None or (result.loss is not None and (best.loss is None or result.loss < best.loss)):
            best = result
    assert best is not None  # the best candidate is always refined
    return replace(best, seconds=time.perf_counter() - start)
