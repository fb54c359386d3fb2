"""Stage 1: one radiance field per rigid part, each in its own frame (docs/design.md §4.1).

Supervision per pixel of a training image: a pixel labelled with one of the part's links gives
colour, opacity 1 and depth (where measured); a background pixel gives opacity 0; a pixel of
another link is an occluder: it says nothing of the part behind it, but the part must be empty in
front of its measured depth (:class:`FreeRays`, the free-space term). Only rays that cross the
part's box are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from narf_core.data.dataset import Dataset
from narf_core.geometry import Rays, invert_pose
from narf_core.kinematics import KinematicTree
from narf_core.render import ray_aabb


@dataclass
class RayTargets:
    """Training rays with their targets; ``rays`` in the field's frame.

    ``rgb [n,3]`` in [0,1], ``opacity [n]`` (1 object, 0 empty), ``depth [n]`` camera z in metres
    (0 = not measured), ``incidence [n]`` the measured surface's :func:`surface_incidence` (None: 1).
    """

    rays: Rays
    rgb: Tensor
    opacity: Tensor
    depth: Tensor
    incidence: Tensor | None = None

    def __len__(self) -> int:
        return len(self.rays)

    def __getitem__(self, index) -> RayTargets:
        incidence = None if self.incidence is None else self.incidence[index]
        return RayTargets(self.rays[index], self.rgb[index], self.opacity[index], self.depth[index], incidence)


def part_meshes(kin: KinematicTree, part: int) -> list[trimesh.Trimesh]:
    """The visual meshes of part ``part``'s links, each placed in the part's own frame (where its field
    lives; a part's links do not move against each other, so any configuration gives the same)."""
    meshes = kin.visual_meshes()  # copies: placing them leaves the tree's own alone
    poses = kin.link_poses(kin.mid_configuration())
    T_part_obj = invert_pose(kin.part_poses(kin.mid_configuration())[part])
    return [meshes[link].apply_transform((T_part_obj @ poses[kin.links.index(link)]).numpy())
            for link in kin.parts[part] if link in meshes]


def part_boxes(kin: KinematicTree, margin: float = 0.01) -> list[Tensor]:
    """Each part's box ``[2,3]`` in its own frame: its links' visual bounds plus ``margin`` metres."""
    boxes = []
    for p in range(len(kin.parts)):
        placed = part_meshes(kin, p)
        if not placed:
            raise ValueError(f"part {kin.part_names[p]!r} has no visual geometry to learn")
        pts = np.concatenate([np.asarray(mesh.vertices) for mesh in placed])
        boxes.append(torch.tensor(np.stack([pts.min(0) - margin, pts.max(0) + margin]), dtype=torch.float32))
    return boxes


def part_surface_points(kin: KinematicTree, part: int, spacing: float, seed: int = 0) -> Tensor:
    """The visual surface ``[m,3]`` of part ``part`` in its own frame (:func:`part_meshes`): its links'
    mesh vertices and points drawn on their faces, about one per ``spacing`` squared of area, so that
    no stretch of the surface much wider than ``spacing`` goes without one."""
    points = [np.zeros((0, 3))]
    for mesh in part_meshes(kin, part):
        drawn, _ = trimesh.sample.sample_surface(mesh, int(np.ceil(mesh.area / spacing**2)) + 1, seed=seed)
        points += [np.asarray(mesh.vertices), drawn]
    return torch.tensor(np.concatenate(points), dtype=torch.float32)


def surface_incidence(rays: Rays, depth: Tensor, height: int, width: int) -> Tensor:
    """``[H*W]``: ``|cos|`` of the angle between each pixel's ray (camera frame, row-major ``[H*W]``)
    and the normal of the surface its depth ``[H*W]`` (camera z, 0 = none) measures; 0 where unknown.

    The normal is the cross product of the two image axes' tangents, each the difference to the
    neighbour nearer in depth, so that a tangent never spans a depth edge where a smoother side
    exists; a pixel with no measured neighbour along an axis gets 0 (as seen edge-on).
    """
    points = (rays.directions * (depth / rays.z_per_t)[:, None]).reshape(height, width, 3)
    valid = (depth > 0).reshape(height, width)
    tangents, known = [], valid
    for axis in (0, 1):
        step = points.diff(dim=axis)  # pixel i+1 minus pixel i
        both = valid.narrow(axis, 1, valid.shape[axis] - 1) & valid.narrow(axis, 0, valid.shape[axis] - 1)
        jump = torch.where(both, step[..., 2].abs(), torch.inf)
        ahead, behind = _pad(jump, axis, front=False), _pad(jump, axis, front=True)
        use_ahead = (ahead <= behind)[..., None]
        tangents.append(torch.where(use_ahead, _pad(step, axis, front=False), _pad(step, axis, front=True)))
        known = known & torch.minimum(ahead, behind).isfinite()
    normal = torch.cross(tangents[0], tangents[1], dim=-1).reshape(-1, 3)
    cos = (normal * rays.directions).sum(-1).abs() / normal.norm(dim=-1).clamp_min(1e-12)
    return torch.where(known.reshape(-1), cos, 0.0)


def _pad(x: Tensor, axis: int, front: bool) -> Tensor:
    """``x`` with one slice of ``inf`` added along ``axis``, before its first slice or after its last."""
    fill = torch.full_like(x.narrow(axis, 0, 1), torch.inf)
    return torch.cat([fill, x] if front else [x, fill], dim=axis)


def _frames(dataset: Dataset, kin: KinematicTree, split: str, incidence: bool):
    """Per frame of ``split``: ``(rays [HW], rgb [HW,3], depth [HW] (0 = none), incidence [HW]
    (:func:`surface_incidence`; None unless ``incidence``), pixel_part [HW] (-1 = background),
    T_part_cam [n_parts,4,4])``, the rays in the camera frame."""
    cam_rays = dataset.camera.rays()
    link_part = torch.tensor([kin.part_of_link[kin.links.index(name)] for name in dataset.links])
    for frame in dataset.frames(split):
        images = dataset.load(frame)
        labels = torch.from_numpy(images.labels.reshape(-1).astype(np.int64))
        rgb = torch.tensor(images.rgb.reshape(-1, 3), dtype=torch.float32) / 255
        depth = (
            torch.from_numpy(images.depth.reshape(-1)).float() if images.depth is not None else torch.zeros(len(labels))
        )
        theta = kin.joint_vector(frame.joints)
        T_cam_part = torch.from_numpy(frame.T_cam_obj).float() @ kin.part_poses(theta).float()
        pixel_part = torch.where(labels > 0, link_part[(labels - 1).clamp_min(0)], torch.full_like(labels, -1))
        cos = surface_incidence(cam_rays, depth, dataset.camera.height, dataset.camera.width) if incidence else None
        yield cam_rays, rgb, depth, cos, pixel_part, invert_pose(T_cam_part)


def _in_box(cam_rays: Rays, keep: Tensor, T_part_cam: Tensor, box: Tensor) -> tuple[Tensor, Rays]:
    """The pixels ``keep`` whose rays cross ``box``, and those rays in the part's frame."""
    rays = cam_rays[keep].transform(T_part_cam)
    _, _, hit = ray_aabb(rays.origins, rays.directions, box)
    return keep[hit], rays[hit]


@dataclass
class FreeRays:
    """Rays ``[n]`` (the part's frame) on which the part must be empty in front of ``depth [n]``, the
    camera z of the surface measured there: the first visible surface of another link (an occluder)
    or of the part's own; ``incidence [n]`` that surface's :func:`surface_incidence` (None: 1)."""

    rays: Rays
    depth: Tensor
    incidence: Tensor | None = None

    def __len__(self) -> int:
        return len(self.rays)

    def __getitem__(self, index) -> FreeRays:
        return FreeRays(self.rays[index], self.depth[index], None if self.incidence is None else self.incidence[index])


def part_rays(
    dataset: Dataset, kin: KinematicTree, boxes: list[Tensor], split: str = "train", free_space: bool = True
) -> tuple[list[RayTargets], list[FreeRays] | None]:
    """For every part, in the part frame and in one pass over ``split``: the supervising rays that
    cross its box (its own pixels and the background's), and, for the free-space term (``free_space``;
    else None and no :func:`surface_incidence`), the rays of other links' pixels with a measured depth
    that cross it (its occluders)."""
    targets: list[list[RayTargets]] = [[] for _ in kin.parts]
    occluders: list[list[FreeRays]] = [[] for _ in kin.parts]
    for cam_rays, rgb, depth, incidence, pixel_part, T_part_cam in _frames(dataset, kin, split, free_space):
        for p, box in enumerate(boxes):
            mine = pixel_part == p
            keep, rays = _in_box(cam_rays, (mine | (pixel_part < 0)).nonzero().squeeze(-1), T_part_cam[p], box)
            cos = None if incidence is None else incidence[keep]
            targets[p].append(RayTargets(rays, rgb[keep], mine[keep].float(), depth[keep] * mine[keep], cos))
            if free_space:
                other = (pixel_part >= 0) & ~mine & (depth > 0)
                keep, rays = _in_box(cam_rays, other.nonzero().squeeze(-1), T_part_cam[p], box)
                occluders[p].append(FreeRays(rays, depth[keep], incidence[keep]))
    return [concat_targets(chunks) for chunks in targets], [concat_free(c) for c in occluders] if free_space else None


def concat_rays(chunks: list[Rays]) -> Rays:
    """One :class:`Rays` from several, in order."""
    return Rays(*(torch.cat([getattr(c, a) for c in chunks]) for a in ("origins", "directions", "z_per_t")))


def concat_targets(chunks: list[RayTargets]) -> RayTargets:
    """One :class:`RayTargets` from several, in order."""
    if not chunks:
        raise ValueError("no training frames")
    return RayTargets(
        concat_rays([c.rays for c in chunks]),
        torch.cat([c.rgb for c in chunks]),
        torch.cat([c.opacity for c in chunks]),
        torch.cat([c.depth for c in chunks]),
        _concat_incidence(chunks),
    )


def concat_free(chunks: list[FreeRays]) -> FreeRays:
    """One :class:`FreeRays` from several, in order."""
    return FreeRays(concat_rays([c.rays for c in chunks]), torch.cat([c.depth for c in chunks]), _concat_incidence(chunks))


def _concat_incidence(chunks: list[RayTargets] | list[FreeRays]) -> Tensor | None:
    """The chunks' ``incidence`` in order (1 for a chunk without), or None if no chunk has one."""
    if all(c.incidence is None for c in chunks):
        return None
    return torch.cat([torch.ones(len(c)) if c.incidence is None else c.incidence for c in chunks])
