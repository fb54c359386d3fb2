"""Tracking over a sequence: the refiner warm-started frame after frame (issue #10).

Each frame is a few iterations of the refiner (:func:`refine_frame`: Gauss-Newton on one set of rays;
see :class:`TrackOptions`) that start from a constant-velocity
prediction of the previous estimate; with depth the prediction is first moved onto the observed depth
(:func:`depth_aligned`) and fitted to its points in pose and θ (:func:`narf_core.surface_fit.surface_fit`).
The state carried from frame to frame is a :class:`TrackState`: the last estimate (pose, θ), its time,
the velocity of the object's box centre and its angular velocity (both in camera axes, so that the
prediction turns the object about itself), the joint velocities and, where the solver gives one, the
covariance Σ.

Without depth the state also carries a colour gain per channel: each tracked frame's own fit at its
estimate moves it a step (``options.colour_rate_rgb``), and once it is far from one
(``options.colour_gate_rgb``) the render's colour is compared times it.

A frame's status (:data:`STATUSES`):
  - ``tracking``: the estimate explains the mask (overlap at least ``options.uncertain_overlap``)
    and Σ, if known, is within ``options.max_position_sigma_m`` / ``max_rotation_sigma_deg``;
  - ``uncertain``: the estimate stands but the overlap is low (an occlusion) or Σ is large;
  - ``lost``: no object in the mask, or no pose found that explains it (overlap below
    ``options.lost_overlap``, a non-finite loss); the state keeps the last estimate;
  - ``reinitialised``: the warm start failed (or the track was lost, or the time gap since the
    last estimate exceeds ``options.max_gap_s``) and the multi-start refiner, started from the last
    estimate moved onto the mask's centroid, found a pose that explains the mask. The velocity
    starts again from zero.

The overlap is cheap and independent of the loss's scale: the model's surface points at the
estimate are projected into the image (no render), and ``overlap = min(inside, covered)`` where
``inside`` is the fraction of the projected points inside the image that land on the (slightly
dilated) mask (so an object leaving the view through an image border keeps its overlap) and
``covered`` the fraction of mask pixels near a projected point. A wrong pose or configuration
lowers one or the other; without depth an occluder lowers ``inside``, with depth ``inside`` leaves out the
points off the mask that a reading stands in front of (an occluder's).

Frames must come in time order (a frame at or before the previous time is an input error).
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from narf_core.checks import check_number, check_option_types, check_pose, option_rule
from narf_core.estimate import (
    GAIN_RANGE, JACOBIANS, MIN_MASK_PIXELS, SOLVERS, UNOBSERVED_CODE, EstimateInputError, EstimateOptions, EstimateResult,
    Uncertainty, _object_rays, colour_gain, line_of_sight, refine, rotation_spread, training_fx, unobserved_joints,
)
from narf_core.gauss_newton import Problem
from narf_core.geometry import Pinhole, Rays, so3_exp, so3_log
from narf_core.modes import MODES, choose_mode
from narf_core.observation import BORDER_CODE, check_observation, dilate, usable_depth
from narf_core.sampling import Samples
from narf_core.surface_fit import SurfaceFitOptions, surface_fit

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.compositing import RenderOutput

STATUSES = ("tracking", "uncertain", "lost", "reinitialised")
MARCHES = ("frame", "iteration")
FIRST_FRAMES = ("multi-start", "warm")
_MIN_VELOCITY_GAP_S = 1e-3  # velocities are measured over at least this long
COLOUR_RAYS = 256  # mask pixels on which a tracked frame's colour gain is fitted (colour_gain_at)
# A frame's band reaches this far beyond the model's surface points at the prediction (refine_frame):
# the prediction's error is a few millimetres.
_FRAME_MARGIN_M = 0.006
# depth_offset's mode of (observed - model) depth: the median again over the differences this close to
# the last one, this many times (the far side's points, where no near one lands, lie centimetres off).
_DEPTH_WINDOW_M = 0.005
_DEPTH_ROUNDS = 3
_DEPTH_CELL = 0.7  # its cells' side over the mean spacing of the projected points (a pixel at least)
# A cell's nearest point is hidden where it lies behind the nearest point within this many cells by
# more than the window plus a 45° surface's rise over that distance (_front_cells).
_DEPTH_HIDDEN_CELLS = 2
# A warm-started frame's σ over the refiner's (TrackOptions.sigma_scale), per solver, with depth and
# without, for a model whose bundle carries no factor of its own for that solver, at a camera as fine as
# the training views: Gauss-Newton's fitted on four tools' seed-1 sequences at 160x120 pooled (the clamp,
# lineman-a, lineman-b, longnose; per tool 0.12-0.24 with depth, 0.24-0.95 without), with the model's error
# in rotation spread by the object's shape (session 59, docs/benchmarks.md); Adam's before that (with depth
# on four tools, without on the clamp's): with the shape its regions are wider than fitted.
SIGMA_SCALE = {"gauss-newton": {"rgbd": 0.18, "rgb": 0.59}, "adam": {"rgbd": 3.0, "rgb": 0.9}}
# At a camera r times finer than the training views (fx over theirs, r > 1) SIGMA_SCALE's factor times
# r ** this, where the frame's error grows faster than its Σ, whose model error is counted in training
# pixels with depth. Before the rotation's shape it did (0.5 against 0.3 at 640x480, 0.37); with it the
# same seed-1 sequences at 640x480 need 0.14 pooled against 0.18, and the four tools' own fits 0.64-1.13
# of their 160x120 factor: no growth (where absent, 0).
SIGMA_SCALE_FINER = {"gauss-newton": {"rgbd": 0.0}}
# The factor at which a frame's Σ is judged for a second round: the one it was tuned with, whatever the
# calibration (a model's factor, or SIGMA_SCALE's, changes Σ, never the track).
RETRY_SIGMA_SCALE = {"gauss-newton": 0.4, "adam": 3.0}
# A frame's solver where TrackOptions.solver is "auto": Levenberg-Marquardt on one set of rays, with depth
# and without (a few iterations reach the bottom that Adam's fixed steps trail behind; without depth its
# steps along the line of sight follow the silhouette's scale, where Adam's drift: docs/benchmarks.md).
AUTO_SOLVER = {"rgbd": "gauss-newton", "rgb": "gauss-newton"}
# How a warm-started frame with a depth image trusts its mask (EstimateOptions.mask_trust, mask_band_px,
# outside_weight). A single image's "auto" trusts it partially where the depth contradicts it (an occluder, a
# segmenter's edge): its rays outside the mask weigh less, none behind an occluder, and a band along the mask's
# edge carries no silhouette. A frame starts a few millimetres from its answer, where that band takes away the
# outline that holds a thin part and the pliers' tracks under a segmenter's faults drift off (docs/benchmarks.md,
# session 42): no band, and the rays outside the mask weigh in full but for those where the observed depth stands
# in front of the render (an occluder, which the mask leaves out with the part it hides: a render of that part
# there is no evidence against it; TrackOptions.occluder_test, session 56).
DEPTH_MASK_TRUST = {"mask_trust": "partial", "mask_band_px": 0, "outside_weight": 1.0, "partial_theta_starts": 0}
# A frame's iterations and rays per iteration per solver, where TrackOptions leaves them at 0.
BUDGETS = {"adam": (6, 768), "gauss-newton": (2, 768)}
# A frame's iterations without depth, per solver, where TrackOptions leaves them at 0 (else BUDGETS'): there
# a frame's steps along the directions the silhouette barely sees (the distance, a flat tool's roll) are
# short and noisy, and one more iteration each frame keeps a thin tool's track from drifting off
# (docs/benchmarks.md, session 36).
RGB_ITERATIONS = {"gauss-newton": 3}
# Rays per Gauss-Newton iteration on a CUDA device, where TrackOptions leaves them at 0: there a frame's time is
# its kernel launches', about the same for 768 rays as for 6144, and 4x the rays halve the track's error
# (docs/benchmarks.md, session 29).
GPU_RAYS = {"gauss-newton": 3072}
# A Gauss-Newton frame's Jacobian without depth where TrackOptions.jacobian_rgb is "auto" and the model's tracker
# calibration chose none: the field's derivatives (one pass, where the differences take 2 (6 + k) renders).
JACOBIAN_RGB = "derivatives"
# The calibration takes the differences without depth only where they lower the mean ADD of its sequences'
# frames below this share of the derivatives' (on the CPU they cost 2-3x the time).
DIFFERENCES_GAIN = 0.8
# With depth on the CPU, a Gauss-Newton frame takes FEWER_RAYS rays per iteration where the model's tracker
# calibration chose them: where its frames' mean ADD over its sequences stays within FEWER_RAYS_LOSS of the
# solver's own budget's (BUDGETS), and that one's within TRACK_HELD of the object's diameter. A frame's time is
# mostly its rays' renders (2 (6 + k) + 1 of them in its Jacobian): a large, textured object such as the gripper
# tracks as well on fewer at about 1.3x the rate, a thin one (the clamp, longnose) loses more, and a track that
# wanders (the lamp's, 2 % of its diameter) wanders further on fewer, whatever its fitting sequences' draw said
# (docs/benchmarks.md, session 62).
FEWER_RAYS = 512
FEWER_RAYS_LOSS = 1.15
# A model's track holds where its frames' mean ADD over the calibration's sequences stays within this share of the
# object's diameter: only such a track takes FEWER_RAYS, and only one that does not is tried with WIDE_HUBER.
TRACK_HELD = 0.01
# With depth, a Gauss-Newton frame's Huber scale (EstimateOptions.robust_scale) where the model's tracker calibration
# chose it: where the track on the preset's scale does not hold (TRACK_HELD) and this one's frames' mean ADD comes out
# below WIDE_HUBER_GAIN of that one's. A track that wanders along a valley of its object's poses (the lamp's, its
# round foot turned about the joints' axis against the shoulder) sees there residuals of centimetres of depth that the
# preset's scale weighs as outliers, and wandered less at the wider one; tracks that hold came out worse with it
# (docs/benchmarks.md, session 63).
WIDE_HUBER = 0.3
WIDE_HUBER_GAIN = 0.85


def budget_text(which: int = 0) -> str:
    """:data:`BUDGETS`' iterations (``which`` 0, with :data:`RGB_ITERATIONS`') or rays per iteration (1)
    per solver, for help texts: "2 gauss-newton (3 without depth), 6 adam"."""
    def text(solver: str, budget: tuple[int, int]) -> str:
        rgb = RGB_ITERATIONS.get(solver, budget[0]) if which == 0 else budget[which]
        return f"{budget[which]} {solver}" + (f" ({rgb} without depth)" if rgb != budget[which] else "")

    return ", ".join(text(solver, budget) for solver, budget in sorted(BUDGETS.items(), reverse=True))


def jacobian_text() -> str:
    """The default frame Jacobian in words, with depth and without (for the CLI's help)."""
    o = TrackOptions()
    rgb = (f"{JACOBIAN_RGB} without, or what the model's tracker calibration chose" if o.jacobian_rgb == "auto"
           else f"{o.jacobian_rgb} without")
    return f"{o.jacobian}, with depth and without" if o.jacobian == o.jacobian_rgb else f"{o.jacobian} with depth, {rgb}"


def tracker_calibration(model: NarfModel | None) -> dict:
    """The model's tracker calibration (``metadata["uncertainty"]["track"]``, fitted on sequences of its object by
    :func:`narf_core.train.track_sigma.track_calibration`); empty where it has none (or there is no model)."""
    return ((model.metadata.get("uncertainty") or {}).get("track") or {}) if model is not None else {}


def calibrated_jacobian(model: NarfModel, key: str) -> str | None:
    """The frame Jacobian the model's tracker calibration chose for frames with depth (``key`` "rgbd") or
    without ("rgb"); None where it chose none (a bundle calibrated before the choice, or never)."""
    return (tracker_calibration(model).get("jacobians") or {}).get(key)


def calibrated_rays(model: NarfModel | None, key: str = "rgbd") -> int | None:
    """The rays per Gauss-Newton iteration the model's tracker calibration chose for frames with depth (``key``
    "rgbd"); None where it chose none (a bundle calibrated before the choice, or never)."""
    return (tracker_calibration(model).get("rays") or {}).get(key)


def calibrated_huber(model: NarfModel | None, key: str = "rgbd") -> float | None:
    """The Huber scale of a Gauss-Newton frame with depth (``key`` "rgbd") the model's tracker calibration fitted its
    factors with (:data:`WIDE_HUBER` where it chose that one, else the preset's); None where it records none (a
    bundle calibrated before the choice, or never)."""
    return (tracker_calibration(model).get("robust_scale") or {}).get(key)


def auto_solver_text() -> str:
    """:data:`AUTO_SOLVER` for help texts: "gauss-newton, with depth and without"."""
    if AUTO_SOLVER["rgbd"] == AUTO_SOLVER["rgb"]:
        return f"{AUTO_SOLVER['rgbd']}, with depth and without"
    return f"{AUTO_SOLVER['rgbd']} with depth, {AUTO_SOLVER['rgb']} without"


TRACK_SOLVERS = ("auto", *SOLVERS)


class TrackInputError(EstimateInputError):
    """Unusable input to the tracker (frames out of order, a non-finite state, ...); names the field."""


@dataclass
class TrackOptions:
    """Tracker settings (plain JSON-able fields).

    ``solver``: a warm-started frame's solver, "adam" (the robust preset with one start),
    "gauss-newton", or "auto" (:data:`AUTO_SOLVER`: by whether the frame has depth).
    ``iterations``/``rays_per_iteration``: its budget per frame from the prediction, 0 for the
    solver's own (:data:`BUDGETS`, without depth :data:`RGB_ITERATIONS`, on a GPU :data:`GPU_RAYS`, with depth on
    the CPU the rays the model's calibration chose, :data:`FEWER_RAYS`; few iterations on many rays: an
    iteration's cost is mostly per render call, little per ray); ``reinit_iterations``/
    ``reinit_theta_starts``: that of a re-initialisation (multi-start, coarse-to-fine).
    """

    solver: str = "auto"
    # A Gauss-Newton frame's Jacobian (EstimateOptions.jacobian), with depth and without: by differences, the
    # lamp's track followed its three joints (the field's derivatives stalled, and the track ran off by
    # centimetres), and a model whose thin jaw the derivatives lost was held (docs/benchmarks.md, session 53).
    jacobian: str = "differences"
    # Without depth neither wins everywhere (the lamp's track needs the differences; the clamp's and the pliers' fare
    # worse with them): "auto" takes what the model's tracker calibration measured on its own sequences
    # (:func:`calibrated_jacobian`), else :data:`JACOBIAN_RGB`.
    jacobian_rgb: str = "auto"
    # With depth, a Gauss-Newton frame's later iterations keep its first Jacobian (EstimateOptions.jacobian_once):
    # one linearisation a frame, at the same error (docs/benchmarks.md, session 55); without depth the tracks
    # drifted off with it.
    jacobian_once: bool = True
    iterations: int = 0
    rays_per_iteration: int = 0
    # With depth, a frame's Huber scale (EstimateOptions.robust_scale, residual units): 0 (the default) for a Gauss-Newton
    # frame the one the model's tracker calibration chose (:data:`WIDE_HUBER` or the preset's), else the preset's.
    robust_scale: float = 0.0
    lr_pose: float = 0.003  # Adam moves every parameter by about its rate per step: small, from a close start
    lr_theta: float = 0.01
    lr_decay: float = 0.5
    silhouette_weight: float = 1.0  # Adam's, with depth (Gauss-Newton: its preset's)
    ray_sampling: str = "uniform"
    # Without depth the silhouette's scale is the main cue to distance: it weighs more in Adam's loss, and
    # half the rays go near the mask's edges and image gradients ("edges"), where a distance error shows.
    silhouette_weight_rgb: float = 5.0
    ray_sampling_rgb: str = "edges"
    # Without depth, Adam's frames hold the box centre's distance from the camera to the prediction's by
    # this weight (refine_frame's distance_prior) where the mask's box is at most the preset's reference size: there
    # the silhouette's scale alone lets it wander; in a larger box it pins the distance well enough.
    distance_prior_rgb: float = 3.0
    # With depth, the prediction is first moved along the line of sight so that the model's surface
    # points meet the observed depth (depth_aligned): the iterations' fixed step sizes alone let the
    # track lag behind the object's motion in depth.
    depth_align: bool = True
    # With depth, the (aligned) prediction is then fitted to the observed depth's points in pose and joints, this
    # many iterations of articulated ICP (narf_core/surface_fit.py; 0 = off): a thin part's joint moves the
    # photometric iterations' rays by a pixel or less a frame, and alone they fell behind the lamp's joints by a
    # degree a frame (docs/benchmarks.md, session 64).
    surface_fit_iterations: int = 3
    mode: str = "auto"  # the render mode (narf_core/modes.py)
    # "frame": where a ray can meet the object is found once per frame, from the model's surface
    # points at the prediction, and no iteration marches (refine_frame; narf mode, band_m 0);
    # "iteration": the refiner marches its rays at every iteration (refine), as with band_m or parts mode.
    march: str = "frame"
    band_m: float = 0.0  # march only this far around the model's surface (EstimateOptions.band_m); 0 = off
    eval_rays: int = 512  # rays of the final loss (only reported: one start, nothing to choose between)
    # A warm-started frame's occluder test (EstimateOptions.occlusion_margin, metres; never at a
    # re-initialisation). Off: the robust preset's 1 cm drifted the track (docs/benchmarks.md).
    occlusion_margin: float = 0.0
    uncertainty_rays: int = 256  # rays for Σ per frame; 0 = no Σ
    # A warm-started frame's σ over the single-image refiner's, with depth (sigma_scale_rgb: without): a
    # few iterations from a prediction leave a part of the error that a converged estimate's Σ does not
    # model. 0 (the default): the model's own factor where its bundle has one (metadata["uncertainty"]
    # ["track"], from benchmarks/calibration.py), else SIGMA_SCALE's pooled one; see sigma_scale().
    sigma_scale: float = 0.0
    sigma_scale_rgb: float = 0.0  # without depth
    # With depth, the colour residual up to which the refiner's model error is in pixel footprints alone
    # (EstimateOptions.uncertainty_usual_residual); above it σ grows with the residual, which there marks a
    # track turning away, or colours the model was not trained on (another renderer's light, a camera's
    # noise): on our renderer's sequences the residual stays below it in most frames (its 90th percentile
    # 0.005-0.017 on four tools), and σ with it.
    # Path-traced frames sit at 0.03-0.06 with errors five times our renderer's, and σ grown from 0.02
    # left up to a fifth of them outside the 95 % region (docs/benchmarks.md, session 61). Without depth the
    # refiner's Σ is kept (the residual follows the error there).
    usual_residual: float = 0.014
    # With depth, the silhouette's mean squared misfit up to which σ does not grow with it
    # (EstimateOptions.uncertainty_usual_silhouette): above it a mask the model's outline disagrees with
    # (a segmenter's, an occluder's edge) widens the region, whose colours alone did not (0: off).
    usual_silhouette: float = 0.02
    # With depth, a warm-started frame whose Σ passed the limits below (its colour residual far above
    # usual_residual) gets a second round of iterations from where the first ended, before its status.
    retry_uncertain: bool = True
    reinit_solver: str = "robust"
    reinit_iterations: int = 100
    reinit_theta_starts: int = 4
    # The track's first frame (track()): "multi-start" refines the caller's pose and joints, a rough
    # guess, as a re-initialisation does; "warm" takes them as exact (a label, a fixture's pose) and
    # tracks the frame as a warm-started one from them, at rest (the multi-start only if it fails).
    first_frame: str = "multi-start"
    velocity_smoothing: float = 0.6  # weight of the newest velocity measurement
    # Without depth, that weight for the box centre's motion along the line of sight (0: the prediction
    # keeps the last estimate's distance). There the distance is the silhouette's scale, measured anew
    # each frame with an error of millimetres to centimetres: its differences, carried forward, drove
    # the pliers' tracks into oscillations of several centimetres (docs/benchmarks.md).
    velocity_smoothing_along_rgb: float = 0.0
    # Without depth, a Gauss-Newton frame is held to the prediction by a Gaussian prior of these σ (the box
    # centre's position per camera axis, the rotation about it per axis; either 0: off): a turn out of the
    # image plane and the distance are what the silhouette barely sees, and unheld, a frame's long steps
    # there on one draw of rays now and then set a track off by several centimetres (docs/benchmarks.md).
    frame_prior_position_m_rgb: float = 0.005
    frame_prior_rotation_deg_rgb: float = 1.0
    # With depth, the same prior, looser: the rotation about a thin tool's long axis is what the depth of a
    # few pixels' width barely sees, and unheld it now and then ran off by tens of degrees (docs/benchmarks.md).
    frame_prior_position_m: float = 0.01
    frame_prior_rotation_deg: float = 5.0
    # With depth, a joint whose moved parts the mask hardly shows at the prediction (an occluder over them, a missed
    # blob; estimate.HIDDEN_SHARE) is held to its prediction by the prior above with this σ, a share of its half
    # range (0: free). The occluder's rays carry no residual (occluder_test), and unheld the joint wandered anywhere
    # out of sight; without depth those rays still pull it and the hold did not pay (docs/benchmarks.md, session 56).
    hidden_joint_sigma: float = 0.02
    # Without depth, the track carries a colour gain per channel: each tracked frame's fit at its estimate
    # (colour_gain_at) moves it by this share (its first frames by 1/n). 0 = off.
    colour_rate_rgb: float = 0.2
    # ... and once a channel's is this far from one, the render's colour is compared times it. A light, exposure
    # or white balance other than the training views' (gains of 0.7-1.7 on path-traced views) otherwise pulls a
    # thin tool's track towards poses that hide the mismatch; the models' own colour is within 5 % of their
    # training renderer's, and a correction that small sets as many tracks off as it saves (docs/benchmarks.md,
    # session 38).
    colour_gate_rgb: float = 0.1
    # Without depth, a warm-started frame weighs its rays outside the mask this much (EstimateOptions.mask_trust
    # "partial", no edge band): there an occluder may hide the tool, and without depth nothing tells it from the
    # background. 0.3 holds the pliers' tracks under an occluder that stays over one end (160x120, 2.7-4.3 cm ->
    # 1.1-2.3), but costs the clamp and a segmenter's faulty masks (docs/benchmarks.md, session 38): for a view
    # where a hand or a fixture stays in front of the tool. 1 (the default) = the mask trusted in full.
    outside_weight_rgb: float = 1.0
    # With depth, a frame's rays outside the mask where the observed depth stands in front of the render (an
    # occluder) carry no residual (DEPTH_MASK_TRUST); off: the mask trusted in full (to compare).
    occluder_test: bool = True
    max_gap_s: float = 0.25  # longer since the last estimate: no prediction, re-initialise
    # Longer since the last estimate (or lost after an `uncertain` or `reinitialised` frame): re-initialise
    # by detection (every orientation scored, the best refined; narf_core/detect.py) instead of the
    # multi-start refiner from the last pose. 0 = never.
    redetect_after_s: float = 0.5
    # Without depth, the detector runs only after redetect_after_s away (then once per redetect_after_s
    # while lost: a detection costs seconds) and where the multi-start refiner from the last pose does not
    # explain the mask (the silhouette cannot tell a flat tool's turns apart;
    # right after an `uncertain` frame it turned a track over), and its distance comes from
    # the silhouette's size, which a mask cut by the image's border or by an occluder makes small: not where
    # the mask touches the border, and its answer is kept only within this factor of the last estimate's
    # distance (a lost track's distance may be tens of per cent off). 0 = never without depth
    # (docs/benchmarks.md).
    redetect_rgb_distance: float = 2.0
    # With depth, a re-detection turned more than this (degrees) from the last estimate is checked against the
    # multi-start refiner from that estimate, and the lower loss is kept: a flat tool turned over about its long
    # axis looks much the same, and under an occluder and a segmenter's faults the turned-over pose can score best
    # among the detector's orientations where the track was a centimetre or two off (docs/benchmarks.md, session
    # 39). 180 = never.
    redetect_turn_deg: float = 90.0
    # Without depth, a track lost for longer than this since its last estimate runs the multi-start
    # refiner from its last pose (a second or two per frame on 2 cores) once per this many seconds and
    # not at every frame between (a frame of redetect_after_s's schedule still runs it). 0 = at every lost frame.
    reinit_period_s_rgb: float = 0.1
    lost_overlap: float = 0.35
    uncertain_overlap: float = 0.6
    # A re-initialisation from a view that may show only part of the object (a mask that touches the image's
    # border, or the frame after an `uncertain` one: an occluder coming over it) is kept only where it explains
    # this share of the mask, else the frame is lost: a part fits many poses, and re-initialisations that
    # explained 67-71 % of such masks were 12-20 cm off (docs/benchmarks.md, session 39).
    reinit_partial_overlap: float = 0.9
    # Σ includes the model's error (estimate.model_error): a good 160x120 frame at 0.6 m has σ 5-10 mm.
    max_position_sigma_m: float = 0.02
    max_rotation_sigma_deg: float = 10.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_option_types(self, TrackInputError)
        need = option_rule(self, TrackInputError)
        need(self.iterations >= 0, "iterations", "must be >= 0 (0 = the solver's own)")
        need(self.rays_per_iteration >= 0, "rays_per_iteration", "must be >= 0 (0 = the solver's own)")
        need(self.robust_scale >= 0, "robust_scale", "must be >= 0 (0 = the model's own or the preset's)")
        need(self.reinit_iterations >= 1, "reinit_iterations", "must be >= 1")
        need(0 <= self.surface_fit_iterations <= 100, "surface_fit_iterations", "must be in [0, 100] (0 = off)")
        need(1 <= self.reinit_theta_starts <= 64, "reinit_theta_starts", "must be in [1, 64]")
        need(self.first_frame in FIRST_FRAMES, "first_frame", f"must be one of {', '.join(FIRST_FRAMES)}")
        need(0 < self.velocity_smoothing <= 1, "velocity_smoothing", "must be in (0, 1]")
        need(0 <= self.velocity_smoothing_along_rgb <= 1, "velocity_smoothing_along_rgb", "must be in [0, 1]")
        need(self.frame_prior_position_m_rgb >= 0, "frame_prior_position_m_rgb", "must be >= 0 (0 = off)")
        need(self.frame_prior_rotation_deg_rgb >= 0, "frame_prior_rotation_deg_rgb", "must be >= 0 (0 = off)")
        need(self.frame_prior_position_m >= 0, "frame_prior_position_m", "must be >= 0 (0 = off)")
        need(self.frame_prior_rotation_deg >= 0, "frame_prior_rotation_deg", "must be >= 0 (0 = off)")
        need(self.hidden_joint_sigma >= 0, "hidden_joint_sigma", "must be >= 0 (0 = off)")
        need(0 <= self.colour_rate_rgb <= 1, "colour_rate_rgb", "must be in [0, 1] (0 = off)")
        need(0 <= self.colour_gate_rgb < 1, "colour_gate_rgb", "must be in [0, 1)")
        need(0 <= self.outside_weight_rgb <= 1, "outside_weight_rgb", "must be in [0, 1] (1 = the mask trusted in full)")
        need(self.max_gap_s > 0, "max_gap_s", "must be > 0")
        need(self.redetect_after_s >= 0, "redetect_after_s", "must be >= 0 (0 = never)")
        need(self.redetect_rgb_distance == 0 or self.redetect_rgb_distance > 1, "redetect_rgb_distance",
             "must be > 1 (a factor) or 0 (never without depth)")
        need(0 <= self.redetect_turn_deg <= 180, "redetect_turn_deg", "must be in [0, 180] degrees (180 = never)")
        need(self.reinit_period_s_rgb >= 0, "reinit_period_s_rgb", "must be >= 0 (0 = at every lost frame)")
        need(0 <= self.lost_overlap <= self.uncertain_overlap <= 1, "lost_overlap",
             "must satisfy 0 <= lost_overlap <= uncertain_overlap <= 1")
        need(0 <= self.reinit_partial_overlap <= 1, "reinit_partial_overlap", "must be in [0, 1]")
        need(self.solver in TRACK_SOLVERS, "solver", f"must be one of {', '.join(TRACK_SOLVERS)}")
        need(self.jacobian in JACOBIANS, "jacobian", f"must be one of {', '.join(JACOBIANS)}")
        need(self.jacobian_rgb in ("auto", *JACOBIANS), "jacobian_rgb", f"must be one of auto, {', '.join(JACOBIANS)}")
        need(self.reinit_solver in ("robust", "gauss-newton"), "reinit_solver", "must be 'robust' or 'gauss-newton'")
        need(self.uncertainty_rays >= 0, "uncertainty_rays", "must be >= 0")
        need(self.sigma_scale >= 0, "sigma_scale", "must be >= 0 (0 = the model's own)")
        need(self.sigma_scale_rgb >= 0, "sigma_scale_rgb", "must be >= 0 (0 = the model's own)")
        need(self.usual_residual >= 0, "usual_residual", "must be >= 0")
        need(self.usual_silhouette >= 0, "usual_silhouette", "must be >= 0 (0 = off)")
        need(self.silhouette_weight >= 0, "silhouette_weight", "must be >= 0")
        need(self.silhouette_weight_rgb >= 0, "silhouette_weight_rgb", "must be >= 0")
        need(self.distance_prior_rgb >= 0, "distance_prior_rgb", "must be >= 0")
        need(self.occlusion_margin >= 0, "occlusion_margin", "must be >= 0")
        for name in ("ray_sampling", "ray_sampling_rgb"):
            need(getattr(self, name) in ("uniform", "stratified", "edges"), name,
                 "must be 'uniform', 'stratified' or 'edges'")
        need(self.mode in MODES, "mode", f"must be one of {', '.join(MODES)}")
        need(self.band_m == 0 or 0.001 <= self.band_m <= 1, "band_m", "must be 0 (off) or in [0.001, 1] metres")
        need(self.eval_rays >= 16, "eval_rays", "must be >= 16")
        need(self.march in MARCHES, "march", f"must be one of {', '.join(MARCHES)}")

    def solver_for(self, depth: bool) -> str:
        """A warm-started frame's solver, with ``depth`` or without."""
        return AUTO_SOLVER["rgbd" if depth else "rgb"] if self.solver == "auto" else self.solver

    def jacobian_for(self, depth: bool, model: NarfModel | None = None) -> str:
        """A Gauss-Newton frame's Jacobian with ``depth`` or without, on ``model`` (``jacobian_rgb`` "auto": its
        calibration's choice, else :data:`JACOBIAN_RGB`)."""
        if depth:
            return self.jacobian
        if self.jacobian_rgb != "auto":
            return self.jacobian_rgb
        return (calibrated_jacobian(model, "rgb") if model is not None else None) or JACOBIAN_RGB

    def rays_for(self, depth: bool, device: torch.device | str = "cpu", model: NarfModel | None = None) -> int:
        """A frame's rays per iteration with ``depth`` or without, on ``device`` and ``model``: the option where
        set, else on a GPU :data:`GPU_RAYS`, else with depth the rays ``model``'s calibration chose
        (:func:`calibrated_rays`, a Gauss-Newton frame's), else :data:`BUDGETS`'."""
        if self.rays_per_iteration:
            return self.rays_per_iteration
        solver = self.solver_for(depth)
        if torch.device(device).type == "cuda" and solver in GPU_RAYS:
            return GPU_RAYS[solver]
        own = calibrated_rays(model) if depth and solver == "gauss-newton" else None
        return own or BUDGETS[solver][1]

    def huber_for(self, depth: bool, model: NarfModel | None = None) -> float | None:
        """A frame's Huber scale with ``depth`` or without, on ``model``: with depth the option where set, else for a
        Gauss-Newton frame the one ``model``'s calibration chose (:func:`calibrated_huber`); None: the preset's."""
        if not depth:
            return None
        if self.robust_scale:
            return self.robust_scale
        return calibrated_huber(model) if self.solver_for(depth) == "gauss-newton" else None

    def step_options(self, depth: bool, device: torch.device | str = "cpu",
                     model: NarfModel | None = None) -> EstimateOptions:
        """The refiner's options for a warm-started frame on ``model`` on ``device`` (from the prediction
        alone: a frame that misses is the re-initialisation's to find, so no pose starts and no slide along
        the object's axis)."""
        solver = self.solver_for(depth)
        iterations = BUDGETS[solver][0]
        if not depth:
            iterations = RGB_ITERATIONS.get(solver, iterations)
        common = {"iterations": self.iterations or iterations, "rays_per_iteration": self.rays_for(depth, device, model),
                  "mode": self.mode,
                  "theta_starts": 1, "coarse_to_fine": 1, "early_stop": False, "seed": self.seed,
                  "band_m": self.band_m, "eval_rays": self.eval_rays,
                  "ray_sampling": self.ray_sampling if depth else self.ray_sampling_rgb,
                  "uncertainty": self.uncertainty_rays > 0, "uncertainty_rays": max(self.uncertainty_rays, 16),
                  "uncertainty_usual_residual": self.usual_residual if depth else 0.0,
                  "uncertainty_usual_silhouette": self.usual_silhouette if depth else 0.0,
                  "uncertainty_trained_footprint": depth, "uncertainty_rotation_shape": True,
                  "occlusion_margin": self.occlusion_margin, "refinements": 0, "rgb_refinements": 0, "rgb_polish": 0,
                  "pose_starts": 1, "search_theta_starts": 0, "slide_share": 0.0,
                  "surface_fit_iterations": 0, "surface_polish_iterations": 0,  # the tracker fits on its own
                  "jacobian": self.jacobian_for(depth, model), "jacobian_once": self.jacobian_once and depth}
        if depth:
            common.update(DEPTH_MASK_TRUST if self.occluder_test else {"mask_trust": "full"})
            if (huber := self.huber_for(depth, model)) is not None:
                common["robust_scale"] = huber
        elif self.outside_weight_rgb < 1:
            common.update(mask_trust="partial", mask_band_px=0, outside_weight=self.outside_weight_rgb,
                          partial_theta_starts=0)
        if solver != "adam":
            return EstimateOptions.preset(solver, **common)
        return EstimateOptions.preset("robust", lr_pose=self.lr_pose, lr_theta=self.lr_theta, lr_decay=self.lr_decay,
                                      silhouette_weight=self.silhouette_weight if depth else self.silhouette_weight_rgb,
                                      **common)

    def reinit_options(self) -> EstimateOptions:
        """The multi-start refiner's options for a re-initialisation. No occluder test
        (``occlusion_margin``): from a start centimetres off, the observed depth lies in front of the
        render on the very rays that would pull the object in (on the bundled clamp's first frame
        from a rough pose: ADD 3.9 cm with the preset's 1 cm margin, 0.8 cm without)."""
        return EstimateOptions.preset(self.reinit_solver, iterations=self.reinit_iterations, mode=self.mode,
                                      theta_starts=self.reinit_theta_starts, seed=self.seed, band_m=self.band_m,
                                      uncertainty=self.uncertainty_rays > 0, uncertainty_rays=max(self.uncertainty_rays, 16),
                                      occlusion_margin=0.0, refinements=0, rgb_refinements=0, rgb_polish=0)


@dataclass
class TrackFrame:
    """One observation: ``image [H,W,3]`` uint8, ``mask [H,W]`` (None = no mask this frame),
    ``depth [H,W]`` metres (None = RGB only) at ``time`` seconds."""

    image: np.ndarray
    mask: np.ndarray | None
    time: float
    depth: np.ndarray | None = None


@dataclass
class TrackState:
    """What the tracker carries from one frame to the next.

    ``T_cam_obj [4,4]`` and ``joints``: the last estimate, made at ``anchor_time``; ``time``: the
    last frame seen; ``velocity [6]``: the box centre's velocity (m/s) and the angular velocity
    (rad/s), camera axes; ``joint_velocity``: per joint, units per second; ``covariance``
    ``[6+k, 6+k]`` or None; ``status``: the last frame's; ``lost_frames``: frames since the last
    estimate that stood; ``colour_gain [3]``: the colour gain the track carries without depth, fitted on
    ``colour_frames`` frames so far (``TrackOptions.colour_rate_rgb``, ``colour_gate_rgb``).
    """

    T_cam_obj: np.ndarray
    joints: dict[str, float]
    time: float
    anchor_time: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(6))
    joint_velocity: dict[str, float] = field(default_factory=dict)
    covariance: np.ndarray | None = None
    status: str = "tracking"
    lost_frames: int = 0
    colour_gain: np.ndarray = field(default_factory=lambda: np.ones(3))
    colour_frames: int = 0

    @classmethod
    def initial(cls, model: NarfModel, T_cam_obj: np.ndarray, joints: Mapping[str, float] | None, time: float,
                status: str = "lost") -> TrackState:
        """A state at rest at ``T_cam_obj`` and ``joints`` (missing joints at mid-range), just before
        ``time``; ``lost`` by default, so that the first frame is found by the multi-start refiner."""
        theta = _joints(model, joints, "joints")
        pose = _pose(T_cam_obj, "T_cam_obj")
        t = _finite(time, "time")
        return cls(pose, theta, t - 1e-6, t, status=status)

    def check(self, model: NarfModel) -> None:
        """Raise :class:`TrackInputError` for a state that cannot be tracked from (non-finite, wrong joints)."""
        _pose(self.T_cam_obj, "state.T_cam_obj")
        _finite(self.time, "state.time")
        _finite(self.anchor_time, "state.anchor_time")
        v = np.asarray(self.velocity, dtype=np.float64)
        if v.shape != (6,) or not np.isfinite(v).all():
            raise TrackInputError("state.velocity must be 6 finite numbers")
        names = [j.name for j in model.joints]
        if sorted(self.joints) != sorted(names):
            raise TrackInputError(f"state.joints must name exactly the model's joints {names}")
        for name, value in [*self.joints.items(), *self.joint_velocity.items()]:
            _finite(value, f"state.joints.{name}")
        if self.covariance is not None and not np.isfinite(np.asarray(self.covariance)).all():
            raise TrackInputError("state.covariance must be finite")
        if self.status not in STATUSES:
            raise TrackInputError(f"state.status must be one of {', '.join(STATUSES)}, got {self.status!r}")
        gain = np.asarray(self.colour_gain, dtype=np.float64)
        if gain.shape != (3,) or not (np.isfinite(gain).all() and (gain >= GAIN_RANGE[0]).all()
                                      and (gain <= GAIN_RANGE[1]).all()):
            raise TrackInputError(f"state.colour_gain must be 3 numbers in [{GAIN_RANGE[0]}, {GAIN_RANGE[1]}]")
        if not isinstance(self.colour_frames, int) or self.colour_frames < 0:
            raise TrackInputError("state.colour_frames must be an integer >= 0")


@dataclass
class TrackResult:
    """One frame's answer: its ``time``, ``status``, the estimate (for ``lost``: the last one that
    stood), the uncertainty (``position_sigma_m``, ``rotation_sigma_rad``, ``joint_sigma``) where
    known, ``overlap`` (None when not measured), the refiner's ``loss`` and ``iterations``, the
    wall-clock ``seconds``, for ``lost``/``reinitialised``/``uncertain`` a ``reason``, and the estimate's
    ``warnings`` (``"<code>: <message>"``: the input checks' doubts, ``unobserved_joint``)."""

    time: float
    status: str
    T_cam_obj: np.ndarray
    joints: dict[str, float]
    overlap: float | None
    loss: float | None
    iterations: int
    seconds: float
    reason: str | None = None
    uncertainty: dict | None = None
    covariance: np.ndarray | None = None
    mode: str | None = None  # the render mode the refiner used (``options.mode``, ``auto`` resolved) and why
    mode_reason: str | None = None
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "time": self.time, "status": self.status, "T_cam_obj": np.asarray(self.T_cam_obj).tolist(),
            "joints": dict(self.joints), "overlap": self.overlap, "loss": self.loss, "iterations": self.iterations,
            "seconds": self.seconds, "reason": self.reason, "uncertainty": self.uncertainty,
            "mode": self.mode, "mode_reason": self.mode_reason, "warnings": list(self.warnings),
        }


# --------------------------------------------------------------------------------------------
# checks


# The core's rules (narf_core/checks.py), raising TrackInputError.
_finite = partial(check_number, error=TrackInputError)
_pose = partial(check_pose, error=TrackInputError)


def _joints(model: NarfModel, joints: Mapping[str, float] | None, name: str) -> dict[str, float]:
    return model.joint_dict(model.kinematics.joint_vector(joints, field=name, error=TrackInputError))


# --------------------------------------------------------------------------------------------
# motion model


def _centre(model: NarfModel) -> np.ndarray:
    """The object's box centre ``[3]`` in its frame."""
    box = model.aabb.double().cpu().numpy()
    return (box[0] + box[1]) / 2


def predict(model: NarfModel, state: TrackState, time: float) -> tuple[np.ndarray, dict[str, float]]:
    """``T_cam_obj`` and joints at ``time`` under constant velocity from the state's estimate
    (the box centre moves straight, the object turns about it; joints stay within their limits)."""
    dt = time - state.anchor_time
    T = np.array(state.T_cam_obj, dtype=np.float64)
    c_obj = _centre(model)
    centre = T[:3, :3] @ c_obj + T[:3, 3] + state.velocity[:3] * dt
    R = so3_exp(torch.from_numpy(state.velocity[3:] * dt)).numpy() @ T[:3, :3]
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, centre - R @ c_obj
    joints = {}
    for j in model.joints:
        value = state.joints[j.name] + state.joint_velocity.get(j.name, 0.0) * dt
        joints[j.name] = float(min(max(value, j.lower), j.upper))
    return out, joints


def _velocity(model: NarfModel, before: TrackState, T: np.ndarray, dt: float) -> np.ndarray:
    """The box centre's velocity and the angular velocity ``[6]`` from ``before``'s estimate to ``T``."""
    c_obj = _centre(model)
    T0 = before.T_cam_obj
    v = ((T[:3, :3] @ c_obj + T[:3, 3]) - (T0[:3, :3] @ c_obj + T0[:3, 3])) / dt
    w = so3_log(torch.from_numpy(T[:3, :3] @ T0[:3, :3].T)).numpy() / dt
    return np.concatenate([v, w])


def _blended_velocity(model: NarfModel, before: TrackState, T: np.ndarray, dt: float, weight: float,
                      along_weight: float) -> np.ndarray:
    """``before``'s velocity ``[6]`` moved towards the one measured from its estimate to ``T``: by
    ``weight``, and the box centre's motion along the line of sight to ``T``'s centre by ``along_weight``."""
    old = np.asarray(before.velocity, dtype=np.float64)
    new = _velocity(model, before, T, dt)
    out = weight * new + (1 - weight) * old
    centre = T[:3, :3] @ _centre(model) + T[:3, 3]
    view = centre / max(float(np.linalg.norm(centre)), 1e-12)
    along = along_weight * float(new[:3] @ view) + (1 - along_weight) * float(old[:3] @ view)
    out[:3] += (along - float(out[:3] @ view)) * view
    return out


# --------------------------------------------------------------------------------------------
# overlap: the model's surface points against the mask


def _pixels(camera: Pinhole, x_cam: np.ndarray) -> np.ndarray:
    """The pixels ``[N, 2]`` (u, v, float) of camera-frame points ``x_cam [N, 3]`` in front of the camera."""
    uv = x_cam @ camera.K.detach().double().cpu().numpy().T
    return uv[:, :2] / uv[:, 2:3]


def _surface_points_cam(model: NarfModel, T_cam_obj: np.ndarray, joints: Mapping[str, float]) -> np.ndarray:
    """The model's surface points ``[N, 3]`` in the camera frame, those in front of the camera."""
    theta = model.kinematics.joint_vector(joints)
    links = model.kinematics.link_poses(theta).double().numpy()
    points = []
    for i, name in enumerate(model.links):
        p = model.sample_points.get(name)
        if p is not None and len(p):
            points.append(np.asarray(p, dtype=np.float64) @ links[i, :3, :3].T + links[i, :3, 3])
    if not points:
        return np.zeros((0, 3))
    x = np.concatenate(points) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    return x[x[:, 2] > 1e-6]


def overlap(model: NarfModel, camera: Pinhole, mask: np.ndarray, T_cam_obj: np.ndarray, joints: Mapping[str, float],
            depth: np.ndarray | None = None) -> float:
    """``min(inside, covered)`` of the projected surface points and the mask (see the module docstring); with a
    ``depth`` image [H, W] (metres, 0 = no return), ``inside`` leaves out the points off the mask that a reading
    stands over ``estimate._BEHIND_M`` in front of (an occluder's, which the mask leaves out with what it hides)."""
    from narf_core.estimate import _BEHIND_M

    mask = np.asarray(mask) != 0
    h, w = mask.shape
    n_mask = int(mask.sum())
    x = _surface_points_cam(model, T_cam_obj, joints)
    if n_mask == 0 or len(x) == 0:
        return 0.0
    px = np.floor(_pixels(camera, x)).astype(np.int64)
    in_image = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    spacing = max(1, int(math.ceil(math.sqrt(n_mask / max(1, int(in_image.sum()))))))
    if not in_image.any():
        return 0.0
    px, z = px[in_image], x[in_image, 2]
    behind = np.zeros(len(px), dtype=bool)  # behind a nearer reading
    if depth is not None:
        reading = np.asarray(depth, dtype=np.float64)[px[:, 1], px[:, 0]]
        behind = (reading > 0) & (reading < z - _BEHIND_M)
    # The same sums on the crop around the mask and the points, grown by the widest dilation (nothing
    # outside it is set or reached), instead of the whole image.
    v, u = np.nonzero(mask)
    u0, v0 = max(0, min(u.min(), px[:, 0].min()) - spacing - 1), max(0, min(v.min(), px[:, 1].min()) - spacing - 1)
    u1, v1 = min(w, max(u.max(), px[:, 0].max()) + spacing + 2), min(h, max(v.max(), px[:, 1].max()) + spacing + 2)
    mask, px = mask[v0:v1, u0:u1], px - np.array([u0, v0])
    grown = dilate(mask, max(1, spacing // 2))
    on_mask = grown[px[:, 1], px[:, 0]]
    seen = on_mask | ~behind  # an occluder's points off the mask say nothing
    if not seen.any():
        return 0.0
    inside = float(on_mask.sum()) / int(seen.sum())  # the image shows no more
    splat = np.zeros_like(mask)
    splat[px[:, 1], px[:, 0]] = True
    covered = float((dilate(splat, spacing) & mask).sum()) / n_mask
    return min(inside, covered)


def colour_gain_at(model: NarfModel, camera: Pinhole, image: np.ndarray, mask: np.ndarray, T_cam_obj: np.ndarray,
                   joints: Mapping[str, float], *, mode: str = "narf", rays: int = COLOUR_RAYS,
                   seed: int = 0) -> np.ndarray | None:
    """The gain per channel ``[3]`` that maps the model's colour at an estimate (``T_cam_obj``, ``joints``)
    onto ``image``'s (uint8 ``[H, W, 3]``), fitted on up to ``rays`` pixels of ``mask`` drawn with ``seed``
    (:func:`narf_core.estimate.colour_gain`); None where fewer than 16 pixels qualify."""
    v, u = np.nonzero(np.asarray(mask) != 0)
    if len(u) < 16:
        return None
    pick = np.sort(np.random.default_rng(seed).choice(len(u), min(rays, len(u)), replace=False))
    device = model.aabb.device
    cam = Pinhole(camera.K.detach().to(device, torch.float32), camera.width, camera.height)
    rays_cam = cam.rays(torch.from_numpy(np.stack([u[pick], v[pick]], -1)).to(device))
    T = torch.as_tensor(np.asarray(T_cam_obj), dtype=torch.float32, device=device)
    with torch.no_grad():
        out = model.render_rays(_object_rays(rays_cam, T[None]), model.joint_vector(joints).to(device, torch.float32),
                                mode=mode, outputs=("rgb", "opacity"))
    observed = torch.as_tensor(np.asarray(image)[v[pick], u[pick]], dtype=torch.float64) / 255
    rgb, opacity = out.rgb.detach().double().cpu()[None], out.opacity.detach().double().cpu()[None]
    ones = torch.ones(len(pick), dtype=torch.float64)
    if int((opacity > 0.5).sum()) < 16:
        return None
    return colour_gain(rgb, opacity, observed, ones, ones[None].bool())[0].numpy()


# --------------------------------------------------------------------------------------------
# the prediction's distance, from the depth image


def depth_offset(model: NarfModel, camera: Pinhole, T_cam_obj: np.ndarray, joints: Mapping[str, float],
                 mask: np.ndarray, depth: np.ndarray, min_cells: int = 20) -> float | None:
    """How far (m, along z) the observed surface lies behind the model's at ``T_cam_obj``, over the
    image's cells (square, a pixel unless the mask has more pixels than surface points project into
    the image) where both the mask's depth and a surface point the camera sees (:func:`_front_cells`)
    lie: the nearest observed depth minus the nearest point's, its median taken again
    (``_DEPTH_ROUNDS`` times) over the differences within ``_DEPTH_WINDOW_M`` of the last one. None
    where fewer than ``min_cells`` cells have both (where fewer than that are seen, every cell with a
    point counts).

    The surface points stand in for a render (no field evaluation); they are sparse, so in some
    cells only a point of the far side or of a part inside lands, centimetres behind: a tail that
    would pull a plain median towards the camera. On a thin tool the window leaves it out; on a deep
    object (a cabinet, its drawers inside) such cells are most of them, and only the visibility test
    does."""
    x = _surface_points_cam(model, T_cam_obj, joints)
    h, w = mask.shape
    px = np.floor(_pixels(camera, x)).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    cell = max(1, math.ceil(_DEPTH_CELL * math.sqrt(int(mask.sum()) / max(1, int(inside.sum())))))
    rows, cols = -(-h // cell), -(-w // cell)
    nearest = np.full(rows * cols, np.inf)
    np.minimum.at(nearest, (px[inside, 1] // cell) * cols + px[inside, 0] // cell, x[inside, 2])
    observed = np.where(mask & np.isfinite(depth) & (depth > 0), depth, np.inf)
    observed = np.pad(observed, ((0, rows * cell - h), (0, cols * cell - w)), constant_values=np.inf)
    observed = observed.reshape(rows, cell, cols, cell).min(axis=(1, 3)).reshape(-1)
    both = np.isfinite(nearest) & np.isfinite(observed)
    seen = both & _front_cells(nearest.reshape(rows, cols), cell / float(camera.K[0, 0])).reshape(-1)
    if int(seen.sum()) >= min_cells:
        both = seen
    elif int(both.sum()) < min_cells:
        return None
    difference = observed[both] - nearest[both]
    offset = float(np.median(difference))
    for _ in range(_DEPTH_ROUNDS):
        near = difference[np.abs(difference - offset) < _DEPTH_WINDOW_M]
        offset = float(np.median(near)) if len(near) else offset
    return offset


def _front_cells(nearest: np.ndarray, cell_angle: float) -> np.ndarray:
    """Which cells of ``nearest [rows, cols]`` (the nearest surface point's z per cell, m; inf where
    none) hold a point the camera sees: one no more than ``_DEPTH_WINDOW_M`` plus a 45° surface's rise
    behind the nearest point within ``_DEPTH_HIDDEN_CELLS`` cells (a cell spans ``cell_angle`` rad, so
    its depth times that in metres). A cell whose points all lie on the far side or on a part inside
    has a nearer surface's point close by."""
    r = _DEPTH_HIDDEN_CELLS
    rows, cols = nearest.shape
    padded = np.pad(nearest, r, constant_values=np.inf)
    around = np.full_like(nearest, np.inf)
    for dv in range(2 * r + 1):
        for du in range(2 * r + 1):
            np.minimum(around, padded[dv:dv + rows, du:du + cols], out=around)
    return nearest <= around + _DEPTH_WINDOW_M + r * cell_angle * nearest


def depth_aligned(model: NarfModel, camera: Pinhole, T_cam_obj: np.ndarray, joints: Mapping[str, float],
                  mask: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``T_cam_obj [4,4]`` moved along the line of sight to the object's box centre by
    :func:`depth_offset` (unchanged where there is none, or the centre is behind the camera). A few Adam steps move the pose by a
    fixed rate each, so a prediction off by more along the line of sight than they reach leaves the
    track lagging behind the depth; this closes that gap before they start."""
    dz = depth_offset(model, camera, T_cam_obj, joints, mask, depth)
    centre = T_cam_obj[:3, :3] @ _centre(model) + T_cam_obj[:3, 3]
    if dz is None or not math.isfinite(dz) or centre[2] <= 0:
        return T_cam_obj
    out = np.array(T_cam_obj, dtype=np.float64)
    out[:3, 3] += dz * centre / centre[2]
    return out


# --------------------------------------------------------------------------------------------
# one warm-started frame, without marching


def refine_frame(
    model: NarfModel,
    camera: Pinhole,
    image: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray | None,
    T_pred: np.ndarray,
    joints_pred: Mapping[str, float],
    options: EstimateOptions,
    distance_prior: float = 0.0,
    polish: bool = False,
    prior: tuple[float, float] | None = None,
    hidden_joint_sigma: float = 0.0,
    checks: list[str] | None = None,
) -> EstimateResult:
    """The refiner's iterations for a warm-started frame without marching, each ray sampled only in a
    band that is known for the whole frame: ``options.solver`` "adam", :func:`refine`'s loss on fresh
    rays at every iteration, or "gauss-newton", Levenberg-Marquardt on one set of rays
    (:class:`FrameProblem`).

    At the prediction (``T_pred``, ``joints_pred``) the model's surface points give every box pixel
    the depths where its ray can meet the object (:func:`narf_core.band.ray_band`, widened by
    ``_FRAME_MARGIN_M``, the prediction's error being a few millimetres; nothing where no point
    projects near it). An iteration takes the lattice samples of its rays in that band
    (:func:`frame_band`), keeps those the occupancy grid holds at the iteration's pose
    (:func:`occupied`) and evaluates the field there: no marching rounds, one field call; with
    depth (without it, only in a box larger than the reference box, :data:`~narf_core.estimate.ROBUST_BOX_PX`,
    whatever the preset's ``reference_box_px``: a finer camera where the silhouette pins the distance; at
    the reference size the RGB-only track is bistable and the pruning was not harmless, docs/benchmarks.md),
    only at those light reaches (:func:`visible`), so that the
    backward pass skips what lies behind the surface. The final loss (``options.eval_rays`` rays) and the covariance
    (``options.uncertainty_rays`` rays) take their samples the same way. ``narf`` mode; where the
    band cannot be trusted (surface points behind the camera) this is :func:`refine`.
    ``distance_prior`` (for a view without depth) adds that weight times the squared motion of the
    box centre along the line of sight, in object radii, to Adam's loss where the mask's box is no
    larger than ``options.reference_box_px``. ``polish`` (for a view without depth): every
    Gauss-Newton iteration polishes (:attr:`narf_core.gauss_newton.GaussNewtonRun.polish_only`);
    ``prior`` ``(σ position m, σ rotation rad)``: its iterations are held to the prediction, the box centre's
    position per camera axis and the rotation about it per axis (:meth:`~narf_core.gauss_newton.GaussNewtonRun.
    hold_to`), and with it a joint the mask hardly shows at the prediction (:func:`~narf_core.estimate.
    joint_mask_shares` under :data:`~narf_core.estimate.HIDDEN_SHARE`) by ``hidden_joint_sigma``, a share of its half
    range (0: the joints are free): what the view does not show of it cannot move it, nor should noise. ``checks``: the
    frame's input checks, already made (the tracker's step makes them before it aligns its prediction): not made
    again. ``options.mask_trust``
    "auto" means what it means to :func:`refine` (partial where the depth contradicts the mask, with its
    edge band); the tracker's own frames pass :data:`DEPTH_MASK_TRUST`'s options with depth.
    """
    from narf_core.band import ray_band
    from narf_core.compositing import composite
    from narf_core.estimate import (
        HIDDEN_SHARE, ROBUST_BOX_PX, _box_scale, _check_observation, _Loss, _mask_box, _object_rays, _observation,
        _overlaps, _Parameterisation, _partial_trust, _ray_index, _uncertainty, coarse_model, joint_mask_shares,
    )
    from narf_core.gauss_newton import GaussNewtonRun, Problem, cluster_sample
    from narf_core.geometry import pose_to_position_quaternion

    start = _time.perf_counter()
    image, mask, depth = _check_observation(image, mask, depth, camera)
    T0 = torch.from_numpy(check_pose(T_pred, "T_init", error=EstimateInputError))
    warnings = (list(checks) if checks is not None
                else check_observation(image, mask, depth, camera, expected_depth_m=float(T0[2, 3])))
    depth = usable_depth(depth, warnings)
    warnings += coarse_model(model, camera, depth)
    theta0 = model.kinematics.joint_vector(joints_pred, field="joints_init", error=EstimateInputError)
    device = model.aabb.device
    camera = Pinhole(camera.K.detach().to(device, torch.float32), camera.width, camera.height)
    box = _mask_box(mask, options.box_margin)
    scale = _box_scale(box, options)
    partial = _partial_trust(options, mask, depth)  # "auto" resolved as refine resolves it
    options = replace(options, mask_trust="partial" if partial else "full")
    obs = _observation(image, mask, depth, box, 1, device, options.mask_band_px if partial else 0)
    obs.scale = scale
    param = _Parameterisation.around(T0, model)
    uses_depth = depth is not None and options.depth_weight > 0
    prune = uses_depth or max(obs.shape) > ROBUST_BOX_PX  # keep only the samples light reaches (visible)

    def result(status: str, p: Tensor | None, loss: float | None, iterations: int = 0, trace=(),
               uncertainty=None, recovered: bool = False) -> EstimateResult:
        T, theta = (T0, theta0) if p is None else (param.poses(p)[0], param.thetas(p)[0])
        position, quaternion = pose_to_position_quaternion(T)
        return EstimateResult(T.numpy().copy(), position.numpy().copy(), quaternion.numpy().copy(),
                              param.joints(model, theta), loss, iterations, _time.perf_counter() - start, list(trace),
                              status, recovered, uncertainty=uncertainty, warnings=warnings)

    if not _overlaps(camera, obs.pixels, T0, model.aabb):
        return result("no_overlap", None, None)
    rays_box = camera.rays(obs.pixels.to(torch.float32))
    around = ray_band(model, camera, rays_box, T0[None], theta0[None], _FRAME_MARGIN_M)
    if around is None:
        return refine(model, image, mask, camera, T_pred, joints_init=joints_pred, depth=depth, options=options)
    near, far = (b.detach().double() for b in around)  # on the model's device, like the rays
    field, grid = model._field_for("narf", theta0.to(device, torch.float32))

    class FrameLoss(_Loss):
        """The refiner's loss, rendered from the band's samples of the rays (:attr:`index` into the box)."""

        index: Tensor

        def _render(self, rays_obj, theta, outputs, band=None):
            th = theta[0].to(rays_obj.origins)
            lattice = frame_band(near[self.index], far[self.index], model.step)
            samples = occupied(grid, rays_obj, lattice, th)
            if torch.is_grad_enabled() and prune:
                samples = visible(field, rays_obj, samples, th)
            out = composite(field, rays_obj, samples, theta=th, outputs=outputs)
            return out.rgb, out.opacity, out.depth

    loss_fn = FrameLoss(model, replace(options, band_m=0.0), param.radius, uses_depth)
    target = obs.levels[-1]
    rng = torch.Generator().manual_seed(options.seed)
    n_pixels = obs.pixels.shape[0]
    n_rays = min(round(scale * options.rays_per_iteration), n_pixels)

    view = param.T_centre[:3, 3] / param.T_centre[:3, 3].norm()  # the line of sight to the box centre

    def loss_at(p: Tensor, index: Tensor) -> Tensor:
        loss_fn.index = index
        loss = loss_fn(rays_box[index], target, index, param.poses(p), param.thetas(p))
        if distance_prior > 0 and scale == 1:  # the centre's motion along the line of sight, in object radii
            loss = loss + (distance_prior * (p[:, :3] @ view) ** 2).to(loss)
        return loss

    k = theta0.shape[0]
    p0 = torch.cat([torch.zeros(1, 6, dtype=torch.float64), param.u_of(theta0[None])], dim=1)
    if options.solver == "gauss-newton":  # Levenberg-Marquardt on one set of rays, their samples in the band
        problem = FrameProblem(model, options, param.radius, uses_depth, near=near, far=far, field=field, grid=grid,
                               prune=prune)
        run = GaussNewtonRun(problem, obs, camera, param, p0, start, options.seed)
        run.polish_only = polish
        if prior is not None:  # σ of the box centre's position (m, per camera axis) and its rotation (rad, per axis)
            sigma = torch.full((p0.shape[1],), math.inf, dtype=torch.float64)
            sigma[:3], sigma[3:6] = prior[0] / param.radius, prior[1]
            if hidden_joint_sigma > 0 and k:  # a hidden joint's σ in u, where θ = mid + half sin(u)
                hidden = joint_mask_shares(model, camera, T0, theta0, obs) < HIDDEN_SHARE
                sigma[6:] = torch.where(hidden, hidden_joint_sigma / torch.cos(p0[0, 6:]).clamp_min(1e-3), math.inf)
            run.hold_to(p0, sigma)
        run.optimise()
        candidates, trace, failures = (run.params, run.best_params), run.trace, int(run.recovered)
    else:
        candidates, trace, failures = _adam_steps(options, p0, loss_at, lambda: _ray_index(obs, options, n_rays, rng, True),
                                                  start)
    index = torch.arange(n_pixels) if n_pixels <= options.eval_rays else torch.randperm(n_pixels, generator=rng)[
        : options.eval_rays]
    final = None
    for candidate in candidates:
        if candidate is not None and final is None:
            with torch.no_grad():
                value = float(loss_at(candidate, index).sum())
            final = (candidate, value) if math.isfinite(value) else None
    if final is None:
        return result("non_finite", None, None, options.iterations, trace, recovered=True)
    p, loss = final
    uncertainty = None
    if options.uncertainty:
        T, theta = param.poses(p)[0], param.thetas(p)[0]
        index, cluster, weight = cluster_sample(obs.pixels.cpu(), obs.importance, options.uncertainty_patch,
                                                options.uncertainty_rays, torch.Generator().manual_seed(options.seed + 1))
        rays_obj, th = _object_rays(rays_box[index], T[None]), theta.to(rays_box.origins)
        lattice = occupied(grid, rays_obj, frame_band(near[index], far[index], model.step), th)
        lattice = visible(field, rays_obj, lattice, th) if prune else lattice
        problem = Problem(model, options, param.radius, uses_depth, samples=lattice)
        uncertainty = _uncertainty(model, options, obs, camera, param, T, theta, uses_depth, problem,
                                   (index, cluster, weight))
    return result("max_iterations", p, loss, options.iterations, trace, uncertainty, failures > 0)


def _adam_steps(options: EstimateOptions, p0: Tensor, loss_at, rays, start: float) -> tuple[tuple, list, int]:
    """``options.iterations`` Adam steps from ``p0 [1, d]`` on ``loss_at(p, index)``, fresh rays (``rays()``, an
    index into the box) at each; a non-finite step goes back to the last finite iterate at half the rate.
    Returns the candidates for the estimate (the last iterate, the last finite one), the trace and the
    number of recoveries."""
    from narf_core.estimate import _MAX_RECOVERIES, _Adam

    k = p0.shape[1] - 6
    adam = _Adam(p0.clone(), torch.tensor([options.lr_pose] * 6 + [options.lr_theta] * k, dtype=torch.float64))
    last_finite, rate, trace, failures = None, 1.0, [], 0
    for i in range(options.iterations):
        p = adam.params.clone().requires_grad_(True)
        loss = loss_at(p, rays())
        value = float(loss.detach().sum())
        grad = torch.autograd.grad(loss.sum(), p)[0] if loss.requires_grad else torch.zeros_like(p)
        if not (math.isfinite(value) and bool(torch.isfinite(grad).all())):
            failures += 1  # back to the last finite iterate, fresh moments, half the rate
            adam.params = p0.clone() if last_finite is None else last_finite.clone()
            adam.reset()
            rate *= 0.5
            if failures >= _MAX_RECOVERIES:
                break
            continue
        last_finite = adam.params.clone()
        trace.append((value, _time.perf_counter() - start))
        adam.step(grad, rate * options.lr_decay ** ((i + 1) / max(options.iterations - 1, 1)))
    return (adam.params, last_finite), trace, failures


@dataclass
class FrameProblem(Problem):
    """Gauss-Newton's residuals on a warm-started frame (:func:`refine_frame`) without marching: the rays
    through the box pixels ``index`` take their lattice samples between ``near`` and ``far`` (the frame's
    band, per box pixel), those the posed grid holds at the pose asked (:func:`occupied`) and, for a
    Jacobian where ``prune``, those light reaches (:func:`visible`): the Adam frame's samples. One start, or
    several rows of it (a Jacobian by differences: the same rays at shifted poses, rendered without a graph),
    each taking the band's samples its own grid holds; where ``prune``, renders without a graph go in two rounds
    from where the rays saw at the linearisation point (:meth:`_render_in_rounds`)."""

    near: Tensor | None = None
    far: Tensor | None = None
    field: object = None
    grid: object = None
    prune: bool = False
    index: Tensor | None = None  # the box pixels of the rays being rendered (set by residuals)
    # (index, [n] distance): how far each ray of the last Jacobian by differences saw at its linearisation point
    reach: tuple[Tensor, Tensor] | None = None

    def residuals(self, chain, p, rays_cam, target, index, jacobian, group=1, along_ray=False):
        self.index = index
        return super().residuals(chain, p, rays_cam, target, index, jacobian, group, along_ray)

    def difference_residuals(self, chain, p, rays_cam, target, index, group=1):
        self.index = index
        return super().difference_residuals(chain, p, rays_cam, target, index, group)

    def _samples_run_behind(self) -> bool:
        """The band's lattice samples run through the object unless pruned to those light reaches."""
        return not self.prune

    def _render(self, rays, theta, S, n, outputs, band, fixed=None):
        """Where pruned, a render without a graph goes in two rounds (:meth:`_render_in_rounds`): a Jacobian's
        rows by differences, and a trial step's row on the rays of the last such Jacobian."""
        rows = len(rays) // max(len(self.index), 1)
        own = self.reach is not None and self.reach[0] is self.index
        if fixed is not None or not self.prune or torch.is_grad_enabled() or not (rows > 1 or own):
            return super()._render(rays, theta, S, n, outputs, band, fixed)
        out = self._render_in_rounds(rays, theta, rows, outputs)
        return torch.cat([out.rgb, out.opacity[:, None], out.depth[:, None]], -1)

    def _render_in_rounds(self, rays: Rays, theta: Tensor, rows: int, outputs) -> RenderOutput:
        """``rows`` rows of the box pixels' rays (object frame, ``θ [rows n, k]`` per ray; several: a Jacobian by
        differences, row 0 at its linearisation point) composited in two rounds (:func:`composite_in_rounds`): each
        ray's samples up to where it turned opaque at the linearisation point (its :attr:`reach`, found here
        from row 0 where there are several), then the rest where light still crosses; each round evaluates the
        samples its row's own grid holds. So light's reach is not found again for every row (:func:`visible`: an
        evaluation at every other sample), nor the grid asked about every sample of the band for every row: with
        several rows only the band's samples near an occupied cell at row 0 (``occupied_near``, a block of cells
        or more) are asked about: every row's occupied samples where the row moves them less than that. A
        Jacobian's shifts move the surface about a sample spacing, but a turn's moves the far end of a long object
        more than a block of a fine grid, and the samples such a row moves into occupied cells beyond it are left
        out (checking each row's bound took the rows back to the whole band and the rate's gain with them, at the
        same errors: docs/benchmarks.md, session 55)."""
        from narf_core.compositing import composite_in_rounds

        n = len(self.index)
        fixed = Rays(rays.origins.detach(), rays.directions.detach(), rays.z_per_t)
        lattice = frame_band(self.near[self.index], self.far[self.index], self.model.step)
        if rows > 1:
            first = fixed[:n]
            self.reach = (self.index, _reach(self.field, self.grid, first, lattice, theta[0], self.model.step))
            near = getattr(self.grid, "occupied_near", None)
            held = near(_points(first, lattice), theta[0]) if near is not None and len(lattice) else slice(None)
            lattice = Samples(torch.cat([lattice.ray[held] + r * n for r in range(rows)]), lattice.t[held].repeat(rows),
                              lattice.delta[held].repeat(rows))
        grid = self.grid
        return composite_in_rounds(self.field, fixed, lattice, self.reach[1].repeat(rows), theta=theta, outputs=outputs,
                                   keep=None if grid is None else grid.occupied)

    def _fixed_samples(self, rays: Rays, theta: Tensor, jacobian: bool, band=None) -> tuple[object, Samples]:
        n = 0 if self.index is None else len(self.index)
        if n == 0 or len(rays) % n:
            raise ValueError("FrameProblem renders rows of rays through the box pixels of its index")
        rows = len(rays) // n
        fixed = Rays(rays.origins.detach(), rays.directions.detach(), rays.z_per_t)
        lattice = frame_band(self.near[self.index], self.far[self.index], self.model.step)
        held = [occupied_mask(self.grid, fixed[r * n:(r + 1) * n], lattice, theta[r * n]) for r in range(rows)]
        ray = torch.cat([lattice.ray[h] + r * n for r, h in enumerate(held)])
        samples = Samples(ray, torch.cat([lattice.t[h] for h in held]), torch.cat([lattice.delta[h] for h in held]))
        if not (self.prune and jacobian):  # a render without a graph: every sample (pruned: _render's rounds)
            return self.field, samples
        return self.field, visible(self.field, fixed, samples, theta[0] if rows == 1 else theta)


def visible(field, rays_obj: Rays, samples: Samples, theta: Tensor, eps: float = 1e-5) -> Samples:
    """The ``samples`` (ray-major, ascending ``t``) that light reaches: those before which the ray's
    transmittance at ``θ [k]`` (or one ``θ`` per ray, ``[n, k]``) is still at least about ``eps`` (the
    march's early stop, after the fact), so that a render evaluates the field only where it counts. The optical
    depth comes from one field evaluation without a graph at every other sample of a ray (each
    standing for two): half the cost, and ``eps`` small enough that what is dropped weighs a few
    thousandths at most in any render (tests/test_track.py)."""
    if len(samples) == 0:
        return samples
    from narf_core.occupancy import density_fn

    with torch.no_grad():
        index = torch.arange(len(samples), device=samples.ray.device)
        first = torch.ones_like(samples.ray, dtype=torch.bool)
        first[1:] = samples.ray[1:] != samples.ray[:-1]
        start = torch.cummax(torch.where(first, index, torch.zeros_like(index)), 0).values  # each ray's first sample
        pick = (index - start) % 2 == 0
        ray, t = samples.ray[pick], samples.t[pick]
        x = rays_obj.origins[ray] + t[:, None].to(rays_obj.origins) * rays_obj.directions[ray]
        th = theta.detach() if theta.dim() == 1 else theta.detach()[ray]  # shared, or one per ray
        tau = torch.zeros(len(samples), dtype=torch.float64, device=samples.ray.device)
        tau[pick] = density_fn(field)(x, th).double() * samples.delta[pick].double() * 2
        total = torch.cumsum(tau, 0)
        before = total - tau - (total[start] - tau[start])  # the optical depth in front of each sample
        keep = before < -math.log(eps)
    return Samples(samples.ray[keep], samples.t[keep], samples.delta[keep])


# A ray's reach (FrameProblem's first round) runs this many sample spacings beyond the last sample its light reached
# at the linearisation point: about the surface's move in a Jacobian's shifted rows.
REACH_STEPS = 2


def _reach(field, grid, rays_obj: Rays, lattice: Samples, theta: Tensor, step: float) -> Tensor:
    """``[n]``: the distance of the last of the ``lattice`` samples of ``rays_obj`` that light reaches at ``θ [k]``
    (:func:`occupied`, then :func:`visible`), plus :data:`REACH_STEPS` sample spacings; ``-inf`` on a ray it
    reaches none of."""
    seen = visible(field, rays_obj, occupied(grid, rays_obj, lattice, theta), theta)
    far = torch.full((len(rays_obj),), -math.inf, dtype=lattice.t.dtype, device=lattice.t.device)
    return far.scatter_reduce(0, seen.ray, seen.t, "amax") + REACH_STEPS * step


def _points(rays_obj: Rays, samples: Samples) -> Tensor:
    """``[s, 3]``: the positions of the ``samples`` of ``rays_obj``."""
    return rays_obj.origins[samples.ray] + samples.t[:, None].to(rays_obj.origins) * rays_obj.directions[samples.ray]


def frame_band(near: Tensor, far: Tensor, step: float) -> Samples:
    """The lattice samples (interval ``step``, anchored at ``t = 0`` like the march's, each at its
    interval's middle) of rays between the distances ``near [n]`` and ``far [n]`` (none where
    ``far <= near``)."""
    k0 = torch.floor(near / step)
    count = torch.where(far > near, torch.ceil(far / step) - k0, torch.zeros_like(k0)).long()
    ray = torch.repeat_interleave(torch.arange(len(near), device=near.device), count)
    j = torch.arange(len(ray), device=near.device) - (torch.cumsum(count, 0) - count)[ray]
    t = (k0[ray] + j + 0.5) * step
    return Samples(ray, t, torch.full_like(t, step))


def occupied(grid, rays_obj: Rays, samples: Samples, theta: Tensor) -> Samples:
    """The ``samples`` of ``rays_obj`` in occupied cells of ``grid`` at ``θ [k]`` (all without a grid)."""
    if grid is None or len(samples) == 0:
        return samples
    keep = occupied_mask(grid, rays_obj, samples, theta)
    return Samples(samples.ray[keep], samples.t[keep], samples.delta[keep])


def occupied_mask(grid, rays_obj: Rays, samples: Samples, theta: Tensor) -> Tensor:
    """``[len(samples)]`` bool: which of the ``samples`` of ``rays_obj`` lie in occupied cells of ``grid`` at ``θ [k]``
    (all without a grid)."""
    if grid is None or len(samples) == 0:
        return torch.ones(len(samples), dtype=torch.bool, device=samples.ray.device)
    with torch.no_grad():
        return grid.occupied(_points(rays_obj, samples), theta.detach())


# --------------------------------------------------------------------------------------------
# one frame


def _recentred(model: NarfModel, camera: Pinhole, T: np.ndarray, joints: Mapping[str, float], mask: np.ndarray,
               depth: np.ndarray | None) -> np.ndarray:
    """``T`` shifted so that its projected surface points' centroid lands on the mask's centroid and,
    where there is depth, their median depth on the median depth observed inside the mask."""
    x = _surface_points_cam(model, T, joints)
    if len(x) == 0:
        return T
    K = camera.K.detach().double().cpu().numpy()
    uv = _pixels(camera, x)
    z = float(np.median(x[:, 2]))
    target_z = z
    v, u = np.nonzero(mask)
    if depth is not None:
        d = np.asarray(depth)[v, u]
        d = d[np.isfinite(d) & (d > 0)]
        if len(d):
            target_z = float(np.median(d))
    here = np.linalg.solve(K, np.array([*uv.mean(0), 1.0])) * z
    there = np.linalg.solve(K, np.array([u.mean() + 0.5, v.mean() + 0.5, 1.0])) * target_z
    if not np.isfinite(there - here).all():
        return T
    out = T.copy()
    out[:3, 3] += there - here
    return out


def _uncertainty(
    result: EstimateResult, sigma_scale: float = 1.0, colour: bool = False
) -> tuple[dict | None, np.ndarray | None]:
    """The estimate's uncertainty (as a dict) and covariance, σ times ``sigma_scale`` (but for the prior of
    joints whose parts the mask leaves out, ``Uncertainty.unseen_variance``); Nones without one.
    ``colour``: the covariance as the colour residual alone widens it (``Uncertainty.colour_covariance``)."""
    u = result.uncertainty
    if u is None:
        return None, None
    chosen = u.colour_covariance if colour and u.colour_covariance is not None else u.covariance
    unseen = np.diag(u.unseen_variance) if u.unseen_variance is not None else 0.0
    cov = (np.asarray(chosen, dtype=np.float64) - unseen) * sigma_scale**2 + unseen
    if not np.isfinite(cov).all():
        return None, None
    if sigma_scale != 1.0 or chosen is not u.covariance:
        u = Uncertainty.from_covariance(cov, list(u.joint_sigma), u.residual_variance, u.dof, u.view_joint_sigma,
                                        unseen_variance=u.unseen_variance)
    return u.to_dict(), cov


def sigma_scale(model: NarfModel, options: TrackOptions, depth: bool, camera: Pinhole | None = None) -> float:
    """The factor on a warm-started frame's σ, with ``depth`` or without: the option where set (> 0),
    else the model's own for the frame's solver (its bundle's ``metadata["uncertainty"]["track"]``, keys
    ``rgbd`` / ``rgb``, fitted with the solvers under ``solvers``: "adam" where that is absent, on
    sequences of a camera of focal length ``fx`` in pixels), else :data:`SIGMA_SCALE`'s (fitted at the
    training views' resolution). A pooled or own factor, for a ``camera`` finer than the one it was
    fitted at, is multiplied by their ratio to the power :data:`SIGMA_SCALE_FINER`, or, for an own factor
    also fitted at a finer camera (``fine``: its ``fx`` and factors), to the power that joins the two
    fits (and the finer fit's as it is for a camera finer still); an own factor that does not name its
    camera is taken as it is. An own factor fitted with another frame Jacobian (``jacobians``) than the
    frame's is not the frame's: Σ comes from the field's derivatives either way, and its misfit differs; nor is
    one fitted on another number of rays per iteration (``rays``, where the calibration chose one) on the CPU, nor
    with depth one fitted at another Huber scale (``robust_scale``, where it records one)."""
    key, solver = "rgbd" if depth else "rgb", options.solver_for(depth)
    chosen = options.sigma_scale if depth else options.sigma_scale_rgb
    if chosen:
        return float(chosen)
    track = tracker_calibration(model)
    own = track.get(key) if (track.get("solvers") or {}).get(key, "adam") == solver else None
    fitted_with = calibrated_jacobian(model, key)
    if own and solver == "gauss-newton" and fitted_with and fitted_with != options.jacobian_for(depth, model):
        own = None
    fitted_rays = calibrated_rays(model, key)
    if own and fitted_rays and model.aabb.device.type == "cpu" and fitted_rays != options.rays_for(depth, "cpu", model):
        own = None
    fitted_huber = calibrated_huber(model, key)
    if own and fitted_huber and fitted_huber != options.huber_for(depth, model):
        own = None
    factor, fitted_fx = (own, track.get("fx")) if own else (SIGMA_SCALE[solver][key], training_fx(model))
    if camera is None or not fitted_fx:
        return float(factor)
    finer = max(1.0, float(camera.K[0, 0]) / float(fitted_fx))
    exponent = SIGMA_SCALE_FINER.get(solver, {}).get(key, 0.0)
    fine = track.get("fine") or {}
    if own and fine.get(key) and fine.get("fx", 0) > fitted_fx:  # fitted at a finer camera too: its own growth,
        exponent = math.log(fine[key] / own) / math.log(fine["fx"] / fitted_fx)  # up to that camera
        finer = min(finer, fine["fx"] / fitted_fx)
    return float(factor * finer ** exponent)


def _warm_refine(model: NarfModel, camera: Pinhole, image: np.ndarray, mask: np.ndarray, depth: np.ndarray | None,
                 T: np.ndarray, joints: Mapping[str, float], opts: TrackOptions,
                 checks: list[str] | None = None, colour: tuple[float, float, float] | None = None) -> EstimateResult:
    """A warm-started frame's iterations from ``T`` and ``joints``: :func:`refine_frame` (narf mode,
    ``march = "frame"``, no band; given the frame's input ``checks``) or :func:`refine` (any other mode or
    march); the render's colour compared times ``colour`` where given."""
    step_options = _coloured(opts.step_options(depth is not None, model.aabb.device, model), colour)
    if (opts.march == "frame" and opts.band_m == 0
            and choose_mode(model, opts.mode, error=TrackInputError)[0] == "narf"):
        position, rotation = ((opts.frame_prior_position_m, opts.frame_prior_rotation_deg) if depth is not None
                              else (opts.frame_prior_position_m_rgb, opts.frame_prior_rotation_deg_rgb))
        prior = (position, math.radians(rotation)) if position > 0 and rotation > 0 else None
        hold = opts.hidden_joint_sigma if depth is not None else 0.0  # without depth no ray tells an occluder
        return refine_frame(model, camera, image, mask, depth, T, joints, step_options,
                            0.0 if depth is not None else opts.distance_prior_rgb, polish=depth is None, prior=prior,
                            hidden_joint_sigma=hold, checks=checks)
    return refine(model, image, mask, camera, T, joints_init=joints, depth=depth, options=step_options)


def _warnings(model: NarfModel, result: EstimateResult, checks: list[str]) -> list[str]:
    """A frame's warnings: the input checks' (``checks``, then any other its estimate found), and
    ``unobserved_joint`` judged on the view's own σ (``Uncertainty.view_joint_sigma``: whether the
    view constrains a joint is the linearisation's to say, before the model's error and the tracker's
    factor, which a factor below 1 would hide it behind), whichever refiner ran the frame."""
    more = [w for w in result.warnings if w not in checks and not w.startswith(f"{UNOBSERVED_CODE}:")]
    return [*checks, *more, *unobserved_joints(model, result.uncertainty)]


def _too_uncertain(info: dict | None, options: TrackOptions, sight: tuple[Tensor, float] | None = None,
                   spread: Tensor | None = None) -> bool:
    """Whether a frame's σ (``info``: ``Uncertainty.to_dict``) passes the options' limits. ``sight``: a frame
    without depth, its line of sight and stretch (``estimate.line_of_sight``): along it the position may be
    the stretch times the limit uncertain, as the model's error is there; across it the limit holds.
    ``spread`` (the second round's test): the frame's ``estimate.rotation_spread``, which widens the model's
    error in rotation about the axes the object's surface lies near, every frame's alike; the rotation's limit
    then holds with it taken out (σ per axis of ``S C S``, ``S = spread^-½``), so that the second round follows
    the model error's growth alone. A frame's status is judged on its σ as reported."""
    if info is None:
        return False
    rotation = math.degrees(max(info.get("rotation_sigma_rad", [0.0])))
    if spread is not None and "covariance" in info:
        w, V = np.linalg.eigh(spread.numpy())
        S = V @ np.diag(w ** -0.5) @ V.T
        C = S @ np.asarray(info["covariance"], dtype=np.float64)[3:6, 3:6] @ S
        rotation = math.degrees(math.sqrt(max(float(np.diagonal(C).max()), 0.0)))
    if sight is None:
        position = max(info.get("position_sigma_m", [0.0]))
    else:
        u, stretch = sight[0].numpy(), sight[1]
        C = np.asarray(info["covariance"], dtype=np.float64)[:3, :3]
        across = np.eye(3) - np.outer(u, u)
        position = max(math.sqrt(max(float(u @ C @ u), 0.0)) / stretch,
                       math.sqrt(max(float(np.linalg.eigvalsh(across @ C @ across)[-1]), 0.0)))
    return position > options.max_position_sigma_m or rotation > options.max_rotation_sigma_deg


def _spread(model: NarfModel, result: EstimateResult) -> Tensor:
    """``estimate.rotation_spread`` at a frame's estimate: what widened its Σ's rotation (the tracker's step
    options spread the model's error by the object's shape)."""
    theta = model.kinematics.joint_vector(result.joints, field="joints")
    return rotation_spread(model, torch.from_numpy(np.asarray(result.T_cam_obj, dtype=np.float64)), theta)


def _check_frame(frame: TrackFrame, camera: Pinhole) -> np.ndarray | None:
    """The frame's mask as bool (None when missing), after checking sizes against the camera."""
    image = np.asarray(frame.image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise TrackInputError(f"image must be uint8 [H, W, 3], got {image.dtype} {list(image.shape)}")
    if (camera.width, camera.height) != (image.shape[1], image.shape[0]):
        raise TrackInputError(f"image is {image.shape[1]}x{image.shape[0]} but the camera is {camera.width}x{camera.height}")
    for name, array in (("mask", frame.mask), ("depth", frame.depth)):
        if array is not None and np.asarray(array).shape != image.shape[:2]:
            raise TrackInputError(f"{name} must be [H, W] = {list(image.shape[:2])}, got {list(np.asarray(array).shape)}")
    return None if frame.mask is None else np.asarray(frame.mask) != 0


def step(
    model: NarfModel,
    camera: Pinhole,
    frame: TrackFrame,
    state: TrackState,
    options: TrackOptions | None = None,
) -> tuple[TrackResult, TrackState]:
    """Track one frame from ``state``; returns the frame's result (with the render mode used and
    why) and the next state.

    Raises:
        TrackInputError: a frame at or before the state's time, a non-finite state, size mismatches,
            ``options.mode`` ``parts`` on a model without part fields.
    """
    opts = options or TrackOptions()
    mode, mode_reason = choose_mode(model, opts.mode, error=TrackInputError)
    result, nxt = _step(model, camera, frame, state, replace(opts, mode=mode))  # resolved once for the frame
    result.mode, result.mode_reason = mode, mode_reason
    return result, nxt


def _redetected(model: NarfModel, camera: Pinhole, image: np.ndarray, mask: np.ndarray, depth: np.ndarray | None,
                T0: np.ndarray, joints: Mapping[str, float], opts: TrackOptions, checks: list[str],
                colour: tuple[float, float, float] | None = None) -> EstimateResult | None:
    """A re-initialisation by detection (:func:`narf_core.detect.detect`, ``T0`` and ``joints`` its hint); with
    depth always, without it None where it cannot be trusted: a mask cut by the image's border (``checks``' warning) or
    a detected distance more than ``opts.redetect_rgb_distance`` times ``T0``'s or less than its inverse
    (both from the silhouette's size, which a partial mask makes small). Its refinement compares the render's
    colour times ``colour`` where given."""
    from narf_core.detect import DetectOptions, detect

    if depth is None and (opts.redetect_rgb_distance == 0 or _cut_by_border(checks)):
        return None
    detector = DetectOptions(preset=opts.reinit_solver, seed=opts.seed)
    refine_options = replace(opts.reinit_options(), iterations=detector.iterations,
                             theta_starts=detector.refine_theta_starts)
    result = detect(model, camera, image, mask, depth, joints=joints, options=detector, hints=[(T0, joints)],
                    refine_options=_coloured(refine_options, colour))
    if depth is None:
        ratio = np.linalg.norm(result.T_cam_obj[:3, 3]) / np.linalg.norm(np.asarray(T0)[:3, 3])
        if not 1 / opts.redetect_rgb_distance <= ratio <= opts.redetect_rgb_distance:
            return None
    return result


def _cut_by_border(checks: list[str]) -> bool:
    """Whether a frame's input checks found its mask touching the image's border."""
    return any(w.startswith(f"{BORDER_CODE}:") for w in checks)


def _unless_turned_over(model: NarfModel, camera: Pinhole, image: np.ndarray, mask: np.ndarray, depth: np.ndarray,
                        T0: np.ndarray, joints: Mapping[str, float], detected: EstimateResult,
                        opts: TrackOptions) -> tuple[EstimateResult, int]:
    """``detected`` (a re-detection from the hint ``T0``, ``joints``), or where it turned the object more than
    ``opts.redetect_turn_deg`` from ``T0``, the multi-start refiner's estimate from ``T0`` if its loss is lower
    (both refined with the same preset on the same frame). Returns the estimate kept and the refiner's
    iterations (0 where it did not run)."""
    from narf_core.detect import rotation_angle

    R0 = np.asarray(T0, dtype=np.float64)[:3, :3]
    turn = math.degrees(float(rotation_angle(np.asarray(detected.T_cam_obj, dtype=np.float64)[:3, :3], R0)))
    if turn <= opts.redetect_turn_deg:  # (at most 180)
        return detected, 0
    local = refine(model, image, mask, camera, T0, joints_init=joints, depth=depth, options=opts.reinit_options())
    failed = local.status in ("no_overlap", "non_finite") or local.loss is None
    keep_local = not failed and (detected.loss is None or local.loss < detected.loss)
    return (local if keep_local else detected), local.iterations


def _coloured(options: EstimateOptions, colour: tuple[float, float, float] | None) -> EstimateOptions:
    """``options`` comparing the render's colour times ``colour``, where given."""
    return options if colour is None else replace(options, colour_gain=colour)


def _carried_colour(model: NarfModel, camera: Pinhole, image: np.ndarray, mask: np.ndarray, result: EstimateResult,
                    state: TrackState, opts: TrackOptions) -> tuple[np.ndarray, int]:
    """The track's colour gain and its count of fitted frames after a tracked frame without depth: moved
    towards the frame's own fit at its estimate (:func:`colour_gain_at`) by ``opts.colour_rate_rgb``, over
    its first frames by 1/n (they have nothing better: the mean of their fits); kept where the fit fails."""
    fit = colour_gain_at(model, camera, image, mask, result.T_cam_obj, result.joints, mode=opts.mode, seed=opts.seed)
    if fit is None:
        return state.colour_gain, state.colour_frames
    fitted = state.colour_frames + 1
    gain = np.asarray(state.colour_gain, dtype=np.float64)
    return np.clip(gain + max(opts.colour_rate_rgb, 1.0 / fitted) * (fit - gain), *GAIN_RANGE), fitted


def _period_passed(before: float, gap: float, period: float) -> bool:
    """Whether a multiple of ``period`` seconds since the track's last estimate fell between the previous
    frame (``before`` seconds after that estimate) and this one (``gap``): a lost track's retries on a
    schedule that needs no state beyond the frames' times."""
    return gap // period > before // period


def _step(
    model: NarfModel, camera: Pinhole, frame: TrackFrame, state: TrackState, opts: TrackOptions
) -> tuple[TrackResult, TrackState]:
    start = _time.perf_counter()
    t = _finite(frame.time, "frame.time")
    state.check(model)
    if t <= state.time:
        raise TrackInputError(f"frame.time {t:.6f} s is not after the previous frame's {state.time:.6f} s: "
                              "frames must come in time order")
    mask = _check_frame(frame, camera)
    depth = None if frame.depth is None else np.asarray(frame.depth, dtype=np.float32)
    checks: list[str] = []  # the input checks' warnings, once the mask is known

    def lost(reason: str, loss: float | None = None, iterations: int = 0, score: float | None = None):
        nxt = TrackState(state.T_cam_obj, dict(state.joints), t, state.anchor_time, np.asarray(state.velocity),
                         dict(state.joint_velocity), state.covariance, "lost", state.lost_frames + 1,
                         state.colour_gain, state.colour_frames)
        return TrackResult(t, "lost", state.T_cam_obj.copy(), dict(state.joints), score, loss, iterations,
                           _time.perf_counter() - start, reason, warnings=list(checks)), nxt

    if mask is None:
        return lost("no mask in this frame")
    if int(mask.sum()) < MIN_MASK_PIXELS:
        return lost("the object is not in view (empty mask)")
    # A depth in the wrong unit or off the mask is dropped before the prediction is aligned to it or a
    # re-initialisation starts from it (the refiners would drop it too, after those had used it).
    checks = check_observation(np.asarray(frame.image), mask, depth, camera,
                               expected_depth_m=float(np.asarray(state.T_cam_obj)[2, 3]))
    depth = usable_depth(depth, checks)
    fits_colour = depth is None and opts.colour_rate_rgb > 0
    colour = None  # the gain the render's colour is compared at, where the carried one passed the gate
    if fits_colour and np.abs(np.asarray(state.colour_gain) - 1).max() >= opts.colour_gate_rgb:
        colour = tuple(float(g) for g in state.colour_gain)
    gap = t - state.anchor_time
    iterations = 0
    if state.status != "lost" and gap <= opts.max_gap_s:
        T_pred, joints_pred = predict(model, state, t)
        if depth is not None and opts.depth_align:
            T_pred = depth_aligned(model, camera, T_pred, joints_pred, mask, depth)
        if depth is not None and opts.surface_fit_iterations:
            fit = surface_fit(model, camera, T_pred, joints_pred, mask, depth,
                              SurfaceFitOptions(iterations=opts.surface_fit_iterations))
            T_pred, joints_pred = fit.T_cam_obj, fit.joints
        result = _warm_refine(model, camera, frame.image, mask, depth, T_pred, joints_pred, opts, checks, colour)
        iterations += result.iterations
        retry_scale = opts.sigma_scale or RETRY_SIGMA_SCALE[opts.solver_for(True)]
        if depth is not None and opts.retry_uncertain and _too_uncertain(_uncertainty(result, retry_scale, True)[0], opts,
                                                                         spread=_spread(model, result)):
            # Σ grew past the limits with the colour residual: the estimate explains the image much worse
            # than the model usually does (a track turning away); one more round from where it ended. (Judged
            # at RETRY_SIGMA_SCALE, not the model's own or the camera's, on the colours' growth alone, not
            # the silhouette's, which a mask's own faults cause, and with the object's shape taken out of the
            # rotation, which widens every frame's alike: a calibration changes Σ, never the track.)
            result = _warm_refine(model, camera, frame.image, mask, depth, result.T_cam_obj, result.joints, opts, checks)
            iterations += result.iterations
        score = 0.0 if result.loss is None else overlap(model, camera, mask, result.T_cam_obj, result.joints, depth)
        if result.status not in ("no_overlap", "non_finite") and score >= opts.lost_overlap:
            info, cov = _uncertainty(result, sigma_scale(model, opts, depth is not None, camera))
            status, reason = "tracking", None
            if score < opts.uncertain_overlap:
                status, reason = "uncertain", f"the estimate explains only {score:.0%} of the mask (occlusion?)"
            elif _too_uncertain(info, opts, None if depth is not None else line_of_sight(model, result.T_cam_obj)):
                status, reason = "uncertain", "large covariance"
            velocity, joint_velocity = np.asarray(state.velocity, dtype=np.float64), dict(state.joint_velocity)
            if gap >= _MIN_VELOCITY_GAP_S:  # (not at a track's first frame, where the estimate has no predecessor)
                a = opts.velocity_smoothing
                along = a if depth is not None else opts.velocity_smoothing_along_rgb
                velocity = _blended_velocity(model, state, result.T_cam_obj, gap, a, along)
                joint_velocity = {name: a * (value - state.joints[name]) / gap + (1 - a) * joint_velocity.get(name, 0.0)
                                  for name, value in result.joints.items()}
            gain, fitted = state.colour_gain, state.colour_frames
            if fits_colour:
                gain, fitted = _carried_colour(model, camera, frame.image, mask, result, state, opts)
            nxt = TrackState(result.T_cam_obj, dict(result.joints), t, t, velocity, joint_velocity, cov, status, 0,
                             gain, fitted)
            return TrackResult(t, status, result.T_cam_obj, dict(result.joints), score, result.loss, iterations,
                               _time.perf_counter() - start, reason, info, cov,
                               warnings=_warnings(model, result, checks)), nxt
        why = "the warm start lost the object"
    else:
        why = "the track was lost" if state.lost_frames else "first frame: multi-start initialisation"
        if gap > opts.max_gap_s:
            why = f"{gap:.3f} s since the last estimate"
    # Long gone, or lost from an estimate that did not hold well: the object may be anywhere, and the
    # last pose may be wrong (narf_core/detect.py; the last pose is one of the detector's candidates).
    # Without depth the silhouette cannot tell a flat tool's turns apart: the detector only after
    # redetect_after_s away and where the multi-start refiner from the last pose does not explain the mask,
    # and once per such period while lost (judged from the previous frame's time: the state needs nothing more).
    before = state.time - state.anchor_time  # the previous frame's time since the last estimate
    if depth is not None:
        redetect = opts.redetect_after_s > 0 and (gap > opts.redetect_after_s
                                                  or state.status in ("uncertain", "reinitialised"))
    else:
        period = opts.redetect_after_s
        redetect = period > 0 and gap > period and (before <= period or _period_passed(before, gap, period))
    retry = opts.reinit_period_s_rgb
    if (depth is None and not redetect and state.lost_frames and retry > 0
            and before >= retry and not _period_passed(before, gap, retry)):
        return lost(f"{why}; the next re-initialisation within {retry:g} s")
    T0 = _recentred(model, camera, state.T_cam_obj, state.joints, mask, depth)
    score = None  # the re-initialisation's overlap with the mask, once measured
    if redetect and depth is not None:
        result = _redetected(model, camera, frame.image, mask, depth, T0, state.joints, opts, checks)
        result, more = _unless_turned_over(model, camera, frame.image, mask, depth, T0, state.joints, result, opts)
        iterations += more
    else:
        result = refine(model, frame.image, mask, camera, T0, joints_init=state.joints, depth=depth,
                        options=_coloured(opts.reinit_options(), colour))
        failed = result.status in ("no_overlap", "non_finite")
        score = None if failed else overlap(model, camera, mask, result.T_cam_obj, result.joints, depth)
        if redetect and (failed or score < opts.uncertain_overlap):  # (here without depth)
            found = _redetected(model, camera, frame.image, mask, depth, T0, state.joints, opts, checks, colour)
            if found is not None:
                iterations, result, score = iterations + result.iterations, found, None
    iterations += result.iterations
    if result.status in ("no_overlap", "non_finite"):
        return lost(f"{why}; re-initialisation failed ({result.status})", result.loss, iterations)
    if score is None:
        score = overlap(model, camera, mask, result.T_cam_obj, result.joints, depth)
    if score < opts.uncertain_overlap:
        return lost(f"{why}; re-initialisation explains only {score:.0%} of the mask", result.loss, iterations, score)
    partial = ("the mask touches the image's border" if _cut_by_border(checks)
               else "after an uncertain frame" if state.status == "uncertain" else None)
    if partial and score < opts.reinit_partial_overlap:
        return lost(f"{why}; {partial}, and the re-initialisation explains only {score:.0%} of the mask", result.loss,
                    iterations, score)
    info, cov = _uncertainty(result)
    nxt = TrackState(result.T_cam_obj, dict(result.joints), t, t, np.zeros(6), {}, cov, "reinitialised", 0,
                     state.colour_gain, state.colour_frames)
    return TrackResult(t, "reinitialised", result.T_cam_obj, dict(result.joints), score, result.loss, iterations,
                       _time.perf_counter() - start, why, info, cov, warnings=_warnings(model, result, checks)), nxt


def track(
    model: NarfModel,
    frames: Iterable[TrackFrame],
    camera: Pinhole,
    T_first: np.ndarray,
    joints_first: Mapping[str, float] | None = None,
    options: TrackOptions | None = None,
) -> Iterator[TrackResult]:
    """Track ``frames`` (in time order) from the pose ``T_first`` and joints ``joints_first`` at the
    first frame (a rough estimate that the multi-start refiner refines there, or with
    ``options.first_frame = "warm"`` an exact one); yields one :class:`TrackResult` per frame."""
    state: TrackState | None = None
    first = "tracking" if (options or TrackOptions()).first_frame == "warm" else "lost"
    for frame in frames:
        if state is None:
            state = TrackState.initial(model, T_first, joints_first, _finite(frame.time, "frame.time"), first)
        result, state = step(model, camera, frame, state, options)
        yield result
