"""Stage 1: one radiance field per rigid part, each in its own frame (docs/design.md §4.1).

Supervision per pixel of a training image: a pixel labelled with one of the part's links gives
colour, opacity 1 and depth (where measured); a background pixel gives opacity 0; a pixel of
another link is an occluder and is ignored. Only rays that cross the part's box are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from narf_core.data.dataset import Dataset
from narf_core.geometry import Rays, invert_pose
from narf_core.kinematics import KinematicTree
from narf_core.render import ray_aabb


@dataclass
class RayTargets:
    """Training rays with their targets; ``rays`` in the field's frame.

    ``rgb [n,3]`` in [0,1], ``opacity [n]`` (1 object, 0 empty), ``depth [n]`` camera z in metres
    (0 = not measured).
    """

    rays: Rays
    rgb: Tensor
    opacity: Tensor
    depth: Tensor

    def __len__(self) -> int:
        return len(self.rays)

    def __getitem__(self, index) -> RayTargets:
        return RayTargets(self.rays[index], self.rgb[index], self.opacity[index], self.depth[index])


def part_boxes(kin: KinematicTree, margin: float = 0.01) -> list[Tensor]:
    """Each part's box ``[2,3]`` in its own frame: its links' visual bounds plus ``margin`` metres."""
    meshes = kin.visual_meshes()
    poses = kin.link_poses(kin.mid_configuration())
    part_poses = kin.part_poses(kin.mid_configuration())
    boxes = []
    for p, links in enumerate(kin.parts):
        T_part_obj = invert_pose(part_poses[p])
        corners = []
        for link in links:
            if link not in meshes:
                continue
            T = (T_part_obj @ poses[kin.links.index(link)]).numpy()
            v = meshes[link].vertices
            corners.append(v @ T[:3, :3].T + T[:3, 3])
        if not corners:
            raise ValueError(f"part {kin.part_names[p]!r} has no visual geometry to learn")
        pts = np.concatenate(corners)
        boxes.append(torch.tensor(np.stack([pts.min(0) - margin, pts.max(0) + margin]), dtype=torch.float32))
    return boxes


def part_rays(dataset: Dataset, kin: KinematicTree, boxes: list[Tensor], split: str = "train") -> list[RayTargets]:
    """For every part, the supervising rays of ``split`` that cross its box, in the part frame."""
    camera = dataset.camera
    cam_rays = camera.rays()
    link_part = torch.tensor([kin.part_of_link[kin.links.index(name)] for name in dataset.links])
    collected: list[list[RayTargets]] = [[] for _ in kin.parts]
    for frame in dataset.frames(split):
        images = dataset.load(frame)
        labels = torch.from_numpy(images.labels.reshape(-1).astype(np.int64))
        rgb = torch.tensor(images.rgb.reshape(-1, 3), dtype=torch.float32) / 255
        depth = (
            torch.from_numpy(images.depth.reshape(-1)).float() if images.depth is not None else torch.zeros(len(labels))
        )
        theta = kin.joint_vector(frame.joints)
        T_obj_part = kin.part_poses(theta).float()
        T_cam_obj = torch.from_numpy(frame.T_cam_obj).float()
        pixel_part = torch.where(labels > 0, link_part[(labels - 1).clamp_min(0)], torch.full_like(labels, -1))
        for p, box in enumerate(boxes):
            T_part_cam = invert_pose(T_cam_obj @ T_obj_part[p])
            mine, empty = pixel_part == p, labels == 0
            keep = (mine | empty).nonzero().squeeze(-1)
            rays = cam_rays[keep].transform(T_part_cam)
            _, _, hit = ray_aabb(rays.origins, rays.directions, box)
            keep, rays = keep[hit], rays[hit]
            collected[p].append(RayTargets(rays, rgb[keep], mine[keep].float(), depth[keep] * mine[keep]))
    return [concat_targets(chunks) for chunks in collected]


def concat_targets(chunks: list[RayTargets]) -> RayTargets:
    """One :class:`RayTargets` from several, in order."""
    if not chunks:
        raise ValueError("no training frames")
    return RayTargets(
        Rays(
            torch.cat([c.rays.origins for c in chunks]),
            torch.cat([c.rays.directions for c in chunks]),
            torch.cat([c.rays.z_per_t for c in chunks]),
        ),
        torch.cat([c.rgb for c in chunks]),
        torch.cat([c.opacity for c in chunks]),
        torch.cat([c.depth for c in chunks]),
    )
