"""``narf train``: dataset -> part fields -> composition -> configuration field -> bundle.

Resumable: work in progress lives in ``<out>.work/`` beside the bundle. Each finished part field
is written there as soon as it is done; each running stage checkpoints every few seconds. Running
the same command again continues where it stopped; the folder is removed once the bundle exists.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from narf_core import __version__
from narf_core.bundle import NarfModel, load_bundle, march_step, save_bundle
from narf_core.checks import InputError, check_option_types, option_rule
from narf_core.data.dataset import Dataset
from narf_core.fields import ArticulatedField, make_field
from narf_core.fields.composed import ComposedField, union_occupancy
from narf_core.kinematics import KinematicTree
from narf_core.modes import RECORD_KEY, measure_modes
from narf_core.occupancy import density_fn
from narf_core.render import OccupancyGrid, render_rays
from narf_core.threads import free_cores
from narf_core.train.distill import composite_rays
from narf_core.train.loop import run_stage, save_atomic
from narf_core.train.track_sigma import calibrate_tracker, dataset_tool, draw_ahead
from narf_core.train.parts import (
    FreeRays, RayTargets, concat_free, concat_targets as _concat_targets, part_boxes, part_meshes, part_rays,
    part_surface_points,
)


@dataclass
class TrainConfig:
    """Hyper-parameters of both stages; ``budget_s`` caps their training time (the measurement of the render
    modes and the tracker's fit that follow are not counted).

    ``field``: the configuration field. ``articulated`` (:class:`~narf_core.fields.ArticulatedField`)
    holds the part fields' K-planes and the forward kinematics, so stage 2 takes seconds (the part
    fields are copied in, no distillation); ``distilled`` is the paper's field of ``arch``, trained
    on renders of the composed parts. ``articulated`` needs K-planes parts and at least one joint;
    otherwise the distilled field is trained.

    ``free_space_weight``: stage 1's free-space term (:func:`free_space_loss`), the mean opacity a
    part renders in front of the surface measured on a pixel, its own or another link's (0: off).

    ``sparsity_weight``: stage 1's sparsity term (:func:`sparsity_loss`), the mean opacity over one
    march step at ``sparsity_points`` random points of the part's box (0: off). No training ray reaches
    where another part hides this one in every view (the inside of the other part at the training
    configurations): without the term a part field fills it, and at other configurations that density
    shows where the other part has moved away (the pliers' crotch, rendered closed). The cells near the
    surfaces the part's own pixels measured are left out (:func:`observed_surface`), and with
    ``sparsity_keeps_meshes`` those near the part's own URDF meshes (a part that runs on inside another,
    a clamp's jaw in its body, keeps what no view shows of it). On by default (0.1): it helps most where
    parts hide one another at the training configurations and costs the others little (docs/benchmarks.md).

    ``exclusion_weight``: stage 1's exclusion term (:func:`exclusion_loss`), the mean opacity of a part field
    at ``exclusion_points`` points a step drawn on the other parts' URDF surfaces as they stand at the training
    configurations, away from the part's own surface and outside its own meshes (:func:`exclusion_points`).
    Where two parts touch at every training configuration (closed pliers' jaws side by side) no ray sees where
    one runs on into the other, and a part field is free to fill it; at another configuration that density
    shows as a fat inner edge. No part can be where another's surface is, so that space is emptied (0: off;
    the measured gains and costs per object: docs/benchmarks.md, Session 45).

    ``track_sequences``: after both stages, the tracker's own factor on σ is fitted on this many smooth
    60-frame sequences of the dataset's object at its camera and at one 4x finer (:mod:`narf_core.train.track_sigma`;
    half a minute to two minutes of CPU each) where the dataset names the object that drew it; 0: none (the
    tracker's pooled factor applies). Where a core is free beside the training's threads, the sequences are
    drawn on it while the fields train (:func:`~narf_core.train.track_sigma.draw_ahead`).

    Every field is checked when the configuration is made: :class:`TrainInputError` names the first
    bad one (``options.<name>``).
    """

    arch: str = "kplanes"
    field: str = "articulated"
    part_steps: int = 800
    distill_steps: int = 1000
    batch_rays: int = 2048
    lr: float = 0.02
    grid_resolution: int = 192
    theta_bins: int = 16  # occupancy bins over the joint box (per axis: the k-th root)
    views_per_batch: int = 64
    composites: int = 0
    distance: tuple[float, float] = (0.4, 1.0)
    depth_weight: float = 0.1
    opacity_weight: float = 1.0
    free_space_weight: float = 0.0
    sparsity_weight: float = 0.1
    sparsity_points: int = 4096
    sparsity_keeps_meshes: bool = True
    exclusion_weight: float = 1.0
    exclusion_points: int = 1024
    budget_s: float | None = None
    seed: int = 0
    keep_parts: bool = True
    track_sequences: int = 3

    def __post_init__(self) -> None:
        check_option_types(self, TrainInputError)
        need = option_rule(self, TrainInputError)
        need(self.arch in ARCHS, "arch", f"must be one of {', '.join(ARCHS)}")
        need(self.field in FIELDS, "field", f"must be one of {', '.join(FIELDS)}")
        for name in ("part_steps", "distill_steps", "batch_rays", "views_per_batch", "theta_bins", "sparsity_points",
                     "exclusion_points"):
            need(getattr(self, name) >= 1, name, "must be >= 1")
        need(self.grid_resolution >= 2, "grid_resolution", "must be >= 2")
        need(self.composites >= 0, "composites", "must be >= 0 (0 = fresh rays every step)")
        need(self.lr > 0, "lr", "must be > 0")
        for name in ("depth_weight", "opacity_weight", "free_space_weight", "sparsity_weight", "exclusion_weight"):
            need(getattr(self, name) >= 0, name, "must be >= 0")
        near_far = self.distance
        need(
            isinstance(near_far, (tuple, list)) and len(near_far) == 2
            and all(isinstance(d, (int, float)) and not isinstance(d, bool) and math.isfinite(d) for d in near_far)
            and 0 < near_far[0] <= near_far[1],
            "distance", "must be (near, far) metres with 0 < near <= far",
        )
        need(
            self.budget_s is None or (not isinstance(self.budget_s, bool) and isinstance(self.budget_s, (int, float))
                                      and 0 <= self.budget_s < math.inf),
            "budget_s", "must be None (no cap) or a finite number of seconds >= 0",
        )
        need(self.seed >= 0, "seed", "must be >= 0")
        need(0 <= self.track_sequences <= 16, "track_sequences", "must be in [0, 16] (0 = none)")

    def for_arch(self) -> TrainConfig:
        """This configuration with the learning rate suited to ``arch`` (MLPs want a smaller one)."""
        return replace(self, lr=5e-4) if self.arch == "fastnerf" else self


class TrainError(ValueError):
    """Training cannot start or resume (e.g. a work folder left by a different run)."""


class TrainInputError(InputError, TrainError):
    """A :class:`TrainConfig` field the training cannot use; ``field`` is ``options.<name>``."""


ARCHS = ("kplanes", "fastnerf")
FIELDS = ("articulated", "distilled")


def articulated_field(config: TrainConfig, kin: KinematicTree) -> bool:
    """Whether :func:`train` builds the articulated field (else it distils the paper's field)."""
    return config.field == "articulated" and config.arch == "kplanes" and kin.n_joints > 0


def ray_loss(out, targets: RayTargets, config: TrainConfig) -> torch.Tensor:
    """Colour (premultiplied on black), opacity and depth terms of a rendered batch."""
    rgb_loss = ((out.rgb - targets.rgb * targets.opacity[:, None]) ** 2).mean()
    opacity_loss = ((out.opacity - targets.opacity) ** 2).mean()
    has_depth = targets.depth > 0
    depth_loss = (
        (out.depth[has_depth] - targets.depth[has_depth] * out.opacity[has_depth].detach()).abs().mean()
        if bool(has_depth.any())
        else out.rgb.new_zeros(())
    )
    return rgb_loss + config.opacity_weight * opacity_loss + config.depth_weight * depth_loss


FREE_SPACE_MARGIN = 0.005  # metres along the measured surface's normal where the free space ends
MIN_INCIDENCE = 0.1  # the |cos| a surface seen more edge-on (or of unknown normal) counts as


def free_space_end(free: FreeRays) -> torch.Tensor:
    """``[n]``: the distance along each ray of ``free`` at which its free space ends, :data:`FREE_SPACE_MARGIN`
    from the measured surface along the surface's normal (so ``margin / |cos|`` along the ray; with
    :data:`MIN_INCIDENCE` as the least ``|cos|``).

    A margin taken along the ray (or in camera z) is a fraction of a millimetre from a surface seen
    edge-on, inside the field's density ramp, and erodes thin panels seen that way."""
    incidence = torch.ones_like(free.depth) if free.incidence is None else free.incidence
    return (free.depth / free.rays.z_per_t - FREE_SPACE_MARGIN / incidence.clamp_min(MIN_INCIDENCE)).clamp_min(0)


def free_space_loss(field, free: FreeRays, box, grid, step: float) -> torch.Tensor:
    """Mean opacity of ``field`` rendered on each ray of ``free`` from its start to its
    :func:`free_space_end` (jittered samples).

    The depth term alone may not empty the space in front of a surface: training stops a ray once it
    is opaque, so a false surface in front of the true one hides what is behind it, and the depth
    term, acting only on the samples that were marched, can pull its density up rather than down;
    nothing at all acts on a part where another link is seen. This term marches exactly the space
    that must be empty (as Urban NeRF's and DS-NeRF's free-space losses)."""
    far = free_space_end(free)
    out = render_rays(field, free.rays, box, grid=grid, step=step, outputs=("opacity",), jitter=True,
                      t_range=(torch.zeros_like(far), far))
    return out.opacity.mean()


SURFACE_CELLS = 3  # grid cells around a measured surface point that the sparsity term leaves alone


def measured_points(targets: RayTargets) -> torch.Tensor:
    """The surface points ``[n,3]`` the part's own pixels of ``targets`` measured (each its depth along its ray)."""
    own = (targets.opacity > 0.5) & (targets.depth > 0)
    rays = targets.rays[own]
    return rays.origins + (targets.depth[own] / rays.z_per_t)[:, None] * rays.directions


def observed_surface(targets: RayTargets, box: torch.Tensor, resolution: int,
                     known: torch.Tensor | None = None) -> OccupancyGrid | None:
    """The cells of ``box [2,3]`` (a grid of ``resolution``) within :data:`SURFACE_CELLS` of a surface point
    that one of the part's own pixels measured (its depth along its ray) or of a ``known [m,3]`` point of
    its surface (its URDF meshes: :func:`~narf_core.train.parts.part_surface_points`); ``None`` without any."""
    points = [measured_points(targets)]
    if known is not None:
        points.append(known.to(points[0]))
    x = torch.cat(points)
    if len(x) == 0:
        return None
    return OccupancyGrid.from_points(box, resolution, x, dilate=SURFACE_CELLS)


def sparsity_loss(field, box: torch.Tensor, step: float, n: int, generator: torch.Generator,
                  surface: OccupancyGrid | None = None) -> torch.Tensor:
    """Mean opacity over one march ``step`` (``1 - exp(-σ step)``) of ``field`` at ``n`` points drawn
    uniformly in ``box [2,3]``, those in ``surface``'s cells left out (:func:`observed_surface`): a small
    pull towards empty space wherever no ray asks for density, which leaves the measured surfaces as
    sharp as the rays make them (a softer surface takes a march more samples to stop)."""
    x = box[0] + torch.rand(n, 3, generator=generator).to(box) * (box[1] - box[0])
    if surface is not None:
        x = x[~surface.occupied(x)]
    if len(x) == 0:
        return box.new_zeros(())
    sigma = density_fn(field)(x, None)
    return (1 - torch.exp(-sigma * step)).mean()


EXCLUSION_CELLS = 1  # grid cells around a part's own surface that the exclusion term leaves alone
_INSIDE_RAY = (0.4395064455, 0.617598629942, 0.652231566745)  # exclusion_points' inside test's direction


def exclusion_points(kin: KinematicTree, part: int, box: torch.Tensor, resolution: int, thetas: torch.Tensor,
                     measured: torch.Tensor | None = None, seed: int = 0) -> torch.Tensor:
    """The other parts' URDF surfaces ``[m,3]`` in part ``part``'s frame, as they stand at each of the training
    configurations ``thetas [c,k]``: those inside the part's ``box [2,3]``, farther than :data:`EXCLUSION_CELLS`
    cells (a grid of ``resolution``) from the part's own surface (its meshes' and what its own pixels
    ``measured [n,3]``, :func:`measured_points`) and outside its own meshes. Empty for an object of one part."""
    others = [q for q in range(len(kin.parts)) if q != part]
    if not others:
        return torch.zeros(0, 3, dtype=box.dtype)
    spacing = float((box[1] - box[0]).min()) / resolution
    own = [part_surface_points(kin, part, spacing, seed)]
    if measured is not None:
        own.append(measured.to(own[0]))
    near = OccupancyGrid.from_points(box, resolution, torch.cat(own).to(box), dilate=EXCLUSION_CELLS)
    surfaces = {q: part_surface_points(kin, q, spacing, seed).double() for q in others}
    points = []
    for T in kin.part_poses(thetas.double()).reshape(-1, len(kin.parts), 4, 4):  # object from part, per configuration
        part_from_object = torch.linalg.inv(T[part])
        for q in others:
            M = part_from_object @ T[q]
            points.append(surfaces[q] @ M[:3, :3].T + M[:3, 3])
    x = torch.cat(points).to(box)
    x = x[((x >= box[0]) & (x <= box[1])).all(-1)]
    x = x[~near.occupied(x)]
    from trimesh.ray.ray_util import contains_points

    inside = torch.zeros(len(x), dtype=torch.bool)
    for mesh in part_meshes(kin, part):  # where the meshes pass through each other (a jaw in its body): its own
        # One fixed ray direction (trimesh's own default): where its two senses disagree (an open mesh) the point
        # counts as outside, instead of trimesh retrying on a random direction, so training stays reproducible.
        found = contains_points(mesh.ray, x.detach().cpu().double().numpy(), check_direction=_INSIDE_RAY)
        inside |= torch.from_numpy(found)
    return x[~inside.to(x.device)]


def exclusion_loss(field, points: torch.Tensor, step: float, n: int, generator: torch.Generator,
                   cell: torch.Tensor) -> torch.Tensor:
    """Mean opacity over one march ``step`` of ``field`` at ``n`` of ``points [m,3]`` (:func:`exclusion_points`)
    drawn with ``generator``, each moved at random within a grid cell of sides ``cell [3]``."""
    x = points[torch.randint(len(points), (n,), generator=generator)]
    x = x + (torch.rand(x.shape, generator=generator).to(x) - 0.5) * cell
    sigma = density_fn(field)(x, None)
    return (1 - torch.exp(-sigma * step)).mean()


def free_rays(batch: RayTargets, occluders: FreeRays, n: int, generator: torch.Generator) -> FreeRays:
    """The free-space rays of a step: ``batch``'s rays with a measured depth and ``n`` drawn from ``occluders``."""
    own = batch.depth > 0
    drawn = occluders[torch.randint(len(occluders), (n,), generator=generator)] if len(occluders) else occluders
    return concat_free([FreeRays(batch.rays[own], batch.depth[own], None if batch.incidence is None else batch.incidence[own]), drawn])


def _git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5, cwd=Path(__file__).parent
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def train(
    dataset_root: str | Path,
    out: str | Path,
    config: TrainConfig | None = None,
    *,
    command: str | None = None,
    progress: bool = True,
) -> Path:
    """Train every stage on ``dataset_root`` and write the bundle to ``out``; resumes if interrupted."""
    config = config or TrainConfig()
    out = Path(out)
    dataset = Dataset.open(dataset_root)
    kin = KinematicTree.from_urdf(dataset.urdf_path)
    articulated = articulated_field(config, kin)
    dataset_hash = hashlib.sha256((Path(dataset_root) / "scene.json").read_bytes()).hexdigest()[:16]
    work = out.parent / f"{out.name}.work"
    _check_work_folder(work, config, dataset_hash)
    tool = dataset_tool(dataset) if config.track_sequences else None
    seeds = list(range(1, config.track_sequences + 1))
    size = (dataset.camera.width, dataset.camera.height)
    drawing = None if tool is None else draw_ahead(tool, size, work / "sequences", seeds)
    torch.manual_seed(config.seed)
    t_start = time.perf_counter()
    # without a distillation stage the part fields get (nearly) the whole budget
    share = 0.9 if articulated else 0.35
    budget_parts = None if config.budget_s is None else share * config.budget_s / len(kin.parts)

    boxes = part_boxes(kin)
    train_thetas = training_configurations(dataset, kin)
    rays_per_part: list[RayTargets] | None = None
    occluders: list[FreeRays | None] = [None] * len(boxes)
    part_fields, part_grids, timings = [], [], {}
    for p, box in enumerate(boxes):
        done = work / f"part{p}.pt"
        field = make_field({"arch": config.arch, "aabb": box.tolist()})
        if done.exists():
            state = torch.load(done, weights_only=True)
            field.load_state_dict(state["field"])
            grid = OccupancyGrid(box, state["grid"].bool())
            timings[f"part{p}_s"] = float(state["seconds"])
        else:
            if rays_per_part is None:
                rays_per_part, found = part_rays(dataset, kin, boxes, free_space=config.free_space_weight > 0)
                if found is not None:
                    occluders = found
            known = None
            if config.sparsity_weight > 0 and config.sparsity_keeps_meshes:
                known = part_surface_points(kin, p, float((box[1] - box[0]).min()) / config.grid_resolution, config.seed)
            exclusion = None
            if config.exclusion_weight > 0:
                exclusion = exclusion_points(kin, p, box, config.grid_resolution, train_thetas,
                                             measured_points(rays_per_part[p]), config.seed)
            grid, seconds = _train_part(
                field, box, rays_per_part[p], config, work / f"part{p}.ckpt", budget_parts, progress, kin.part_names[p],
                occluders[p], known, exclusion,
            )
            save_atomic({"field": field.state_dict(), "grid": grid.occupancy.to(torch.uint8), "seconds": seconds}, done)
            timings[f"part{p}_s"] = seconds
        part_fields.append(field.eval())
        part_grids.append(grid)

    teacher = ComposedField(part_fields, part_grids, kin.part_poses)
    aabb = torch.as_tensor(kin.bounds(), dtype=torch.float32)
    lower, upper = kin.lower.float(), kin.upper.float()
    union_path = work / "union_grid.pt"
    if union_path.exists():
        state = torch.load(union_path, weights_only=True)
        union = OccupancyGrid(aabb, state["grid"].bool(), state["theta_range"])
    else:
        cell = float(OccupancyGrid.full(aabb, config.grid_resolution).cell_size.min())
        per_axis = round(len(_theta_samples(kin, boxes, cell)) ** (1 / max(len(lower), 1)))
        bins = max(2, round(config.theta_bins ** (1 / max(len(lower), 1))))  # per axis
        union = union_occupancy(
            part_grids, kin.part_poses, lower, upper, aabb, config.grid_resolution,
            bins=bins, samples_per_bin=max(2, -(-(per_axis - 1) // bins) + 1),
        )
        save_atomic({"grid": union.occupancy.to(torch.uint8), "theta_range": union.theta_range}, union_path)
    if articulated:
        started = time.perf_counter()
        student = ArticulatedField.from_parts(kin, part_fields, part_grids, aabb)
        timings["articulated_s"] = time.perf_counter() - started
    else:
        student = make_field({"arch": config.arch, "aabb": aabb.tolist(), "theta_lower": lower.tolist(), "theta_upper": upper.tolist()})
        spent = time.perf_counter() - t_start
        budget_distill = None if config.budget_s is None else max(config.budget_s - spent, 0.0)
        seconds = distill(student, teacher, union, aabb, lower, upper, config, work / "distill.ckpt", budget_distill, progress)
        timings["distill_s"] = seconds

    model = NarfModel(
        name=out.stem,
        kinematics=kin,
        field=student.eval(),
        grid=union,
        part_fields=part_fields if config.keep_parts else None,
        part_grids=part_grids if config.keep_parts else None,
        metadata={
            "provenance": {
                "dataset": str(Path(dataset_root)),
                "dataset_hash": dataset_hash,
                "command": command,
                "git_commit": _git_commit(),
                "narf_version": __version__,
                "config": asdict(config),
                "timings_s": timings,
            },
            # the views' camera: the finest footprint the model's error is counted in (estimate.trained_footprint)
            "training_camera": {"width": dataset.camera.width, "height": dataset.camera.height,
                                "fx": float(dataset.camera.K[0, 0]), "fy": float(dataset.camera.K[1, 1])},
        },
        step=march_step(aabb),
    )
    record = measure_modes(model, dataset, progress=progress)  # what `mode: auto` renders (narf_core/modes.py)
    if record is not None:
        model.metadata[RECORD_KEY] = record
    save_bundle(out, model)
    if config.track_sequences:  # the tracker's own factor on σ (narf_core/train/track_sigma.py), fitted on
        started = time.perf_counter()  # the model as it loads (its stored surface points, fields and grids)
        model = load_bundle(out)
        why = f"{dataset_root} does not name an object to draw sequences of"
        if drawing is not None:
            drawing.join()  # what it left undrawn, the fit draws
        if tool is not None:
            try:
                fitted = calibrate_tracker(model, tool, size, work / "sequences", seeds, bundle=out,
                                           workers=free_cores())
                model.metadata["uncertainty"] = {**(model.metadata.get("uncertainty") or {}), "track": fitted}
                model.metadata["provenance"]["timings_s"]["track_sigma_s"] = time.perf_counter() - started
                save_bundle(out, model)
                why = None
            except ValueError as e:  # e.g. every frame of a modality lost: nothing to fit on
                why = str(e)
        if why is not None and progress:
            print(f"narf train: the tracker's pooled factor on σ stays: {why}", file=sys.stderr)
    shutil.rmtree(work, ignore_errors=True)
    return out


def training_configurations(dataset: Dataset, kin: KinematicTree) -> torch.Tensor:
    """``[c,k]``: the distinct configurations of the dataset's ``train`` frames."""
    thetas = [kin.joint_vector(frame.joints) for frame in dataset.frames("train")]
    if not thetas or kin.n_joints == 0:  # a rigid object has one configuration, the empty one
        return torch.zeros(min(len(thetas), 1), kin.n_joints, dtype=torch.float64)
    return torch.unique(torch.stack(thetas), dim=0)


def _check_work_folder(work: Path, config: TrainConfig, dataset_hash: str) -> None:
    # Step counts and the budget only say how long to train: a resumed run may change them.
    how_long = ("budget_s", "part_steps", "distill_steps", "track_sequences")
    key = {"config": {k: v for k, v in asdict(config).items() if k not in how_long}, "dataset_hash": dataset_hash}
    key = json.loads(json.dumps(key))
    marker = work / "run.json"
    if marker.exists():
        if json.loads(marker.read_text()) != key:
            raise TrainError(
                f"{work} holds an interrupted run with other settings or data; delete it to start afresh"
            )
        return
    work.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps(key, indent=1))


def _theta_samples(kin: KinematicTree, boxes: list[torch.Tensor], cell: float, max_total: int = 4096) -> torch.Tensor:
    """``[m, k]`` configurations on a grid spanning the joint box, limits included, ``m <= max(max_total, 2^k)``.

    The grid is refined (halving its spacing) until no point of any part box ``[2,3]`` (part frame)
    moves more than ``cell`` metres between neighbouring samples, as :func:`union_occupancy` needs,
    or until a finer grid would exceed ``max_total`` (then it has as many samples as fit).
    A rigid motion displaces the points of a box by an affine function of the point, so the largest
    displacement is at one of the box's eight corners.
    """
    k = len(kin.lower)
    if k == 0:
        return torch.zeros(1, 0, dtype=torch.float64)
    corners = torch.stack([torch.cartesian_prod(*box.double().T) for box in boxes])  # [n_parts, 8, 3]
    most = 2  # samples per axis within max_total
    while (most + 1) ** k <= max_total:
        most += 1
    per_axis = 2
    while True:
        axes = [torch.linspace(float(lo), float(hi), per_axis, dtype=torch.float64) for lo, hi in zip(kin.lower, kin.upper)]
        thetas = torch.cartesian_prod(*axes).reshape(-1, k)
        T = kin.part_poses(thetas)  # [m, n_parts, 4, 4]
        points = (T[:, :, None, :3, :3] @ corners[None, :, :, :, None])[..., 0] + T[:, :, None, :3, 3]
        points = points.reshape(*[per_axis] * k, -1, 3)
        move = max(float(points.diff(dim=axis).norm(dim=-1).max()) for axis in range(k))
        if move <= cell or per_axis >= most:
            return thetas
        per_axis = min(2 * per_axis - 1, most)


def _fit_step(
    field, optimizer, batch: RayTargets, theta, box, grid, step: float, config: TrainConfig, free: FreeRays | None = None,
    generator: torch.Generator | None = None, surface: OccupancyGrid | None = None,
    exclusion: torch.Tensor | None = None,
) -> float:
    """One optimiser step of ``field`` on the rays of ``batch`` (jittered samples), with the free-space
    term on ``free`` and, given the ``generator`` of its points, the sparsity term away from ``surface``
    and the exclusion term at ``exclusion``'s points (a part field's step); returns the loss."""
    out = render_rays(field, batch.rays, box, theta=theta, grid=grid, step=step, outputs=("rgb", "opacity", "depth"), jitter=True)
    loss = ray_loss(out, batch, config) + field.regularization()
    if free is not None and len(free):
        loss = loss + config.free_space_weight * free_space_loss(field, free, box, grid, step)
    if generator is not None and config.sparsity_weight > 0:
        loss = loss + config.sparsity_weight * sparsity_loss(field, box, step, config.sparsity_points, generator, surface)
    if generator is not None and config.exclusion_weight > 0 and exclusion is not None and len(exclusion):
        cell = (box[1] - box[0]) / config.grid_resolution
        loss = loss + config.exclusion_weight * exclusion_loss(field, exclusion, step, config.exclusion_points,
                                                               generator, cell)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.item()


EARLY_REFRESH_STEPS = 50
GRID_PASSES = (1, 3)  # density evaluations per cell: the grids stage 1 rebuilds while training, its final grid


def refreshes_grid(step: int, steps: int) -> bool:
    """Whether stage 1 rebuilds a part's occupancy grid after ``step`` of ``steps``: every
    :data:`EARLY_REFRESH_STEPS` steps during the warm-up (the first quarter), then every 200.

    Until its first rebuild the grid is full and every ray is marched through the whole box, which
    makes a warm-up step several times dearer than a later one. The grid keeps every cell where the
    field reaches 1 % opacity, dilated by a cell, so a young field's surfaces stay in it, and each
    rebuild evaluates every cell again. Never after the last step: the part's final grid is built
    then anyway (:data:`GRID_PASSES`).
    """
    if step >= steps:
        return False
    warmup = steps // 4
    if step < warmup:
        return step % EARLY_REFRESH_STEPS == 0
    return step % 200 == warmup % 200


def _train_part(
    field, box, targets: RayTargets, config: TrainConfig, ckpt: Path, budget_s, progress: bool, name: str,
    occluders: FreeRays | None = None, known: torch.Tensor | None = None, exclusion: torch.Tensor | None = None,
):
    """Stage 1 for one part; with ``occluders`` (the free-space term on) each step also draws them in
    the proportion they have to ``targets``, so every labelled pixel crossing the box bounds the free space;
    ``known``: its URDF surface points (the sparsity term leaves them alone); ``exclusion``: the exclusion
    term's points (:func:`exclusion_points`)."""
    n_occluders = 0 if occluders is None else round(config.batch_rays * len(occluders) / max(len(targets), 1))
    generator = torch.Generator().manual_seed(config.seed)
    optimizer = torch.optim.Adam(field.parameters(), lr=config.lr, eps=1e-15)
    step = march_step(box)
    grid = OccupancyGrid.full(box, config.grid_resolution)
    surface = observed_surface(targets, box, config.grid_resolution, known) if config.sparsity_weight > 0 else None

    def refresh(i: int) -> None:
        nonlocal grid
        if refreshes_grid(i, config.part_steps):
            grid = OccupancyGrid.from_field(field, box, config.grid_resolution, passes=GRID_PASSES[0])

    def step_fn(i: int) -> float:
        idx = torch.randint(len(targets), (config.batch_rays,), generator=generator)
        batch = targets[idx]
        free = None if occluders is None else free_rays(batch, occluders, n_occluders, generator)
        return _fit_step(field, optimizer, batch, None, box, grid, step, config, free, generator, surface, exclusion)

    result = run_stage(
        f"part {name}", field, optimizer, step_fn, steps=config.part_steps, budget_s=budget_s, checkpoint=ckpt,
        on_step=refresh, progress=progress, generator=generator,
    )
    return OccupancyGrid.from_field(field, box, config.grid_resolution, passes=GRID_PASSES[1]), result.seconds


def distill(
    student, teacher, grid, aabb, lower, upper, config: TrainConfig, ckpt: Path, budget_s: float | None, progress: bool
) -> float:
    """Stage 2: fit ``student`` to renders of ``teacher`` (the composition) within ``budget_s``.

    Streams fresh composited rays every step, or with ``config.composites = N`` samples a pool of N
    views rendered first (the paper). Returns the seconds spent, the pool's rendering included.
    """
    started = time.perf_counter()
    generator = torch.Generator().manual_seed(config.seed + 1)
    optimizer = torch.optim.Adam(student.parameters(), lr=config.lr, eps=1e-15)
    step = march_step(aabb)
    rays_per_view = max(config.batch_rays // config.views_per_batch, 1)

    def teacher_render(field, rays, theta):
        return render_rays(field, rays, aabb, theta=theta, grid=grid, step=step, outputs=("rgb", "opacity", "depth"))

    def draw(n_views: int) -> tuple[RayTargets, torch.Tensor]:
        return composite_rays(
            teacher, teacher_render, aabb, lower, upper,
            n_views=n_views, rays_per_view=rays_per_view, distance=config.distance, generator=generator,
        )

    if config.composites:
        # The paper's variant: a fixed pool of composited views, rendered once, sampled every step.
        chunks = [draw(min(config.views_per_batch, config.composites - v)) for v in range(0, config.composites, config.views_per_batch)]
        pool = _concat_targets([c[0] for c in chunks])
        pool_theta = torch.cat([c[1] for c in chunks])
    pool_s = time.perf_counter() - started  # the budget covers rendering the pool too
    if budget_s is not None:
        budget_s = max(budget_s - pool_s, 0.0)

    def step_fn(i: int) -> float:
        if config.composites:
            idx = torch.randint(len(pool), (config.batch_rays,), generator=generator)
            batch, theta = pool[idx], pool_theta[idx]
        else:
            batch, theta = draw(config.views_per_batch)
        return _fit_step(student, optimizer, batch, theta, aabb, grid, step, config)

    return pool_s + run_stage(
        "configuration field", student, optimizer, step_fn, steps=config.distill_steps, budget_s=budget_s,
        checkpoint=ckpt, progress=progress, generator=generator,
    ).seconds
