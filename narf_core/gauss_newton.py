"""The second-order refiner and the covariance of an estimate (``options.solver = "gauss-newton"``).

Residuals. Every ray ``i`` predicts ``P_i = (rgb [3], opacity, depth)`` (colour and depth
premultiplied by opacity, over black) and is compared with the box pixel it goes through. The
residuals are linear in the prediction, ``r_i = M_i P_i - y_i`` with ``M_i [5, 5]`` fixed for an
iteration:

  - colour ``a_c rgb_c + b_c opacity - image_c * mask`` (``a = colour_gain, b = 0`` unless
    ``photometric_compensation``: gain and bias per channel, solved in closed form on the mask's
    rays at every iteration and held fixed in the Jacobian),
  - silhouette ``sqrt(silhouette_weight) (opacity - mask)``,
  - depth, where a depth is observed inside the mask, ``sqrt(depth_weight) (depth - opacity z) / s``
    with ``s`` the object's radius, or the sensor's ``depth_sigma * z^2`` when that is set,
  - none at all for a ray whose observed depth lies more than ``occlusion_margin`` in front of the
    rendered surface (an occluder, not the object);
  - with a mask trusted only partially (``mask_trust``, narf_core/estimate.py), as in Adam's loss: on
    the mask's edge band the colour against the unmasked image (``a_c rgb_c + (b_c - image_c)
    opacity``) and no silhouette or depth, and every residual of a ray weighted by
    :func:`narf_core.estimate._outside_weight` (square-rooted: it weighs the squares).

Jacobian. The residuals of a ray depend on the parameters ``p [6 + k]`` only through the ray's
object-frame origin and direction and its configuration ``θ``. The renderer is asked for one
differentiable composite with those as leaves (``θ`` per ray), and reverse mode gives
``dP_i / d(o_i, d_i, θ_i)`` for every ray at once, one backward pass per predicted channel (5 at
most, the graph kept between them); the chain to ``p`` is a ``[6 + k]``-column product with
the small Jacobian of the pose (central differences of a 4x4 product, one batch). So the cost is one composite and five
vector-Jacobian products whatever ``k`` is, where finite differences need ``6 + k`` extra renders
(and are no more exact), and forward mode through the field is not available (PyTorch has no
forward-mode rule for ``grid_sample``, the field's K-planes lookup); ``narf bench estimate``
prints the measured CPU time of each (benchmarks/jacobian.py). In ``parts`` mode, where the composition takes
one configuration per call, the ``θ`` columns are forward differences. In ``narf`` mode, where the field
is view-independent (``supports_jacobian``), the backward passes go: the samples are found first (the
tracker's frame has them; otherwise a march on densities without a graph, :meth:`Problem._fixed_samples`,
the samples the differentiable render would take), then the field gives every
sample's value and derivatives in ``(x, θ)`` itself, by forward differences in its lookup coordinates,
all in one batched evaluation without a graph (``ArticulatedField.jacobian``, ``KPlanesField.jacobian``),
and the compositing is differentiated in closed form (:func:`narf_core.compositing.composite_jacobian`;
where the samples run on behind the surface, only at those a ray still sees: the field's values come first).
``options.jacobian = "differences"`` instead renders every row and its ``2 (6 + k)`` copies shifted by
``±h`` in one parameter each (:data:`_DIFFERENCE_STEPS`: about one sample spacing of the surface's motion) in
one batch and takes central differences (:meth:`Problem.difference_residuals`): ``2 (6 + k)`` renders without
a graph, where the derivatives are one pass, but the slope they give is the render's over a sample spacing, not
the density's between two samples. The derivatives of a sharp surface are noisy at that scale (so ``JᵀWJ`` is
too large, the LM step too short and turned), and where several parameters move one outline together (a
lamp's joints and its pose) the steps stall; the tracker's frames with depth take the differences
(narf_core/track.py).

Step. Levenberg-Marquardt on the iteratively reweighted normal equations ``(JᵀWJ + λ diag(JᵀWJ)) δ
= -JᵀWr``, with Huber or Cauchy weights ``W`` (``robust_loss``, scale ``robust_scale`` in residual
units); the step and 2x and 4x it are tried on the same rays and the lowest robust cost is kept if it
is lower than the current one, else ``λ`` grows, by a factor that doubles with every rejection in a
row (4, 8, 16, ...: Nielsen's rule, so a run stuck at a tiny ``λ`` reaches a useful one in a few
iterations). After a rejection at the fine level the rays and the parameters are those of the last
iteration, so its residuals and Jacobian serve again and only the trial step is rendered. Once one
start is left at the fine level of a pyramid (the polish), the origins' derivatives along each ray
are replaced by the render's change over a sample spacing (:func:`along_ray_exact`) and the trial
steps go on to 32x the LM step: autograd through a render of fixed samples sees a sharp surface
only through the density's slope between two samples, which puts noise in ``J`` (so ``JᵀWJ`` is too
large and the LM step too short) and leaves most of the depth's change along the line of sight out
of it. A run may be held to a prior (:meth:`GaussNewtonRun.hold_to`, a tracker's frame: to the
prediction): ``½ Σ w_j (p_j - c_j)²`` joins the cost, ``w_j = s² / σ_j²`` with ``s²`` the
residuals' mean square at the first iteration (the cost is a negative log-likelihood times ``s²``), so
a direction the image barely sees moves only as far as the image asks clearly. A tracker's frame without depth polishes from its first iteration (``polish_only``, trial
steps to 8x): there the silhouette's scale is the only cue to the distance, and without the exact
along-ray part the LM step along the line of sight is too short to follow the object. Coarse pyramid levels average ``_GROUP`` jittered rays per pixel (the render blurred like the
target); the fine level keeps one set of rays, so the last iterations are a deterministic LM that
can converge.

Covariance. At the estimate, the parameters are re-centred there (position of the box centre in
metres, rotation in radians about it, both on camera axes, and ``θ`` in joint units) and
``Σ = (JᵀWJ / σ² + Σ₀⁻¹)⁻¹``, ``σ²`` the weighted residual variance, over the box's rays.
``Σ₀`` is a weak prior (one object radius, one radian, the joint's half range), so a direction the
view does not constrain (a hidden jaw) gets a large, finite σ instead of a singular matrix.
Neighbouring pixels' residuals are correlated, so the scores ``JᵀWr`` are summed over
``uncertainty_patch``-pixel squares before they are squared (cluster-robust "sandwich" form)
rather than over independent rays. Every quantity is a sum over the box's rays; where the box has
more than ``uncertainty_rays``, whole squares are drawn (weighted to the image's edges) and each
sum is estimated without bias by weighting the drawn terms (:func:`cluster_sample`). This is the
statistical part only: the model's own error, which these residuals cannot see, is added by
:func:`narf_core.estimate._uncertainty`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from narf_core.band import ray_band
from narf_core.compositing import composite, composite_jacobian
from narf_core.geometry import Rays, invert_pose, se3_exp

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.estimate import EstimateOptions, _Observation, _Parameterisation, _Target
    from narf_core.geometry import Pinhole
    from narf_core.sampling import Samples

_CHANNELS = 5  # rgb, opacity, depth
_LAMBDA_UP, _LAMBDA_DOWN = 4.0, 3.0
_LAMBDA_UP_GROWTH = 2.0  # each further rejection in a row multiplies λ by this much more (Nielsen's rule)
_LAMBDA_MIN, _LAMBDA_MAX = 1e-6, 1e8
_FD_THETA = 1e-3  # forward-difference step for θ in parts mode, as a fraction of the joint's range
_FD_POSE = 1e-5  # central-difference step of the pose columns (object radii, radians)
# The steps of a Jacobian by differences (options.jacobian "differences"): the box centre's translation (object
# radii), the rotation about it (radians), u of the joints (θ = mid + half sin u). A hundredth of a radius moves
# the surface by about one sample spacing of a model's lattice (its box's diagonal over a few hundred samples);
# a joint's step moves its part about as far or a little further out along its lever.
_DIFFERENCE_STEPS = (0.01, 0.01, 0.03)
_MAX_FAILURES = 8
_FIELD_JACOBIAN = True  # the field's own derivatives where the samples are fixed (module docstring); False: reverse mode
_STEP_FACTORS = (1.0, 2.0, 4.0)  # multiples of the LM step tried, in order, while the cost keeps falling
# Once one start is left at the fine level of a pyramid (the polish), the multiples go on to 32x: the
# Jacobian's noise (the surface seen only through the density's slope between samples) inflates JᵀWJ,
# so the LM step there falls several times short of the minimum along it (docs/benchmarks.md).
_POLISH_STEP_FACTORS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
# A run that polishes from its start (polish_only: a tracker's frame without depth, a few millimetres
# from its answer) stops at 8x: the longer steps cost renders and did not lower the track's error.
_FRAME_POLISH_STEP_FACTORS = (1.0, 2.0, 4.0, 8.0)
_GROUP = 4  # jittered rays averaged per pixel at a coarse pyramid level
# At the pruning (a third of the iterations) every start whose cost on the fine rays is within this factor
# of the lowest goes on, until _LAST_PRUNE_SHARE of the iterations, where the lowest goes on alone: there
# the starts have not converged, and the right one can trail a wrong one by a few per cent (docs/benchmarks.md).
_PRUNE_TIE = 1.15
_LAST_PRUNE_SHARE = 0.5
_INFORMATION_CHUNK = 256  # rays linearised at once for the covariance (bounds its render graph's memory)


# --------------------------------------------------------------------------------------------
# Chains: parameters -> (poses, configurations) with their derivatives


@dataclass
class Chain:
    """How rows ``p [S, 6 + k]`` make poses and configurations.

    ``T(p) = C exp([scale ρ, ω]) C⁻¹ T_ref`` (``C`` the translation to the box centre under
    ``T_ref``); ``θ(p) = mid + half sin(u)`` when ``sine`` (the refiner's bounded
    parameterisation), else ``θ = p[6:]`` (joint units, for the covariance).
    """

    T_ref: Tensor  # [4, 4] float64
    T_centre: Tensor  # [4, 4]
    scale: float
    mid: Tensor  # [k]
    half: Tensor  # [k]
    sine: bool

    @classmethod
    def of(cls, param: _Parameterisation) -> Chain:
        return cls(param.T_init, param.T_centre, param.radius, param.mid, param.half, True)

    @classmethod
    def local(cls, T: Tensor, param: _Parameterisation, centre_obj: Tensor) -> Chain:
        """Metres of the box centre and radians about it, at the pose ``T [4, 4]``; θ in joint units."""
        T_centre = torch.eye(4, dtype=torch.float64)
        T_centre[:3, 3] = T[:3, :3] @ centre_obj + T[:3, 3]
        return cls(T, T_centre, 1.0, param.mid, param.half, False)

    def poses(self, p: Tensor) -> Tensor:
        xi = torch.cat([p[..., :3] * self.scale, p[..., 3:6]], dim=-1)
        return self.T_centre @ se3_exp(xi) @ invert_pose(self.T_centre) @ self.T_ref

    def thetas(self, p: Tensor) -> Tensor:
        return self.mid + self.half * torch.sin(p[..., 6:]) if self.sine else p[..., 6:]

    def theta_derivative(self, p: Tensor) -> Tensor:
        """``dθ/dp[6:]`` ``[S, k]`` (the map is diagonal)."""
        return self.half * torch.cos(p[:, 6:]) if self.sine else torch.ones_like(p[:, 6:])

    def object_from_camera_jacobian(self, p: Tensor) -> tuple[Tensor, Tensor]:
        """``T_obj_cam`` of every row ``[S, 4, 4]`` and the derivative of its top 3x4 block, ``[S, 3, 4, 6]``
        in the pose columns: central differences in float64 (step ``_FD_POSE``: truncation and rounding
        both near 1e-10 of a 4x4 product of unit size), all 12 shifted poses of every row in one batch.
        Not ``torch.func.jacfwd``: its first call imports torch._dynamo, about 1.5 s and 66 MiB of
        resident memory in every process that estimates; not 12 vector-Jacobian products: a dozen
        small backward passes cost more than the render they serve."""
        p = p.detach().double()
        S = p.shape[0]
        shift = torch.zeros(2, 6, p.shape[1], dtype=torch.float64)
        shift[0, :, :6] = torch.eye(6, dtype=torch.float64) * _FD_POSE
        shift[1, :, :6] = -shift[0, :, :6]
        rows = torch.cat([p, (p[:, None, None, :] + shift[None]).reshape(-1, p.shape[1])])  # [S + 12 S, d]
        T_obj_cam = invert_pose(self.poses(rows))
        ahead, behind = T_obj_cam[S:, :3, :].reshape(S, 2, 6, 3, 4).unbind(1)
        return T_obj_cam[:S], ((ahead - behind) / (2 * _FD_POSE)).permute(0, 2, 3, 1)


# --------------------------------------------------------------------------------------------
# Residuals and their Jacobian


@dataclass
class Residuals:
    """``r [S, n, 5]`` (0 where a residual is unused) and, when asked, ``J [S, n, 5, d]``; ``used``
    ``[S, n, 5]`` marks the residuals that exist."""

    r: Tensor
    J: Tensor | None
    used: Tensor


@dataclass
class Problem:
    """Everything fixed about the residuals of one run; ``camera``: where ``options.band_m`` marches only
    the band around the surface (narf_core/band.py); ``samples``: where every render is of the same
    rays, their samples, marched once (the tracker's frame, :mod:`narf_core.track`): the field is
    evaluated there at each pose instead of marching again (``narf`` mode, one start)."""

    model: NarfModel
    options: EstimateOptions
    radius: float
    uses_depth: bool
    camera: Pinhole | None = None
    samples: Samples | None = None

    def predictions(
        self, rays_cam: Rays, T_obj_cam: Tensor, theta: Tensor, grad: bool, along_ray: bool = False
    ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor] | None]:
        """``P [S, n, 5]`` (float64) of every start and, with ``grad``, the leaves' derivatives
        ``dP/do, dP/dd [S, n, 5, 3]`` and ``dP/dθ [S, n, 5, k]``; ``along_ray``: ``dP/do``'s part along
        each ray the render's change over a sample spacing (:func:`along_ray_exact`)."""
        S, n, k = T_obj_cam.shape[0], len(rays_cam), theta.shape[1]
        like = rays_cam.origins  # the rays' dtype and device (the model's); poses and θ come from the CPU
        R = T_obj_cam[:, :3, :3].to(like)
        o = T_obj_cam[:, None, :3, 3].to(like).expand(S, n, 3).reshape(-1, 3)
        d = (rays_cam.directions @ R.transpose(-1, -2)).reshape(-1, 3)
        th = theta.to(like)[:, None, :].expand(S, n, k).reshape(S * n, k)
        outputs = ("rgb", "opacity", "depth")
        parts = self.options.mode == "parts" and k > 0
        band = None
        if self.options.band_m > 0 and self.camera is not None:
            band = ray_band(self.model, self.camera, rays_cam, invert_pose(T_obj_cam), theta, self.options.band_m)
        rays_obj = Rays(o, d, rays_cam.z_per_t.repeat(S))
        fixed = self._fixed_samples(rays_obj, th, True, band) if grad and not parts and k > 0 else None
        if fixed is not None and _FIELD_JACOBIAN and getattr(fixed[0], "supports_jacobian", False):
            field = fixed[0] if self._samples_run_behind() else None
            P, J = composite_jacobian(fixed[0].jacobian, rays_obj, fixed[1], theta=th, field=field)
            P_cpu, J = P.reshape(S, n, _CHANNELS).cpu(), J.reshape(S, n, _CHANNELS, -1).cpu()
            dP = [J[..., :3], J[..., 3:6], J[..., 6:]]
            if along_ray:
                dP[0] = along_ray_exact(dP[0], P_cpu, d.reshape(S, n, 3).double().cpu(), rays_cam.z_per_t.double().cpu())
            return P_cpu, tuple(dP)
        with torch.enable_grad() if grad else torch.no_grad():
            if grad:
                o, d = o.detach().requires_grad_(True), d.detach().requires_grad_(True)
                if not parts and k > 0:
                    th = th.detach().requires_grad_(True)
            P = self._render(Rays(o, d, rays_cam.z_per_t.repeat(S)), th, S, n, outputs, band, fixed)  # [S*n, 5]
            if not grad:
                return P.reshape(S, n, _CHANNELS).double().cpu(), None
            leaves = (o, d) if (parts or k == 0) else (o, d, th)
            # Without depth residuals the depth channel's derivatives are never used: one backward pass fewer.
            grads = _channel_gradients(P, leaves, _CHANNELS if self.uses_depth else _CHANNELS - 1)
        grads = [x.new_zeros(_CHANNELS, S * n, x.shape[1]) if g is None else g for g, x in zip(grads, leaves)]
        dP = [g.permute(1, 0, 2).reshape(S, n, _CHANNELS, -1).double().cpu() for g in grads]  # [S, n, 5, ·]
        P_cpu = P.detach().reshape(S, n, _CHANNELS).double().cpu()  # the solve is in float64 on the CPU
        if along_ray:
            dP[0] = along_ray_exact(dP[0], P_cpu, d.detach().reshape(S, n, 3).double().cpu(),
                                    rays_cam.z_per_t.double().cpu())
        if k == 0:
            dP.append(P_cpu.new_zeros(S, n, _CHANNELS, 0))
        elif parts:
            dP.append(self._theta_differences(rays_cam, o.detach(), d.detach(), theta, P.detach(), S, n, band))
        return P_cpu, tuple(dP)

    def _samples_run_behind(self) -> bool:
        """Whether a Jacobian's samples run on behind the surface, so that :func:`composite_jacobian` takes
        the field's derivatives only where a ray still sees (its values first): not the march's, which
        stops where a ray turns opaque."""
        return False

    def _fixed_samples(
        self, rays: Rays, theta: Tensor, jacobian: bool, band: tuple[Tensor, Tensor] | None = None
    ) -> tuple[object, Samples] | None:
        """The field and the samples a render of ``rays`` (object frame, ``θ [m, k]`` per ray, ``band`` as for
        :meth:`~narf_core.bundle.NarfModel.render_rays`) evaluates: the problem's own, or for a Jacobian
        (``jacobian``) in ``narf`` mode the march's; else ``None`` (the renderer marches and composites)."""
        if self.samples is not None:
            return self.model.field, self.samples
        if not jacobian or self.options.mode == "parts" or theta.shape[1] == 0:
            return None
        return self.model.march(rays, theta, mode=self.options.mode, t_range=band)

    def _render(
        self, rays: Rays, theta: Tensor, S: int, n: int, outputs: tuple[str, ...], band: tuple[Tensor, Tensor] | None,
        fixed: tuple[object, Samples] | None = None,
    ) -> Tensor:
        """``P [S*n, 5]`` of ``rays``; ``fixed``: their field and samples where already found."""
        fixed = fixed or self._fixed_samples(rays, theta, torch.is_grad_enabled(), band)
        if fixed is not None:
            out = composite(fixed[0], rays, fixed[1], theta=theta, outputs=outputs, background=0.0)
            return torch.cat([out.rgb, out.opacity[:, None], out.depth[:, None]], -1)
        kw = dict(mode=self.options.mode, outputs=outputs, background=0.0)
        render = self.model.render_rays
        if self.options.mode == "parts" and theta.shape[1] > 0:
            rows = [slice(s * n, (s + 1) * n) for s in range(S)]
            outs = [render(rays[r], theta[s * n], t_range=None if band is None else (band[0][r], band[1][r]), **kw)
                    for s, r in enumerate(rows)]
        elif theta.shape[1] == 0:
            outs = [render(rays, theta[0], t_range=band, **kw)]
        else:
            outs = [render(rays, theta, t_range=band, **kw)]
        return torch.cat([torch.cat([o.rgb, o.opacity[:, None], o.depth[:, None]], -1) for o in outs])

    @torch.no_grad()
    def _theta_differences(
        self, rays_cam: Rays, o: Tensor, d: Tensor, theta: Tensor, P: Tensor, S: int, n: int,
        band: tuple[Tensor, Tensor] | None = None,
    ) -> Tensor:
        """``dP/dθ [S, n, 5, k]`` by forward differences (``parts`` mode)."""
        k = theta.shape[1]
        step = _FD_THETA * (2 * self.model.kinematics.upper.double() - 2 * self.model.kinematics.lower.double()).clamp_min(1e-6) / 2
        cols = []
        for j in range(k):
            shifted = theta.clone()
            upper = self.model.kinematics.upper.double()[j]
            sign = torch.where(shifted[:, j] + step[j] > upper, -1.0, 1.0).to(theta)
            shifted[:, j] = shifted[:, j] + sign * step[j]
            th = shifted.to(o)[:, None, :].expand(S, n, k).reshape(-1, k)
            Q = self._render(Rays(o, d, rays_cam.z_per_t.repeat(S)), th, S, n, ("rgb", "opacity", "depth"), band)
            diff = (Q - P).reshape(S, n, _CHANNELS).double().cpu() / (sign.double() * step[j])[:, None, None]
            cols.append(diff)
        return torch.stack(cols, -1)

    def residuals(
        self,
        chain: Chain,
        p: Tensor,
        rays_cam: Rays,
        target: _Target,
        index: Tensor,
        jacobian: bool,
        group: int = 1,
        along_ray: bool = False,
    ) -> Residuals:
        """Residuals of every row of ``p [S, d]`` on the rays ``rays_cam [n * group]`` through the box
        pixels ``index [n]`` (see the module docstring), with their Jacobian if asked (``along_ray``:
        see :meth:`predictions`). With ``group > 1`` each pixel's prediction is the mean of ``group``
        consecutive rays (jittered over a pyramid level's square, so the render is box-filtered like
        the level's target)."""
        T_obj_cam, dT = chain.object_from_camera_jacobian(p) if jacobian else (invert_pose(chain.poses(p)), None)
        theta = chain.thetas(p)
        P, dP = self.predictions(rays_cam, T_obj_cam, theta, jacobian, along_ray)
        if jacobian:
            dPo, dPd, dPt = dP
            dirs = rays_cam.directions.double().cpu()  # [n * group, 3] camera frame
            # o = T_obj_cam[:3, 3]; d = R_obj_cam d_cam
            jo = torch.einsum("snci,sid->sncd", dPo, dT[:, :, 3, :])
            jd = torch.einsum("snci,sijd,nj->sncd", dPd, dT[:, :, :3, :], dirs)
            jt = dPt * chain.theta_derivative(p)[:, None, None, :]
            dP = torch.cat([jo + jd, jt], dim=-1)
        if group > 1:
            S = P.shape[0]
            P = P.reshape(S, -1, group, _CHANNELS).mean(2)
            dP = None if dP is None else dP.reshape(S, -1, group, *dP.shape[2:]).mean(2)
        M, y, used = self._linear_map(P, target, index)
        r = (M @ P[..., None])[..., 0] - y
        J = None if dP is None else M @ dP
        return Residuals(r, J, used)

    def difference_residuals(
        self, chain: Chain, p: Tensor, rays_cam: Rays, target: _Target, index: Tensor, group: int = 1
    ) -> Residuals:
        """:meth:`residuals` with the Jacobian from central differences of the render over about one sample
        spacing (:data:`_DIFFERENCE_STEPS`; ``options.jacobian = "differences"``): every row of ``p [S, d]``
        and its ``2d`` shifted copies rendered in one batch, the rows' linear map ``M`` taken at the row itself
        and held for its copies (as the derivatives' Jacobian holds it)."""
        S, d = p.shape
        steps = torch.tensor([_DIFFERENCE_STEPS[0]] * 3 + [_DIFFERENCE_STEPS[1]] * 3 + [_DIFFERENCE_STEPS[2]] * (d - 6),
                             dtype=p.dtype)
        shift = torch.diag(steps)
        rows = torch.cat([p[:, None], p[:, None] + shift, p[:, None] - shift], dim=1).reshape(-1, d)  # [S (1 + 2d), d]
        P, _ = self.predictions(rays_cam, invert_pose(chain.poses(rows)), chain.thetas(rows), False)
        if group > 1:
            P = P.reshape(len(rows), -1, group, _CHANNELS).mean(2)
        P = P.reshape(S, 1 + 2 * d, -1, _CHANNELS)
        dP = ((P[:, 1:d + 1] - P[:, d + 1:]) / (2 * steps)[None, :, None, None]).permute(0, 2, 3, 1)  # [S, n, 5, d]
        M, y, used = self._linear_map(P[:, 0], target, index)
        return Residuals((M @ P[:, 0, ..., None])[..., 0] - y, M @ dP, used)

    def _linear_map(self, P: Tensor, target: _Target, index: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``M [S, n, 5, 5]``, ``y [S, n, 5]`` and ``used [S, n, 5]`` with ``r = M P - y``."""
        opts = self.options
        S, n = P.shape[:2]
        rgb_t = target.rgb[index].double().cpu()  # [n, 3]
        mask_t = target.mask[index].double().cpu()  # [n]
        M = P.new_zeros(S, n, _CHANNELS, _CHANNELS)
        y = P.new_zeros(S, n, _CHANNELS)
        used = torch.zeros(S, n, _CHANNELS, dtype=torch.bool)
        keep = torch.ones(S, n, dtype=torch.bool)
        depth = target.depth[index].double().cpu() if (self.uses_depth and target.depth is not None) else None
        opacity = P[..., 3]
        if depth is not None and opts.occlusion_margin > 0:
            surface = P[..., 4] / opacity.clamp_min(1e-6)
            keep = ~((depth > 0) & (opacity > 0.5) & (depth < surface - opts.occlusion_margin))
        gain, bias = self._compensation(P, rgb_t, mask_t, keep)
        edge = None if target.band is None or target.image is None else target.band[index].cpu()
        for c in range(3):
            M[..., c, c] = gain[:, None, c]
            M[..., c, 3] = bias[:, None, c]
        y[..., :3] = rgb_t
        used[..., :3] = True
        if edge is not None:  # the render against the unmasked image where it draws the object; no mask there
            image = target.image[index].double().cpu()  # [n, 3]
            M[:, edge, :3, 3] -= image[edge]
            y[:, edge, :3] = 0.0
        if opts.silhouette_weight > 0:
            w = math.sqrt(opts.silhouette_weight)
            M[..., 3, 3] = w
            y[..., 3] = w * mask_t
            used[..., 3] = True
            if edge is not None:  # a segmenter's edge: neither object nor background for sure
                M[:, edge, 3, 3], y[:, edge, 3], used[:, edge, 3] = 0.0, 0.0, False
        if depth is not None:
            valid = (depth > 0) & (mask_t > 0.5)
            if edge is not None:  # a segmenter's edge pixel may be the table's
                valid = valid & ~edge
            if opts.depth_sigma > 0:
                scale = 1.0 / (opts.depth_sigma * depth.clamp_min(1e-3) ** 2)
            else:
                scale = torch.full_like(depth, 1.0 / self.radius)
            w = math.sqrt(opts.depth_weight) * scale * valid
            M[..., 4, 4] = w
            M[..., 4, 3] = -w * depth
            used[..., 4] = valid
        from narf_core.estimate import _outside_weight, weighs_outside

        if weighs_outside(opts, depth):
            weight = _outside_weight(mask_t, edge, depth, P[..., 4], opacity, opts.outside_weight).sqrt()  # [S, n]
            M, y = M * weight[..., None, None], y * weight[..., None]
            keep = keep & (weight > 0)
        M = M * keep[..., None, None]
        y = y * keep[..., None]
        return M, y, used & keep[..., None]

    def _compensation(self, P: Tensor, rgb_t: Tensor, mask_t: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
        """Per-start gain and bias ``[S, 3]`` fitting ``gain * rgb + bias * opacity`` of ``P [S, n, 5]`` to
        the observed colour (:func:`narf_core.estimate._gain_bias`); when off, ``options.colour_gain`` and zeros."""
        if not self.options.photometric_compensation:
            S = P.shape[0]
            return P.new_tensor(self.options.colour_gain).expand(S, 3), P.new_zeros(S, 3)
        from narf_core.estimate import _gain_bias

        return _gain_bias(P[..., :3], P[..., 3], rgb_t, mask_t, keep)


def along_ray_exact(dPo: Tensor, P: Tensor, d: Tensor, z_per_t: Tensor) -> Tensor:
    """``dP/do [S, n, 5, 3]`` with its part along each ray's unit direction ``d [S, n, 3]`` replaced by
    the render's change over a sample spacing.

    A ray's origin moved one sample spacing along the ray meets the same points one sample on, so
    colour and opacity stay and the premultiplied depth falls by ``opacity z_per_t`` per metre
    (``P [S, n, 5]``, ``z_per_t [n]``). Autograd gives the slope between two samples instead (their
    distances are fixed, the surface is seen through the density's slope there): on a sharp surface
    (a thin tool's, a sample or two deep) anything from a small fraction of that depth change to
    twice it, and a colour change that is not there. The part across the ray is left as it is."""
    along = torch.einsum("snci,sni->snc", dPo, d)  # [S, n, 5]
    exact = torch.zeros_like(along)
    exact[..., 4] = -P[..., 3] * z_per_t[None, :]
    return dPo + (exact - along)[..., None] * d[:, :, None, :]


def _channel_gradients(P: Tensor, leaves: tuple[Tensor, ...], channels: int = _CHANNELS) -> list[Tensor | None]:
    """``dP[:, c] / d leaf`` for the first ``channels`` channels ``c`` of ``P [m, 5]`` (zero for the
    others), ``[5, m, ·]`` per leaf (``None`` for a leaf ``P`` does not reach): one backward pass per
    channel on the kept graph. Every leaf row belongs to one ray, so the gradient of the channel's sum
    is the per-ray derivative. Neither ``is_grads_batched`` nor a tensor ``grad_outputs``: their first
    use imports sympy (about 0.5 s and 33 MiB of resident memory in every process that estimates)."""
    rows = []
    for c in range(channels):
        rows.append(torch.autograd.grad(P[:, c].sum(), leaves, retain_graph=c < channels - 1, allow_unused=True))
    rows += [(None,) * len(leaves)] * (_CHANNELS - channels)
    out = []
    for i, leaf in enumerate(leaves):
        if all(row[i] is None for row in rows):
            out.append(None)
        else:
            out.append(torch.stack([torch.zeros_like(leaf) if row[i] is None else row[i] for row in rows]))
    return out


# --------------------------------------------------------------------------------------------
# Robust weights


def robust_weights(r: Tensor, kind: str, scale: float) -> Tensor:
    """IRLS weights of residuals ``r`` (same shape): 1 (``none``), Huber or Cauchy at ``scale``."""
    if kind == "none":
        return torch.ones_like(r)
    z = r.abs() / scale
    if kind == "huber":
        return torch.where(z <= 1, torch.ones_like(z), 1 / z.clamp_min(1e-12))
    return 1 / (1 + z**2)


def robust_cost(r: Tensor, kind: str, scale: float) -> Tensor:
    """``Σ ρ(r)`` over the last two axes ``[S, n, 5] -> [S]`` (``ρ = r²/2`` for ``none``)."""
    if kind == "none":
        rho = r**2 / 2
    elif kind == "huber":
        a = r.abs()
        rho = torch.where(a <= scale, r**2 / 2, scale * (a - scale / 2))
    else:
        rho = scale**2 / 2 * torch.log1p((r / scale) ** 2)
    return rho.sum(dim=(-1, -2))


# --------------------------------------------------------------------------------------------
# The solver


class GaussNewtonRun:
    """Levenberg-Marquardt over the rows of ``params [S, d]`` (one per start); the record mirrors the
    Adam run's (``iteration``, ``status``, ``trace``, ``history``, ``best_params``)."""

    should_stop = None  # refine's hook, ``Callable[[], str | None]``: a status ends the loop
    fine_only = False  # after an Adam warm start: every iteration at the finest level
    polish_only = False  # one start from near its answer (a tracker's frame without depth): every iteration polishes
    prior_sigma: Tensor | None = None  # [d] (hold_to): σ of a Gaussian prior about prior_centre [S, d]
    prior_centre: Tensor | None = None
    prior_weight: Tensor | None = None  # [S, d]: its weight against the residuals, fixed at the first iteration

    def __init__(
        self,
        problem: Problem,
        obs: _Observation,
        camera: Pinhole,
        param: _Parameterisation,
        params0: Tensor,
        start_time: float,
        seed: int,
    ) -> None:
        self.problem, self.obs, self.camera, self.param = problem, obs, camera, param
        self.opts = problem.options
        self.chain = Chain.of(param)
        self.params = params0.clone()
        self.best_params = params0.clone()
        self.lam = torch.full((params0.shape[0],), self.opts.damping, dtype=torch.float64)
        self.lam_up = torch.full_like(self.lam, _LAMBDA_UP)  # λ's factor at the next rejection
        self.rng = torch.Generator().manual_seed(seed)
        self.start_time = start_time
        self.iteration, self.status, self.recovered = 0, "max_iterations", False
        self.trace: list[tuple[float, float]] = []
        self.history: list = []
        self.small_steps = 0
        self.pruned = False  # the starts were pruned once (the ties to the lowest cost may go on)
        self.fine_index: Tensor | None = None  # the fine level keeps one set of rays: a deterministic LM
        # The last linearisation ``(index, params, residuals)``: after a rejected step the fine level's
        # next iteration has the same rays and parameters, so its residuals and Jacobian are these.
        self.linearised: tuple[Tensor, Tensor, Residuals] | None = None
        self.accepted_trial: tuple[Tensor, Residuals] | None = None  # the last trial step taken (jacobian_once)
        self.timing = {"jacobian_s": 0.0, "trial_s": 0.0, "solve_s": 0.0}

    def _rays(self, target: _Target, several: bool) -> tuple[Tensor, Rays, int]:
        """This iteration's box pixels ``[n]``, their rays and the rays per pixel: at a coarse level
        ``_GROUP`` jittered rays per pixel, for the same number of rays in all."""
        from narf_core.estimate import _ray_index

        n_pixels = self.obs.pixels.shape[0]
        group = _GROUP if target.width > 1 else 1
        n_rays = min(max(self.opts.rays_per_iteration // (2 if several else 1) // group, 1), n_pixels)
        if target.width == 1 and self.fine_index is not None and len(self.fine_index) == n_rays:
            index = self.fine_index
        else:
            index = _ray_index(self.obs, self.opts, n_rays, self.rng, target.width == 1)
            if target.width == 1:
                self.fine_index = index
        pixels = self.obs.pixels[index].to(torch.float32).repeat_interleave(group, 0)
        if target.width > 1:
            pixels = pixels + (torch.rand(len(pixels), 2, generator=self.rng).to(pixels) - 0.5) * target.width
        return index, self.camera.rays(pixels), group

    def optimise(self, snapshot=None) -> None:
        from narf_core.estimate import _PRUNE_SHARE, _level

        opts, n_levels = self.opts, len(self.obs.levels)
        prune_at, last_prune_at = int(opts.iterations * _PRUNE_SHARE), int(opts.iterations * _LAST_PRUNE_SHARE)
        failures = 0
        kind, scale = opts.robust_loss, opts.robust_scale
        while self.iteration < opts.iterations:
            if self.should_stop is not None and (reason := self.should_stop()):
                self.status = reason
                return
            level = n_levels - 1 if self.fine_only else _level(self.iteration, opts.iterations, n_levels)
            target = self.obs.levels[level]
            self.iteration += 1
            index, rays, group = self._rays(target, self.params.shape[0] > 1)
            t0 = time.perf_counter()
            # The polish: one start left at the fine level after a pyramid (or every iteration where
            # polish_only): the along-ray derivatives over a sample spacing and longer trial steps.
            polish = (n_levels > 1 or self.polish_only) and level == n_levels - 1 and self.params.shape[0] == 1
            res = self._linearise(rays, target, index, group, polish)
            t1 = time.perf_counter()
            self.timing["jacobian_s"] += t1 - t0
            if not (bool(torch.isfinite(res.r).all()) and bool(torch.isfinite(res.J).all())):
                failures += 1
                self.recovered = True
                self.params = self.best_params.clone()
                self.lam = (self.lam * 10).clamp(max=_LAMBDA_MAX)
                if failures >= _MAX_FAILURES:
                    self.status = "non_finite"
                    return
                continue
            failures = 0
            S, d = self.params.shape
            w = robust_weights(res.r, kind, scale) * res.used
            Jf = res.J.reshape(S, -1, d)
            wf, rf = w.reshape(S, -1), res.r.reshape(S, -1)
            H = Jf.transpose(1, 2) @ (wf[..., None] * Jf)
            g = Jf.transpose(1, 2) @ (wf * rf)[..., None]
            cost = robust_cost(res.r * res.used, kind, scale)
            if self.prior_sigma is not None:
                if self.prior_weight is None:  # the residuals' variance at the start: the data term's scale
                    variance = 2 * cost / res.used.reshape(S, -1).sum(-1).clamp_min(1)
                    self.prior_weight = variance[:, None] / self.prior_sigma[None, :] ** 2  # [S, d]
                H = H + torch.diag_embed(self.prior_weight)
                g = g + (self.prior_weight * (self.params - self.prior_centre))[..., None]
                cost = cost + self._prior_cost(self.params)
            step = self._solve(H, g)
            t2 = time.perf_counter()
            self.timing["solve_s"] += t2 - t1
            # The step, and longer ones along it while the cost on the same rays falls (renders only, no
            # Jacobian): the linear model of a sharp edge reaches only about a sample's length.
            trial_params, trial_cost = self.params, cost.clone()
            factors = _STEP_FACTORS if not polish else (
                _FRAME_POLISH_STEP_FACTORS if self.polish_only else _POLISH_STEP_FACTORS)
            for factor in factors:
                candidate = self.params + factor * step
                trial = self.problem.residuals(self.chain, candidate, rays, target, index, False, group)
                c = robust_cost(trial.r * trial.used, kind, scale)
                if self.prior_sigma is not None:
                    c = c + self._prior_cost(candidate)
                take = torch.isfinite(c) & (c < trial_cost)
                if opts.jacobian_once and bool(take.all()):
                    self.accepted_trial = (candidate, trial)
                trial_params = torch.where(take[:, None], candidate, trial_params)
                trial_cost = torch.where(take, c, trial_cost)
                if not bool(take.any()):
                    break
            self.timing["trial_s"] += time.perf_counter() - t2
            better = torch.isfinite(trial_cost) & (trial_cost < cost)
            before = self.params
            self.params = torch.where(better[:, None], trial_params, self.params)
            self.best_params = self.params.clone()
            self.lam = torch.where(better, self.lam / _LAMBDA_DOWN, self.lam * self.lam_up).clamp(_LAMBDA_MIN, _LAMBDA_MAX)
            self.lam_up = torch.where(better, _LAMBDA_UP, self.lam_up * _LAMBDA_UP_GROWTH)
            n_res = max(int(res.used.sum()) // S, 1)
            current = torch.where(better, trial_cost, cost) / n_res
            elapsed = time.perf_counter() - self.start_time
            self.trace.append((float(current.min()), elapsed))
            if snapshot is not None and opts.record_every and self.iteration % opts.record_every == 0:
                self.history.append(snapshot(self.params, current, self.iteration, elapsed))
            if S > 1 and self.iteration >= prune_at and (not self.pruned or self.iteration >= last_prune_at):
                self._keep_best_starts(_PRUNE_TIE if self.iteration < last_prune_at else 1.0)
                self.pruned = True
                continue
            # Converged: `patience` accepted steps in a row each moved less than `tolerance`, or λ is at its cap.
            moved = float(self.param.motion(self.params, before).max())
            small = (bool(better.all()) and moved < opts.tolerance) or float(self.lam.min()) >= _LAMBDA_MAX
            self.small_steps = self.small_steps + 1 if small else 0
            if opts.early_stop and level == n_levels - 1 and S == 1 and self.small_steps >= opts.patience:
                self.status = "converged"
                return

    def hold_to(self, centre: Tensor, sigma: Tensor) -> None:
        """A Gaussian prior on the rows: ``centre [S, d]`` with ``sigma [d]`` per parameter (``inf``: none),
        weighed against the residuals as a likelihood whose variance is their mean square at the first
        iteration (see the module docstring)."""
        self.prior_centre, self.prior_sigma, self.prior_weight = centre.clone(), sigma.double(), None

    def _prior_cost(self, params: Tensor) -> Tensor:
        return 0.5 * (self.prior_weight * (params - self.prior_centre) ** 2).sum(-1)

    def _linearise(self, rays: Rays, target: _Target, index: Tensor, group: int, along_ray: bool = False) -> Residuals:
        """The residuals and Jacobian at ``params`` on this iteration's rays; the last ones again where
        neither changed (a rejected step at the fine level, whose rays are fixed: only ``λ`` differs). With
        ``jacobian_once``, on the last one's rays the residuals where the parameters are now (the accepted trial
        step's, not rendered again) with the last Jacobian."""
        last = self.linearised
        if last is not None and last[0] is index and torch.equal(last[1], self.params):
            return last[2]
        if self.opts.jacobian_once and last is not None and last[0] is index and self.params.shape[0] == 1:
            trial = self.accepted_trial
            now = trial[1] if trial is not None and torch.equal(trial[0], self.params) else self.problem.residuals(
                self.chain, self.params, rays, target, index, False, group)
            res = Residuals(now.r, last[2].J, now.used)
        elif self.opts.jacobian == "differences":  # the along-ray change over a sample is in the differences already
            res = self.problem.difference_residuals(self.chain, self.params, rays, target, index, group)
        else:
            res = self.problem.residuals(self.chain, self.params, rays, target, index, True, group, along_ray)
        finite = bool(torch.isfinite(res.r).all()) and bool(torch.isfinite(res.J).all())
        self.linearised = (index, self.params.clone(), res) if finite else None
        return res

    def _solve(self, H: Tensor, g: Tensor) -> Tensor:
        """LM steps ``[S, d]`` from ``H [S, d, d]``, ``g [S, d, 1]`` and the per-row damping."""
        diag = torch.diagonal(H, dim1=-2, dim2=-1)
        scale = diag.clamp_min(1e-9 * diag.amax(-1, keepdim=True).clamp_min(1e-12))
        A = H + torch.diag_embed(self.lam[:, None] * scale + 1e-12)
        try:
            step = -torch.linalg.solve(A, g)[..., 0]
        except RuntimeError:  # singular even with damping: take a small gradient step
            step = -g[..., 0] / scale
        return torch.where(torch.isfinite(step), step, torch.zeros_like(step))

    def _keep_best_starts(self, tie: float) -> None:
        """Keep the starts whose robust cost on up to ``_EVAL_RAYS`` fine box rays is at most ``tie`` times
        the lowest (``tie`` 1: the lowest alone), lowest first."""
        from narf_core.estimate import _EVAL_RAYS

        n_pixels = self.obs.pixels.shape[0]
        index = torch.randperm(n_pixels, generator=self.rng)[: min(n_pixels, _EVAL_RAYS)]
        target = self.obs.levels[-1]
        with torch.no_grad():
            res = self.problem.residuals(self.chain, self.params, self.camera.rays(self.obs.pixels[index]), target, index, False)
        cost = robust_cost(res.r * res.used, self.opts.robust_loss, self.opts.robust_scale)
        cost = torch.where(torch.isfinite(cost), cost, math.inf)
        keep = cost.sort(stable=True).indices[: max(1, int((cost <= tie * cost.min()).sum()))]
        self.params, self.lam, self.lam_up = self.params[keep], self.lam[keep], self.lam_up[keep]
        self.best_params = self.params.clone()


# --------------------------------------------------------------------------------------------
# Covariance at the estimate


@dataclass
class Information:
    """What the residuals of every ray of the box say about the parameters ``[d]`` at the estimate.

    Each field is a sum over clusters (``patch``-pixel squares); when only some clusters were drawn
    (:func:`cluster_sample`), the drawn clusters' terms are weighted by the inverse of their expected
    draw count (Horvitz-Thompson), which keeps every sum unbiased:

    - ``H = Σ Jᵀ W J [d, d]``, the Gauss-Newton information;
    - ``B = Σ_c g_c g_cᵀ [d, d]``, the spread of the cluster scores ``g_c = Σ_{i ∈ c} Jᵢᵀ Wᵢ rᵢ``
      (the sandwich's "meat": residuals correlated inside a cluster add up before they are squared);
    - ``rss = Σ W r²`` and ``count``, the residuals that carry information;
    - ``colour_ss = Σ r²`` and ``colour_count`` over the colour residuals alone, unweighted: how well
      the render explains the image, comparable between option sets (every one has colour residuals);
    - ``silhouette_ss`` and ``silhouette_count`` the same over the silhouette residuals, each over the
      silhouette's weight's root: the squared difference of the render's opacity and the mask, how well
      the render's outline explains the mask (0 without a silhouette term).
    """

    H: Tensor
    B: Tensor
    rss: float
    count: float
    colour_ss: float
    colour_count: float
    silhouette_ss: float = 0.0
    silhouette_count: float = 0.0

    def variance(self) -> float:
        """The weighted residual variance ``σ² = rss / (count - d)``."""
        v = self.rss / max(self.count - self.H.shape[0], 1.0)
        return max(v, 1e-12) if math.isfinite(v) else 1.0

    def colour_variance(self) -> float:
        """The mean squared colour residual (colour in [0, 1])."""
        return self.colour_ss / max(self.colour_count, 1.0)

    def silhouette_misfit(self) -> float:
        """The mean squared difference of the render's opacity and the mask (0 without a silhouette term)."""
        return self.silhouette_ss / max(self.silhouette_count, 1.0)


@dataclass
class Covariance:
    """The statistical covariance at an estimate: ``sigma [d, d]``, the weighted residual variance
    ``variance`` with ``dof`` degrees of freedom, the mean squared colour residual ``colour_variance``
    and the silhouette's ``silhouette_misfit`` (:meth:`Information.silhouette_misfit`)."""

    sigma: Tensor
    variance: float
    dof: int
    colour_variance: float
    silhouette_misfit: float = 0.0


def cluster_sample(
    pixels: Tensor, importance: Tensor | None, patch: int, max_rays: int, rng: torch.Generator
) -> tuple[Tensor, Tensor, Tensor]:
    """Whole ``patch x patch`` squares of the box's ``pixels [N, 2]``, about ``max_rays`` pixels in all
    (every pixel when they fit): their ``index [n]`` into ``pixels``, each one's cluster ``[n]``
    (``0 .. m-1``) and the clusters' weights ``[m]`` (1 / expected draws).

    Clusters are drawn with replacement in proportion to half their share of ``importance [N]`` (the
    observation's edges and texture, where a pose error changes the residuals most) and half their
    share of pixels: a uniform draw misses the few edge rays that hold most of the information, and
    the uniform half keeps the weights bounded where the importance is wrong (docs/benchmarks.md)."""
    key = (pixels[:, 1] // patch) * 1_000_003 + pixels[:, 0] // patch
    _, cluster = torch.unique(key, return_inverse=True)
    clusters = int(cluster.max()) + 1
    if len(pixels) <= max_rays:
        return torch.arange(len(pixels)), cluster, torch.ones(clusters, dtype=torch.float64)
    share = torch.zeros(clusters, dtype=torch.float64).index_add_(0, cluster, torch.ones(len(pixels), dtype=torch.float64))
    q = share / len(pixels)
    if importance is not None:
        imp = importance.double().cpu()
        q = (q + torch.zeros_like(q).index_add_(0, cluster, imp / imp.sum())) / 2
    draws = max(1, round(clusters * max_rays / len(pixels)))
    counts = torch.bincount(torch.multinomial(q, draws, replacement=True, generator=rng), minlength=clusters)
    chosen = counts > 0
    index = torch.nonzero(chosen[cluster])[:, 0]
    _, local = torch.unique(cluster[index], return_inverse=True)
    return index, local, (counts[chosen] / (draws * q[chosen])).double()


def information(
    problem: Problem, obs: _Observation, camera: Pinhole, chain: Chain, p: Tensor, index: Tensor, cluster: Tensor,
    weight: Tensor, chunk: int = _INFORMATION_CHUNK,
) -> Information | None:
    """:class:`Information` at ``p [1, d]`` from the box pixels ``index [n]`` in clusters ``cluster [n]``
    of weights ``weight [m]``; ``None`` when the render is not finite. Every field is a sum over rays
    (``B`` over cluster scores, themselves sums over rays), so the rays go ``chunk`` at a time: one
    chunk's render graph is alive at once, whatever ``n``."""
    opts = problem.options
    H = G = None
    rss = count = colour_ss = colour_count = silhouette_ss = silhouette_count = 0.0
    silhouette_scale = 1.0 / opts.silhouette_weight if opts.silhouette_weight > 0 else 0.0
    for start in range(0, len(index), chunk):
        part, part_cluster = index[start:start + chunk], cluster[start:start + chunk]
        res = problem.residuals(chain, p, camera.rays(obs.pixels[part].to(torch.float32)), obs.levels[-1], part, True)
        J, r = res.J[0], res.r[0]  # [c, 5, d], [c, 5]
        if not (bool(torch.isfinite(J).all()) and bool(torch.isfinite(r).all())):
            return None
        # Residuals that are exactly zero with a zero Jacobian row (empty background on both sides)
        # carry no information and would only dilute σ².
        informative = res.used[0] & ((J.abs().sum(-1) > 0) | (r != 0))
        w = robust_weights(r, opts.robust_loss, opts.robust_scale) * informative  # [c, 5]
        ray_weight = weight[part_cluster][:, None]  # [c, 1]
        h = torch.einsum("nci,nc,ncj->ij", J, w * ray_weight, J)
        score = torch.einsum("nci,nc->ni", J, w * r)  # [c, d]
        g = score.new_zeros(len(weight), score.shape[1]).index_add(0, part_cluster, score)  # [m, d] cluster scores
        H, G = (h, g) if H is None else (H + h, G + g)
        colour = informative[:, :3] * ray_weight
        rss += float((ray_weight * w * r**2).sum())
        count += float((ray_weight * informative).sum())
        colour_ss += float((colour * r[:, :3] ** 2).sum())
        colour_count += float(colour.sum())
        outline = res.used[0][:, 3:4] * ray_weight
        silhouette_ss += silhouette_scale * float((outline * r[:, 3:4] ** 2).sum())
        silhouette_count += float(outline.sum())
    if H is None:
        return None
    return Information(H, (G * weight[:, None]).T @ G, rss, count, colour_ss, colour_count, silhouette_ss,
                       silhouette_count)


def prior_precision(param: _Parameterisation) -> Tensor:
    """``Σ₀⁻¹ [6 + k]`` (a diagonal): one object radius, one radian, the joint's half range."""
    return torch.cat([
        torch.full((3,), param.radius ** -2, dtype=torch.float64),
        torch.ones(3, dtype=torch.float64),
        param.half.double().cpu().clamp_min(1e-6) ** -2,
    ])


def sandwich(info: Information, prior: Tensor, variance: float) -> Tensor:
    """The cluster-robust covariance ``A⁻¹ (B / σ⁴) A⁻¹`` with ``A = H / σ² + Σ₀⁻¹`` ``[d, d]``, its
    diagonal never below ``A⁻¹``'s (the independent-ray covariance; the prior keeps directions the
    view does not constrain bounded)."""
    inv = _spd_inverse(_symmetric(info.H / variance + torch.diag(prior)))
    robust = inv @ (info.B / variance**2) @ inv
    sigma = torch.maximum(robust.diagonal(), inv.diagonal()).sqrt()
    return _correlation(robust) * sigma[:, None] * sigma[None, :]


def covariance(
    problem: Problem,
    obs: _Observation,
    camera: Pinhole,
    param: _Parameterisation,
    T: Tensor,
    theta: Tensor,
    centre_obj: Tensor,
    max_rays: int,
    patch: int,
    rng: torch.Generator,
    rays: tuple[Tensor, Tensor, Tensor] | None = None,
) -> Covariance:
    """``Σ [6+k, 6+k]`` and the residuals' statistics at the estimate ``T [4,4]``, ``θ [k]`` in the local
    parameterisation of :class:`~narf_core.estimate.Uncertainty` (see the module docstring), from
    about ``max_rays`` rays of the box in whole ``patch``-pixel clusters, scaled to the whole box.
    ``patch = 1``: independent rays, ``Σ = (H / σ² + Σ₀⁻¹)⁻¹``; else the cluster sandwich. ``rays``:
    ``(index [n], cluster [n], weight [m])`` as :func:`cluster_sample` gives, drawn by the caller (the
    rays of ``problem.samples``, linearised in one chunk) instead of here."""
    chain = Chain.local(T, param, centre_obj)
    d = 6 + theta.shape[0]
    p = torch.cat([torch.zeros(6, dtype=torch.float64), theta.double()])[None]
    if rays is None:
        index, cluster, weight = cluster_sample(obs.pixels.cpu(), obs.importance, patch, max_rays, rng)
        info = information(problem, obs, camera, chain, p, index, cluster, weight)
    else:
        index, cluster, weight = rays
        info = information(problem, obs, camera, chain, p, index, cluster, weight, chunk=max(len(index), 1))
    if info is None:  # a non-finite render: no Σ
        return Covariance(torch.full((d, d), math.nan, dtype=torch.float64), math.nan, 1, math.nan, math.nan)
    variance, prior = info.variance(), prior_precision(param)
    if patch > 1:
        Sigma = sandwich(info, prior, variance)
    else:
        Sigma = _spd_inverse(_symmetric(info.H / variance + torch.diag(prior)))
    Sigma = _symmetric(Sigma)
    if not bool(torch.isfinite(Sigma).all()):
        Sigma = torch.diag(1 / prior)
    return Covariance(Sigma, variance, max(round(info.count) - d, 1), info.colour_variance(), info.silhouette_misfit())


def _symmetric(A: Tensor) -> Tensor:
    return (A + A.T) / 2


def _spd_inverse(A: Tensor) -> Tensor:
    """Inverse of a symmetric positive (semi)definite matrix; eigenvalues floored for safety."""
    vals, vecs = torch.linalg.eigh(A)
    vals = vals.clamp_min(1e-12 * float(vals.abs().max().clamp_min(1e-300)))
    return (vecs / vals) @ vecs.T


def _correlation(S: Tensor) -> Tensor:
    sd = S.diagonal().clamp_min(1e-300).sqrt()
    C = S / sd[:, None] / sd[None, :]
    C = C.clamp(-1, 1)
    C.fill_diagonal_(1.0)
    return C
