"""How the Gauss-Newton refiner's Jacobian is computed, measured: CPU seconds per Jacobian of one
iteration's residuals (``rays`` rays at the estimate's start) for each way of computing it.

- ``field``: the refiner's way where the field serves it (narf_core/gauss_newton.py): the samples
  marched without a graph, the field's own forward differences in its lookup coordinates at every
  sample in one batched evaluation, the compositing differentiated in closed form.
- ``reverse``: ray origins, directions and θ as leaves of one differentiable composite, one batched
  vector-Jacobian product per predicted channel (the refiner's way for other fields).
- ``forward_differences``: ``6 + k`` extra renders of the residuals, no graph.
- ``forward_mode``: dual numbers through the composite, one pass per parameter (``None`` where the
  field uses an operation without forward-mode support, with the reason).
- the same ``reverse`` against ``field`` on the tracker's fixed samples (each ray's lattice samples in
  a band around the model's surface, as a tracked frame has them), with how far the second's
  Jacobian is from the first's.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from narf_core.bundle import NarfModel
from narf_core.data.dataset import Dataset, Frame


def measure(model: NarfModel, dataset: Dataset, frame: Frame, rays: int = 1024, repeats: int = 3) -> dict:
    """CPU seconds per Jacobian (mean of ``repeats``) of each method, with the parameter count."""
    import torch.autograd.forward_ad as fwAD

    from narf_core import estimate as E
    from narf_core import gauss_newton as gn
    from narf_core.geometry import Pinhole, Rays

    images = dataset.load(frame)
    mask = images.labels > 0
    # The configuration field's Jacobian (one composite, θ per ray), whatever mode `auto` picks for the model.
    options = E.EstimateOptions.preset("gauss-newton", theta_starts=1, mode="narf")
    obs = E._observation(images.rgb, mask, images.depth, E._mask_box(mask, options.box_margin), 1, model.aabb.device)
    param = E._Parameterisation.around(torch.from_numpy(np.asarray(frame.T_cam_obj, np.float64)), model)
    problem = gn.Problem(model, options, param.radius, images.depth is not None)
    chain = gn.Chain.of(param)
    theta = model.kinematics.joint_vector(frame.joints).double()
    p = torch.cat([torch.zeros(6, dtype=torch.float64), param.u_of(theta[None])[0]])[None]
    index = torch.randint(obs.pixels.shape[0], (rays,), generator=torch.Generator().manual_seed(0))
    camera = dataset.camera
    cam_rays = Pinhole(camera.K.to(obs.pixels.device), camera.width, camera.height).rays(obs.pixels[index].float())
    target = obs.levels[-1]
    d = p.shape[1]

    def cpu(fn) -> float:
        fn()
        start = time.process_time()
        for _ in range(repeats):
            fn()
        return (time.process_time() - start) / repeats

    def differences() -> None:
        problem.residuals(chain, p, cam_rays, target, index, False)
        for j in range(d):
            step = torch.zeros_like(p)
            step[0, j] = 1e-3
            problem.residuals(chain, p + step, cam_rays, target, index, False)

    T_obj_cam = torch.linalg.inv(chain.poses(p))[0].to(cam_rays.directions)
    origins = T_obj_cam[:3, 3].expand(rays, 3).contiguous()
    directions = cam_rays.directions @ T_obj_cam[:3, :3].T
    thetas = chain.thetas(p).to(cam_rays.directions).expand(rays, -1).contiguous()

    def forward_mode() -> None:
        for j in range(d):
            with fwAD.dual_level():
                tangents = [torch.zeros_like(origins), torch.zeros_like(directions), torch.zeros_like(thetas)]
                tangents[0 if j < 3 else 1 if j < 6 else 2][:, j % 3 if j < 6 else j - 6] = 1.0
                o = fwAD.make_dual(origins, tangents[0])
                dirs = fwAD.make_dual(directions, tangents[1])
                th = fwAD.make_dual(thetas, tangents[2])
                origins.requires_grad_(True)  # the differentiable (two-phase) path, as in the refiner
                out = model.render_rays(Rays(o, dirs, cam_rays.z_per_t), th, outputs=("rgb", "opacity", "depth"))
                fwAD.unpack_dual(out.rgb).tangent
                origins.requires_grad_(False)

    from narf_core.band import ray_band
    from narf_core.estimate import _object_rays
    from narf_core.track import _FRAME_MARGIN_M, frame_band, occupied

    T_cam_obj = chain.poses(p)
    near, far = ray_band(model, Pinhole(camera.K.to(obs.pixels.device), camera.width, camera.height), cam_rays,
                         T_cam_obj, chain.thetas(p), _FRAME_MARGIN_M)
    field, grid = model._field_for("narf", chain.thetas(p)[0].to(cam_rays.directions))
    samples = occupied(grid, _object_rays(cam_rays, T_cam_obj), frame_band(near.double(), far.double(), model.step),
                       chain.thetas(p)[0].to(cam_rays.directions))
    fixed = gn.Problem(model, options, param.radius, images.depth is not None, samples=samples)

    def jacobian(of: gn.Problem, field_jacobian: bool):
        before, gn._FIELD_JACOBIAN = gn._FIELD_JACOBIAN, field_jacobian
        try:
            return of.residuals(chain, p, cam_rays, target, index, True)
        finally:
            gn._FIELD_JACOBIAN = before

    J_reverse, J_field = jacobian(fixed, False).J, jacobian(fixed, True).J
    serves = getattr(field, "supports_jacobian", False)
    try:
        forward, why = cpu(forward_mode), None
    except (NotImplementedError, RuntimeError) as e:
        forward, why = None, str(e).splitlines()[0][:160]
    return {
        "rays": rays,
        "parameters": d,
        "field_s": cpu(lambda: jacobian(problem, True)) if serves else None,
        "reverse_s": cpu(lambda: jacobian(problem, False)),
        "forward_differences_s": cpu(differences),
        "forward_mode_s": forward,
        "forward_mode_unavailable": why,
        "residuals_only_s": cpu(lambda: problem.residuals(chain, p, cam_rays, target, index, False)),
        "fixed_samples": len(samples),
        "fixed_reverse_s": cpu(lambda: jacobian(fixed, False)),
        "fixed_field_s": cpu(lambda: jacobian(fixed, True)) if serves else None,
        "fixed_field_relative_error": float((J_field - J_reverse).norm() / J_reverse.norm().clamp_min(1e-30)),
    }


def markdown(rows: dict[str, dict]) -> list[str]:
    lines = ["", "Gauss-Newton Jacobian, CPU seconds per iteration's Jacobian (one thread):", "",
             "| tool | rays | parameters | the field's differences (used) | reverse, per-ray leaves | forward differences "
             "| forward mode | residuals only |",
             "|---|---|---|---|---|---|---|---|"]
    for tool, r in rows.items():
        fwd = f"{r['forward_mode_s']:.3f}" if r["forward_mode_s"] is not None else f"n/a ({r['forward_mode_unavailable']})"
        field = f"{r['field_s']:.3f}" if r.get("field_s") is not None else "n/a (view-dependent field: reverse used)"
        lines.append(f"| {tool} | {r['rays']} | {r['parameters']} | {field} | {r['reverse_s']:.3f} "
                     f"| {r['forward_differences_s']:.3f} | {fwd} | {r['residuals_only_s']:.3f} |")
    lines += ["", "On the tracker's fixed samples (no marching), CPU seconds per Jacobian:", "",
              "| tool | samples | reverse | the field's differences (used) | its distance from reverse (relative) |",
              "|---|---|---|---|---|"]
    for tool, r in rows.items():
        field = f"{r['fixed_field_s']:.3f}" if r["fixed_field_s"] is not None else "n/a (view-dependent field)"
        lines.append(f"| {tool} | {r['fixed_samples']} | {r['fixed_reverse_s']:.3f} | {field} "
                     f"| {r['fixed_field_relative_error']:.3f} |")
    return lines
