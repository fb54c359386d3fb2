"""How the Gauss-Newton refiner's Jacobian is computed, measured: CPU seconds per Jacobian of one
iteration's residuals (``rays`` rays at the estimate's start) for each way of computing it.

- ``reverse``: the refiner's way (narf_core/gauss_newton.py): ray origins, directions and θ as
  leaves of one differentiable composite, one batched vector-Jacobian product per predicted channel.
- ``forward_differences``: ``6 + k`` extra renders of the residuals, no graph.
- ``forward_mode``: dual numbers through the composite, one pass per parameter (``None`` where the
  field uses an operation without forward-mode support, with the reason).
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

    try:
        forward, why = cpu(forward_mode), None
    except (NotImplementedError, RuntimeError) as e:
        forward, why = None, str(e).splitlines()[0][:160]
    return {
        "rays": rays,
        "parameters": d,
        "reverse_s": cpu(lambda: problem.residuals(chain, p, cam_rays, target, index, True)),
        "forward_differences_s": cpu(differences),
        "forward_mode_s": forward,
        "forward_mode_unavailable": why,
        "residuals_only_s": cpu(lambda: problem.residuals(chain, p, cam_rays, target, index, False)),
    }


def markdown(rows: dict[str, dict]) -> list[str]:
    lines = ["", "Gauss-Newton Jacobian, CPU seconds per iteration's Jacobian (one thread):", "",
             "| tool | rays | parameters | reverse, per-ray leaves (used) | forward differences | forward mode | residuals only |",
             "|---|---|---|---|---|---|---|"]
    for tool, r in rows.items():
        fwd = f"{r['forward_mode_s']:.3f}" if r["forward_mode_s"] is not None else f"n/a ({r['forward_mode_unavailable']})"
        lines.append(f"| {tool} | {r['rays']} | {r['parameters']} | {r['reverse_s']:.3f} | {r['forward_differences_s']:.3f} "
                     f"| {fwd} | {r['residuals_only_s']:.3f} |")
    return lines
