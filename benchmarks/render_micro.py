"""Micro-benchmark of the renderer and the K-planes configuration field on a synthetic hinged object.

Fits a K-planes field (k = 1) to an analytic two-bar hinge (a bar and a jaw that swings about a
pin, striped so that colour matters), builds its occupancy grid, then reports the median of
``--repeat`` runs (wall and CPU time) of: a 160x120 and a 640x480 render in which the object covers
about 14% of the image; a refiner step (forward + backward over 1024 foreground rays, gradients for
the pose and theta only); a training step (1024 random rays, gradients for the field's weights).

    python -m benchmarks.render_micro --threads 2 --fit-seconds 90 --save /tmp/hinge.pt
    python -m benchmarks.render_micro --threads 2 --load /tmp/hinge.pt
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch
from torch import Tensor

from narf_core.fields import KPlanesField
from narf_core.bundle import march_step
from narf_core.geometry import Pinhole, Rays, invert_pose, look_at, se3_exp
from narf_core.render import OccupancyGrid, render_image, render_rays

AABB = torch.tensor([[-0.10, -0.06, -0.015], [0.10, 0.06, 0.015]])
THETA_LIMITS = (0.0, 0.8)  # radians
STEP = march_step(AABB)


class Hinge:
    """Analytic field: a fixed bar along x and a jaw hinged at ``(0.02, 0, 0)`` rotating about z by theta."""

    def __init__(self, sigma: float = 3000.0) -> None:
        self.sigma = sigma

    @staticmethod
    def _bar(p: Tensor, half: tuple[float, float, float]) -> Tensor:
        return (p.abs() <= torch.tensor(half, dtype=p.dtype)).all(-1)

    def __call__(self, x: Tensor, d: Tensor, theta: Tensor | None) -> tuple[Tensor, Tensor]:
        base = self._bar(x - torch.tensor([-0.03, 0.0, 0.0], dtype=x.dtype), (0.065, 0.012, 0.008))
        a = theta[:, 0].to(x.dtype)
        c, s = torch.cos(a), torch.sin(a)
        q = x - torch.tensor([0.02, 0.0, 0.0], dtype=x.dtype)
        local = torch.stack([c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2]], dim=-1)
        jaw = self._bar(local - torch.tensor([0.035, 0.0, 0.0], dtype=x.dtype), (0.04, 0.008, 0.006))
        stripes = 0.5 + 0.5 * torch.sin(60 * x[:, 0])
        base_rgb = torch.stack([0.9 * stripes, 0.3 + 0 * stripes, 0.2 + 0.6 * (1 - stripes)], dim=-1)
        jaw_rgb = torch.stack([0.2 + 0 * a, 0.4 + 0.5 * torch.sin(40 * local[:, 0]).abs(), 0.9 + 0 * a], dim=-1)
        sigma = torch.where(base | jaw, self.sigma, 0.0).to(x.dtype)
        return sigma, torch.where(jaw[:, None], jaw_rgb, base_rgb)


def camera_pose(azimuth: float, elevation: float, distance: float) -> Tensor:
    """``T_cam_obj``: a camera on a sphere around the origin looking at it (z up)."""
    eye = distance * torch.tensor(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )
    return invert_pose(look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])))


def random_rays(n: int, generator: torch.Generator, distance: float = 0.35) -> tuple[Rays, Tensor]:
    """Rays from random cameras (object frame) through random points of the box, and a theta per ray."""
    u = torch.rand(n, 3, generator=generator)
    z = 2 * u[:, 0] - 1
    phi = 2 * math.pi * u[:, 1]
    origin = distance * torch.stack([(1 - z**2).sqrt() * phi.cos(), (1 - z**2).sqrt() * phi.sin(), z], dim=-1)
    target = AABB[0] + (AABB[1] - AABB[0]) * torch.rand(n, 3, generator=generator)
    d = target - origin
    d = d / d.norm(dim=-1, keepdim=True)
    theta = THETA_LIMITS[0] + (THETA_LIMITS[1] - THETA_LIMITS[0]) * u[:, 2:3]
    return Rays(origin, d, torch.ones(n)), theta


def fit(field: KPlanesField, cpu_seconds: float, batch: int = 1024, lr: float = 0.02) -> None:
    """Distil the analytic hinge into ``field`` for ``cpu_seconds`` of process time."""
    teacher = Hinge()
    g = torch.Generator().manual_seed(0)
    opt = torch.optim.Adam(field.parameters(), lr=lr, eps=1e-15)
    grid = OccupancyGrid.full(AABB, 64)
    start, it = time.process_time(), 0
    while time.process_time() - start < cpu_seconds:
        rays, theta = random_rays(batch, g)
        with torch.no_grad():
            target = render_rays(teacher, rays, AABB, theta=theta, step=STEP, outputs=("rgb", "opacity"))
        out = render_rays(field, rays, AABB, theta=theta, grid=grid, step=STEP, outputs=("rgb", "opacity"), jitter=True, generator=g)
        loss = ((out.rgb - target.rgb) ** 2).mean() + ((out.opacity - target.opacity) ** 2).mean() + field.regularization()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        it += 1
        if it % 25 == 0:
            grid = OccupancyGrid.from_field(field, AABB, 64, theta_bins=4, passes=1)


def held_out_psnr(field: KPlanesField, grid: OccupancyGrid) -> float:
    rays, theta = random_rays(8192, torch.Generator().manual_seed(123))
    with torch.no_grad():
        target = render_rays(Hinge(), rays, AABB, theta=theta, step=STEP)
        pred = render_rays(field, rays, AABB, theta=theta, grid=grid, step=STEP)
    return -10 * math.log10(float(((pred.rgb - target.rgb) ** 2).mean()))


def median_ms(fn, repeat: int) -> dict:
    """Median wall and CPU milliseconds of ``fn()`` over ``repeat`` runs (after one warm-up).

    Also the smallest CPU time: on a shared machine the closest to the uncontended cost.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {
        "wall_ms": round(1e3 * statistics.median(wall), 1),
        "cpu_ms": round(1e3 * statistics.median(cpu), 1),
        "min_cpu_ms": round(1e3 * min(cpu), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch threads while timing")
    parser.add_argument("--fit-seconds", type=float, default=90.0, help="CPU seconds of fitting (1 thread)")
    parser.add_argument("--load", help="a state dict saved by --save (skips fitting)")
    parser.add_argument("--save", help="save the fitted state dict here")
    parser.add_argument("--grid-resolution", type=int, default=128)
    parser.add_argument("--dilate", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    torch.manual_seed(0)
    torch.set_num_threads(1)
    field = KPlanesField(AABB, [THETA_LIMITS[0]], [THETA_LIMITS[1]])
    if args.load:
        field.load_state_dict(torch.load(args.load, weights_only=True))
    else:
        fit(field, args.fit_seconds)
    if args.save:
        torch.save(field.state_dict(), args.save)
    field.eval().requires_grad_(False)
    start = time.process_time()
    grid = OccupancyGrid.from_field(field, AABB, args.grid_resolution, dilate=args.dilate, generator=torch.Generator().manual_seed(0))
    result: dict = {
        "threads": args.threads,
        "held_out_psnr_db": round(held_out_psnr(field, grid), 2),
        "grid": {"resolution": grid.resolution, "bins": grid.occupancy.shape[0], "fraction": round(grid.fraction, 3),
                 "build_cpu_s": round(time.process_time() - start, 1)},
        "step_m": STEP,
    }
    torch.set_num_threads(args.threads)

    theta = torch.tensor([0.4])
    T = camera_pose(0.7, 1.2, 0.17)
    for w, h in ((160, 120), (640, 480)):
        cam = Pinhole.primesense(w, h)
        with torch.no_grad():
            img = render_image(field, cam, T, theta=theta, aabb=AABB, grid=grid, step=STEP, outputs=("opacity",))
            timing = median_ms(lambda: render_image(field, cam, T, theta=theta, aabb=AABB, grid=grid, step=STEP), args.repeat)
        result[f"render_{w}x{h}"] = {**timing, "coverage": round(float((img["opacity"] > 0.5).float().mean()), 3)}

    cam = Pinhole.primesense(160, 120)
    with torch.no_grad():
        mask = render_image(field, cam, T, theta=theta, aabb=AABB, grid=grid, step=STEP, outputs=("opacity",))["opacity"]
    foreground = (mask.reshape(-1) > 0.5).nonzero()[:, 0]
    pick = foreground[torch.randperm(len(foreground), generator=torch.Generator().manual_seed(1))[:1024]]
    rays_cam = cam.rays(cam.pixel_grid()[pick])
    xi = torch.zeros(6, requires_grad=True)
    th = theta.clone().requires_grad_(True)

    def refiner_step() -> None:
        T_obj_cam = invert_pose(se3_exp(xi) @ T)
        out = render_rays(field, rays_cam.transform(T_obj_cam), AABB, theta=th, grid=grid, step=STEP, outputs=("rgb", "opacity"))
        (out.rgb.square().mean() + out.opacity.mean()).backward()

    result["refiner_step_1024_rays"] = median_ms(refiner_step, args.repeat)
    field.requires_grad_(True)
    g = torch.Generator().manual_seed(2)

    def training_step() -> None:
        rays, thetas = random_rays(1024, g)
        out = render_rays(field, rays, AABB, theta=thetas, grid=grid, step=STEP, outputs=("rgb", "opacity"), jitter=True, generator=g)
        (out.rgb.square().mean() + out.opacity.mean()).backward()

    result["training_step_1024_rays"] = median_ms(training_step, args.repeat)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
