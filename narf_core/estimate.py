"""The refiner: an object's pose and configuration from one masked RGB(-D) view (docs/design.md §4.4).

iNeRF-style render-and-compare, as in NARF22 §III-C: from an initial pose ``T_init`` and the
mid-range configuration, Adam moves ``(T_cam_obj, θ)`` so that rays rendered through the model
match the observed pixels.

Parameterisation (one row per start, ``[n_starts, 6 + k]``):
  - pose: ``T = se3_exp(ξ) @ T_init``, a left-multiplied twist. ``ξ`` is expressed at the object's
    centre with the camera's axes (``ξ = Ad(C) [r ρ, ω]``, ``C`` the translation to the centre of
    the object's box under ``T_init``, ``r`` its half-diagonal), so a rotation turns the object
    about itself instead of swinging it around the camera, and one step moves surface points about
    equally for ``ρ`` and ``ω``: the pose is learnt in radians and object radii.
  - configuration: ``θ = mid + half_range * sin(u)``, inside the limits by construction and reaching
    either limit at a finite ``u = ±π/2`` (a sigmoid would only approach it). ``u`` starts at most
    ``_U_LIMIT`` from ±π/2 so that a start at a limit still has a gradient.

Learning rates. The paper uses Adam with 0.001 (pose) and 0.01 (θ, metres for its clamp) for 150
iterations. Ours are per normalised unit: ``lr_pose`` in radians / object radii, ``lr_theta`` in
``u`` (near mid-range one step moves θ by about ``lr_theta * half_range``); both decay
exponentially to ``lr_decay`` times their start. The paper's pose rate moves at most 150 * 0.001 rad
= 8.6 deg in 150 steps, less than its own 10 deg perturbation, so ours is larger. The defaults
(0.01, 0.05, decay 0.1) were the best of a sweep on the analytic toy clamp of tests/test_estimate.py.

Presets (:meth:`EstimateOptions.preset`): ``paper`` is the defaults: the paper's loss, one start at
mid-range. ``robust`` adds a silhouette term, a depth term (when a depth image is given), 4 joint
starts, 2 pyramid levels and twice the pose rate. On the bundled clamp (160x120, the paper's
protocol, 17 test views; ``narf bench estimate`` has the figures) the paper preset rarely finds the
jaw from mid-range: its 18 cm travel is 7 jaw widths, and where the rendered and the observed jaw do
not overlap the photometric loss is flat in θ. The robust preset does, and the depth term fixes the
distance that a 160x120 view hardly constrains. ``gauss-newton`` (``solver = "gauss-newton"``,
narf_core/gauss_newton.py) uses the robust preset's terms with Levenberg-Marquardt steps and Huber
weights for at most ``GN_ITERATIONS`` iterations, with a heavier depth weight (:meth:`EstimateOptions.gauss_newton`):
about half the robust preset's CPU time for a similar error from the paper's 10 deg / 2 cm, but
its basin is narrower (a wrong jaw start or a 3x perturbation more often ends in a wrong minimum;
docs/benchmarks.md), which its pose starts (``pose_starts_overlap``) widen again. ``auto`` (the
default of the command line and the API; :func:`choose_preset`) is ``gauss-newton`` for a view with a
depth image and ``robust`` for one without.

Every estimate carries an :class:`Uncertainty` (``options.uncertainty``): one Gauss-Newton
linearisation at the optimum, whatever the solver, plus the model's own error (:func:`model_error`).

Loss, averaged over the rays of one iteration: the paper's masked photometric MSE
``|render - image * mask|^2`` (rendered on a black background), plus ``silhouette_weight * (opacity
- mask)^2`` and, where a depth is observed inside the mask, ``depth_weight * ((depth - observed) /
r)^2``. Rays come only from the mask's box dilated by ``box_margin``. With ``coarse_to_fine = L``
the first quarter of the iterations goes through L - 1 coarse levels whose targets are box-filtered
over ``2^l + 1`` pixels (l = L-1 .. 1), with rays jittered over the same square, so the loss seen
is the fine loss smoothed over small image shifts; the rest uses the paper's plain loss at pixel
centres. (A 5-pixel level, or half the run spent coarse, cost accuracy on the thin clamp.)

Pixels at the camera's own resolution. ``ray_sampling`` chooses an iteration's rays in the box:
independent draws, one per cell of a grid (``stratified``), half on the mask's edges and the
image's texture (``edges``), or ``auto`` (uniform in a box up to ``reference_box_px``, edges in a
larger one). The silhouette's edges carry the distance in an RGB-only view (a distance error is a
change of scale), and in a large box (a fine camera) few uniform rays land on them: the gradient
along the line of sight is then mostly noise and Adam random-walks the distance by centimetres.
``reference_box_px`` keeps the rays per unit of silhouette as they are at that box size: a box k
times larger draws k times the rays (``narf bench shift`` has the measurements).
``photometric_compensation`` (gain and bias per channel, closed form on the rays at every
iteration, held fixed in the gradient), ``robust_loss`` (Huber or Cauchy per residual, scale
``robust_scale``) and ``occlusion_margin`` (no residual for a ray whose observed depth lies that
far in front of the render) apply to both solvers.

A segmenter's mask is not the truth: its edge is off by a pixel or two, it misses a blob or adds
one, and it marks only the visible part of an occluded object. With ``mask_band_px`` the pixels
that near the mask's boundary carry no silhouette, masked-colour or depth residual; there the render
is compared with the unmasked image where it draws the object (a render over a pixel of another
colour costs; the unknown background does not). ``outside_weight`` weighs the rays outside the
mask less (a render of the object there may be right: an occluder or a missed blob), except where
the observed depth lies behind the rendered surface (1) or in front of it (0: an occluder's ray is
no evidence; so at ``outside_weight`` 1 with a depth image, only an occluder's rays lose their
weight). Both act on the Adam solver's fine level; ``partial_theta_starts`` raises the configuration
starts there (a hidden part lets a wrong configuration fit from more places).
``mask_trust = "auto"`` trusts the mask partially where the depth contradicts it
(:func:`narf_core.observation.mask_evidence`: an occluder beside it, its edge on a continuous surface).

``theta_starts = S`` runs S configurations (the given one and S-1 spread over the joint box) as
ONE batch of ``S * rays_per_iteration / 2`` rays for the first third of the iterations (in
``parts`` mode, whose composition takes one configuration, one render call per start), then keeps
the start with the lowest loss on one fixed set of up to 4096 fine rays: half the rays per start
while the starts compete cost no accuracy, and a third of the iterations is long enough for the
right jaw start to pull ahead (docs/benchmarks.md). ``pose_starts = P`` widens the basin in
pose: the given pose and P - 1 turned about the object's centre (out of the image plane first,
where a silhouette changes least for a wrong angle), each also moved onto the mask and the observed
depth, are scored with every θ start once, on one set of rays without gradients, and each θ start
is refined from the given pose and from its best other one. With ``pose_starts_overlap`` (on in
``gauss-newton``) the pose starts are refined only where they are needed: after a refinement from the
given pose whose estimate's silhouette overlaps the mask less than that (intersection over union), a
second one from them, the estimate of lower loss kept (:func:`_adaptive_refinement`); a start within the
basin then costs one render of the eval rays. With two joints or more,
``theta_search = N`` (on in ``robust`` and ``gauss-newton``) first fits N configurations to the mask
(and the observed depth's surface) through the model's surface points, and the S that fit best are
the θ starts (:func:`_theta_search`): a few spread starts leave most of a several-joint box unvisited
(docs/benchmarks.md). A non-finite loss or gradient
never reaches the parameters: the best finite iterate is restored, Adam's moments reset and its
rates halved.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from narf_core.band import ray_band
from narf_core.checks import InputError, check_option_types, check_pose, option_rule
from narf_core.geometry import (
    Pinhole,
    Rays,
    invert_pose,
    pose_to_position_quaternion,
    se3_exp,
    se3_log,
    so3_log,
    transform_points,
)
from narf_core.kinematics import MAX_JOINTS
from narf_core.metrics import add, add_s, joint_errors, success_rates
from narf_core.modes import MODES, choose_mode
from narf_core.observation import check_observation, mask_evidence, usable_depth
from narf_core.render import ray_aabb

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel

PRESETS = ("paper", "robust", "gauss-newton")  # the named sets of options
PRESET_NAMES = ("auto", *PRESETS)  # what a caller may ask for: "auto" is resolved per view (choose_preset)
SOLVERS = ("adam", "gauss-newton")
ROBUST_LOSSES = ("none", "huber", "cauchy")
JACOBIANS = ("derivatives", "differences")  # how gauss-newton finds its Jacobian (EstimateOptions.jacobian)
RAY_SAMPLINGS = ("uniform", "stratified", "edges", "auto")
MASK_TRUSTS = ("full", "partial", "auto")
MIN_MASK_PIXELS = 4
_U_LIMIT = 0.2  # a start keeps u this far inside ±π/2 (where dθ/du = 0): 2% of the half-range from a limit
_MAX_RECOVERIES = 8  # consecutive non-finite iterations before giving up
_COARSE_SHARE = 0.25  # of the iterations go to the coarse pyramid levels
_PRUNE_SHARE = 1 / 3  # of the iterations run every θ start (half the rays each); then the best goes on alone
_MAX_BOX_SCALE = 4  # reference_box_px multiplies the rays per iteration by at most this
_BEHIND_M = 0.01  # observed depth this far behind the rendered surface: the object is not on that ray
_EVAL_RAYS = 4096  # starts are compared, and the final loss measured, on at most this many rays of the box
_CHOICE_RAYS = 16384  # box rays on which several refinements' estimates are compared (refinements)
# A candidate estimate drawing the object on less than this share of the mask's rays that another draws it on
# is not chosen (_fixed_rays_loss).
_MIN_COVER_SHARE = 0.5
_SCORE_RAYS = 1024  # box rays on which every (pose, θ) start is scored before the refinement
_POSES_KEPT = 1  # pose starts refined per θ start besides the given pose (the best scored; docs/benchmarks.md)
# ... and per θ start in the second refinement of pose_starts_overlap, which has no given pose's starts beside it
_RETRY_POSES_KEPT = 2
# The configuration search (_theta_search): surface points per link and mask pixels matched, Adam steps and
# their rates (pose in radians and object radii, configuration in u), and how far in front of the observed
# depth a point may lie before it costs.
_SEARCH_POINTS = 64
_SEARCH_PIXELS = 256
_SEARCH_STEPS = 30
_SEARCH_RATES = (0.02, 0.1)
_SEARCH_DEPTH_MARGIN = 0.01
# Directions of the turned pose starts (camera axes, in order): about the camera's x axis (up and down),
# its y axis (left and right), the diagonals between them, then the viewing axis.
_POSE_TURNS = ((0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0),
               (1, 1, 0), (-1, -1, 0), (1, -1, 0), (-1, 1, 0), (0, 0, 1), (0, 0, -1))
_ADAM_BETAS = (0.9, 0.999)
_ADAM_EPS = 1e-8
GN_ITERATIONS = 25  # the gauss-newton preset's Levenberg-Marquardt iterations (at most; docs/benchmarks.md)
# rgb_polish stops once _POLISH_PATIENCE accepted steps in a row each moved less than this (radii, radians):
# the valley it follows is shallow, and the gauss-newton preset's 3e-3 stops it at its first steps.
_POLISH_TOLERANCE = 1e-5
_POLISH_PATIENCE = 2
RGB_POLISH = 60  # the robust preset's rgb_polish (docs/benchmarks.md, session 47)
# rgb_polish runs only where Adam's silhouette overlaps the mask at least this much (polish_overlap): exact masks
# 0.95-0.99, a segmenter's and an occluder's 0.6-0.8 on path-traced 640x480 pliers (docs/benchmarks.md, session 48).
POLISH_OVERLAP = 0.9
GN_DEPTH_WEIGHT = 50.0  # the gauss-newton preset's depth_weight (see EstimateOptions.gauss_newton)
GN_UNCERTAINTY_RAYS = 1024  # the gauss-newton preset's uncertainty_rays
GN_POSE_STARTS = 9  # the gauss-newton preset's pose_starts, refined only below ...
GN_POSE_OVERLAP = 0.8  # ... this overlap of the first estimate's silhouette with the mask (pose_starts_overlap)
GN_SLIDE_SHARE = 0.05  # the gauss-newton preset's slide_share (docs/benchmarks.md, session 49)
GN_SURFACE_FIT = 20  # the gauss-newton preset's surface_fit_iterations (docs/benchmarks.md, session 64)
GN_SURFACE_POLISH = 5  # the gauss-newton preset's surface_polish_iterations (docs/benchmarks.md, session 65)
# The robust preset's reference_box_px: the largest mask box (grown by box_margin) of the bundled
# clamp's test and novel views at 160x120, its training size; boxes up to it keep the plain sampling.
ROBUST_BOX_PX = 144
GAIN_RANGE = (0.5, 2.0)  # a colour gain per channel, fitted (photometric_compensation, colour_gain()) or given
# Both robust presets trust a mask the depth image contradicts only partially: a 2-pixel edge band (a
# segmenter's edge is off by about that much) and 8 configuration starts (EstimateOptions.robust).
PARTIAL_MASK = {"mask_trust": "auto", "partial_theta_starts": 8, "mask_band_px": 2}


class EstimateInputError(InputError):
    """Unusable input to :func:`refine`; the message names the argument and what is wrong."""


@dataclass
class EstimateOptions:
    """Refiner settings; plain JSON-able fields, so ``EstimateOptions(**asdict(o)) == o``.

    The defaults follow the paper's protocol (150 Adam iterations on the masked photometric loss,
    one start at mid-range); :meth:`robust` switches on the extras.
    """

    iterations: int = 150
    lr_pose: float = 0.01  # per step, radians and object radii (see the module docstring)
    lr_theta: float = 0.05  # per step, in u where θ = mid + half_range * sin(u)
    lr_decay: float = 0.1  # final rate / first rate, exponential in between
    rays_per_iteration: int = 1024
    mode: str = "auto"  # "narf" (the configuration field), "parts" (composed part fields) or "auto" (narf_core/modes.py)
    silhouette_weight: float = 0.0
    depth_weight: float = 0.0
    theta_starts: int = 1
    coarse_to_fine: int = 1  # pyramid levels; 1 = the plain loss throughout
    box_margin: float = 0.15  # rays come from the mask's box grown by this fraction of its size
    early_stop: bool = True
    tolerance: float = 3e-4  # early stop: mean motion per iteration (radii, radians, θ range) ...
    loss_tolerance: float = 0.02  # ... and relative change of the mean loss, over `patience` iterations
    patience: int = 15
    record_every: int = 0  # keep the pose every this many iterations in `EstimateResult.history`
    seed: int = 0
    # The second-order solver and the refiner's robustness (narf_core/gauss_newton.py; off in `paper`).
    solver: str = "adam"  # "adam" or "gauss-newton" (Levenberg-Marquardt)
    robust_loss: str = "none"  # per-residual "none", "huber" or "cauchy" (gauss-newton)
    robust_scale: float = 0.1  # where the robust loss bends, in residual units (colour in [0, 1])
    damping: float = 1e-3  # first Levenberg-Marquardt λ (relative to diag JᵀWJ)
    # How gauss-newton's Jacobian is found: "derivatives", the field's own at the render's samples (one
    # batched pass), or "differences", central differences of the render over about one sample spacing
    # (2 (6 + k) more rows in one batch). The derivatives see a sharp surface only through the density's
    # slope between two samples, so they are noisy, and the steps they give can stall where several
    # parameters move one outline together (a lamp's joints and its pose, docs/benchmarks.md, session 53).
    jacobian: str = "derivatives"
    # Whether gauss-newton's later iterations on the same rays (one start, at the fine level) keep the first one's
    # Jacobian with the residuals where the parameters are (the chord method: one linearisation, then a render
    # per step), or take it again at each. A tracker's frame with depth, millimetres from its answer, keeps it
    # (docs/benchmarks.md, session 55); a frame without depth drifts off with it, and a single image's
    # iterations start centimetres off.
    jacobian_once: bool = False
    photometric_compensation: bool = False  # per-channel gain and bias, closed form each iteration
    # Otherwise the render's colour times this gain per channel before it is compared: a known change of the
    # camera's exposure, white balance or light from the training views' (the tracker carries one; in GAIN_RANGE).
    colour_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    occlusion_margin: float = 0.0  # metres; observed depth this far in front of the render = occluder (0 = off)
    depth_sigma: float = 0.0  # sensor depth noise at 1 m (σ = depth_sigma z²); 0: depth residuals in object radii
    # How far the given mask is trusted (Adam's loss; a segmenter's mask is not the truth): "full",
    # "partial" or "auto" (partial where a depth image contradicts the mask: _partial_trust). Partial: no
    # silhouette, masked-colour or depth residual within mask_band_px pixels of the mask's boundary
    # (its edge is uncertain by a few pixels; there the render is compared with the unmasked image
    # where it draws the object), and the rays outside the mask weigh outside_weight (an occluder or
    # a blob the mask missed may hide the object there) unless the observed depth lies behind the render,
    # and not at all where it lies in front (an occluder's ray; with a depth image, at outside_weight 1 too).
    mask_trust: str = "full"
    mask_band_px: int = 3
    outside_weight: float = 0.3
    # With partial trust, at least this many configuration starts (0: theta_starts): an occluder or a
    # wrong mask edge hides part of the object, and a wrong configuration then fits from more places.
    partial_theta_starts: int = 0
    # Where one refinement is least reliable, without depth (the distance along the line of sight is weakly
    # observed) or with a partially trusted mask (occluders, a segmenter's edge), and the random rays'
    # trajectory decides where a run ends: this many refinements from the same starts, each with its own ray
    # seed and every other one on a single pyramid level (Adam); gauss-newton: up to three whole estimates,
    # with pose_starts_overlap only where the first misses the mask, the second with half its rays on edges
    # from the given pose alone, the third (partial trust) from starts not moved by align_start
    # (_gauss_newton_estimates); the one whose estimate has the lowest loss on one fixed set of _CHOICE_RAYS
    # box rays is returned (_lowest_run). 0 or 1: one refinement.
    refinements: int = 0
    # Where the view comes without a depth image, at least this many refinements (as above). Only then, not
    # where a given depth turns out unusable: a request's work is bounded before its depth is read (max_rays).
    rgb_refinements: int = 0
    # Where the view comes without a depth image (as above), at most this many Levenberg-Marquardt iterations
    # after Adam's iterations (none: none), from its estimate, on one fixed set of up to polish_rays box rays and
    # Adam's loss; the estimate of lower loss is kept (_polished). 0 = off. Adam only (gauss-newton is that
    # solver already). Only where Adam's silhouette overlaps the mask (intersection over union) at least
    # polish_overlap (0 = always).
    rgb_polish: int = 0
    polish_rays: int = 16384
    polish_overlap: float = POLISH_OVERLAP
    # Rays of an iteration: "uniform" (independent draws over the box), "stratified" (one per cell of a
    # grid over the box), "edges" (half drawn on silhouette edges and texture, half uniform) or
    # "auto" (uniform in a box up to reference_box_px, edges in a larger one).
    ray_sampling: str = "uniform"
    # > 0: the box side (pixels) that rays_per_iteration is meant for. A box k = side / this > 1 times
    # larger (a finer camera, a nearer object) draws k times the rays (k at most _MAX_BOX_SCALE): the
    # same density of rays along the silhouette, whose edges carry the distance in RGB.
    reference_box_px: int = 0
    adam_iterations: int = 0  # gauss-newton: Adam iterations (the rates above) first, to find the basin
    # March each ray only within this many metres of the model's surface points at the iterate, and not
    # at all where none projects near its pixel (narf_core/band.py); 0 = the whole box.
    band_m: float = 0.0
    eval_rays: int = _EVAL_RAYS  # starts are compared, and the final loss measured, on at most this many box rays
    # A wider basin: the given pose and pose_starts - 1 others turned about the object's centre by
    # pose_spread_deg (_pose_turns), each with every θ start, are scored once on the same rays; every θ
    # start then goes on from the given pose and from its best other, until the starts are pruned
    # (twice the starts in the first third of the iterations). 1 = the given pose only.
    pose_starts: int = 1
    pose_spread_deg: float = 30.0
    # > 0, with pose_starts > 1: the wider basin only where it is needed. The refinement runs from the given
    # pose first, and only where its estimate's silhouette overlaps the mask less than this (intersection over
    # union on eval_rays box rays: _silhouette_overlap) once more from the pose starts (_turned_rows), the
    # estimate of lower loss kept (_adaptive_refinement). 0: every pose start from the beginning.
    pose_starts_overlap: float = 0.0
    # > 0: where the mask is trusted only partially (mask_trust), the estimate slid along the object's longest
    # box axis by ± this share of that axis's length and by twice that is scored on eval_rays box rays, and where
    # a slid copy scores lower than the estimate, one more refinement runs from the lowest; the estimate of
    # lower loss is kept (_slid_refinement). 0 = off.
    slide_share: float = 0.0
    # Every θ start's given pose replaced by its copy moved onto the mask's centroid and the observed depth
    # (_aligned) where that copy scores lower on the pose starts' rays: for a start centimetres off along
    # the line of sight, which Gauss-Newton's narrower basin does not pull back; on in `gauss-newton` (whose
    # pruning keeps the starts that tie, see narf_core/gauss_newton.py), off in the Adam presets.
    align_start: bool = False
    # With depth, every start row (pose and θ, after align_start and the configuration search) is first fitted to
    # the observed depth's points inside the mask, this many iterations of articulated ICP (narf_core/surface_fit.py;
    # 0 = off): a thin part's joint moves few of the refiner's rays, whose robust loss is flat until the part's edge
    # crosses them, while every observed point of the part pulls it; on in `gauss-newton`.
    surface_fit_iterations: int = 0
    # With depth and a fully trusted mask, the final estimate is fitted the same way, this many iterations (0 = off):
    # the photometric minimum carries the field's own error of a degree or two on a thin part's joint, the depth's
    # points on the meshes' surface points less (docs/benchmarks.md, session 65); on in `gauss-newton`. Not where
    # the mask is trusted partially (a segmenter's or an occluder's mask, whose pixels the fit would pull on).
    surface_polish_iterations: int = 0
    # With two joints or more: this many configurations (the given one and a Latin hypercube over the joint
    # box) are first fitted to the mask through the model's surface points (_theta_search: a silhouette
    # chamfer, whose basin is wide where a thin rendered part that misses its image has no gradient, and with
    # depth the observed surface's distance to them), and the theta_starts that fit best replace the spread
    # starts of _theta_starts (Gauss-Newton with depth: at the poses fitted, _keeps_search_pose). 0 = off.
    theta_search: int = 0
    # Where the search runs (two joints or more), at least one of its configurations per corner of the joint
    # box, up to this many, are the θ starts (0: theta_starts): with three joints, a fit that couples the
    # pose and the joints (a cabinet moved forward, its drawers pushed back as far) scores among the best
    # four, and the start that leads to the truth is among the next (docs/benchmarks.md).
    search_theta_starts: int = 0
    uncertainty: bool = True  # a covariance of the estimate (one linearisation at the optimum)
    uncertainty_rays: int = 4096  # rays of the box used for it
    uncertainty_patch: int = 4  # pixels per side of the squares whose residuals count as correlated
    # Extra σ added to the covariance's diagonal on top of the model's error (see `model_error`).
    sigma_floor_position: float = 0.0  # metres
    sigma_floor_rotation: float = 0.0  # radians
    sigma_floor_joint: float = 0.0  # fraction of the joint's range
    # > 0: colour residuals up to this count as the model's usual one, and the model's error (MODEL_ERROR)
    # grows only with a residual above it; 0: MODEL_ERROR's reference (model_error; the tracker's with depth).
    uncertainty_usual_residual: float = 0.0
    # > 0: the silhouette's mean squared misfit (the render's opacity against the mask) up to this counts as
    # usual, and above it the model's error grows with its ratio to this squared (SILHOUETTE_EXPONENT): an
    # outline that disagrees with the mask (a segmenter's blobs, an occluder's edge, depth holes the mask
    # follows) marks an estimate the colours do not rank. 0: off (the tracker's with depth sets it).
    uncertainty_usual_silhouette: float = 0.0
    # With depth, the model's error in pixels no finer than the training views' (trained_footprint): an
    # estimate from a few iterations (the tracker's frame) keeps the model's error at a finer camera.
    uncertainty_trained_footprint: bool = False
    # The model's error in rotation spread by the object's shape (rotation_spread): about an axis its surface
    # lies near, the rotation its position error means is wider than over the box's radius (the tracker's).
    uncertainty_rotation_shape: bool = False

    def __post_init__(self) -> None:
        check_option_types(self, EstimateInputError)
        need = option_rule(self, EstimateInputError)
        need(self.iterations >= 0, "iterations", "must be >= 0")
        need(self.lr_pose > 0, "lr_pose", "must be > 0")
        need(self.lr_theta > 0, "lr_theta", "must be > 0")
        need(0 < self.lr_decay <= 1, "lr_decay", "must be in (0, 1]")
        need(self.rays_per_iteration >= 1, "rays_per_iteration", "must be >= 1")
        need(self.mode in MODES, "mode", f"must be one of {', '.join(MODES)}")
        need(self.silhouette_weight >= 0, "silhouette_weight", "must be >= 0")
        need(self.depth_weight >= 0, "depth_weight", "must be >= 0")
        need(1 <= self.theta_starts <= 64, "theta_starts", "must be in [1, 64]")
        need(1 <= self.coarse_to_fine <= 6, "coarse_to_fine", "must be in [1, 6]")
        need(self.box_margin >= 0, "box_margin", "must be >= 0")
        need(self.tolerance >= 0, "tolerance", "must be >= 0")
        need(self.loss_tolerance >= 0, "loss_tolerance", "must be >= 0")
        need(self.patience >= 1, "patience", "must be >= 1")
        need(self.record_every >= 0, "record_every", "must be >= 0")
        need(self.solver in SOLVERS, "solver", f"must be one of {', '.join(SOLVERS)}")
        need(self.robust_loss in ROBUST_LOSSES, "robust_loss", f"must be one of {', '.join(ROBUST_LOSSES)}")
        need(self.robust_scale > 0, "robust_scale", "must be > 0")
        need(0 <= self.damping <= 1e6, "damping", "must be in [0, 1e6]")
        need(self.jacobian in JACOBIANS, "jacobian", f"must be one of {', '.join(JACOBIANS)}")
        need(self.occlusion_margin >= 0, "occlusion_margin", "must be >= 0")
        need(self.depth_sigma >= 0, "depth_sigma", "must be >= 0")
        need(self.mask_trust in MASK_TRUSTS, "mask_trust", f"must be one of {', '.join(MASK_TRUSTS)}")
        need(0 <= self.mask_band_px <= 32, "mask_band_px", "must be in [0, 32] pixels (0 = trust the mask's edge)")
        need(0 <= self.outside_weight <= 1, "outside_weight", "must be in [0, 1] (1 = trust the mask outside it)")
        need(0 <= self.partial_theta_starts <= 64, "partial_theta_starts", "must be in [0, 64] (0 = theta_starts)")
        need(0 <= self.refinements <= 8, "refinements", "must be in [0, 8] (0 or 1 = one refinement)")
        need(0 <= self.rgb_refinements <= 8, "rgb_refinements", "must be in [0, 8] (0 = refinements)")
        need(0 <= self.rgb_polish <= 1000, "rgb_polish", "must be in [0, 1000] (0 = off)")
        need(self.rgb_polish == 0 or self.solver == "adam", "rgb_polish",
             "is for the adam solver (gauss-newton's iterations are the polish)")
        need(self.polish_rays >= 16, "polish_rays", "must be >= 16")
        need(0 <= self.polish_overlap <= 1, "polish_overlap", "must be in [0, 1] (0 = always polish)")
        need(self.reference_box_px >= 0, "reference_box_px", "must be >= 0 (0 = off)")
        need(self.ray_sampling in RAY_SAMPLINGS, "ray_sampling", f"must be one of {', '.join(RAY_SAMPLINGS)}")
        need(self.uncertainty_rays >= 16, "uncertainty_rays", "must be >= 16")
        need(self.adam_iterations >= 0, "adam_iterations", "must be >= 0")
        need(self.band_m == 0 or 0.001 <= self.band_m <= 1, "band_m", "must be 0 (off) or in [0.001, 1] metres")
        need(self.eval_rays >= 16, "eval_rays", "must be >= 16")
        need(1 <= self.pose_starts <= len(_POSE_TURNS), "pose_starts", f"must be in [1, {len(_POSE_TURNS)}]")
        need(0 < self.pose_spread_deg <= 90, "pose_spread_deg", "must be in (0, 90] degrees")
        need(0 <= self.pose_starts_overlap < 1, "pose_starts_overlap", "must be in [0, 1) (0 = every pose start at once)")
        need(0 <= self.slide_share <= 0.25, "slide_share", "must be in [0, 0.25] (0 = off)")
        need(0 <= self.theta_search <= 256, "theta_search", "must be in [0, 256] (0 = off)")
        need(0 <= self.surface_fit_iterations <= 100, "surface_fit_iterations", "must be in [0, 100] (0 = off)")
        need(0 <= self.surface_polish_iterations <= 100, "surface_polish_iterations", "must be in [0, 100] (0 = off)")
        need(0 <= self.search_theta_starts <= 64, "search_theta_starts", "must be in [0, 64] (0 = theta_starts)")
        need(1 <= self.uncertainty_patch <= 64, "uncertainty_patch", "must be in [1, 64]")
        for name in ("sigma_floor_position", "sigma_floor_rotation", "sigma_floor_joint", "uncertainty_usual_residual",
                     "uncertainty_usual_silhouette"):
            need(getattr(self, name) >= 0, name, "must be >= 0")
        gain = self.colour_gain
        need(isinstance(gain, (tuple, list)) and len(gain) == 3
             and all(isinstance(g, (int, float)) and not isinstance(g, bool) and GAIN_RANGE[0] <= g <= GAIN_RANGE[1]
                     for g in gain), "colour_gain", f"must be 3 numbers in [{GAIN_RANGE[0]}, {GAIN_RANGE[1]}]")
        self.colour_gain = tuple(float(g) for g in gain)  # (a JSON list compares equal once read)

    @classmethod
    def robust(cls, **overrides) -> EstimateOptions:
        """The defaults plus a silhouette term, a depth term (used when a depth image is given), 4
        configuration starts, 2 pyramid levels and twice the pose rate: a wider basin and a
        well-determined distance (see the module docstring for measurements). A mask box larger
        than ``ROBUST_BOX_PX`` (a camera finer than the model was trained at, a near object) draws
        proportionally more rays, half of them on the silhouette's edges (``reference_box_px``,
        ``ray_sampling = "auto"``); up to that size nothing changes. Where a depth image contradicts
        the mask (an occluder beside it, its edge on a continuous surface: a segmenter's mask), the
        mask is trusted only partially (``mask_trust = "auto"``), with a 2-pixel band: a segmenter's
        edge is off by about that much, and a wider band leaves a small visible part no evidence. With two
        joints or more the configuration starts come from a search over 16 (``theta_search``): 4 spread
        starts leave most of a 3-joint box unvisited. Without a depth image, at most ``RGB_POLISH``
        Levenberg-Marquardt iterations from Adam's estimate on ``polish_rays`` fixed rays (``rgb_polish``):
        there the distance along the line of sight is weakly observed, and Adam stops in the valley where
        it trades against a turn, wherever its random rays leave it (three refinements of it and the best
        of them, ``rgb_refinements`` 3, were this preset's before: less exact in more time)."""
        return cls(**{
            "silhouette_weight": 1.0, "depth_weight": 1.0, "theta_starts": 4, "coarse_to_fine": 2, "lr_pose": 0.02,
            "reference_box_px": ROBUST_BOX_PX, "ray_sampling": "auto", **PARTIAL_MASK, "theta_search": 16,
            "rgb_polish": RGB_POLISH, **overrides,
        })

    @classmethod
    def gauss_newton(cls, **overrides) -> EstimateOptions:
        """Levenberg-Marquardt on the robust preset's terms (colour, silhouette, depth) with Huber
        weights, 4 configuration starts and 2 pyramid levels, at most ``GN_ITERATIONS`` iterations
        (narf_core/gauss_newton.py), the covariance on ``GN_UNCERTAINTY_RAYS`` rays. With two joints or
        more the starts come from a search over 16 (``theta_search``), with depth at the poses it fitted, one
        per corner of the joint box up to 8 (``search_theta_starts``).
        ``adam_iterations`` runs Adam first instead of the pyramid. Each configuration start begins at the
        given pose or its copy moved onto the mask and the depth, whichever scores lower (``align_start``):
        a thin tool's start 2 cm off along the line of sight otherwise ends there, or in a wrong joint
        basin (docs/benchmarks.md); with depth each start is then fitted to the observed surface's points
        (``surface_fit_iterations``, ``GN_SURFACE_FIT``): the lamp's joints came out twice as near; where the
        mask is trusted in full, so is the final estimate (``surface_polish_iterations``, ``GN_SURFACE_POLISH``).
        Where the
        estimate's silhouette then overlaps the mask less than
        ``GN_POSE_OVERLAP`` (intersection over union), it refines once more from ``GN_POSE_STARTS`` pose starts
        (``pose_starts_overlap``): Gauss-Newton's basin is narrower than Adam's, and a start 30 deg off
        often ends in a wrong minimum, while one within the basin explains the mask and pays only the check.
        Where a depth image contradicts the mask, the mask is trusted only partially, as in the robust
        preset (``mask_trust = "auto"``, its 2-pixel edge band and 8 configuration starts): on path-traced
        views with every sensor, mask and occlusion fault a fully trusted mask cost it several centimetres
        (docs/benchmarks.md). There, and without a depth image, where the estimate's silhouette overlaps the
        mask less than ``GN_POSE_OVERLAP``, it refines once more from the given pose alone with half its rays
        on the mask's edges and the image's texture (a thin, partly hidden tool meets few uniform rays) and,
        where the mask is trusted partially, once more from starts not moved onto the mask (an occluder moves
        its centroid), and keeps the estimate of lowest loss (``refinements``).

        ``depth_weight`` is ``GN_DEPTH_WEIGHT``, not the robust preset's 1: Gauss-Newton sums its
        residuals (three colour channels, the silhouette and the depth of every ray) where Adam's
        loss averages the colour over its channels and the depth term over the rays with a depth
        alone, so the same weight gives the depth a several times smaller share, and a 160x120
        view's colour barely constrains the distance (docs/benchmarks.md). It stops once
        ``patience`` accepted steps in a row each moved less than ``tolerance``."""
        return cls(**{
            "solver": "gauss-newton", "iterations": GN_ITERATIONS, "silhouette_weight": 1.0,
            "depth_weight": GN_DEPTH_WEIGHT, "theta_starts": 4, "coarse_to_fine": 2, "robust_loss": "huber",
            "tolerance": 3e-3, "patience": 2, "uncertainty_rays": GN_UNCERTAINTY_RAYS, "theta_search": 16,
            "search_theta_starts": 8, "align_start": True, "pose_starts": GN_POSE_STARTS,
            "pose_starts_overlap": GN_POSE_OVERLAP, "refinements": 3, "slide_share": GN_SLIDE_SHARE, **PARTIAL_MASK,
            "surface_fit_iterations": GN_SURFACE_FIT, "surface_polish_iterations": GN_SURFACE_POLISH, **overrides,
        })

    def max_rays(self, depth: bool = True) -> int:
        """An upper bound on the rays a refinement traces, known before any work: the scoring of
        ``align_start``'s starts, every estimate (:meth:`_estimate_rays`: its refinements' iterations at the
        largest box scale for every start, the pose starts' scoring, its final choice and, with
        ``pose_starts_overlap``, the overlap check and the choice between its two refinements) and the
        covariance; with ``refinements``, all that many refinements (Adam: inside the estimate) or
        estimates (``gauss-newton``: :func:`_gauss_newton_estimates`, their overlap check), and the choice
        among them, and the loss of ``surface_polish_iterations``' fitted estimate. ``depth``: whether the view
        comes with a depth image (without one:
        ``rgb_refinements``, and a mask trusted partially only where ``mask_trust`` is "partial", as nothing
        else contradicts it; with one, also where it is "auto"). Not counted: ``parts`` mode's forward
        differences in θ for ``gauss-newton`` (one more render per joint at each linearisation), which
        depend on the model."""
        scale = _MAX_BOX_SCALE if self.reference_box_px else 1
        partial = self.mask_trust == "partial" or (depth and self.mask_trust == "auto")  # as _partial_trust
        theta_starts = _configuration_starts(self, partial, joints=MAX_JOINTS)  # the most any object runs
        scoring = 3 * theta_starts * _SCORE_RAYS if self.align_start else 0  # _start_rows's alignment
        # cluster_sample draws at most uncertainty_rays squares of uncertainty_patch² pixels each
        covariance = self.uncertainty_rays * self.uncertainty_patch**2 if self.uncertainty else 0
        # refinements with a depth image too: one found unusable (usable_depth) leaves a view refine runs them on
        runs = max(1, self.refinements, 0 if depth else self.rgb_refinements)
        polish = self.eval_rays if self.surface_polish_iterations and depth and self.mask_trust != "partial" else 0
        if self.solver != "gauss-newton":  # the runs inside the estimate (_best_refinement)
            work = self._estimate_rays(theta_starts,
                                       lambda starts: self._adam_rays(self.iterations, starts, scale, runs))
            slide = self._slide_rays(self._adam_rays(self.iterations, 1, scale, runs)) if partial else 0
            return scoring + work + slide + (0 if depth else self._polish_rays()) + polish + covariance
        estimates = _gauss_newton_estimates(replace(self, mask_trust="partial" if partial else "full"), runs)
        work = sum(o._estimate_rays(theta_starts, lambda starts, o=o: o._gauss_newton_run_rays(starts, scale))
                   for o in estimates)
        several = len(estimates) > 1
        check = self.eval_rays if several and self.pose_starts_overlap > 0 else 0  # _best_gauss_newton's
        choice = len(estimates) * _CHOICE_RAYS if several else 0  # _lowest_run among the estimates
        slide = self._slide_rays(self._gauss_newton_run_rays(1, scale)) if partial else 0
        return scoring + work + check + choice + slide + polish + covariance

    def _slide_rays(self, refinement: int) -> int:
        """The rays of ``slide_share`` (:func:`_slid_refinement`, where the mask is trusted partially): the
        estimate's and its four slid copies' scoring, one more refinement (``refinement`` rays, from one start) and
        the choice between both estimates."""
        return (5 + 4) * self.eval_rays + refinement if self.slide_share > 0 else 0

    def _estimate_rays(self, theta_starts: int, refinement: Callable[[int], int]) -> int:
        """The rays of one estimate from ``theta_starts`` θ starts (``refinement(starts)``: one refinement's
        from ``starts`` rows): with ``pose_starts_overlap`` (:func:`_adaptive_refinement`) the given pose's
        refinement, the overlap check, the turned starts' scoring and refinement, and the choice between
        both estimates; else the pose starts' scoring, one refinement from every start and its final
        choice of the last and best rows."""
        pose_scoring = 3 * self.pose_starts * theta_starts * _SCORE_RAYS if self.pose_starts > 1 else 0
        if self.pose_starts > 1 and self.pose_starts_overlap > 0:
            first, second = theta_starts, theta_starts * _RETRY_POSES_KEPT
            choices = (2 * first + 1 + 2 * (1 + second)) * self.eval_rays  # the first's, the check, both estimates'
            return pose_scoring + refinement(first) + refinement(second) + choices
        starts = theta_starts * (1 + _POSES_KEPT) if self.pose_starts > 1 else theta_starts
        return pose_scoring + refinement(starts) + 2 * starts * self.eval_rays

    def _adam_rays(self, iterations: int, starts: int, scale: int, runs: int = 1) -> int:
        """The rays of ``runs`` Adam refinements (``_Run``) of ``iterations`` from ``starts`` rows: every
        iteration's rays for every start (half each while several run: bounded by all), the pruning to
        the best start on up to ``eval_rays`` rays per start and each run's final choice of its last and
        best rows; where several run (:func:`_best_refinement`), the choice among them."""
        per_run = iterations * self.rays_per_iteration * scale * starts + 3 * starts * self.eval_rays
        return runs * per_run + (runs * _CHOICE_RAYS if runs > 1 else 0)

    def _polish_rays(self) -> int:
        """The rays of ``rgb_polish`` (:func:`_polished`): every iteration's linearisation and its longest
        series of trial steps on ``polish_rays`` rays, the overlap that lets it run, and the choice of both
        estimates."""
        from narf_core.gauss_newton import _POLISH_STEP_FACTORS, _STEP_FACTORS

        steps = max(len(_POLISH_STEP_FACTORS), len(_STEP_FACTORS))
        return self.rgb_polish * self.polish_rays * (1 + steps) + 3 * self.eval_rays if self.rgb_polish else 0

    def _gauss_newton_run_rays(self, starts: int, scale: int) -> int:
        """The rays of one ``GaussNewtonRun`` from ``starts`` rows (narf_core/gauss_newton.py), after the
        Adam warm start (``adam_iterations``: :meth:`_adam_rays`) where there is one. Each
        iteration renders the linearisation and then every trial step: while several starts run, half the
        rays each and ``_STEP_FACTORS``; one start alone at the fine level of a pyramid (the polish), all
        the rays and ``_POLISH_STEP_FACTORS``; several starts are pruned on up to ``_EVAL_RAYS`` rays
        (:func:`_gauss_newton_prunings`)."""
        from narf_core.gauss_newton import _GROUP, _POLISH_STEP_FACTORS, _STEP_FACTORS

        rays = self.rays_per_iteration * scale
        polish_steps = len(_POLISH_STEP_FACTORS) if self.coarse_to_fine > 1 else len(_STEP_FACTORS)
        iteration = max(rays, _GROUP) * (1 + polish_steps)  # at a coarse level a pixel's _GROUP rays at least
        prunings = 0
        if starts > 1:
            iteration = max(iteration, starts * max(rays // 2, _GROUP) * (1 + len(_STEP_FACTORS)))
            prunings = _gauss_newton_prunings(self.iterations) * starts * _EVAL_RAYS
        warm = self._adam_rays(self.adam_iterations, starts, scale) if self.adam_iterations else 0
        return warm + self.iterations * iteration + prunings

    @classmethod
    def preset(cls, name: str = "paper", *, depth: bool | None = None, **overrides) -> EstimateOptions:
        """The options of a named preset (``paper``: the defaults; ``robust``: :meth:`robust`;
        ``gauss-newton``: :meth:`gauss_newton`; ``auto``: the one :func:`choose_preset` picks for a view
        with a depth image or without, ``depth``) with ``overrides`` applied."""
        if name == "auto" and depth is None:
            reason = "'auto' depends on the view: say whether it has a depth image (preset('auto', depth=...))"
            raise EstimateInputError(f"options.preset {reason}", "options.preset", reason)
        name = choose_preset(name, bool(depth))[0]  # (an unknown name is refused there)
        if name == "paper":
            return cls(**overrides)
        if name == "robust":
            return cls.robust(**overrides)
        return cls.gauss_newton(**overrides)


def choose_preset(name: str, depth: bool) -> tuple[str, str]:
    """``(preset, reason)``: the named preset that ``name`` (one of :data:`PRESET_NAMES`) comes to for a
    view with a depth image (``depth``) or without.

    ``auto``: ``gauss-newton`` with a depth image, ``robust`` without. With depth, Gauss-Newton's
    error is as small as the robust preset's or smaller, in less time where the mask is not
    contradicted, on our renderer's views and on path-traced ones with sensor, mask and occlusion
    faults; without depth, where the distance along the line of sight is weakly observed, Adam's
    wider basin and its Levenberg-Marquardt polish (``rgb_polish``) are several times more exact at a
    camera's native resolution (docs/benchmarks.md has the figures). A depth image the refiner finds
    unusable (a wrong unit, off the mask: a warning) still counts as given here."""
    if name not in PRESET_NAMES:
        reason = f"must be one of {', '.join(PRESET_NAMES)}, got {name!r}"
        raise EstimateInputError(f"options.preset {reason}", "options.preset", reason)
    if name != "auto":
        return name, "requested"
    if depth:
        return "gauss-newton", "the view has a depth image"
    return "robust", "no depth image: Adam's wider basin and its polish hold the distance better"


def _configuration_starts(opts: EstimateOptions, partial: bool, joints: int) -> int:
    """How many configuration starts a refinement of an object with ``joints`` joints runs: ``theta_starts``,
    at least ``partial_theta_starts`` where the mask is trusted partially (``partial``) and, where the
    configuration search runs (``theta_search``, two joints or more: :func:`_given_rows`), at least one per
    corner of the joint box (``2 ** joints``) up to ``search_theta_starts``."""
    starts = max(opts.theta_starts, opts.partial_theta_starts) if partial else opts.theta_starts
    return max(starts, min(opts.search_theta_starts, 2**joints)) if opts.theta_search and joints > 1 else starts


def _gauss_newton_prunings(iterations: int) -> int:
    """The most times a ``GaussNewtonRun`` of ``iterations`` prunes its starts: once at ``_PRUNE_SHARE``
    of them (at the first at the earliest), then at every iteration from ``_LAST_PRUNE_SHARE`` on while
    several starts tie exactly (a joint no ray sees, or no start with a finite cost)."""
    from narf_core.gauss_newton import _LAST_PRUNE_SHARE

    if iterations < 1:
        return 0
    first = max(int(iterations * _PRUNE_SHARE), 1)
    return 1 + max(0, iterations - max(first + 1, int(iterations * _LAST_PRUNE_SHARE)) + 1)


@dataclass
class Snapshot:
    """The estimate after ``iteration`` steps, ``seconds`` into the run (``options.record_every``)."""

    iteration: int
    seconds: float
    loss: float
    T_cam_obj: np.ndarray  # [4, 4]
    joints: dict[str, float]


@dataclass
class Uncertainty:
    """The covariance of an estimate, in the local parameterisation at the estimate.

    Order of ``covariance [6 + k, 6 + k]``: the displacement of the object's box centre (metres,
    camera axes), the rotation about that centre (radians, camera axes, left-multiplied:
    ``R_true = exp(δω) R_est``), then θ (joint units, model order). The statistical part comes from
    the normal equations at the estimate, scaled by the weighted residual variance
    ``residual_variance`` with ``dof`` degrees of freedom (see narf_core/gauss_newton.py). The
    model's error, which residual statistics cannot see, is added on the diagonal
    (:func:`model_error`; on the bundled clamp the statistical σ alone is 20-100x smaller than the
    true error), and the options' ``sigma_floor_*`` on top of it.
    """

    covariance: np.ndarray  # [6 + k, 6 + k]
    position_sigma_m: np.ndarray  # [3]
    rotation_sigma_rad: np.ndarray  # [3]
    joint_sigma: dict[str, float]
    residual_variance: float
    dof: int
    # Each joint's σ from the view alone: the statistical part, whose prior bounds a joint no ray sees,
    # without the model's error (which grows with the residual whatever the view shows); what
    # :func:`unobserved_joints` judges. Not in :meth:`to_dict`.
    view_joint_sigma: dict[str, float] | None = None
    # The covariance with the model's error widened by the colour residual alone, where the silhouette's
    # misfit widened it more (EstimateOptions.uncertainty_usual_silhouette; else None, the same as
    # ``covariance``): what the tracker's second round judges, a track turning away, which the colours
    # show. Not in :meth:`to_dict`.
    colour_covariance: np.ndarray | None = None
    # The variances ``[6 + k]`` on the diagonal of both covariances for joints whose parts the mask leaves
    # out (:data:`HIDDEN_SHARE`: their half range squared; zeros elsewhere): their prior, not a model error,
    # so a factor on σ (the tracker's) leaves it as it is. Not in :meth:`to_dict`.
    unseen_variance: np.ndarray | None = None

    @classmethod
    def from_covariance(cls, covariance: np.ndarray, joint_names: list[str], variance: float, dof: int,
                        view_joint_sigma: dict[str, float] | None = None,
                        colour_covariance: np.ndarray | None = None,
                        unseen_variance: np.ndarray | None = None) -> Uncertainty:
        sd = np.sqrt(np.clip(np.diag(covariance), 0, None))
        return cls(covariance, sd[:3].copy(), sd[3:6].copy(), dict(zip(joint_names, map(float, sd[6:]), strict=True)),
                   float(variance), int(dof), view_joint_sigma, colour_covariance, unseen_variance)

    def to_dict(self) -> dict:
        """A JSON-able copy."""
        return {
            "covariance": self.covariance.tolist(),
            "position_sigma_m": self.position_sigma_m.tolist(),
            "rotation_sigma_rad": self.rotation_sigma_rad.tolist(),
            "joint_sigma": dict(self.joint_sigma),
            "residual_variance": self.residual_variance,
            "dof": self.dof,
        }


# A joint whose σ is at least this share of its half range: what bounds it is the prior Σ₀ (the half range,
# narf_core/gauss_newton.py), not the view, which hardly sees it (a drawer whose front faces away, a part
# behind another): its value is a guess within its range (docs/benchmarks.md, session 31).
UNOBSERVED_SHARE = 0.5
UNOBSERVED_CODE = "unobserved_joint"  # the warning's code: "unobserved_joint: <joint>: <why>"


def unobserved_joints(model: NarfModel, uncertainty: Uncertainty | None) -> list[str]:
    """One warning ``"unobserved_joint: <joint>: ..."`` (:data:`UNOBSERVED_CODE`) for each joint of ``model``
    whose σ from the view (:attr:`Uncertainty.view_joint_sigma`) is at least :data:`UNOBSERVED_SHARE` of its
    half range, saying why: the mask hardly shows the part it moves (:attr:`Uncertainty.unseen_variance`), or
    the view barely constrains it; none without an uncertainty."""
    joint_sigma = None if uncertainty is None else uncertainty.view_joint_sigma
    if joint_sigma is None:
        return []
    unseen = uncertainty.unseen_variance
    out = []
    lower, upper = model.kinematics.lower.tolist(), model.kinematics.upper.tolist()
    for i, (joint, lo, hi) in enumerate(zip(model.joints, lower, upper, strict=True)):
        sigma, half = joint_sigma[joint.name], (hi - lo) / 2
        if half > 0 and sigma >= UNOBSERVED_SHARE * half:
            scale, unit = (1000.0, "mm") if joint.type == "prismatic" else (180.0 / math.pi, "deg")
            hidden = unseen is not None and unseen[6 + i] > 0
            why = (f"the mask shows under {HIDDEN_SHARE:.0%} of the part it moves, or another part hides it" if hidden
                   else "the view hardly constrains it")
            out.append(f"{UNOBSERVED_CODE}: {joint.name}: {why} (σ {sigma * scale:.1f} {unit} "
                       f"over a range of {2 * half * scale:.1f} {unit}); its value is a guess within that range")
    return out


# Without depth the distance is read off the size of the object's outline in the image, and a field trained
# on views coarser than the camera's draws that outline less exactly at the camera's pixels: over this ratio
# of focal lengths (the camera's over the training views') a view without depth is warned (docs/benchmarks.md,
# sessions 48 and 51: the pliers on path-traced 640x480 views, trained on 160x120, 320x240 and 640x480 views).
COARSE_MODEL_RATIO = 2.0
COARSE_MODEL_CODE = "coarse_model"  # the warning's code


def coarse_model(model: NarfModel, camera: Pinhole, depth: np.ndarray | None) -> list[str]:
    """One warning ``"coarse_model: ..."`` (:data:`COARSE_MODEL_CODE`) for a view without ``depth`` (the depth
    the refiner uses: ``None`` also where the input checks dropped it) whose ``camera``'s focal length is over
    :data:`COARSE_MODEL_RATIO` times that of the views ``model`` was trained on (:func:`training_fx`), else
    none: with depth the distance does not hang on the outline."""
    if depth is not None:
        return []
    ratio = float(camera.K[0, 0]) / training_fx(model)
    if ratio <= COARSE_MODEL_RATIO:
        return []
    width, height = camera.width, camera.height
    return [f"{COARSE_MODEL_CODE}: the model was trained on views {ratio:.1f}x coarser than this "
            f"{width}x{height} camera's; without depth the distance follows the model's outline, which a model "
            f"trained on views of the camera's size draws more exactly (narf synth --size {width} {height})"]


def local_error(
    T_est: np.ndarray, theta_est: Mapping[str, float], T_true: np.ndarray, theta_true: Mapping[str, float], model: NarfModel
) -> np.ndarray:
    """The true error ``[6 + k]`` of an estimate in :class:`Uncertainty`'s parameterisation: the box
    centre's displacement (m), the left rotation ``log(R_true R_estᵀ)`` (rad), ``θ_true - θ_est``."""
    aabb = model.aabb.detach().double().cpu().numpy()
    centre = (aabb[0] + aabb[1]) / 2
    T_est, T_true = np.asarray(T_est, np.float64), np.asarray(T_true, np.float64)
    dc = (T_true[:3, :3] @ centre + T_true[:3, 3]) - (T_est[:3, :3] @ centre + T_est[:3, 3])
    dr = so3_log(torch.from_numpy(T_true[:3, :3] @ T_est[:3, :3].T)).numpy()
    dt = [float(theta_true[j.name]) - float(theta_est[j.name]) for j in model.joints]
    return np.concatenate([dc, dr, np.asarray(dt, np.float64)])


def nees(
    result_or_uncertainty: EstimateResult | Uncertainty,
    T_est: np.ndarray,
    theta_est: Mapping[str, float],
    T_true: np.ndarray,
    theta_true: Mapping[str, float],
    model: NarfModel,
) -> float:
    """Normalised estimation error squared ``eᵀ Σ⁻¹ e`` (``e`` from :func:`local_error`); below
    ``chi2.ppf(0.95, 6 + k)`` when the truth lies inside the 95 % region. ``nan`` without a covariance."""
    unc = result_or_uncertainty.uncertainty if isinstance(result_or_uncertainty, EstimateResult) else result_or_uncertainty
    if unc is None:
        return math.nan
    e = local_error(T_est, theta_est, T_true, theta_true, model)
    return float(e @ np.linalg.pinv(unc.covariance, hermitian=True) @ e)


def chi2_quantile(probability: float, dof: int) -> float:
    """The ``probability`` quantile of χ² with ``dof`` degrees of freedom (bisection on its CDF, the
    regularised lower incomplete gamma function): the NEES bound of a ``probability`` region."""
    lo, hi = 0.0, float(dof) + 40.0 * math.sqrt(max(dof, 1)) + 40.0
    half = torch.tensor(dof / 2, dtype=torch.float64)
    for _ in range(100):
        mid = (lo + hi) / 2
        if float(torch.special.gammainc(half, torch.tensor(mid / 2, dtype=torch.float64))) < probability:
            lo = mid
        else:
            hi = mid
    return (lo + hi) / 2


@dataclass
class EstimateResult:
    """What :func:`refine` found.

    ``status``: ``converged`` (stopped early), ``max_iterations``, ``no_overlap`` (no ray of the
    mask's box meets the object's box under ``T_init``: the initial pose comes back unchanged) or
    ``non_finite`` (the loss stayed non-finite for several iterations in a row despite recovery:
    the best finite iterate comes back, or the initial pose if there was none). ``loss`` is the
    final loss on a fixed set of up to ``options.eval_rays`` rays of the box, or ``None`` (JSON ``null``) when none
    could be computed. ``trace`` holds ``(loss, seconds since the start)`` of every finite
    iteration; ``history`` the estimate every ``options.record_every`` iterations. ``metrics``
    (with ``ground_truth``): ``rotation_error_deg`` and ``translation_error_m`` of the root link,
    ``joint_error/<name>`` (radians or metres) and, when the model has surface points, ``add`` and
    ``add_s`` (metres), ``add<1cm`` and ``add<0.1d`` (0 or 1).
    """

    T_cam_obj: np.ndarray  # [4, 4] float64
    position: np.ndarray  # [3]
    quaternion: np.ndarray  # [4], xyzw
    joints: dict[str, float]
    loss: float | None
    iterations: int
    seconds: float
    trace: list[tuple[float, float]]
    status: str
    recovered_non_finite: bool
    metrics: dict[str, float] | None = None
    history: list[Snapshot] = field(default_factory=list)
    uncertainty: Uncertainty | None = None
    warnings: list[str] = field(default_factory=list)  # narf_core.observation.check_observation's
    mode: str | None = None  # the render mode that ran (``options.mode``, ``auto`` resolved) ...
    mode_reason: str | None = None  # ... and why (narf_core.modes.choose_mode)

    def to_dict(self) -> dict:
        """A JSON-able copy (arrays as nested lists)."""
        return {
            "T_cam_obj": self.T_cam_obj.tolist(),
            "position": self.position.tolist(),
            "quaternion": self.quaternion.tolist(),
            "joints": dict(self.joints),
            "loss": self.loss,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "trace": [list(t) for t in self.trace],
            "status": self.status,
            "recovered_non_finite": self.recovered_non_finite,
            "metrics": None if self.metrics is None else dict(self.metrics),
            "history": [
                {"iteration": s.iteration, "seconds": s.seconds, "loss": s.loss, "T_cam_obj": s.T_cam_obj.tolist(),
                 "joints": dict(s.joints)}
                for s in self.history
            ],
            "uncertainty": None if self.uncertainty is None else self.uncertainty.to_dict(),
            "warnings": list(self.warnings),
            "mode": self.mode,
            "mode_reason": self.mode_reason,
        }


# --------------------------------------------------------------------------------------------
# Input checks


def _check_call(options, options_type: type, camera: Pinhole, error: type[EstimateInputError]):
    """``options`` (``options_type()`` where None) once checked to be an ``options_type``, and
    ``camera`` a :class:`Pinhole`: the opening checks of :func:`refine` and of the detector;
    ``error`` is the caller's error class."""
    opts = options if options is not None else options_type()
    if not isinstance(opts, options_type):
        raise error(f"options must be {options_type.__name__}, got {type(opts).__name__}")
    if not isinstance(camera, Pinhole):
        raise error(f"camera must be a narf_core.geometry.Pinhole, got {type(camera).__name__}")
    return opts


def _check_observation(
    image: np.ndarray, mask: np.ndarray, depth: np.ndarray | None, camera: Pinhole,
    error: type[EstimateInputError] = EstimateInputError,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validated ``image [H,W,3]`` uint8, ``mask [H,W]`` bool and ``depth [H,W]`` (0 = none);
    ``error`` is the caller's error class."""
    image, mask = np.asarray(image), np.asarray(mask)
    if image.ndim != 3 or image.shape[2] != 3:
        raise error(f"image must be an RGB array [H, W, 3], got shape {image.shape}")
    if image.dtype != np.uint8:
        raise error(f"image must be uint8 sRGB, got dtype {image.dtype}")
    if mask.ndim != 2:
        raise error(f"mask must be a 2-D array [H, W], got shape {mask.shape}")
    if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
        raise error(f"mask must be boolean (or integer, nonzero = object), got dtype {mask.dtype}")
    height, width = image.shape[:2]
    if mask.shape != (height, width):
        raise error(f"mask is {mask.shape[1]}x{mask.shape[0]} but image is {width}x{height} (WxH)")
    if (camera.width, camera.height) != (width, height):
        raise error(
            f"camera is {camera.width}x{camera.height} but image is {width}x{height} (WxH)"
        )
    K = camera.K.detach().double().cpu().numpy()
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise error(f"camera K must be finite with fx, fy > 0 and last row [0, 0, 1], got {K.tolist()}")
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise error(
            f"camera K's principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the {width}x{height} image: "
            "K is probably for another resolution"
        )
    mask = mask != 0
    count = int(mask.sum())
    if count == 0:
        raise error("mask is empty: no object pixel to fit")
    if count < MIN_MASK_PIXELS:
        raise error(f"mask has only {count} object pixel(s); at least {MIN_MASK_PIXELS} are needed")
    if depth is not None:
        depth = np.asarray(depth)
        if depth.shape != (height, width):
            raise error(f"depth must be [H, W] = {(height, width)} like the image, got shape {depth.shape}")
        if not np.issubdtype(depth.dtype, np.floating):
            raise error(f"depth must be float metres, got dtype {depth.dtype}")
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        if (depth < 0).any():
            raise error("depth has negative values; expected metres with 0 (or NaN) = no return")
    return image, mask, depth


# --------------------------------------------------------------------------------------------
# The observation, cropped to the rays' box


@dataclass
class _Target:
    """Per-pixel targets of the box at one pyramid level, flattened row-major."""

    rgb: Tensor  # [P, 3] the masked image, box-filtered over `width` pixels
    mask: Tensor  # [P] mask coverage in [0, 1]
    depth: Tensor | None  # [P] metres, 0 = none (never filtered: only at the finest level)
    width: int  # box filter width in pixels (odd)
    band: Tensor | None = None  # [P] bool: within options.mask_band_px of the mask's boundary (None: no band)
    image: Tensor | None = None  # [P, 3] the unmasked image, for the band's rays (finest level only)


@dataclass
class _Observation:
    """The dilated mask box ``[u0, u1) x [v0, v1)`` with its pixels and per-level targets."""

    pixels: Tensor  # [P, 2] integer (u, v) of the box
    levels: list[_Target]  # coarse to fine
    importance: Tensor | None = None  # [P] sums to 1: silhouette edges and image gradient (ray_sampling "edges")
    shape: tuple[int, int] = (0, 0)  # (h, w) of the box: P = h * w, row-major
    scale: float = 1.0  # the box's size over options.reference_box_px (_box_scale)


def _mask_box(mask: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """``(u0, v0, u1, v1)``: the mask's bounding box grown by ``margin`` of its size, inside the image."""
    rows, cols = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    v0, v1, u0, u1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    grow = max(2, round(margin * max(u1 - u0, v1 - v0)))
    height, width = mask.shape
    return max(0, u0 - grow), max(0, v0 - grow), min(width, u1 + grow), min(height, v1 + grow)


def _box_scale(box: tuple[int, int, int, int], opts: EstimateOptions) -> float:
    """``k``: the box's longer side over ``opts.reference_box_px``, in [1, _MAX_BOX_SCALE] (1 when
    that option is 0). An iteration draws ``k`` times the rays, so that as many land on the
    silhouette's edges per unit of its length as in a box of the reference size."""
    if not opts.reference_box_px:
        return 1.0
    return min(float(_MAX_BOX_SCALE), max(1.0, max(box[2] - box[0], box[3] - box[1]) / opts.reference_box_px))


def _box_filter(image: Tensor, width: int) -> Tensor:
    """Mean over ``width x width`` pixels (odd ``width``), shrinking at the borders: ``[h,w,c] -> [h,w,c]``."""
    if width == 1:
        return image
    x = image.permute(2, 0, 1)[None]
    out = F.avg_pool2d(x, width, stride=1, padding=width // 2, count_include_pad=False)
    return out[0].permute(1, 2, 0)


def _observation(
    image: np.ndarray, mask: np.ndarray, depth: np.ndarray | None, box: tuple[int, int, int, int], levels: int, device,
    band_px: int = 0,
) -> _Observation:
    """The box's pixels and targets; ``band_px > 0`` marks the pixels within that distance of the
    mask's boundary (:func:`_mask_band`) and keeps the unmasked image for them."""
    u0, v0, u1, v1 = box
    rgb = torch.tensor(image[v0:v1, u0:u1], dtype=torch.float32) / 255
    m = torch.tensor(mask[v0:v1, u0:u1], dtype=torch.float32)[..., None]
    masked = torch.cat([rgb * m, m], dim=-1)  # [h, w, 4]
    d = None if depth is None else torch.tensor(depth[v0:v1, u0:u1]).reshape(-1)
    band = _mask_band(m[..., 0], band_px).reshape(-1) if band_px > 0 else None
    targets = []
    for level in range(levels):
        width = 2 ** (levels - 1 - level) + 1 if level < levels - 1 else 1
        blurred = _box_filter(masked, width).reshape(-1, 4)
        targets.append(_Target(blurred[:, :3], blurred[:, 3], d if width == 1 else None, width, band,
                               rgb.reshape(-1, 3) if band is not None and width == 1 else None))
    v, u = torch.meshgrid(torch.arange(v0, v1), torch.arange(u0, u1), indexing="ij")
    pixels = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    targets = [
        _Target(*(None if x is None else x.to(device) for x in (t.rgb, t.mask, t.depth)), t.width,
                *(None if x is None else x.to(device) for x in (t.band, t.image)))
        for t in targets
    ]
    return _Observation(pixels.to(device), targets, _importance(masked), (v1 - v0, u1 - u0))


def _partial_trust(opts: EstimateOptions, mask: np.ndarray, depth: np.ndarray | None) -> bool:
    """Whether the mask is trusted only partially (``opts.mask_trust`` "partial"; "auto": where a
    depth image used by the loss contradicts it as the object's whole silhouette, an occluder
    beside it or its edge on a continuous surface, :func:`~narf_core.observation.mask_evidence`).
    An exact mask keeps full trust at any size; without depth nothing tells the background from an
    occluder (and a cheaper outside pulls the estimate nearer), so "auto" trusts the mask in full."""
    if opts.mask_trust != "auto":
        return opts.mask_trust == "partial"
    return depth is not None and opts.depth_weight > 0 and mask_evidence(mask, depth).doubtful


def _mask_band(mask: Tensor, px: int) -> Tensor:
    """``[h, w]`` bool: pixels within ``px`` (chessboard distance) of the boundary of ``mask [h, w]``
    (0/1): those the mask's dilation by ``px`` adds or its erosion by ``px`` removes, except the
    middle of a part no wider than the band (:func:`_mask_spine`). A segmenter's edge is off by a
    pixel or two (and bleeds or shrinks as a whole), so its pixels there are no evidence of where
    the object's silhouette lies; the middle of a thin part stays where it is when its edges move
    out or in together, and without it a small, thin mask (a tool seen from afar or end-on) would
    be nearly all band, leaving nothing to say where the object is."""
    x = mask[None, None]
    grown = F.max_pool2d(x, 2 * px + 1, stride=1, padding=px)[0, 0]
    shrunk = -F.max_pool2d(-x, 2 * px + 1, stride=1, padding=px)[0, 0]
    return (grown > 0.5) & (shrunk < 0.5) & ~_mask_spine(mask, px)


def _mask_spine(mask: Tensor, px: int) -> Tensor:
    """``[h, w]`` bool: the mask's pixels within ``px`` of its boundary whose chessboard distance to the
    background (1 on the boundary) is largest among their 8 neighbours: a 1-2 pixel line along the
    middle of every part at most ``2 px + 1`` pixels wide, nothing elsewhere."""
    inside = mask > 0.5
    distance = torch.zeros_like(mask)
    eroded = mask[None, None]
    for _ in range(px + 1):  # distances above px + 1 are not told apart: those pixels are off the band
        distance = distance + (eroded[0, 0] > 0.5).to(mask.dtype)
        eroded = -F.max_pool2d(-eroded, 3, stride=1, padding=1)
    ridge = distance >= F.max_pool2d(distance[None, None], 3, stride=1, padding=1)[0, 0]
    return inside & (distance <= px) & ridge


def _importance(masked: Tensor) -> Tensor:
    """``[h*w]`` sampling weights of the box ``masked [h, w, 4]`` (rgb * mask, mask): the gradient
    magnitude of the mask and of the masked colour, spread over 3x3 pixels, plus a floor."""
    gy = torch.zeros_like(masked)
    gx = torch.zeros_like(masked)
    gy[1:-1] = (masked[2:] - masked[:-2]) / 2
    gx[:, 1:-1] = (masked[:, 2:] - masked[:, :-2]) / 2
    strength = (gx**2 + gy**2).sum(-1, keepdim=True).sqrt()
    strength = _box_filter(strength, 3).reshape(-1)
    weights = strength + 0.05 * float(strength.mean().clamp_min(1e-6))
    return (weights / weights.sum()).double()


# --------------------------------------------------------------------------------------------
# Parameterisation


@dataclass
class _Parameterisation:
    """Maps the optimised rows ``p [S, 6 + k]`` to poses ``[S,4,4]`` and configurations ``[S,k]``."""

    T_init: Tensor  # [4, 4] float64
    T_centre: Tensor  # [4, 4] translation to the object's centre in the camera frame under T_init
    radius: float  # metres per unit of the normalised translation
    mid: Tensor  # [k] float64
    half: Tensor  # [k] half the joint ranges

    @classmethod
    def around(cls, T_init: Tensor, model: NarfModel) -> _Parameterisation:
        aabb = model.aabb.to("cpu", torch.float64)  # the parameters live on the CPU, whatever the model's device
        T_centre = torch.eye(4, dtype=torch.float64)
        T_centre[:3, 3] = transform_points(T_init, (aabb[0] + aabb[1]) / 2)
        lower, upper = model.kinematics.lower.to(torch.float64), model.kinematics.upper.to(torch.float64)
        return cls(T_init, T_centre, float((aabb[1] - aabb[0]).norm()) / 2, (lower + upper) / 2, (upper - lower) / 2)

    def poses(self, p: Tensor) -> Tensor:
        xi = torch.cat([p[:, :3] * self.radius, p[:, 3:6]], dim=-1)
        return self.T_centre @ se3_exp(xi) @ invert_pose(self.T_centre) @ self.T_init

    def thetas(self, p: Tensor) -> Tensor:
        return self.mid + self.half * torch.sin(p[:, 6:])

    def rows_of(self, T: Tensor, theta: Tensor) -> Tensor:
        """``[S, 6 + k]``: the rows whose :meth:`poses` are ``T [S, 4, 4]`` and :meth:`thetas` ``θ [S, k]`` (θ kept
        ``_U_LIMIT`` inside its limits, as :meth:`u_of` keeps it)."""
        xi = se3_log(invert_pose(self.T_centre) @ T @ invert_pose(self.T_init) @ self.T_centre)
        return torch.cat([xi[:, :3] / self.radius, xi[:, 3:6], self.u_of(theta)], -1)

    def moved(self, p: Tensor, shift: Tensor) -> Tensor:
        """The rows ``p [R, 6 + k]`` with their poses moved by ``shift [R, 3]`` metres in the camera frame."""
        T_shift = torch.eye(4, dtype=torch.float64).repeat(len(p), 1, 1)
        T_shift[:, :3, 3] = shift
        xi = se3_log(T_shift @ se3_exp(torch.cat([p[:, :3] * self.radius, p[:, 3:6]], -1)))  # the centre frame
        out = p.clone()
        out[:, :3], out[:, 3:6] = xi[:, :3] / self.radius, xi[:, 3:6]
        return out

    def joints(self, model: NarfModel, theta: Tensor) -> dict[str, float]:
        """``θ [k]`` as ``{joint: value}``, rounding kept inside the limits."""
        inside = torch.minimum(torch.maximum(theta.detach(), self.mid - self.half), self.mid + self.half)
        return model.kinematics.joint_dict(inside)

    def u_of(self, theta: Tensor) -> Tensor:
        """Inverse of :meth:`thetas` on ``[-π/2, π/2]``, kept ``_U_LIMIT`` inside."""
        ratio = torch.where(self.half > 0, (theta - self.mid) / self.half.clamp_min(1e-12), torch.zeros_like(theta))
        return torch.asin(ratio.clamp(-1, 1)).clamp(-math.pi / 2 + _U_LIMIT, math.pi / 2 - _U_LIMIT)

    def motion(self, a: Tensor, b: Tensor) -> Tensor:
        """Largest motion ``[S]`` between rows: radii, radians, or fractions of a joint's range."""
        pose = (a[:, :6] - b[:, :6]).abs().amax(-1)
        if a.shape[1] == 6:
            return pose
        span = (2 * self.half).clamp_min(1e-12)
        theta = ((self.thetas(a) - self.thetas(b)).abs() / span).amax(-1)
        return torch.maximum(pose, theta)


def _theta_starts(theta0: Tensor, param: _Parameterisation, count: int) -> Tensor:
    """``[S, k]``: ``theta0`` first, then ``count - 1`` configurations spread over the joint box.

    Each joint's range is cut into ``count`` equal strata; ``theta0`` takes one, and the other
    starts take the middles of the others, assigned per joint with a shift (a Latin hypercube):
    every joint sees every stratum, and no two starts repeat a value. A rigid object (``k = 0``)
    gets one start.
    """
    if theta0.shape[0] == 0:
        return theta0[None]
    lower, span = param.mid - param.half, (2 * param.half).clamp_min(1e-12)
    taken = ((theta0 - lower) / span * count).floor().clamp(0, count - 1).long()
    rows = [theta0]
    for i in range(1, count):
        row = []
        for j in range(theta0.shape[0]):
            free = [s for s in range(count) if s != int(taken[j])]
            row.append(lower[j] + span[j] * (free[(i - 1 + j) % (count - 1)] + 0.5) / count)
        rows.append(torch.stack(row))
    return torch.stack(rows)


def _pose_turns(count: int, spread_deg: float) -> Tensor:
    """``[count, 3]`` rotation vectors (camera axes, radians) of the pose starts: none first, then
    ``spread_deg`` about the directions of :data:`_POSE_TURNS` in order. Turns out of the image
    plane come first: they change the silhouette least for a small angle, so a wrong one is where
    the loss's basin is narrowest; a turn in the image plane rotates the silhouette, which the
    silhouette term sees from far."""
    turns = torch.tensor(_POSE_TURNS[:count], dtype=torch.float64)
    return turns / turns.norm(dim=-1, keepdim=True).clamp_min(1) * math.radians(spread_deg)


@torch.no_grad()
def _given_rows(loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, thetas: Tensor) -> Tensor:
    """``[S, 6 + k]``: each θ start of ``thetas [S, k]`` at the given pose or, with ``options.theta_search``
    and two joints or more, the θ starts the search fits best (:func:`_theta_search`; ``thetas[0]`` is among
    its candidates), with the search's poses where it had a depth."""
    opts = loss_fn.options
    if opts.theta_search and thetas.shape[1] > 1 and any(len(p) for p in loss_fn.model.sample_points.values()):
        return _theta_search(loss_fn, obs, camera, param, thetas[0], max(opts.theta_search, len(thetas)), len(thetas))
    return torch.cat([torch.zeros(len(thetas), 6, dtype=torch.float64), param.u_of(thetas)], dim=1)


@torch.no_grad()
def _start_rows(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, rows: Tensor, align: bool = True
) -> Tensor:
    """The refinement's start rows from the given rows ``rows [S, 6 + k]`` (:func:`_given_rows`): ``[S, 6 + k]``,
    or (``options.pose_starts > 1`` without ``pose_starts_overlap``, which turns them only after a
    refinement: :func:`_adaptive_refinement`) ``[(1 + K) * S, 6 + k]``: those, then :func:`_turned_rows` of
    them. The given pose stays whatever the score: from a small error its own
    start is the best, and a start's score is a rough guide (the refinement compares the starts again
    after a third of its iterations). With ``options.align_start`` (and ``align``) the given pose of each θ
    start is first that pose or its moved copy, whichever scores lower on the same rays (not where the
    search kept its own poses)."""
    opts = loss_fn.options
    # The search's poses, where it kept them, are fitted to the observed surface already; moving them onto
    # the mask's centroid and depth again loses that fit (a gripper's fingers).
    align = align and opts.align_start and not bool(rows[:, :6].any())
    wide = opts.pose_starts > 1 and opts.pose_starts_overlap == 0
    if align:
        index, rays = _score_rays(obs, camera, opts.seed)
        both = torch.cat([rows, _aligned(loss_fn, obs, camera, param, rows, index, rays)])
        losses = loss_fn(rays, obs.levels[0], index, param.poses(both), param.thetas(both)).cpu()
        losses = torch.where(torch.isfinite(losses), losses, math.inf).reshape(2, -1)  # [given, moved] per θ start
        rows = both.reshape(2, len(rows), -1)[losses.argmin(0), torch.arange(len(rows))]
    if opts.surface_fit_iterations and loss_fn.uses_depth:
        rows = _surface_fitted(loss_fn.model, obs, camera, param, rows, opts)
    return torch.cat([rows, _turned_rows(loss_fn, obs, camera, param, rows)]) if wide else rows


def _surface_fitted(model: NarfModel, obs: _Observation, camera: Pinhole, param: _Parameterisation, rows: Tensor,
                    opts: EstimateOptions) -> Tensor:
    """``rows [S, 6 + k]``, each fitted to the observed depth's points inside the mask (``opts.surface_fit_iterations``
    iterations of :func:`narf_core.surface_fit.fit_points`, all rows at once; the points drawn with ``opts.seed``)."""
    from narf_core.surface_fit import SurfaceFitOptions, fit_points, pixel_points

    target = obs.levels[-1]
    inside = (target.mask > 0.5).cpu()
    fit = SurfaceFitOptions(iterations=opts.surface_fit_iterations)
    observed = pixel_points(camera, obs.pixels.cpu()[inside], target.depth.cpu()[inside], fit.observed_points, opts.seed)
    T, theta, _, _ = fit_points(model, camera, param.poses(rows), param.thetas(rows), observed, fit)  # every row at once
    return param.rows_of(T, theta)


def _score_rays(obs: _Observation, camera: Pinhole, seed: int) -> tuple[Tensor, Rays]:
    """The box pixels ``index [n]`` (up to ``_SCORE_RAYS``, drawn with ``seed``) on which starts are scored
    before the refinement, and their camera rays: the same for every call with the same seed."""
    index = _box_pixels(obs, _SCORE_RAYS, torch.Generator().manual_seed(seed + 2))
    return index, camera.rays(obs.pixels[index].to(torch.float32))


def _box_pixels(obs: _Observation, n: int, rng: torch.Generator) -> Tensor:
    """``[min(n, N)]`` indices into the box's ``N`` pixels, on their device: all of them where they fit,
    else ``n`` drawn without repeats with ``rng``."""
    n_pixels = obs.pixels.shape[0]
    index = torch.arange(n_pixels) if n_pixels <= n else torch.randperm(n_pixels, generator=rng)[:n]
    return index.to(obs.pixels.device)


@torch.no_grad()
def _turned_rows(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, rows: Tensor, kept: int = _POSES_KEPT
) -> Tensor:
    """``[K * S, 6 + k]``: each start row of ``rows [S, 6 + k]`` at the ``K = kept`` other pose
    starts whose loss is the lowest on the scoring rays (:func:`_score_rays`) at the coarsest level, where
    the target is smoothest. The pose starts: the turns of :func:`_pose_turns` about the object's centre,
    each also moved onto the observation (:func:`_aligned`)."""
    opts = loss_fn.options
    index, rays = _score_rays(obs, camera, opts.seed)
    turns = _pose_turns(opts.pose_starts, opts.pose_spread_deg)
    n_turns, n_starts = len(turns), len(rows)
    turned = rows.repeat(n_turns, 1)  # turn-major: row t * S + s is θ start s under turn t
    turned[:, 3:6] = turns.repeat_interleave(n_starts, 0)
    candidates = torch.cat([turned, _aligned(loss_fn, obs, camera, param, turned, index, rays)])
    losses = loss_fn(rays, obs.levels[0], index, param.poses(candidates), param.thetas(candidates)).cpu()
    losses = torch.where(torch.isfinite(losses), losses, math.inf).reshape(-1, n_starts)[1:]  # all but the given pose
    best = losses.topk(min(kept, len(losses)), dim=0, largest=False).indices + 1  # [K, S], per θ start
    chosen = candidates.reshape(-1, n_starts, candidates.shape[1])[best, torch.arange(n_starts)]
    return chosen.reshape(-1, candidates.shape[1])


def _theta_search(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, theta0: Tensor, count: int, keep: int
) -> Tensor:
    """``[keep, 6 + k]`` start rows: of ``count`` candidate configurations (``theta0 [k]`` and a Latin
    hypercube over the joint box, :func:`_theta_starts`), the ``keep`` that fit the observation best after
    ``_SEARCH_STEPS`` Adam steps of each one's pose and θ on :func:`_chamfer`, best first.

    The refinement's loss compares rendered rays with pixels: a thin part (an arm 2-3 pixels wide) drawn
    beside its image has no overlap to pull on, so with several joints a few spread starts rarely find
    the configuration. Surface points projected into the image know how far they lie from the mask,
    however far that is. Without a depth image the silhouette leaves the distance along the line of sight
    loose, and the points drift along it, fitting a wrong configuration on the way; with one the observed
    surface holds it (:func:`_chamfer`). The fitted poses are kept where :func:`_keeps_search_pose` says,
    else the rows start at the given pose."""
    model, opts = loss_fn.model, loss_fn.options
    rng = torch.Generator().manual_seed(opts.seed + 3)
    points, link_of = _surface_sample(model, _SEARCH_POINTS, rng)
    fit = _search_fit(loss_fn, obs, camera, rng)
    candidates = _theta_starts(theta0, param, count)
    rows = torch.cat([torch.zeros(count, 6, dtype=torch.float64), param.u_of(candidates)], dim=1)
    rates = [_SEARCH_RATES[0]] * 6 + [_SEARCH_RATES[1]] * len(theta0)
    adam = _Adam(rows, torch.tensor(rates, dtype=torch.float64))
    with torch.enable_grad():
        for _ in range(_SEARCH_STEPS):
            p = adam.params.clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(_chamfer(fit, _camera_points(model, param, p, points, link_of)).sum(), p)
            adam.step(torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0), 1.0)
    score = _chamfer(fit, _camera_points(model, param, adam.params, points, link_of))
    order = torch.where(torch.isfinite(score), score, math.inf).argsort()[:keep]
    rows = adam.params[order].detach().clone()
    if not _keeps_search_pose(opts, fit):
        rows[:, :6] = 0
    return rows


def _keeps_search_pose(opts: EstimateOptions, fit: _Fit) -> bool:
    """Whether the refinement starts from the search's poses (else from the given one): where the observed
    surface held their distance, and for Gauss-Newton only, whose narrow basin a pose started nearer needs;
    Adam's wider steps walk off it and ended further from the truth from the search's poses than from the
    given one (docs/benchmarks.md)."""
    return fit.cloud is not None and len(fit.cloud) > 0 and opts.solver == "gauss-newton"


def _search_fit(loss_fn: _Loss, obs: _Observation, camera: Pinhole, rng: torch.Generator) -> _Fit:
    """What the search's points are compared with: up to ``_SEARCH_PIXELS`` of the mask's pixels (drawn
    with ``rng``) and, where the loss uses a depth image, the observed depth and those pixels' points."""
    target = obs.levels[-1]
    inside = (target.mask > 0.5).cpu()
    chosen = torch.nonzero(inside)[:, 0]
    if len(chosen) > _SEARCH_PIXELS:
        chosen = chosen[torch.randperm(len(chosen), generator=rng)[:_SEARCH_PIXELS]]
    mask_uv = obs.pixels.cpu()[chosen].double() + 0.5
    K = camera.K.detach().double().cpu()
    depth = target.depth.double().cpu() if loss_fn.uses_depth and target.depth is not None else None
    cloud = None if depth is None else _back_projected(K, mask_uv, depth[chosen])
    return _Fit(K, mask_uv, obs.pixels[0].cpu(), obs.shape, inside, depth, cloud)


def _back_projected(K: Tensor, uv: Tensor, z: Tensor) -> Tensor:
    """``[M, 3]`` camera-frame points of the pixels ``uv [Q, 2]`` at their z-depths ``z [Q]``, those with
    one (``z > 0``) only."""
    uv, z = uv[z > 0], z[z > 0]
    xy = (uv - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]]) * z[:, None]
    return torch.cat([xy, z[:, None]], -1)


def _surface_sample(model: NarfModel, per_link: int, rng: torch.Generator) -> tuple[Tensor, Tensor]:
    """Up to ``per_link`` of each link's surface points (``model.sample_points``, link frame), drawn
    with ``rng``: ``points [N, 3]`` float64 and their links' indices ``[N]`` in ``model.links`` order."""
    points, owners = [], []
    for i, link in enumerate(model.links):
        own = torch.as_tensor(np.asarray(model.sample_points.get(link, np.zeros((0, 3)))), dtype=torch.float64)
        own = own[torch.randperm(len(own), generator=rng)[:per_link]]
        points.append(own)
        owners.append(torch.full((len(own),), i, dtype=torch.long))
    return torch.cat(points), torch.cat(owners)


def _camera_points(model: NarfModel, param: _Parameterisation, p: Tensor, points: Tensor, link_of: Tensor) -> Tensor:
    """``[S, N, 3]``: link-frame ``points [N, 3]`` of links ``link_of [N]`` in the camera frame under
    every row of ``p [S, 6 + k]`` (its pose and configuration)."""
    T = param.poses(p)[:, None] @ model.kinematics.link_poses(param.thetas(p))  # [S, links, 4, 4]
    T = T[:, link_of.to(T.device)]
    return (T[..., :3, :3] @ points.to(T)[:, :, None])[..., 0] + T[..., :3, 3]


@dataclass
class _Fit:
    """What :func:`_chamfer` compares points with: ``K [3, 3]``, the mask's pixel centres ``mask_uv [Q, 2]``,
    the box's corner ``(u0, v0)``, shape ``(h, w)``, mask ``[h*w]`` bool, observed depth ``[h*w]`` and the
    observed surface: camera-frame points ``cloud [M, 3]`` of mask pixels with a depth (both None without one)."""

    K: Tensor
    mask_uv: Tensor
    corner: Tensor
    shape: tuple[int, int]
    mask: Tensor
    depth: Tensor | None
    cloud: Tensor | None = None


def _chamfer(fit: _Fit, X: Tensor) -> Tensor:
    """``[S]``: how far camera-frame points ``X [S, N, 3]`` are from explaining the mask, in pixels: the
    mean distance of a projected point to the nearest mask pixel plus that of a mask pixel to the nearest
    projected point (a point set matches the whole silhouette whether or not it is seen), plus, where a
    point falls on the mask with an observed depth, how far (over ``_SEARCH_DEPTH_MARGIN``, in pixels at
    its depth) it lies in front of that depth: a hidden point lies behind it, none in front. With an
    observed surface (``fit.cloud``) also the mean distance of an observed point to the nearest point, in
    pixels at its depth: every observed point lies on the object, which fixes the distance along the line
    of sight that the silhouette leaves loose (and with it the configuration that a wrong distance fits)."""
    z = X[..., 2].clamp_min(1e-3)
    uv = (fit.K[:2, :2] @ (X[..., :2] / z[..., None])[..., None])[..., 0] + fit.K[:2, 2]
    d = torch.cdist(uv, fit.mask_uv.expand(len(uv), -1, -1))  # [S, N, Q]
    score = d.min(-1).values.mean(-1) + d.min(-2).values.mean(-1)
    if fit.depth is None:
        return score
    h, w = fit.shape
    ij = uv.detach().floor().long() - fit.corner
    inbox = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
    at = (ij[..., 1].clamp(0, h - 1) * w + ij[..., 0].clamp(0, w - 1))
    observed = fit.depth[at]
    seen = inbox & fit.mask[at] & (observed > 0)
    front = torch.relu(observed - z - _SEARCH_DEPTH_MARGIN) * fit.K[0, 0] / z
    score = score + (front * seen).sum(-1) / seen.sum(-1).clamp_min(1)
    if fit.cloud is None or not len(fit.cloud):
        return score
    near = torch.cdist(fit.cloud.expand(len(X), -1, -1), X).min(-1).values  # [S, M] metres
    return score + (near * fit.K[0, 0] / fit.cloud[:, 2]).mean(-1)


@torch.no_grad()
def _aligned(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, rows: Tensor, index: Tensor, rays: Rays
) -> Tensor:
    """``rows [R, 6 + k]`` moved in the camera frame so that each one's rendered silhouette on the box
    pixels ``index [n]`` (rays ``rays``) has the mask's centroid and, where a depth is observed, its
    surface the median observed depth in the mask (medians of the whole silhouettes: where a start
    is centimetres off, the pixels that both cover may show different parts of the object). Such a
    start overlaps the object too little for the loss's gradient to pull it across; its
    silhouette's offset says where to go. Rows that draw nothing there stay."""
    n_rows, n = rows.shape[0], len(rays)
    T = param.poses(rows)
    outputs = ("rgb", "opacity") + (("depth",) if loss_fn.uses_depth else ())
    _, opacity, rendered = loss_fn._render(_object_rays(rays, T), param.thetas(rows), outputs)
    opacity = opacity.reshape(n_rows, n).double().cpu()
    target = obs.levels[-1]
    mask = target.mask[index].double().cpu()
    uv = obs.pixels[index].double().cpu() + 0.5
    drawn = opacity.sum(-1)
    offset = (mask @ uv) / mask.sum().clamp_min(1e-9) - (opacity @ uv) / drawn.clamp_min(1e-9)[:, None]  # [R, 2] px
    aabb = loss_fn.model.aabb.detach().double().cpu()
    centre = transform_points(T, (aabb[0] + aabb[1]) / 2)  # [R, 3]
    along = torch.zeros(n_rows, dtype=torch.float64)
    if rendered is not None and target.depth is not None:
        observed = target.depth[index].double().cpu()
        seen = observed[(observed > 0) & (mask > 0.5)]
        surface = rendered.reshape(n_rows, n).double().cpu() / opacity.clamp_min(1e-6)
        surface = torch.where(opacity > 0.5, surface, torch.nan).nanmedian(-1).values
        if len(seen):
            along = torch.nan_to_num(seen.median() - surface, nan=0.0)
    K = camera.K.detach().double().cpu()
    z = centre[:, 2].clamp_min(1e-3)
    z_new = (z + along).clamp_min(1e-3)
    lateral = [(centre[:, i] / z + offset[:, i] / K[i, i]) * z_new - centre[:, i] for i in (0, 1)]  # the ray moves with it
    shift = torch.stack([*lateral, z_new - z], -1)
    shift = torch.where((drawn > 0.5)[:, None], shift, torch.zeros_like(shift))
    return param.moved(rows, shift)


# --------------------------------------------------------------------------------------------
# Rendering and loss


def _object_rays(rays_cam: Rays, T_cam_obj: Tensor) -> Rays:
    """Camera rays ``[n]`` seen from every pose ``T_cam_obj [S,4,4]`` -> object-frame rays ``[S*n]``."""
    T_obj_cam = invert_pose(T_cam_obj).to(rays_cam.origins)  # [S, 4, 4], the rays' dtype and device
    n_starts, n = T_obj_cam.shape[0], len(rays_cam)
    origins = T_obj_cam[:, None, :3, 3].expand(n_starts, n, 3)
    directions = rays_cam.directions @ T_obj_cam[:, :3, :3].transpose(-1, -2)  # [S, n, 3]
    return Rays(origins.reshape(-1, 3), directions.reshape(-1, 3), rays_cam.z_per_t.repeat(n_starts))


@dataclass
class _Loss:
    """Everything fixed about the loss of one run; ``camera``: where ``options.band_m`` marches only
    the band around the surface (narf_core/band.py)."""

    model: NarfModel
    options: EstimateOptions
    radius: float
    uses_depth: bool
    camera: Pinhole | None = None

    def __call__(self, rays_cam: Rays, target: _Target, index: Tensor, T: Tensor, theta: Tensor) -> Tensor:
        """Loss ``[S]`` of every start (``T [S,4,4]``, ``θ [S,k]``) on the rays ``rays_cam [n]``
        through the box pixels ``index [n]``."""
        return self.terms(rays_cam, target, index, T, theta)[0]

    def terms(self, rays_cam: Rays, target: _Target, index: Tensor, T: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
        """The loss ``[S]`` (as :meth:`__call__`) and the share ``[S]`` of the mask's rays among ``index``
        on which each start draws the object (opacity over 0.5; ones where the loss renders no opacity or
        no ray lies in the mask)."""
        opts = self.options
        n_starts, n = T.shape[0], len(rays_cam)
        depth = target.depth[index] if (self.uses_depth and target.depth is not None) else None
        mask, observed = target.mask[index], target.rgb[index]
        needs_opacity = (opts.silhouette_weight > 0 or depth is not None or opts.photometric_compensation
                         or opts.mask_trust == "partial")
        outputs = ("rgb",) + (("opacity",) if needs_opacity else ())
        outputs += ("depth",) if depth is not None else ()
        band = None
        if opts.band_m > 0 and self.camera is not None:
            band = ray_band(self.model, self.camera, rays_cam, T, theta, opts.band_m)
        rgb, opacity, rendered_depth = self._render(_object_rays(rays_cam, T), theta, outputs, band)
        rgb = rgb.reshape(n_starts, n, 3)
        opacity = None if opacity is None else opacity.reshape(n_starts, n)
        rendered_depth = None if rendered_depth is None else rendered_depth.reshape(n_starts, n)
        keep = torch.ones(n_starts, n, dtype=torch.bool, device=rgb.device)
        if depth is not None and opts.occlusion_margin > 0:
            keep = ~_occluded(depth, rendered_depth, opacity, opts.occlusion_margin)
        if opts.photometric_compensation:
            gain, bias = _gain_bias(rgb.detach(), opacity.detach(), observed, mask, keep)
            rgb = gain[:, None] * rgb + bias[:, None] * opacity[..., None]
        elif opts.colour_gain != (1.0, 1.0, 1.0):
            rgb = rgb * rgb.new_tensor(opts.colour_gain)
        used = keep.to(rgb.dtype)
        edge = None if target.band is None or target.image is None else target.band[index]
        if edge is not None:  # the render against the unmasked image where it draws the object; no mask there
            observed = torch.where(edge[:, None], opacity[..., None] * target.image[index], observed)
        if weighs_outside(opts, depth):
            used = used * _outside_weight(mask, edge, depth, rendered_depth, opacity, opts.outside_weight)
        count = used.sum(-1).clamp_min(1)
        colour = _robust((rgb - observed) ** 2, opts.robust_loss, opts.robust_scale).mean(-1)
        loss = (colour * used).sum(-1) / count
        if opts.silhouette_weight > 0:
            silhouette = _robust((opacity - mask) ** 2, opts.robust_loss, opts.robust_scale)
            trusted = used if edge is None else used * ~edge
            loss = loss + opts.silhouette_weight * (silhouette * trusted).sum(-1) / count
        if depth is not None:
            valid = (depth > 0) & (mask > 0.5) & keep
            if edge is not None:  # a segmenter's edge pixel may be the table's
                valid = valid & ~edge
            if bool(valid.any()):
                # Rendered depth is opacity-weighted; compare like with like (no division by opacity).
                err = (rendered_depth - opacity * depth) / self.radius
                depth_cost = _robust(opts.depth_weight * err**2, opts.robust_loss, opts.robust_scale)
                loss = loss + (depth_cost * valid).sum(-1) / valid.sum(-1).clamp_min(1)
        inside = mask > 0.5
        if opacity is None or not bool(inside.any()):
            return loss, torch.ones_like(loss)
        return loss, ((opacity.detach() > 0.5) & inside).sum(-1).to(loss.dtype) / inside.sum()

    def _render(
        self, rays_obj: Rays, theta: Tensor, outputs: tuple[str, ...], band: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """``(rgb, opacity, depth)`` of the rays ``[S*n]``, start ``s`` at ``θ [S,k]`` row ``s``, each
        marched only inside its ``band`` (``(near, far) [S*n]``) when given.

        One configuration: one call with ``θ [k]``. Several: one batched call with ``θ`` per ray in
        ``narf`` mode (the configuration field takes it), one call per start in ``parts`` mode
        (the composition poses its parts for one configuration).
        """
        n_starts, k = theta.shape
        theta = theta.to(rays_obj.origins)
        render = self.model.render_rays
        kw = dict(mode=self.options.mode, outputs=outputs, background=0.0)
        if n_starts == 1 or k == 0:
            out = render(rays_obj, theta[0], t_range=band, **kw)
            return out.rgb, out.opacity, out.depth
        n = len(rays_obj) // n_starts
        if self.options.mode == "narf":
            per_ray = theta[:, None, :].expand(n_starts, n, k).reshape(n_starts * n, k)
            out = render(rays_obj, per_ray, t_range=band, **kw)
            return out.rgb, out.opacity, out.depth
        rows = [slice(s * n, (s + 1) * n) for s in range(n_starts)]
        outs = [render(rays_obj[r], theta[s], t_range=None if band is None else (band[0][r], band[1][r]), **kw)
                for s, r in enumerate(rows)]
        rgb = torch.cat([o.rgb for o in outs])
        opacity = torch.cat([o.opacity for o in outs]) if "opacity" in outputs else None
        depth = torch.cat([o.depth for o in outs]) if "depth" in outputs else None
        return rgb, opacity, depth


def _robust(squared: Tensor, kind: str, scale: float) -> Tensor:
    """Per-residual cost of squared residuals ``r²`` (any shape): ``r²`` itself (``none``), or twice
    the Huber / Cauchy ρ at ``scale`` (so that small residuals cost ``r²`` either way)."""
    if kind == "none":
        return squared
    if kind == "huber":
        a = squared.clamp_min(1e-12).sqrt()
        return torch.where(a <= scale, squared, scale * (2 * a - scale))
    return scale**2 * torch.log1p(squared / scale**2)


def _occluded(depth: Tensor, rendered_depth: Tensor, opacity: Tensor, margin: float) -> Tensor:
    """``[S, n]``: rays whose observed depth ``[n]`` lies more than ``margin`` metres in front of the
    rendered surface (opacity-weighted ``rendered_depth [S, n]`` over ``opacity [S, n]``): something
    else is in front of the object there, so the ray is no evidence about it."""
    surface = rendered_depth.detach() / opacity.detach().clamp_min(1e-6)
    return (depth > 0) & (opacity.detach() > 0.5) & (depth < surface - margin)


def weighs_outside(opts: EstimateOptions, depth: Tensor | None) -> bool:
    """Whether the rays outside a partially trusted mask are weighed (:func:`_outside_weight`): below the full
    weight, or at it with a depth image, which tells an occluder's rays (no evidence) from the background's."""
    return opts.mask_trust == "partial" and (opts.outside_weight < 1 or depth is not None)


def _outside_weight(
    mask: Tensor, edge: Tensor | None, depth: Tensor | None, rendered_depth: Tensor | None, opacity: Tensor, weight: float
) -> Tensor:
    """``[S, n]`` weights of the rays: ``weight`` outside the mask ``[n]`` (and off its boundary band
    ``edge [n]``), 1 elsewhere. The mask is the object's *visible* part as a segmenter saw it: where
    it says background, an occluder or a missed blob may hide the object, so a render of the
    object there is weak evidence against it. Where the observed depth ``[n]`` lies
    :data:`_BEHIND_M` behind the rendered surface (``rendered_depth / opacity [S, n]``), the
    sensor sees past the object, which is not there: 1. Where it lies that far in front outside
    the mask, something stands before the object: 0, no evidence either way (a part hidden there
    costs nothing, as it would not if it were moved elsewhere)."""
    outside = mask <= 0.5 if edge is None else (mask <= 0.5) & ~edge
    w = torch.where(outside, weight, 1.0)[None].expand_as(opacity)
    if depth is not None and rendered_depth is not None:
        surface = rendered_depth.detach() / opacity.detach().clamp_min(1e-6)
        seen = (depth > 0) & (opacity.detach() > 0.5)
        w = torch.where(seen & (depth > surface + _BEHIND_M), 1.0, w)
        w = torch.where(seen & outside & (depth < surface - _BEHIND_M), 0.0, w)
    return w


def _colour_pairs(rgb: Tensor, opacity: Tensor, observed: Tensor, mask: Tensor, keep: Tensor
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """The render's colour ``x [S, n, 3]`` (``rgb [S, n, 3]`` over its ``opacity [S, n]``), the observed
    ``a [1, n, 3]`` (``observed [n, 3]`` over ``mask [n]``) and the weights ``w [S, n]`` of the rays inside
    both (and ``keep [S, n]``): the pairs a colour fit compares."""
    w = ((mask > 0.5)[None] & (opacity > 0.5) & keep).to(rgb.dtype)
    return rgb / opacity[..., None].clamp_min(1e-6), (observed / mask[:, None].clamp_min(1e-6))[None], w


def _gain_bias(rgb: Tensor, opacity: Tensor, observed: Tensor, mask: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
    """Per-start gain and bias ``[S, 3]`` that fit ``gain * colour + bias`` of the render to the observed
    colour (:func:`_colour_pairs`): least squares per channel, bounded (gain in ``GAIN_RANGE``, bias in
    [-0.3, 0.3]); ones and zeros where fewer than 16 rays qualify.
    Another light or exposure changes the object's colour, not its shape."""
    x, a, w = _colour_pairs(rgb, opacity, observed, mask, keep)
    count = w.sum(-1)
    n = count.clamp_min(1)[:, None]
    mx, ma = (w[..., None] * x).sum(1) / n, (w[..., None] * a).sum(1) / n
    cov = (w[..., None] * (x - mx[:, None]) * (a - ma[:, None])).sum(1)
    var = (w[..., None] * (x - mx[:, None]) ** 2).sum(1)
    gain = torch.where(var > 1e-8, cov / var.clamp_min(1e-8), torch.ones_like(var)).clamp(*GAIN_RANGE)
    bias = (ma - gain * mx).clamp(-0.3, 0.3)
    enough = (count >= 16)[:, None]
    return torch.where(enough, gain, torch.ones_like(gain)), torch.where(enough, bias, torch.zeros_like(bias))


def colour_gain(rgb: Tensor, opacity: Tensor, observed: Tensor, mask: Tensor, keep: Tensor) -> Tensor:
    """Per-start gain ``[S, 3]`` that fits ``gain * colour`` of the render to the observed colour
    (:func:`_colour_pairs`): least squares per channel through zero, in ``GAIN_RANGE``; ones where fewer than
    16 rays qualify. One number per channel, unlike :func:`_gain_bias`'s two, which a tool of nearly one
    colour leaves ill-determined (a gain of 0.5 and a bias of 0.3 fit as well as 1 and 0)."""
    x, a, w = _colour_pairs(rgb, opacity, observed, mask, keep)
    gain = ((w[..., None] * x * a).sum(1) / (w[..., None] * x * x).sum(1).clamp_min(1e-8)).clamp(*GAIN_RANGE)
    return torch.where((w.sum(-1) >= 16)[:, None], gain, torch.ones_like(gain))


# --------------------------------------------------------------------------------------------
# Adam on rows, with per-column rates, slicing and resets


class _Adam:
    """Plain Adam over ``params [S, d]`` with per-column rates ``lr [d]``; rows are independent, so
    a start can be dropped (:meth:`keep`) and the moments reset after a non-finite step."""

    def __init__(self, params: Tensor, lr: Tensor) -> None:
        self.params, self.lr = params, lr
        self.reset()

    def reset(self) -> None:
        self.m = torch.zeros_like(self.params)
        self.v = torch.zeros_like(self.params)
        self.step_count = 0

    def step(self, grad: Tensor, scale: float) -> None:
        b1, b2 = _ADAM_BETAS
        self.step_count += 1
        self.m.mul_(b1).add_(grad, alpha=1 - b1)
        self.v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        m_hat = self.m / (1 - b1**self.step_count)
        v_hat = self.v / (1 - b2**self.step_count)
        self.params = self.params - scale * self.lr * m_hat / (v_hat.sqrt() + _ADAM_EPS)

    def keep(self, rows: Tensor) -> None:
        self.params, self.m, self.v = self.params[rows], self.m[rows], self.v[rows]


# --------------------------------------------------------------------------------------------
# The refiner


def refine(
    model: NarfModel,
    image: np.ndarray,
    mask: np.ndarray,
    camera: Pinhole,
    T_init: np.ndarray,
    *,
    joints_init: Mapping[str, float] | None = None,
    depth: np.ndarray | None = None,
    options: EstimateOptions | None = None,
    ground_truth: tuple[np.ndarray, Mapping[str, float]] | None = None,
    should_stop: Callable[[], str | None] | None = None,
) -> EstimateResult:
    """Refine ``T_init`` and ``joints_init`` so that ``model``'s render matches the masked view.

    Args:
        model: a :class:`~narf_core.bundle.NarfModel` (``render_rays``, ``joints``, limits, ``aabb``).
        image: ``[H, W, 3]`` uint8 sRGB observation.
        mask: ``[H, W]`` bool, the object's pixels (integer arrays: nonzero = object).
        camera: the view's intrinsics; its size must be the image's.
        T_init: ``[4, 4]`` initial ``T_cam_obj``.
        joints_init: initial ``{joint: value}`` (missing joints start at mid-range).
        depth: optional ``[H, W]`` metric z-depth, 0 or NaN = no return (used if ``depth_weight > 0``).
        options: :class:`EstimateOptions`; defaults follow the paper.
        ground_truth: optional ``(T_cam_obj [4, 4], {joint: value})`` to score the result against.
        should_stop: polled once per iteration; a status it returns (a service's ``"cancelled"`` or
            ``"budget_exceeded"``) ends the loop, and the best estimate so far comes back with it.

    Raises:
        EstimateInputError: empty or tiny mask, size mismatches, a K for another resolution, a
            non-finite or non-rigid pose, unknown or out-of-limit joints, bad options.
    """
    start_time = time.perf_counter()
    opts = _check_call(options, EstimateOptions, camera, EstimateInputError)
    image, mask, depth = _check_observation(image, mask, depth, camera)
    rgb_only = depth is None  # the view came without a depth image: opts.rgb_refinements
    T0 = torch.from_numpy(check_pose(T_init, "T_init", error=EstimateInputError))
    warnings = check_observation(image, mask, depth, camera, expected_depth_m=float(T0[2, 3]))
    depth = usable_depth(depth, warnings)  # a depth in the wrong unit or off the mask is dropped, and said so
    warnings += coarse_model(model, camera, depth)
    theta0 = model.kinematics.joint_vector(joints_init, field="joints_init", error=EstimateInputError)
    truth = None
    if ground_truth is not None:
        if not isinstance(ground_truth, (tuple, list)) or len(ground_truth) != 2:
            raise EstimateInputError("ground_truth must be a pair (T_cam_obj [4, 4], {joint: value})")
        truth = (
            torch.from_numpy(check_pose(ground_truth[0], "ground_truth.pose", error=EstimateInputError)),
            model.kinematics.joint_vector(ground_truth[1], fill_mid=False, field="ground_truth.joints",
                                          error=EstimateInputError),
        )
    mode, mode_reason = choose_mode(model, opts.mode, error=EstimateInputError)
    opts = replace(opts, mode=mode)

    device = model.aabb.device  # rays and targets live with the model; the pose parameters on the CPU
    camera = Pinhole(camera.K.detach().to(device, torch.float32), camera.width, camera.height)
    box = _mask_box(mask, opts.box_margin)
    scale = _box_scale(box, opts)
    opts = replace(opts, rays_per_iteration=round(scale * opts.rays_per_iteration)) if scale > 1 else opts
    partial = _partial_trust(opts, mask, depth)
    opts = replace(opts, mask_trust="partial" if partial else "full")
    opts = replace(opts, theta_starts=_configuration_starts(opts, partial, len(theta0)))
    obs = _observation(image, mask, depth, box, opts.coarse_to_fine, device, opts.mask_band_px if partial else 0)
    obs.scale = scale
    param = _Parameterisation.around(T0, model)

    uses_depth = depth is not None and opts.depth_weight > 0

    def result(status: str, row: Tensor | None, loss: float | None, run=None) -> EstimateResult:
        T, theta = (T0, theta0) if row is None else (param.poses(row)[0], param.thetas(row)[0])
        position, quaternion = pose_to_position_quaternion(T)
        uncertainty = None
        if opts.uncertainty and row is not None and status != "cancelled":  # nobody waits for a cancelled one
            uncertainty = _uncertainty(model, opts, obs, camera, param, T, theta, uses_depth)
        metrics = None if truth is None else _metrics(model, truth, T, theta)
        if metrics is not None and uncertainty is not None:
            metrics["nees"] = nees(uncertainty, T.numpy(), param.joints(model, theta), truth[0].numpy(),
                                   model.kinematics.joint_dict(truth[1]), model)
        return EstimateResult(
            T_cam_obj=T.numpy().copy(),
            position=position.numpy().copy(),
            quaternion=quaternion.numpy().copy(),
            joints=param.joints(model, theta),
            loss=loss,
            iterations=0 if run is None else run.iteration,
            seconds=time.perf_counter() - start_time,
            trace=[] if run is None else run.trace,
            status=status,
            recovered_non_finite=run is not None and run.recovered,
            metrics=metrics,
            history=[] if run is None else run.history,
            uncertainty=uncertainty,
            warnings=warnings + unobserved_joints(model, uncertainty),
            mode=mode,
            mode_reason=mode_reason,
        )

    if not _overlaps(camera, obs.pixels, T0, model.aabb):
        return result("no_overlap", None, None)
    loss_fn = _Loss(model, opts, param.radius, uses_depth, camera)
    given = _given_rows(loss_fn, obs, camera, param, _theta_starts(theta0, param, opts.theta_starts))
    starts = {opts.align_start: _start_rows(loss_fn, obs, camera, param, given)}

    def start_rows(align: bool) -> Tensor:
        """The start rows with or without ``align_start``'s move onto the mask and depth (made once each,
        from the same given rows)."""
        if align not in starts:
            starts[align] = _start_rows(loss_fn, obs, camera, param, given, align=align)
        return starts[align]

    count = max(opts.refinements, opts.rgb_refinements if rgb_only else 0) if partial or not uses_depth else 1

    def estimate(o: EstimateOptions):
        """A refinement with the options ``o`` (Adam: ``count`` of them, :func:`_best_refinement`), the
        pose-start check included, and its final choice; ``None`` where ``o`` turns ``align_start`` off and
        no start had moved (the estimate would repeat one with it on)."""
        rows = start_rows(o.align_start)
        if not o.align_start and opts.align_start and torch.equal(rows, start_rows(True)):
            return None
        if o.pose_starts > 1 and o.pose_starts_overlap > 0:  # the pose starts only where needed
            return _adaptive_refinement(lambda starts: refinement(o, starts), loss_fn, obs, camera, param, rows)
        run, last = refinement(o, rows)
        return run, _final_choice(loss_fn, obs, camera, param, last, run.best_params, run.rng)

    def refinement(o: EstimateOptions, starts: Tensor):
        """One refinement with the options ``o`` from the rows ``starts`` (Adam: ``count`` of them): its run
        and last parameters."""
        if o.solver == "gauss-newton":
            return _gauss_newton_refinement(model, o, obs, camera, param, loss_fn, starts, start_time, should_stop)
        return _best_refinement(lambda oo, ob: _Run(model, oo, ob, camera, param, loss_fn, starts, start_time),
                                o, obs, count, should_stop)

    if opts.solver == "gauss-newton" and count > 1:
        run, final = _best_gauss_newton(estimate, opts, count, loss_fn, obs, camera, param)
    else:
        run, final = estimate(opts)
    if opts.slide_share > 0 and partial and final is not None and run.status in ("max_iterations", "converged"):
        run, final = _slid_refinement(lambda starts: refinement(opts, starts), loss_fn, obs, camera, param, run, final)
    if rgb_only and opts.rgb_polish > 0 and opts.iterations > 0 and final is not None \
            and run.status in ("max_iterations", "converged"):  # (no iterations: the start itself is asked for)
        final = _polished(model, opts, obs, camera, param, loss_fn, run, final, start_time, should_stop)
    if final is None:
        run.recovered = True
        return result("non_finite", None, None, run)
    row, loss, replaced = final
    run.recovered |= replaced
    if opts.surface_polish_iterations and uses_depth and not partial and opts.iterations > 0 \
            and run.status in ("max_iterations", "converged"):  # (no iterations: the start itself is asked for)
        polish = replace(opts, surface_fit_iterations=opts.surface_polish_iterations)
        row = _surface_fitted(model, obs, camera, param, row, polish)
        loss = float(_fixed_rays_loss(loss_fn, obs, camera, param, row, run.rng)[0])
    return result(run.status, row, loss, run)


def _gauss_newton_refinement(
    model: NarfModel,
    opts: EstimateOptions,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    loss_fn: _Loss,
    params0: Tensor,
    start_time: float,
    should_stop: Callable[[], str | None] | None,
):
    """One Levenberg-Marquardt run (narf_core/gauss_newton.py) from the start rows ``params0 [S, d]``,
    after ``opts.adam_iterations`` Adam iterations where those are asked for (Adam finds the basin and the
    best start, Gauss-Newton the bottom). Returns the run (its iterations, trace and history cover both
    solvers) and its last parameters."""
    from narf_core.gauss_newton import GaussNewtonRun, Problem

    warm = None
    if opts.adam_iterations > 0:
        warm_opts = replace(opts, solver="adam", iterations=opts.adam_iterations, early_stop=False)
        warm = _Run(model, warm_opts, obs, camera, param, loss_fn, params0, start_time)
        warm.should_stop = should_stop
        warm.optimise()
        choice = _final_choice(loss_fn, obs, camera, param, warm.adam.params, warm.best_params, warm.rng)
        if choice is not None:
            params0 = choice[0]
    run = GaussNewtonRun(Problem(model, opts, loss_fn.radius, loss_fn.uses_depth, camera), obs, camera, param, params0,
                         start_time, opts.seed)

    def snapshot(params: Tensor, losses: Tensor, iteration: int, elapsed: float) -> Snapshot:
        return _snapshot(model, param, params, losses, iteration, elapsed)

    run.should_stop = should_stop
    run.fine_only = warm is not None
    if warm is None or warm.status in ("max_iterations", "converged"):
        run.optimise(snapshot)
    else:  # the warm start stopped: non-finite, or cancelled through should_stop
        run.status = warm.status
    if warm is not None:
        run.iteration += warm.iteration
        run.trace = warm.trace + run.trace
        run.history = warm.history + run.history
        run.recovered |= warm.recovered
    return run, run.params


def _polished(
    model: NarfModel,
    opts: EstimateOptions,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    loss_fn: _Loss,
    run,
    final: tuple[Tensor, float, bool],
    start_time: float,
    should_stop: Callable[[], str | None] | None,
) -> tuple[Tensor, float, bool]:
    """``options.rgb_polish``: at most that many Levenberg-Marquardt iterations (narf_core/gauss_newton.py) from
    Adam's estimate ``final`` (its row ``[1, d]``, loss and recovery flag) at the finest level, on one fixed set
    of up to ``polish_rays`` uniform box rays and Adam's own loss (Gauss-Newton sums the three colour channels
    where Adam averages them: the silhouette weighs three times as much there). Returns the final choice of the
    two estimates on the same rays; ``run`` (Adam's) takes the polish's iterations, trace and history, and the
    status a ``should_stop`` gave it. Adam's estimate stands, unpolished, where its silhouette overlaps the mask
    less than ``polish_overlap`` (:func:`_silhouette_overlap`).

    Why: without depth the distance along the line of sight and a turn out of the image plane trade against
    each other in a long, shallow valley. Adam's steps, drawn from a few thousand random rays each, stop in
    it centimetres from the truth while the loss on every pixel still falls towards it; the polish's steps
    follow the valley, on enough rays that its bottom is the loss's over the whole box (docs/benchmarks.md). A mask
    that no pose explains (a segmenter's blob or miss, an occluder) puts that bottom where the silhouette shrinks to
    fit it, decimetres further along the line of sight: there the polish, weighing the silhouette three times, would
    follow it."""
    from narf_core.gauss_newton import GaussNewtonRun, Problem

    row, _, replaced = final
    if opts.polish_overlap > 0 and _silhouette_overlap(loss_fn, obs, camera, param, row) < opts.polish_overlap:
        return final
    o = replace(opts, solver="gauss-newton", iterations=opts.rgb_polish, rays_per_iteration=opts.polish_rays,
                ray_sampling="uniform", silhouette_weight=3 * opts.silhouette_weight, tolerance=_POLISH_TOLERANCE,
                patience=_POLISH_PATIENCE, early_stop=True, rgb_polish=0)
    polish = GaussNewtonRun(Problem(model, o, loss_fn.radius, False, camera), obs, camera, param, row, start_time, o.seed)
    polish.should_stop, polish.fine_only = should_stop, True

    def snapshot(params: Tensor, losses: Tensor, iteration: int, elapsed: float) -> Snapshot:
        return _snapshot(model, param, params, losses, run.iteration + iteration, elapsed)

    polish.optimise(snapshot)
    run.iteration += polish.iteration
    run.trace = run.trace + polish.trace
    run.history = run.history + polish.history
    run.recovered |= polish.recovered
    if polish.status not in ("max_iterations", "converged", "non_finite"):  # should_stop's reason
        run.status = polish.status
    candidates = torch.cat([row, polish.best_params[:1]])
    losses = _fixed_rays_loss(loss_fn, obs, camera, param, candidates, torch.Generator().manual_seed(opts.seed))
    losses = torch.where(torch.isfinite(losses), losses, math.inf)
    i = int(losses.argmin())
    return (candidates[i : i + 1], float(losses[i]), replaced) if math.isfinite(float(losses[i])) else final


def _adaptive_refinement(
    refinement: Callable[[Tensor], tuple],
    loss_fn: _Loss,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    starts: Tensor,
) -> tuple:
    """``options.pose_starts_overlap``: a refinement (``refinement(start rows)`` runs one and returns it and
    its last parameters) from the given pose's ``starts [S, d]``, and only where its estimate's silhouette
    overlaps the mask less than ``pose_starts_overlap`` (:func:`_silhouette_overlap`) a second one from the
    turned pose starts (:func:`_turned_rows`), the ``_RETRY_POSES_KEPT`` best scored of them per θ start (the
    given pose's start has had its refinement). Returns the run (the second where there was one, its
    iterations and trace covering both) and the :func:`_final_choice` of both estimates, on the same rays.

    Why: the pose starts widen the basin (a start 30 deg off) but double the refinement's starts, whatever the
    start. A start within the basin ends where the render explains the mask; one outside ends in a wrong
    minimum, whose silhouette misses part of the mask. So a close start pays one render of the eval rays. Not
    caught: a wrong minimum that draws nearly the mask's silhouette (a turn out of the image plane that the
    silhouette barely shows). A mask that misses part of the object (an occluder) lowers the overlap of a right
    estimate too: there the second refinement runs, at its cost, and the lower loss decides."""
    opts = loss_fn.options
    run, last = refinement(starts)
    final = _final_choice(loss_fn, obs, camera, param, last, run.best_params, run.rng)
    if (final is None or run.status not in ("max_iterations", "converged")
            or _silhouette_overlap(loss_fn, obs, camera, param, final[0]) >= opts.pose_starts_overlap):
        return run, final
    again, last = refinement(_turned_rows(loss_fn, obs, camera, param, starts, _RETRY_POSES_KEPT))
    return _second_refinement(loss_fn, obs, camera, param, run, final, again, last)


def _second_refinement(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, run, final: tuple[Tensor, float, bool],
    again, last: Tensor,
) -> tuple:
    """A first refinement's ``run`` and ``final`` choice, then a second one, ``again`` with its last parameters
    ``last``: the second run with the record of both (iterations, trace, history) and the :func:`_final_choice`
    of both estimates on the same rays (the first's status where the second's is non-finite)."""
    rows = torch.cat([final[0], last.to(final[0])])
    chosen = _final_choice(loss_fn, obs, camera, param, rows, torch.cat([final[0], again.best_params.to(final[0])]),
                           again.rng)
    again.iteration += run.iteration
    again.trace = run.trace + again.trace
    again.history = run.history + again.history
    again.recovered |= run.recovered
    if again.status == "non_finite":  # the first estimate stands
        again.status = run.status
    return again, chosen


def _slid_rows(model: NarfModel, param: _Parameterisation, row: Tensor, share: float) -> Tensor:
    """``[4, d]``: ``row [1, d]`` slid along the object's longest box axis (in its own frame) by ``-2, -1, 1, 2``
    times ``share`` of that axis's length, its rotation and configuration kept."""
    aabb = model.aabb.detach().to("cpu", torch.float64)
    extent = aabb[1] - aabb[0]
    axis = int(extent.argmax())
    steps = torch.tensor([-2.0, -1.0, 1.0, 2.0], dtype=torch.float64) * share * float(extent[axis])
    R = param.poses(row)[0, :3, :3]
    return param.moved(row.repeat(len(steps), 1), steps[:, None] * R[:, axis])  # the object's axis in the camera frame


def _slid_refinement(
    refinement: Callable[[Tensor], tuple],
    loss_fn: _Loss,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    run,
    final: tuple[Tensor, float, bool],
) -> tuple:
    """``options.slide_share``: the estimate ``final`` (its row, loss and recovery flag) and its copies slid along
    the object's longest axis (:func:`_slid_rows`) are scored on the same ``eval_rays`` box rays; where a copy
    scores lower, one more refinement (``refinement(start rows)`` runs one and returns it and its last
    parameters) from the lowest copy, and the estimate of lower loss is kept (:func:`_second_refinement`).
    Returns ``run`` and ``final`` where no copy scored lower. Only where the mask is trusted partially.

    Why: a long, thin tool whose one end an occluder hides and whose other end a segmenter's blob extends
    is pulled along its own axis, where neither the depth of its flat surface nor the silhouette's long sides
    resist; the refinement stops centimetres along it, in a minimum the truth's loss undercuts
    (docs/benchmarks.md). No start near the estimate leads back: the pose starts turn about the centre. An
    exact mask's outline holds both ends: there a copy that scores lower finds another minimum of the model's
    own error as often as the truth."""
    opts = loss_fn.options
    rows = torch.cat([final[0], _slid_rows(loss_fn.model, param, final[0].cpu().double(), opts.slide_share).to(final[0])])
    losses = _fixed_rays_loss(loss_fn, obs, camera, param, rows, torch.Generator().manual_seed(opts.seed))
    losses = torch.where(torch.isfinite(losses), losses, math.inf).cpu()
    best = int(losses.argmin())
    if best == 0 or not math.isfinite(float(losses[best])):
        return run, final
    again, last = refinement(rows[best : best + 1])
    return _second_refinement(loss_fn, obs, camera, param, run, final, again, last)


@torch.no_grad()
def _silhouette_overlap(loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, row: Tensor) -> float:
    """Intersection over union of the rendered silhouette of ``row [1, d]`` and the mask, on up to
    ``options.eval_rays`` box pixels (drawn with ``options.seed``): near 1 where the estimate explains
    the mask, lower where a wrong minimum draws part of the object beside it."""
    opts = loss_fn.options
    index = _box_pixels(obs, opts.eval_rays, torch.Generator().manual_seed(opts.seed))
    rays = _object_rays(camera.rays(obs.pixels[index].to(torch.float32)), param.poses(row))
    _, opacity, _ = loss_fn._render(rays, param.thetas(row), ("opacity",))
    opacity, mask = opacity.reshape(-1).double(), obs.levels[-1].mask[index].double()
    union = (opacity + mask - opacity * mask).sum()
    return float((opacity * mask).sum() / union.clamp_min(1e-9))


def _uncertainty(
    model: NarfModel,
    opts: EstimateOptions,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    T: Tensor,
    theta: Tensor,
    uses_depth: bool,
    problem=None,
    rays: tuple[Tensor, Tensor, Tensor] | None = None,
) -> Uncertainty | None:
    """The covariance at ``(T [4,4], θ [k])``: one Gauss-Newton linearisation on the box's rays
    (narf_core/gauss_newton.py) plus the model's error and the options' floors on the diagonal;
    ``None`` if it cannot be computed (a non-finite render). ``problem`` and ``rays``: a caller's
    own (the tracker's frame: its rays, marched once; see ``gauss_newton.covariance``).

    The model's error is in footprints of a pixel at the object, but never of a pixel finer than in a
    box of the reference size (:data:`ROBUST_BOX_PX`, whatever the preset's ``reference_box_px``): a
    camera finer than the views the model was trained on does not make the model itself more exact.
    With depth and ``opts.uncertainty_trained_footprint``: nor finer than a pixel of the training views
    (:func:`trained_footprint`), for an estimate from a few iterations (the tracker's frame, whichever
    refiner runs it), whose error at a finer camera stays that of the rays' draw of the model's error
    (docs/benchmarks.md, sessions 29 and 33)."""
    from narf_core.gauss_newton import Problem, covariance

    aabb = model.aabb.detach().double().cpu()
    centre = (aabb[0] + aabb[1]) / 2
    problem = problem or Problem(model, opts, param.radius, uses_depth)
    rng = torch.Generator().manual_seed(opts.seed + 1)
    stat = covariance(problem, obs, camera, param, T, theta, centre, opts.uncertainty_rays, opts.uncertainty_patch, rng,
                      rays)
    if not bool(torch.isfinite(stat.sigma).all()):
        return None
    pixel = model_footprint(camera, T, centre, obs.shape)
    if uses_depth and opts.uncertainty_trained_footprint:
        pixel = max(pixel, trained_footprint(model, T, centre))
    span = (2 * param.half).cpu()
    floor = torch.cat([
        torch.full((3,), opts.sigma_floor_position), torch.full((3,), opts.sigma_floor_rotation), opts.sigma_floor_joint * span
    ]).double()
    kind, sight = _error_class(opts, uses_depth), line_of_sight(model, T)
    spread = rotation_spread(model, T, theta) if opts.uncertainty_rotation_shape else None
    hidden = joint_mask_shares(model, camera, T, theta, obs) < HIDDEN_SHARE  # [k]
    unseen = torch.cat([torch.zeros(6, dtype=torch.float64), torch.where(hidden, param.half.double().cpu() ** 2, 0.0)])

    def covariance_at(usual_silhouette: float) -> Tensor:
        sd = model_error(model, kind, pixel, param.radius, stat.colour_variance, opts.uncertainty_usual_residual,
                         stat.silhouette_misfit, usual_silhouette)
        return stat.sigma + model_error_covariance(sd, kind, sight, spread) + torch.diag(floor**2 + unseen)

    Sigma, colour = covariance_at(opts.uncertainty_usual_silhouette), None
    if 0 < opts.uncertainty_usual_silhouette < stat.silhouette_misfit:  # the silhouette may have widened it
        colour = covariance_at(0.0)
        colour = None if torch.equal(colour, Sigma) else colour.numpy().copy()
    names = [j.name for j in model.joints]
    view = torch.sqrt(torch.diagonal(stat.sigma)[6:].clamp_min(0) + unseen[6:]).tolist()
    return Uncertainty.from_covariance(Sigma.numpy().copy(), names, stat.variance, stat.dof,
                                       dict(zip(names, view, strict=True)), colour, unseen.numpy().copy())


# A joint the mask hardly shows: under this share of the surface points of the links it moves that no other
# link hides project inside the mask at the estimate (a visible part's fall 94-98 % inside an exact mask), or
# the model itself hides that part (:data:`SHOWN_POINTS_SHARE`). What the view says of it is then a render
# against a mask that leaves the part out (an occluder over it, a segmenter's missed blob, the image's border,
# a door in front of a drawer), not where the part is, and the estimate may put it anywhere out of sight: its
# σ grows by its prior's, the half range, and it is reported unobserved (docs/benchmarks.md, sessions 42 and
# 50).
HIDDEN_SHARE = 0.5
# Under this share of a joint's surface points not hidden by another link: the part is behind the others.
# On the cabinet's Table II views a drawer that shows keeps 2.2 % of its points or more (2.2 %: its front's
# edge, 146 pixels, under the drawer above it); one behind the open door none.
SHOWN_POINTS_SHARE = 0.005


def joint_mask_shares(model: NarfModel, camera: Pinhole, T: Tensor, theta: Tensor, obs: _Observation) -> Tensor:
    """``[k]`` float64: per joint, the share of the model's surface points on the links it moves that project
    inside the mask of ``obs`` (its finest level over 0.5) at the pose ``T [4,4]`` and ``θ [k]``, among those
    no other link hides (:func:`~narf_core.band.hidden_points`: a mask cannot show a part behind another, so
    those points say nothing of the mask); 0 where under :data:`SHOWN_POINTS_SHARE` of them are not hidden (a
    drawer behind an open door); 1 for a joint that moves no point (nothing to judge)."""
    from narf_core.band import hidden_points, point_spacing, surface_points

    points = getattr(model, "sample_points", None) or {}
    moved = model.kinematics.moved_points(points, theta.detach().cpu())  # [k, N]
    shares = torch.ones(moved.shape[0], dtype=torch.float64)
    if moved.shape[1] == 0:
        return shares
    xyz = surface_points(model, T.detach()[None], theta.detach()[None])[0]  # [N, 3] camera frame
    uv, z = (x.cpu() for x in camera.project(xyz.to(camera.K.device)))
    h, w = obs.shape
    corner = obs.pixels[0].cpu()  # the box's (u0, v0): its pixels run row-major from there
    col = torch.floor(uv[:, 0]).long() - int(corner[0])
    row = torch.floor(uv[:, 1]).long() - int(corner[1])
    inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    box_mask = obs.levels[-1].mask.detach().cpu().reshape(h, w) > 0.5
    in_mask = torch.zeros_like(inside)
    in_mask[inside] = box_mask[row[inside], col[inside]]
    shown = moved & ~hidden_points(xyz, camera, point_spacing(model), ~moved)  # [k, N]
    counts, shown_counts = moved.sum(1), shown.sum(1)
    hits = (shown & in_mask[None]).sum(1)
    behind = shown_counts < SHOWN_POINTS_SHARE * counts
    share = torch.where(behind, 0.0, hits.double() / shown_counts.clamp_min(1))
    return torch.where(counts > 0, share, shares)


# The model's error, which the residuals cannot see: the field renders the object a little
# differently from the camera (a bias, not noise), and the refiner may stop in a wrong basin. Its σ
# is ``pixels`` footprints of a pixel at the object, times ``(v / reference_variance) ^ exponent``
# with ``v`` the estimate's mean squared colour residual: an estimate that explains the image worse
# than the model usually does is less trustworthy. ``pixels`` depends on the loss and the solver
# (:func:`_error_class`), which set how often the refiner ends in a wrong basin: a colour-only loss
# hardly sees the distance or a jaw it does not overlap; without depth the distance is the least
# certain (model_error_covariance). A bundle may carry its own in ``metadata["uncertainty"]``. The
# classes with depth were fitted on the bundled clamp (160x120 synthetic views and a 60-frame sequence
# of seed 1, none of the benchmarks' scenes), the two without on the clamp's and lineman-a's seed-1
# views pooled, given no depth (benchmarks/calibration.py repeats the fit and can store it in a
# bundle): per class the smallest ``pixels`` whose 95 % regions hold 95 % of the errors; ``narf bench
# estimate`` and ``narf bench track`` report the coverage on their scenes.
MODEL_ERROR = {
    "pixels": {"colour": 1.27, "silhouette": 1.24, "shape": 0.57, "shape-gauss-newton": 0.94},
    "reference_variance": 0.0065,
    "exponent": 1.0,
}
# The classes without a depth term, whose position error along the line of sight is the error of the
# object's scale in the image: see model_error_covariance.
LINE_OF_SIGHT_CLASSES = ("colour", "silhouette")


def _error_class(opts: EstimateOptions, uses_depth: bool) -> str:
    """The key of :data:`MODEL_ERROR`'s ``pixels``: without depth ``colour`` (no silhouette term) or
    ``silhouette``; with depth ``shape`` (Adam) or ``shape-gauss-newton``."""
    if not uses_depth:
        return "colour" if opts.silhouette_weight == 0 else "silhouette"
    return "shape-gauss-newton" if opts.solver == "gauss-newton" else "shape"


def model_footprint(camera: Pinhole, T: Tensor, centre: Tensor, box_shape: tuple[int, int]) -> float:
    """The pixel footprint (m) in which the model's error is counted: a pixel's span at the object's
    ``centre [3]`` (object frame) under ``T [4,4]``, times the mask box's longer side (``box_shape``, ``(h,
    w)``) over :data:`ROBUST_BOX_PX` where larger, so never finer than in a box of the reference size."""
    return _centre_depth(T, centre) / float(camera.K[0, 0]) * max(1.0, max(box_shape) / ROBUST_BOX_PX)


# The focal length (pixels) of the views MODEL_ERROR was fitted on (Pinhole.primesense(160, 120)): the training
# camera of a bundle that records none of its own (``metadata["training_camera"]``, which ``narf train`` writes;
# the bundled clamp was trained on such views).
REFERENCE_TRAINING_FX = float(Pinhole.primesense(160, 120).K[0, 0])


def trained_footprint(model: NarfModel, T: Tensor, centre: Tensor) -> float:
    """A pixel's span (m) at the object's ``centre [3]`` (object frame) under ``T [4,4]`` in the views the
    model was trained on: its bundle's ``metadata["training_camera"]["fx"]``, else :data:`REFERENCE_TRAINING_FX`."""
    return _centre_depth(T, centre) / training_fx(model)


def training_fx(model: NarfModel) -> float:
    """The focal length (pixels) of the views the model was trained on: its bundle's
    ``metadata["training_camera"]["fx"]``, else :data:`REFERENCE_TRAINING_FX`."""
    return float((model.metadata.get("training_camera") or {}).get("fx") or REFERENCE_TRAINING_FX)


def _centre_depth(T: Tensor, centre: Tensor) -> float:
    return float(T[2, :3].double() @ centre.double() + T[2, 3])


def model_error(model: NarfModel, kind: str, pixel_m: float, radius: float, colour_variance: float,
                usual: float = 0.0, silhouette_misfit: float = 0.0, usual_silhouette: float = 0.0) -> Tensor:
    """σ ``[6 + k]`` of the model's error (see :data:`MODEL_ERROR`; ``kind`` from :func:`_error_class`)
    at an estimate where a pixel spans ``pixel_m`` metres at the object's centre: in position that
    times ``pixels``, in rotation that over the object's ``radius``, per joint that over the speed at
    which the joint moves the surface (``KinematicTree.surface_speeds``: 1 for a prismatic joint, so the
    position in metres; the moved points' distance from its axis for a revolute one, so a small part
    at the end of a chain gets the wider angle a position error means there; :func:`_joint_speeds`).
    ``usual`` (> 0): the reference colour residual
    instead of the calibration's, and residuals below it count as it
    (``EstimateOptions.uncertainty_usual_residual``). ``usual_silhouette`` (> 0): the error grows with
    ``(silhouette_misfit / usual_silhouette) ^`` :data:`SILHOUETTE_EXPONENT` where that exceeds the
    colour's growth (``EstimateOptions.uncertainty_usual_silhouette``)."""
    own = model.metadata.get("uncertainty") or {}
    calibration = {**MODEL_ERROR, **own, "pixels": {**MODEL_ERROR["pixels"], **own.get("pixels", {})}}
    return model_error_sigma(calibration, kind, pixel_m, radius, colour_variance, _joint_speeds(model, radius), usual,
                             silhouette_misfit, usual_silhouette)


# How the model's error grows with the silhouette's misfit above the usual one (model_error): a frame's
# misfit hardly ranks its error among frames under the same faults, but its level tells faulted images (a
# segmenter's mask, an occluder, depth holes: half the frames' misfits 0.04-0.11) from our renderer's
# (0.02 or less in 95 % of its frames); the exponent chosen on tracks of both (docs/benchmarks.md, session 41).
SILHOUETTE_EXPONENT = 2.0


def model_error_sigma(calibration: Mapping, kind: str, pixel_m: float, radius: float, colour_variance: float,
                      joint_speeds: Tensor, usual: float = 0.0, silhouette_misfit: float = 0.0,
                      usual_silhouette: float = 0.0) -> Tensor:
    """:func:`model_error` under the constants ``calibration`` (:data:`MODEL_ERROR`'s keys), with each
    joint's surface speed ``joint_speeds [k]`` given: the one formula the refiner reports and
    ``narf_benchmarks.calibration`` fits."""
    reference = usual or calibration["reference_variance"]
    fit = (max(colour_variance, usual) / reference) ** calibration["exponent"]
    if usual_silhouette > 0 and math.isfinite(silhouette_misfit):
        fit = max(fit, (silhouette_misfit / usual_silhouette) ** SILHOUETTE_EXPONENT)
    position = calibration["pixels"][kind] * pixel_m * fit
    joints = position / joint_speeds.to(torch.float64)
    return torch.cat([torch.tensor([position] * 3 + [position / radius] * 3, dtype=torch.float64), joints])


def model_error_covariance(sd: Tensor, kind: str, sight: tuple[Tensor, float], spread: Tensor | None = None) -> Tensor:
    """The model error's covariance ``[6+k, 6+k]`` from its σ ``sd [6 + k]`` (:func:`model_error`):
    ``diag(sd²)``, and for a class without depth (:data:`LINE_OF_SIGHT_CLASSES`) the position's σ along
    the line of sight ``sight = (u [3], stretch)`` (:func:`line_of_sight`) ``stretch`` times the σ
    across it. Without depth the distance is read from the object's size in the image: an outline
    ``p`` footprints off moves the object ``p`` footprints times its distance over its radius along
    the line of sight. ``spread [3, 3]`` (:func:`rotation_spread`): the rotation block is ``sd_rotation²``
    times it instead of isotropic, the rotation that a surface error of the position's σ means for the
    object's own shape."""
    cov = torch.diag(sd.to(torch.float64) ** 2)
    if kind in LINE_OF_SIGHT_CLASSES:
        u, stretch = sight
        u = u.to(torch.float64)
        cov[:3, :3] += float(sd[0]) ** 2 * (stretch**2 - 1.0) * torch.outer(u, u)
    if spread is not None:
        cov[3:6, 3:6] = float(sd[3]) ** 2 * spread.to(torch.float64)
    return cov


# The largest eigenvalue of rotation_spread (σ at most its square root, 10x, wider than over the radius): a
# rod's turn about its own axis moves no surface point, and no finite model error would say so.
MAX_ROTATION_SPREAD = 100.0


def rotation_spread(model: NarfModel, T: Tensor, theta: Tensor) -> Tensor:
    """``[3, 3]`` float64, camera axes: ``r² M⁻¹``, with ``M`` the mean of ``|q|² I - q qᵀ`` over the model's
    surface points at ``θ [k]`` under ``T [4,4]`` (``q`` a point from the box centre) and ``r`` half the
    box's diagonal. A rotation ``ω`` about the centre moves the points by ``ω × q``, ``ωᵀ M ω`` in the mean
    square: a surface error of ``σ`` metres is a rotation of covariance ``σ² M⁻¹``, the isotropic ``(σ /
    r)²`` times this. Every point lies within ``r`` of the centre, so its eigenvalues are at least 1 (wider
    on every axis, most about the axis the surface lies near: the clamp's long one), at most
    :data:`MAX_ROTATION_SPREAD`; the identity without surface points."""
    from narf_core.band import surface_points

    eye = torch.eye(3, dtype=torch.float64)
    points = surface_points(model, torch.as_tensor(T)[None], torch.as_tensor(theta)[None])[0]  # [N, 3]
    if len(points) == 0:
        return eye
    aabb = model.aabb.detach().to("cpu", torch.float64)
    T = torch.as_tensor(T).to("cpu", torch.float64)
    q = points - (T[:3, :3] @ ((aabb[0] + aabb[1]) / 2) + T[:3, 3])
    M = (q * q).sum(-1).mean() * eye - q.T @ q / len(q)
    w, V = torch.linalg.eigh(M / (float((aabb[1] - aabb[0]).norm()) / 2) ** 2)
    return V @ torch.diag(1.0 / w.clamp(1.0 / MAX_ROTATION_SPREAD, 1.0)) @ V.T


def line_of_sight(model: NarfModel, T: Tensor) -> tuple[Tensor, float]:
    """The unit vector ``[3]`` (camera frame) to the object's box centre under ``T [4,4]`` and the factor
    ``d / radius`` (at least 1; ``d`` the centre's distance, ``radius`` half the box's diagonal) by which
    the model's error along it exceeds the error across it without depth (:func:`model_error_covariance`)."""
    aabb = model.aabb.detach().to("cpu", torch.float64)
    T = torch.as_tensor(T).to("cpu", torch.float64)
    centre_cam = T[:3, :3] @ ((aabb[0] + aabb[1]) / 2) + T[:3, 3]
    distance = float(torch.linalg.norm(centre_cam))
    return centre_cam / distance, max(distance / (float((aabb[1] - aabb[0]).norm()) / 2), 1.0)


def _joint_speeds(model: NarfModel, radius: float) -> Tensor:
    """``[k]`` metres per unit of each joint (``KinematicTree.surface_speeds`` on the model's surface points);
    where there are none (or a joint moves none): 1 for a prismatic joint, the object's ``radius`` else."""
    fallback = torch.tensor([1.0 if j.type == "prismatic" else radius for j in model.joints], dtype=torch.float64)
    points = getattr(model, "sample_points", None) or {}
    if not any(len(p) for p in points.values()):
        return fallback
    speeds = model.kinematics.surface_speeds(points)
    return torch.where(speeds > 0, speeds, fallback)


def _ray_index(obs: _Observation, opts: EstimateOptions, n_rays: int, rng: torch.Generator, allow_all: bool) -> Tensor:
    """``n_rays`` box pixels ``[n]`` for one iteration: all of them when they fit (and ``allow_all``),
    else uniform draws, one per cell of a grid (``ray_sampling = "stratified"``), or (``"edges"``)
    half of them drawn in proportion to the mask's edges and the image's gradient (where a pose or
    θ error changes the residual most) and half uniform; ``"auto"``: uniform in a box of the
    reference size, edges in a larger one (where uniform rays rarely meet the silhouette)."""
    n_pixels = obs.pixels.shape[0]
    device = obs.pixels.device
    if n_rays == n_pixels and allow_all:
        return torch.arange(n_pixels, device=device)
    sampling = opts.ray_sampling
    if sampling == "auto":
        sampling = "edges" if obs.scale > 1 else "uniform"
    if sampling == "uniform":
        return torch.randint(n_pixels, (n_rays,), generator=rng).to(device)
    if sampling == "stratified":
        return _stratified(obs.shape, n_rays, rng).to(device)
    n_edge = n_rays // 2
    edges = torch.multinomial(obs.importance.cpu(), n_edge, replacement=True, generator=rng)
    rest = torch.randint(n_pixels, (n_rays - n_edge,), generator=rng)
    return torch.cat([edges, rest]).to(device)


def _stratified(shape: tuple[int, int], n: int, rng: torch.Generator) -> Tensor:
    """``n`` pixel indices ``[n]`` of an ``(h, w)`` box, row-major, one per cell of a grid of about
    ``n`` equal cells (a random pixel in each; a random ``n`` of the cells when the grid has more):
    every part of the box gets its share of rays at every iteration, unlike independent draws."""
    h, w = shape
    side = max(1.0, math.sqrt(h * w / max(n, 1)))
    gy, gx = max(1, math.ceil(h / side)), max(1, math.ceil(w / side))
    cells = torch.randperm(gy * gx, generator=rng)[:n] if gy * gx >= n else torch.randint(gy * gx, (n,), generator=rng)
    cy, cx = (cells // gx).double(), (cells % gx).double()
    v = ((cy + torch.rand(len(cells), generator=rng, dtype=torch.float64)) * h / gy).floor().long().clamp(0, h - 1)
    u = ((cx + torch.rand(len(cells), generator=rng, dtype=torch.float64)) * w / gx).floor().long().clamp(0, w - 1)
    return v * w + u


class _Run:
    """The optimisation loop of one :func:`refine` call and its record."""

    should_stop: Callable[[], str | None] | None = None  # refine's hook: a status ends the loop

    def __init__(
        self,
        model: NarfModel,
        opts: EstimateOptions,
        obs: _Observation,
        camera: Pinhole,
        param: _Parameterisation,
        loss_fn: _Loss,
        params0: Tensor,
        start_time: float,
    ) -> None:
        """``params0 [S, 6 + k]``: the starts' rows (:func:`_start_rows`)."""
        self.model, self.opts, self.obs, self.camera, self.param, self.loss_fn = model, opts, obs, camera, param, loss_fn
        self.start_time = start_time
        k = params0.shape[1] - 6
        self.adam = _Adam(params0, torch.tensor([opts.lr_pose] * 6 + [opts.lr_theta] * k, dtype=torch.float64))
        self.best_params, self.best_loss = params0, math.inf
        self.rng = torch.Generator().manual_seed(opts.seed)
        self.rate_scale, self.recovered = 1.0, False
        self.iteration, self.status = 0, "max_iterations"
        self.trace: list[tuple[float, float]] = []
        self.history: list[Snapshot] = []
        self.losses: list[Tensor] = []  # per-start losses of the recent iterations
        self.past: list[Tensor] = []  # parameters of the recent iterations

    def optimise(self) -> None:
        opts, n_levels = self.opts, len(self.obs.levels)
        prune_at = int(opts.iterations * _PRUNE_SHARE)
        failures = 0
        while self.iteration < opts.iterations:
            if self.should_stop is not None and (reason := self.should_stop()):
                self.status = reason
                return
            level = _level(self.iteration, opts.iterations, n_levels)
            self.iteration += 1
            per_start, grad = self._loss_and_gradient(self.obs.levels[level])
            if not (bool(torch.isfinite(per_start).all()) and bool(torch.isfinite(grad).all())):
                failures += 1
                self._recover()
                if failures >= _MAX_RECOVERIES:
                    self.status = "non_finite"
                    return
                continue
            failures = 0
            self._record(per_start)
            decay = opts.lr_decay ** (self.iteration / max(opts.iterations - 1, 1))
            self.adam.step(grad, self.rate_scale * decay)
            if self.adam.params.shape[0] > 1 and self.iteration >= prune_at:
                self._keep_best_start()
            if opts.early_stop and level == n_levels - 1 and self.adam.params.shape[0] == 1 and self._converged():
                self.status = "converged"
                return

    def _loss_and_gradient(self, target: _Target) -> tuple[Tensor, Tensor]:
        """Per-start loss ``[S]`` on this iteration's rays and its gradient ``[S, d]`` (zero if no ray
        reaches the object)."""
        n_pixels = self.obs.pixels.shape[0]
        several = self.adam.params.shape[0] > 1  # while several starts run, each traces half the rays
        n_rays = min(max(self.opts.rays_per_iteration // (2 if several else 1), 1), n_pixels)
        device = self.obs.pixels.device
        index = _ray_index(self.obs, self.opts, n_rays, self.rng, target.width == 1)
        pixels = self.obs.pixels[index].to(torch.float32)
        if target.width > 1:
            pixels = pixels + (torch.rand(n_rays, 2, generator=self.rng).to(device) - 0.5) * target.width
        p = self.adam.params.clone().requires_grad_(True)
        per_start = self.loss_fn(self.camera.rays(pixels), target, index, self.param.poses(p), self.param.thetas(p))
        if not per_start.requires_grad:
            return per_start, torch.zeros_like(p)
        (grad,) = torch.autograd.grad(per_start.sum(), p)
        return per_start.detach(), grad

    def _recover(self) -> None:
        """After a non-finite loss or gradient: back to the best finite iterate, fresh moments, half rate."""
        self.recovered = True
        self.adam.params = self.best_params.clone()
        self.adam.reset()
        self.rate_scale *= 0.5
        self.losses.clear()
        self.past.clear()

    def _record(self, per_start: Tensor) -> None:
        total = float(per_start.sum())
        if total < self.best_loss:
            self.best_loss, self.best_params = total, self.adam.params.clone()
        elapsed = time.perf_counter() - self.start_time
        self.trace.append((float(per_start.min()), elapsed))
        self.losses.append(per_start)
        self.past.append(self.adam.params.clone())
        del self.losses[: -2 * self.opts.patience], self.past[: -self.opts.patience - 1]
        if self.opts.record_every and self.iteration % self.opts.record_every == 0:
            self.history.append(_snapshot(self.model, self.param, self.adam.params, per_start, self.iteration, elapsed))

    def _keep_best_start(self) -> None:
        """Drop every start but the one with the lowest loss on a fixed set of fine rays (the same
        for all starts, and many more than one iteration's share)."""
        losses = _fixed_rays_loss(self.loss_fn, self.obs, self.camera, self.param, self.adam.params, self.rng)
        keep = torch.where(torch.isfinite(losses), losses, math.inf).argmin().cpu().reshape(1)
        self.adam.keep(keep)
        self.best_params = self.adam.params.clone()
        self.best_loss = math.inf
        self.losses = [row[keep] for row in self.losses]
        self.past = [row[keep] for row in self.past]

    def _converged(self) -> bool:
        """Over the last ``patience`` iterations the estimate moved less than ``tolerance`` per
        iteration (net, so Adam's jitter about a minimum cancels out) and the mean loss changed by
        less than ``loss_tolerance`` (relative) from the window before."""
        n = self.opts.patience
        if len(self.past) < n + 1 or len(self.losses) < 2 * n:
            return False
        if float(self.param.motion(self.adam.params, self.past[-n - 1]).max()) > self.opts.tolerance * n:
            return False
        recent = float(torch.stack(self.losses[-n:]).mean())
        before = float(torch.stack(self.losses[-2 * n : -n]).mean())
        return abs(recent - before) <= self.opts.loss_tolerance * max(abs(before), 1e-12)


def _level(iteration: int, iterations: int, levels: int) -> int:
    """The pyramid level of an iteration: coarse levels share the first ``_COARSE_SHARE`` equally."""
    coarse = int(_COARSE_SHARE * iterations)
    if levels == 1 or iteration >= coarse:
        return levels - 1
    return iteration * (levels - 1) // coarse


@torch.no_grad()
def _final_choice(
    loss_fn: _Loss,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    params: Tensor,
    best_params: Tensor,
    rng: torch.Generator,
) -> tuple[Tensor, float, bool] | None:
    """The row ``[1, d]`` with the lowest loss on a fixed set of fine rays, its loss, and whether the
    last iterate had to be replaced by the best finite one (``None`` if nothing is finite)."""
    for candidate, replaced in ((params, False), (best_params, True)):
        loss = _fixed_rays_loss(loss_fn, obs, camera, param, candidate, rng)
        loss = torch.where(torch.isfinite(loss), loss, torch.full_like(loss, math.inf))
        i = int(loss.argmin())
        if math.isfinite(float(loss[i])):
            return candidate[i : i + 1], float(loss[i]), replaced
    return None


def _best_refinement(
    start: Callable[[EstimateOptions, _Observation], _Run],
    opts: EstimateOptions,
    obs: _Observation,
    count: int,
    should_stop: Callable[[], str | None] | None,
) -> tuple[_Run, Tensor]:
    """``max(count, 1)`` Adam refinements (``start(options, observation)`` makes one, from the same
    starts each time): the first with ``opts``, the others each with its own ray seed
    (``opts.seed + i``) and, every other one, the finest pyramid level alone. Which of several
    trajectories a run takes depends on its random rays, and no run's own loss compares with
    another's (each is measured on its own rays), so of every run's :func:`_final_choice` the one
    of lowest loss on one fixed set of ``_CHOICE_RAYS`` fine box rays is kept. Returns the kept run (its iterations and trace cover every run) and its last parameters
    ``[S', d]`` (one run: its last iterate). A run stopped by ``should_stop`` ends the series, and
    its status is the result's."""
    runs, rows = [], []
    for i in range(max(count, 1)):
        single = i % 2 == 1 and len(obs.levels) > 1
        run = start(opts if i == 0 else replace(opts, seed=opts.seed + i),
                    replace(obs, levels=obs.levels[-1:]) if single else obs)
        run.should_stop = should_stop
        run.optimise()
        runs.append(run)
        if count > 1:
            final = _final_choice(run.loss_fn, obs, run.camera, run.param, run.adam.params, run.best_params, run.rng)
            rows.append(run.adam.params[:0] if final is None else final[0])
        if run.status not in ("max_iterations", "converged"):
            break
    if len(runs) == 1:
        return runs[0], runs[0].adam.params
    best = _lowest_run(runs, rows, run.loss_fn, obs, run.camera, run.param, opts.seed)
    if best is None:  # nothing finite anywhere: the last run's own final choice says so
        return runs[-1], runs[-1].adam.params
    return runs[best], rows[best]


def _gauss_newton_estimates(opts: EstimateOptions, count: int) -> list[EstimateOptions]:
    """The options of :func:`_best_gauss_newton`'s first ``count`` estimates (one of each kind), in turn:
    ``opts``; its own ray seed with half its rays on edges (``ray_sampling = "edges"``), from the given
    pose alone (no pose-start check: half the cost of one with it); and, where the mask is trusted only
    partially and ``opts.align_start`` is on, ``opts`` from starts not moved onto the mask and depth."""
    kinds = [opts, replace(opts, seed=opts.seed + 1, ray_sampling="edges", pose_starts=1)]
    if opts.align_start and opts.mask_trust == "partial":
        kinds.append(replace(opts, align_start=False))
    return kinds[:max(count, 1)]


def _best_gauss_newton(
    estimate: Callable[[EstimateOptions], tuple | None],
    opts: EstimateOptions,
    count: int,
    loss_fn: _Loss,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
) -> tuple:
    """Up to ``count`` Gauss-Newton estimates (:func:`_gauss_newton_estimates`; ``estimate(options)`` runs
    one and returns its run and final choice, or ``None`` where it would repeat one) and the one whose
    estimate has the lowest loss on common rays (:func:`_lowest_run`). Where the mask is trusted only
    partially, each kind of estimate fails somewhere the others do not (docs/benchmarks.md): few uniform
    rays meet a thin, partly hidden tool, where edge rays do, and edge rays leave others in wrong minima; an
    occluder or a segmenter's blob moves the mask's centroid, and with it the start that ``align_start``
    moved there, which scored lower on the start's coarse rays. A wrong minimum's loss is mostly above the
    truth's, so the choice keeps the estimate that reached the truth. With ``pose_starts_overlap`` the
    others run only where the first estimate's silhouette overlaps the mask less than that
    (:func:`_silhouette_overlap`): an estimate that explains the mask is not improved by them, and an exact
    mask that the depth contradicts (about half the pliers' path-traced views) would pay for them. Returns
    the kept run, its record covering every run, and its final choice; the last run and ``None`` where
    nothing is finite."""
    runs, finals = [], []
    for i, o in enumerate(_gauss_newton_estimates(opts, count)):
        if i == 1 and opts.pose_starts_overlap > 0 and finals[0] is not None:
            if _silhouette_overlap(loss_fn, obs, camera, param, finals[0][0]) >= opts.pose_starts_overlap:
                break
        outcome = estimate(o)
        if outcome is None:
            continue
        run, final = outcome
        runs.append(run)
        finals.append(final)
        if run.status not in ("max_iterations", "converged"):
            break
    if len(runs) == 1:
        return runs[0], finals[0]
    rows = [run.params[:0] if final is None else final[0] for run, final in zip(runs, finals)]
    best = _lowest_run(runs, rows, loss_fn, obs, camera, param, opts.seed)
    return (runs[-1], None) if best is None else (runs[best], finals[best])


def _lowest_run(
    runs: list, rows: list[Tensor], loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation,
    seed: int,
) -> int | None:
    """The index of the run whose estimate (a row of ``rows[i] [k, d]``, k = 0 where it has none) has the
    lowest loss on one fixed set of ``_CHOICE_RAYS`` fine box rays; ``None`` where none is finite. No run's
    own loss compares with another's (each is measured on its own rays). The kept run's record then covers
    every run: iterations, trace, history, recovery, and the status a ``should_stop`` gave the last."""
    owner = [i for i, row in enumerate(rows) for _ in range(row.shape[0])]
    if not owner:
        return None
    losses = _fixed_rays_loss(loss_fn, obs, camera, param, torch.cat(rows), torch.Generator().manual_seed(seed), _CHOICE_RAYS)
    losses = torch.where(torch.isfinite(losses), losses, math.inf)
    if not math.isfinite(float(losses.min())):
        return None
    best = owner[int(losses.argmin())]
    chosen = runs[best]
    if runs[-1].status not in ("max_iterations", "converged", "non_finite"):  # should_stop's reason holds for all
        chosen.status = runs[-1].status
    chosen.iteration = sum(r.iteration for r in runs)
    chosen.trace = [point for r in runs for point in r.trace]
    chosen.history = [snap for r in runs for snap in r.history]
    chosen.recovered = any(r.recovered for r in runs)
    return best


@torch.no_grad()
def _fixed_rays_loss(
    loss_fn: _Loss, obs: _Observation, camera: Pinhole, param: _Parameterisation, params: Tensor, rng: torch.Generator,
    n: int = 0,
) -> Tensor:
    """Loss ``[S]`` of every row of ``params [S, d]`` on the same up to ``n`` (0: ``options.eval_rays``)
    pixels of the box, at the finest level; infinite for a row that draws the object on less than
    ``_MIN_COVER_SHARE`` of the mask's rays that another row draws it on. The choices between refinements'
    estimates, between Adam's starts and of the final iterate go through here (Gauss-Newton prunes its
    starts on its own robust cost): a render that leaves the mask unexplained is no estimate of the
    object, yet its loss can be the lowest (nothing drawn, no depth or band residual to pay;
    docs/benchmarks.md)."""
    index = _box_pixels(obs, n or loss_fn.options.eval_rays, rng)
    loss, cover = loss_fn.terms(camera.rays(obs.pixels[index]), obs.levels[-1], index, param.poses(params),
                                param.thetas(params))
    finite = torch.isfinite(loss)
    most = float(torch.where(finite, cover, 0.0).max())
    return torch.where(finite & (cover >= _MIN_COVER_SHARE * most), loss, math.inf)


@torch.no_grad()
def _overlaps(camera: Pinhole, pixels: Tensor, T_cam_obj: Tensor, aabb: Tensor) -> bool:
    """Whether any ray through the box pixels ``[P, 2]`` meets the object's box ``aabb [2,3]`` under
    ``T_cam_obj [4,4]`` (in front of the camera)."""
    box = aabb.cpu().double()
    corners = torch.stack(torch.meshgrid(box[:, 0], box[:, 1], box[:, 2], indexing="ij"), -1).reshape(-1, 3)
    if bool((transform_points(T_cam_obj, corners)[:, 2] <= 0).all()):
        return False
    rays = _object_rays(camera.rays(pixels), T_cam_obj[None])
    _, t_far, hit = ray_aabb(rays.origins, rays.directions, aabb)
    return bool((hit & (t_far > 0)).any())


@torch.no_grad()
def _snapshot(
    model: NarfModel, param: _Parameterisation, params: Tensor, losses: Tensor, iteration: int, seconds: float
) -> Snapshot:
    """The start with the lowest loss among ``params [S, d]`` as a :class:`Snapshot`."""
    i = int(losses.argmin())
    row = params[i : i + 1]
    return Snapshot(
        iteration,
        seconds,
        float(losses[i]),
        param.poses(row)[0].numpy().copy(),
        param.joints(model, param.thetas(row)[0]),
    )


def _metrics(model: NarfModel, truth: tuple[Tensor, Tensor], T: Tensor, theta: Tensor) -> dict[str, float]:
    """Root pose errors, per-joint errors and, where the model has surface points, ADD, ADD-S and
    the success flags, against the ground truth."""
    T_true, theta_true = truth
    T, theta = T.detach(), theta.detach()
    out = {
        "rotation_error_deg": math.degrees(float(so3_log(T[:3, :3] @ T_true[:3, :3].T).norm())),
        "translation_error_m": float((T[:3, 3] - T_true[:3, 3]).norm()),
    }
    errors = joint_errors(theta_true.numpy(), theta.numpy(), [j.type for j in model.joints])
    out.update({f"joint_error/{j.name}": float(e) for j, e in zip(model.joints, errors)})
    if any(len(points) for points in model.sample_points.values()):
        kin = model.kinematics
        links_true, links_est = kin.link_poses(theta_true).numpy(), kin.link_poses(theta).numpy()
        args = (model.sample_points, links_true, T_true.numpy(), links_est, T.numpy(), model.links)
        out["add"], out["add_s"] = float(add(*args)), float(add_s(*args))
        if model.diameter > 0:
            out.update(success_rates(np.array([out["add"]]), model.diameter))
    return out
