"""The second-order refiner and the covariance of an estimate (``options.solver = "gauss-newton"``).

Residuals. Every ray ``i`` predicts ``P_i = (rgb [3], opacity, depth)`` (colour and depth
premultiplied by opacity, over black) and is compared with the box pixel it goes through. The
residuals are linear in the prediction, ``r_i = M_i P_i - y_i`` with ``M_i [5, 5]`` fixed for an
iteration:

  - colour ``a_c rgb_c + b_c opacity - image_c * mask`` (``a = 1, b = 0`` unless
    ``photometric_compensation``: gain and bias per channel, solved in closed form on the mask's
    rays at every iteration and held fixed in the Jacobian),
  - silhouette ``sqrt(silhouette_weight) (opacity - mask)``,
  - depth, where a depth is observed inside the mask, ``sqrt(depth_weight) (depth - opacity z) / s``
    with ``s`` the object's radius, or the sensor's ``depth_sigma * z^2`` when that is set,
  - none at all for a ray whose observed depth lies more than ``occlusion_margin`` in front of the
    rendered surface (an occluder, not the object).

Jacobian. The residuals of a ray depend on the parameters ``p [6 + k]`` only through the ray's
object-frame origin and direction and its configuration ``θ``. The renderer is asked for one
differentiable composite with those as leaves (``θ`` per ray), and reverse mode gives
``dP_i / d(o_i, d_i, θ_i)`` for every ray at once, one backward pass per predicted channel (5 at
most, batched with ``is_grads_batched``); the chain to ``p`` is a ``[6 + k]``-column product with
the small Jacobian of the pose, computed by forward mode. So the cost is one composite and five
vector-Jacobian products whatever ``k`` is, where finite differences need ``6 + k`` extra renders
(and are no more exact), and forward mode through the field is not available (PyTorch has no
forward-mode rule for ``grid_sample``, the field's K-planes lookup); ``narf bench estimate``
prints the measured CPU time of each (benchmarks/jacobian.py). In ``parts`` mode, where the composition takes
one configuration per call, the ``θ`` columns are forward differences.

Step. Levenberg-Marquardt on the iteratively reweighted normal equations ``(JᵀWJ + λ diag(JᵀWJ)) δ
= -JᵀWr``, with Huber or Cauchy weights ``W`` (``robust_loss``, scale ``robust_scale`` in residual
units); the step and 2x and 4x it are tried on the same rays and the lowest robust cost is kept if it
is lower than the current one, else ``λ`` grows. Coarse pyramid levels average ``_GROUP`` jittered
rays per pixel (the render blurred like the target); the fine level keeps one set of rays, so the
last iterations are a deterministic LM that can converge.

Covariance. At the estimate, the parameters are re-centred there (position of the box centre in
metres, rotation in radians about it, both on camera axes, and ``θ`` in joint units) and
``Σ = (JᵀWJ / σ² + Σ₀⁻¹)⁻¹``, ``σ²`` the weighted residual variance, on the box's rays.
``Σ₀`` is a weak prior (one object radius, one radian, the joint's half range), so a direction the
view does not constrain (a hidden jaw) gets a large, finite σ instead of a singular matrix.
Neighbouring pixels' residuals are correlated (the same model error spans many pixels), so ``JᵀWJ``
is summed over ``uncertainty_patch``-pixel squares (cluster-robust "sandwich" form) rather than
over independent rays.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from narf_core.geometry import Rays, invert_pose, se3_exp

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.estimate import EstimateOptions, _Observation, _Parameterisation, _Target
    from narf_core.geometry import Pinhole

_CHANNELS = 5  # rgb, opacity, depth
_LAMBDA_UP, _LAMBDA_DOWN = 4.0, 3.0
_LAMBDA_MIN, _LAMBDA_MAX = 1e-6, 1e8
_FD_THETA = 1e-3  # forward-difference step for θ in parts mode, as a fraction of the joint's range
_MAX_FAILURES = 8
_STEP_FACTORS = (1.0, 2.0, 4.0)  # multiples of the LM step tried, in order, while the cost keeps falling
_GROUP = 4  # jittered rays averaged per pixel at a coarse pyramid level
_FORWARD_AD = threading.Lock()  # forward-mode AD levels are process-wide: one jacfwd at a time (service workers)


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
        in the pose columns (forward mode: 6 tangents through a 4x4 product)."""

        def top(pose_row: Tensor) -> Tensor:
            full = torch.cat([pose_row, p.new_zeros(p.shape[1] - 6)])
            return invert_pose(self.poses(full[None]))[0, :3, :]

        with _FORWARD_AD:
            jac = torch.vmap(torch.func.jacfwd(top))(p[:, :6])
        return invert_pose(self.poses(p)), jac


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
    """Everything fixed about the residuals of one run."""

    model: NarfModel
    options: EstimateOptions
    radius: float
    uses_depth: bool

    def predictions(
        self, rays_cam: Rays, T_obj_cam: Tensor, theta: Tensor, grad: bool
    ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor] | None]:
        """``P [S, n, 5]`` (float64) of every start and, with ``grad``, the leaves' derivatives
        ``dP/do, dP/dd [S, n, 5, 3]`` and ``dP/dθ [S, n, 5, k]``."""
        S, n, k = T_obj_cam.shape[0], len(rays_cam), theta.shape[1]
        dtype = rays_cam.origins.dtype
        R = T_obj_cam[:, :3, :3].to(dtype)
        o = T_obj_cam[:, None, :3, 3].to(dtype).expand(S, n, 3).reshape(-1, 3)
        d = (rays_cam.directions @ R.transpose(-1, -2)).reshape(-1, 3)
        th = theta.to(dtype)[:, None, :].expand(S, n, k).reshape(S * n, k)
        outputs = ("rgb", "opacity", "depth")
        parts = self.options.mode == "parts" and k > 0
        with torch.enable_grad() if grad else torch.no_grad():
            if grad:
                o, d = o.detach().requires_grad_(True), d.detach().requires_grad_(True)
                if not parts and k > 0:
                    th = th.detach().requires_grad_(True)
            P = self._render(Rays(o, d, rays_cam.z_per_t.repeat(S)), th, S, n, outputs)  # [S*n, 5]
            if not grad:
                return P.reshape(S, n, _CHANNELS).double(), None
            leaves = (o, d) if (parts or k == 0) else (o, d, th)
            eye = torch.eye(_CHANNELS, dtype=P.dtype)[:, None, :].expand(_CHANNELS, S * n, _CHANNELS)
            grads = torch.autograd.grad(P, leaves, grad_outputs=eye, is_grads_batched=True, allow_unused=True)
        grads = [torch.zeros(_CHANNELS, S * n, x.shape[1]) if g is None else g for g, x in zip(grads, leaves)]
        dP = [g.permute(1, 0, 2).reshape(S, n, _CHANNELS, -1).double() for g in grads]  # [S, n, 5, ·]
        if k == 0:
            dP.append(P.new_zeros(S, n, _CHANNELS, 0).double())
        elif parts:
            dP.append(self._theta_differences(rays_cam, o.detach(), d.detach(), theta, P.detach(), S, n))
        return P.detach().reshape(S, n, _CHANNELS).double(), tuple(dP)

    def _render(self, rays: Rays, theta: Tensor, S: int, n: int, outputs: tuple[str, ...]) -> Tensor:
        kw = dict(mode=self.options.mode, outputs=outputs, background=0.0)
        render = self.model.render_rays
        if self.options.mode == "parts" and theta.shape[1] > 0:
            outs = [render(rays[s * n : (s + 1) * n], theta[s * n], **kw) for s in range(S)]
        elif theta.shape[1] == 0:
            outs = [render(rays, theta[0], **kw)]
        else:
            outs = [render(rays, theta, **kw)]
        return torch.cat([torch.cat([o.rgb, o.opacity[:, None], o.depth[:, None]], -1) for o in outs])

    @torch.no_grad()
    def _theta_differences(
        self, rays_cam: Rays, o: Tensor, d: Tensor, theta: Tensor, P: Tensor, S: int, n: int
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
            th = shifted.to(o.dtype)[:, None, :].expand(S, n, k).reshape(-1, k)
            Q = self._render(Rays(o, d, rays_cam.z_per_t.repeat(S)), th, S, n, ("rgb", "opacity", "depth"))
            diff = (Q - P).reshape(S, n, _CHANNELS).double() / (sign.double() * step[j])[:, None, None]
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
    ) -> Residuals:
        """Residuals of every row of ``p [S, d]`` on the rays ``rays_cam [n * group]`` through the box
        pixels ``index [n]`` (see the module docstring), with their Jacobian if asked. With
        ``group > 1`` each pixel's prediction is the mean of ``group`` consecutive rays (jittered
        over a pyramid level's square, so the render is box-filtered like the level's target)."""
        T_obj_cam, dT = chain.object_from_camera_jacobian(p) if jacobian else (invert_pose(chain.poses(p)), None)
        theta = chain.thetas(p)
        P, dP = self.predictions(rays_cam, T_obj_cam, theta, jacobian)
        if jacobian:
            dPo, dPd, dPt = dP
            dirs = rays_cam.directions.double()  # [n * group, 3] camera frame
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
        for c in range(3):
            M[..., c, c] = gain[:, None, c]
            M[..., c, 3] = bias[:, None, c]
        y[..., :3] = rgb_t
        used[..., :3] = True
        if opts.silhouette_weight > 0:
            w = math.sqrt(opts.silhouette_weight)
            M[..., 3, 3] = w
            y[..., 3] = w * mask_t
            used[..., 3] = True
        if depth is not None:
            valid = (depth > 0) & (mask_t > 0.5)
            if opts.depth_sigma > 0:
                scale = 1.0 / (opts.depth_sigma * depth.clamp_min(1e-3) ** 2)
            else:
                scale = torch.full_like(depth, 1.0 / self.radius)
            w = math.sqrt(opts.depth_weight) * scale * valid
            M[..., 4, 4] = w
            M[..., 4, 3] = -w * depth
            used[..., 4] = valid
        M = M * keep[..., None, None]
        y = y * keep[..., None]
        return M, y, used & keep[..., None]

    def _compensation(self, P: Tensor, rgb_t: Tensor, mask_t: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
        """Per-start gain and bias ``[S, 3]`` fitting ``a rgb + b opacity`` to the observed colour on
        the mask's rays (closed-form least squares, bounded); ones and zeros when off."""
        S = P.shape[0]
        gain, bias = P.new_ones(S, 3), P.new_zeros(S, 3)
        if not self.options.photometric_compensation:
            return gain, bias
        w = ((mask_t > 0.5)[None] & (P[..., 3] > 0.5) & keep).double()  # [S, n]
        count = w.sum(-1).clamp_min(1)  # [S]
        if float(count.min()) < 16:
            return gain, bias
        x, a = P[..., :3] / P[..., 3:4].clamp_min(1e-6), rgb_t[None] / mask_t[None, :, None].clamp_min(1e-6)
        mx = (w[..., None] * x).sum(1) / count[:, None]
        ma = (w[..., None] * a).sum(1) / count[:, None]
        cov = (w[..., None] * (x - mx[:, None]) * (a - ma[:, None])).sum(1)
        var = (w[..., None] * (x - mx[:, None]) ** 2).sum(1)
        gain = torch.where(var > 1e-8, cov / var.clamp_min(1e-8), torch.ones_like(var)).clamp(0.5, 2.0)
        bias = (ma - gain * mx).clamp(-0.3, 0.3)
        return gain, bias


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
        self.rng = torch.Generator().manual_seed(seed)
        self.start_time = start_time
        self.iteration, self.status, self.recovered = 0, "max_iterations", False
        self.trace: list[tuple[float, float]] = []
        self.history: list = []
        self.small_steps = 0
        self.fine_index: Tensor | None = None  # the fine level keeps one set of rays: a deterministic LM
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
            pixels = pixels + (torch.rand(len(pixels), 2, generator=self.rng) - 0.5) * target.width
        return index, self.camera.rays(pixels), group

    def optimise(self, snapshot=None) -> None:
        from narf_core.estimate import _PRUNE_SHARE, _level

        opts, n_levels = self.opts, len(self.obs.levels)
        prune_at = int(opts.iterations * _PRUNE_SHARE)
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
            res = self.problem.residuals(self.chain, self.params, rays, target, index, True, group)
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
            step = self._solve(H, g)
            t2 = time.perf_counter()
            self.timing["solve_s"] += t2 - t1
            # The step, and longer ones along it while the cost on the same rays falls (renders only, no
            # Jacobian): the linear model of a sharp edge reaches only about a sample's length.
            trial_params, trial_cost = self.params, cost.clone()
            for factor in _STEP_FACTORS:
                candidate = self.params + factor * step
                trial = self.problem.residuals(self.chain, candidate, rays, target, index, False, group)
                c = robust_cost(trial.r * trial.used, kind, scale)
                take = torch.isfinite(c) & (c < trial_cost)
                trial_params = torch.where(take[:, None], candidate, trial_params)
                trial_cost = torch.where(take, c, trial_cost)
                if not bool(take.any()):
                    break
            self.timing["trial_s"] += time.perf_counter() - t2
            better = torch.isfinite(trial_cost) & (trial_cost < cost)
            before = self.params
            self.params = torch.where(better[:, None], trial_params, self.params)
            self.best_params = self.params.clone()
            self.lam = torch.where(better, self.lam / _LAMBDA_DOWN, self.lam * _LAMBDA_UP).clamp(_LAMBDA_MIN, _LAMBDA_MAX)
            n_res = max(int(res.used.sum()) // S, 1)
            current = torch.where(better, trial_cost, cost) / n_res
            elapsed = time.perf_counter() - self.start_time
            self.trace.append((float(current.min()), elapsed))
            if snapshot is not None and opts.record_every and self.iteration % opts.record_every == 0:
                self.history.append(snapshot(self.params, current, self.iteration, elapsed))
            if S > 1 and self.iteration >= prune_at:
                self._keep_best_start()
                continue
            # Converged: `patience` accepted steps in a row each moved less than `tolerance`, or λ is at its cap.
            moved = float(self.param.motion(self.params, before).max())
            small = (bool(better.all()) and moved < opts.tolerance) or float(self.lam.min()) >= _LAMBDA_MAX
            self.small_steps = self.small_steps + 1 if small else 0
            if opts.early_stop and level == n_levels - 1 and S == 1 and self.small_steps >= opts.patience:
                self.status = "converged"
                return

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

    def _keep_best_start(self) -> None:
        from narf_core.estimate import _EVAL_RAYS

        n_pixels = self.obs.pixels.shape[0]
        index = torch.randperm(n_pixels, generator=self.rng)[: min(n_pixels, _EVAL_RAYS)]
        target = self.obs.levels[-1]
        with torch.no_grad():
            res = self.problem.residuals(self.chain, self.params, self.camera.rays(self.obs.pixels[index]), target, index, False)
        cost = robust_cost(res.r * res.used, self.opts.robust_loss, self.opts.robust_scale)
        keep = torch.where(torch.isfinite(cost), cost, math.inf).argmin().reshape(1)
        self.params, self.lam = self.params[keep], self.lam[keep]
        self.best_params = self.params.clone()


# --------------------------------------------------------------------------------------------
# Covariance at the estimate


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
) -> tuple[Tensor, float, int]:
    """``(Σ [6+k, 6+k], residual variance, dof)`` at the estimate ``T [4,4]``, ``θ [k]`` in the local
    parameterisation of :class:`~narf_core.estimate.Uncertainty` (see the module docstring)."""
    chain = Chain.local(T, param, centre_obj)
    k = theta.shape[0]
    p = torch.cat([torch.zeros(6, dtype=torch.float64), theta.double()])[None]
    n_pixels = obs.pixels.shape[0]
    index = torch.arange(n_pixels) if n_pixels <= max_rays else torch.randperm(n_pixels, generator=rng)[:max_rays].sort().values
    target = obs.levels[-1]
    res = problem.residuals(chain, p, camera.rays(obs.pixels[index].to(torch.float32)), target, index, jacobian=True)
    d = 6 + k
    opts = problem.options
    w = (robust_weights(res.r, opts.robust_loss, opts.robust_scale) * res.used)[0]  # [n, 5]
    J, r = res.J[0], res.r[0]  # [n, 5, d], [n, 5]
    # Residuals that are exactly zero with a zero Jacobian row (empty background on both sides) carry
    # no information and would only dilute σ².
    informative = res.used[0] & ((J.abs().sum(-1) > 0) | (r != 0))
    w = w * informative
    dof = max(int(informative.sum()) - d, 1)
    variance = float((w * r**2).sum()) / dof
    variance = max(variance, 1e-12) if math.isfinite(variance) else 1.0
    H = torch.einsum("nci,nc,ncj->ij", J, w, J)
    if not (bool(torch.isfinite(H).all()) and bool(torch.isfinite(r).all())):  # a non-finite render: no Σ
        return torch.full((d, d), math.nan, dtype=torch.float64), math.nan, dof
    # Cluster-robust ("sandwich") information: residuals are correlated within a patch of pixels.
    if patch > 1:
        pix = obs.pixels[index].cpu()
        cluster = (pix[:, 1] // patch) * 1_000_003 + pix[:, 0] // patch
        _, cluster = torch.unique(cluster, return_inverse=True)
        score = torch.einsum("nci,nc->ni", J, w * r)  # [n, d]
        G = score.new_zeros(int(cluster.max()) + 1, d).index_add(0, cluster, score)
        B = G.T @ G
    else:
        B = variance * H
    prior = torch.cat([
        torch.full((3,), param.radius ** -2),
        torch.ones(3),
        (param.half.clamp_min(1e-6)) ** -2,
    ]).double()
    H_reg = H / variance + torch.diag(prior)
    H_reg = (H_reg + H_reg.T) / 2
    inv = _spd_inverse(H_reg)
    if patch > 1:
        sigma = inv @ (B / variance**2) @ inv  # sandwich, with the prior's inverse as the bread
        # Never tighter than the independent-ray covariance (Σ₀ keeps unobserved directions bounded).
        sigma = torch.maximum(sigma.diagonal(), inv.diagonal()).sqrt()
        corr = _correlation(inv @ (B / variance**2) @ inv)
        Sigma = corr * sigma[:, None] * sigma[None, :]
    else:
        Sigma = inv
    Sigma = (Sigma + Sigma.T) / 2
    if not bool(torch.isfinite(Sigma).all()):
        Sigma = torch.diag(1 / prior)
    return Sigma, variance, dof


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
