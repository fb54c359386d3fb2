"""URDF kinematic trees and batched, differentiable forward kinematics in torch.

A URDF is parsed with yourdfpy into a :class:`KinematicTree`: its links in topological order (root
first), every joint as a frozen :class:`Joint`, the movable joints that make up the configuration
vector ``theta [k]`` (in the order the URDF file lists them), and the rigid *parts*: groups of
links joined by fixed joints, each with the frame of its top link.

URDF semantics (https://wiki.ros.org/urdf/XML/joint): a joint's ``origin`` is ``T_parent_joint``,
its ``rpy`` fixed-axis angles give ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the child link's frame is
the joint frame moved by the joint value along (prismatic) or about (revolute, continuous) the
joint ``axis``, which is expressed in the joint frame, must be a unit vector (to 1e-3: tools
disagree on other lengths) and is normalised here. So
``T_parent_child(q) = origin @ motion(axis, q)`` and ``T_obj_link`` composes those from the root.

This is the one URDF reader of NARF (the dataset format and the generator use it too), with one
set of rules:
  - joint types: revolute, continuous, prismatic, fixed; a revolute or prismatic joint needs
    finite limits with ``lower < upper`` (a joint that cannot move is a fixed joint);
  - a continuous joint is a revolute joint with limits ``[-pi, pi]``: one full turn, so that fields
    and refiners see a bounded range like any other joint's;
  - fixed joints merge the links they join into one rigid part (a chain of them too);
  - mimic joints are supported: ``<mimic joint="src" multiplier="m" offset="o"/>`` makes the
    joint's value ``m * q_src + o``. The source must be a joint of ``theta`` (not itself a mimic
    joint) and ``m`` non-zero; a mimic joint is not part of ``theta``, and its own ``<limit>`` is
    not used: its range is the source's range mapped through ``m``, ``o``;
  - at most :data:`MAX_JOINTS` joints in ``theta`` (mimic and fixed joints do not count);
  - mesh filenames resolve by :func:`resolve_mesh` (relative, absolute, ``file://``, ``package://``).
"""

from __future__ import annotations

import io
import itertools
import math
import xml.etree.ElementTree as ET
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import trimesh
import yourdfpy
from torch import Tensor

from narf_core.checks import InputError, check_joints
from narf_core.geometry import make_pose, skew

MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
SUPPORTED_TYPES = (*MOVABLE_TYPES, "fixed")
_SPEED_STEP = 1e-4  # radians or metres: the central difference of surface_speeds (and the least speed counted)
MAX_JOINTS = 8  # longest theta: training's occupancy keeps at least 2 configuration bins per joint (2^k grids)
_AXIS_NORM_TOLERANCE = 1e-3  # axes written with 3-4 digits ("0.707 0 0.707") are normalised
_BOUNDS_ANGLE_STEP = math.radians(10.0)
_BOUNDS_MAX_CONFIGS = 4096
_BOUNDS_MARGIN = 0.02  # of the diagonal; 10-degree steps miss at most r (1 - cos 5 deg) < 0.004 r
# The surface points a depth image's points are fitted to (narf_core/surface_fit.py): a point-to-point pair sits
# about half this spacing off the observed surface, a bias of millimetres where a large part's 500 points lie
# centimetres apart (the cabinet's body, 2 cm); at most this many on one link (the cabinet's 1 m² body: 11 mm).
DENSE_SPACING_M = 0.005
DENSE_MOST_PER_LINK = 8000


class UrdfError(ValueError):
    """A URDF that cannot be used; the message is one line: ``<file>: <what is wrong>``."""


def _error(source: str, problem: str) -> UrdfError:
    return UrdfError(" ".join(f"{source}: {problem}".split()))


@dataclass(frozen=True, eq=False)
class Joint:
    """One URDF joint: ``origin [4, 4]`` is ``T_parent_child`` at zero, ``axis [3]`` unit if movable.

    ``lower``/``upper`` are the limits in the joint's unit (radians or metres); a continuous joint
    gets ``[-pi, pi]`` and a fixed joint ``[0, 0]``. ``mimic`` is ``(source joint, multiplier,
    offset)`` for a mimic joint (its limits are then the source's, mapped), else ``None``.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None = None

    @property
    def is_movable(self) -> bool:
        return self.type in MOVABLE_TYPES

    @property
    def is_actuated(self) -> bool:
        """Movable and not a mimic joint: a coordinate of ``theta``."""
        return self.is_movable and self.mimic is None


class KinematicTree:
    """The links, joints and rigid parts of a URDF, with forward kinematics in torch.

    Attributes:
        urdf_text: the URDF it was built from (bundles store it).
        name: the ``<robot name=...>`` (may be empty).
        root: the root link's name; ``T_obj_link`` is expressed in its frame.
        links: link names, root first, parents before children (depth first, in file order).
        links_in_file: link names in the order the file lists them (a dataset's label order).
        joints: every joint, ``joints[i]`` being the parent joint of ``links[i + 1]``.
        movable: the revolute, continuous and prismatic joints in URDF file order, mimic joints
            left out: the order of ``theta``.
        mimics: the mimic joints, in file order.
        joint_names: the names of ``movable``.
        lower, upper: ``[k]`` float64 joint limits.
        parts: rigid groups of link names (links joined by fixed joints), ordered like ``links``;
            a part's frame is its first (top) link's.
        part_of_link: for each link of ``links``, the index of its part.
        part_names: the first link's name of each part.
    """

    def __init__(
        self, urdf_text: str, *, mesh_dir: str | Path | None = None, source: str = "<urdf string>"
    ) -> None:
        """Parse ``urdf_text``; mesh files (if any) are looked up in ``mesh_dir`` when first needed."""
        self.urdf_text = urdf_text
        self.source = source
        self.mesh_dir = None if mesh_dir is None else Path(mesh_dir)
        robot = _parse_robot(urdf_text, source)
        self.name = robot.name or ""
        if not robot.links:
            raise _error(source, "the robot has no <link>")
        for kind, elements in (("link", robot.links), ("joint", robot.joints)):
            repeated = sorted(name for name, n in Counter(e.name for e in elements).items() if n > 1)
            if repeated:
                raise _error(source, f"duplicate {kind} names {repeated}")
        self._robot_links = {link.name: link for link in robot.links}
        joints_in_file = _resolve_mimics([_make_joint(j, set(self._robot_links), source) for j in robot.joints], source)

        self.root, self.joints = _topological_order(list(self._robot_links), joints_in_file, source)
        self.links = [self.root] + [j.child for j in self.joints]
        self.links_in_file = list(self._robot_links)
        self.movable = [j for j in joints_in_file if j.is_actuated]
        if len(self.movable) > MAX_JOINTS:
            first_extra, names = self.movable[MAX_JOINTS].name, ", ".join(repr(j.name) for j in self.movable)
            raise _error(
                source,
                f"joint {first_extra!r} is movable joint number {MAX_JOINTS + 1}; NARF handles at most {MAX_JOINTS} "
                f"(this URDF has {len(self.movable)}: {names}); make the joints you do not need fixed "
                "(fixed and mimic joints do not count)",
            )
        self.mimics = [j for j in joints_in_file if j.mimic is not None]
        self.joint_names = [j.name for j in self.movable]
        self.lower = torch.tensor([j.lower for j in self.movable], dtype=torch.float64)
        self.upper = torch.tensor([j.upper for j in self.movable], dtype=torch.float64)

        link_index = {name: i for i, name in enumerate(self.links)}
        self._parent_index = [link_index[j.parent] for j in self.joints]
        theta_index = {name: i for i, name in enumerate(self.joint_names)}
        self._theta_index = [theta_index.get(j.name if j.mimic is None else j.mimic[0], -1) for j in self.joints]
        self._mimic = [(1.0, 0.0) if j.mimic is None else j.mimic[1:] for j in self.joints]
        self._origins = torch.tensor(np.array([j.origin for j in self.joints]).reshape(-1, 4, 4))
        self._axes = torch.tensor(np.array([j.axis for j in self.joints]).reshape(-1, 3))

        part_of_link, n_parts = [0], 1
        for i, joint in enumerate(self.joints):
            if joint.type == "fixed":
                part_of_link.append(part_of_link[self._parent_index[i]])
            else:
                part_of_link.append(n_parts)
                n_parts += 1
        self.part_of_link = part_of_link
        self.parts = [[n for n, p in zip(self.links, part_of_link) if p == part] for part in range(n_parts)]
        self.part_names = [links[0] for links in self.parts]
        self._part_link_index = [link_index[name] for name in self.part_names]
        self._meshes: dict[str, trimesh.Trimesh] | None = None

    @classmethod
    def from_urdf(cls, path: str | Path, load_meshes: bool = True) -> KinematicTree:
        """Load a URDF file; meshes resolve relative to its folder, and load now if ``load_meshes``."""
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError as e:
            raise _error(str(path), "no such URDF file") from e
        except (OSError, UnicodeDecodeError) as e:
            raise _error(str(path), f"cannot read the file ({e.__class__.__name__})") from e
        tree = cls(text, mesh_dir=path.parent, source=str(path))
        if load_meshes:
            tree.visual_meshes()
        return tree

    @classmethod
    def from_urdf_string(cls, text: str, mesh_dir: str | Path | None = None) -> KinematicTree:
        """Build from URDF text (as bundles store it); kinematics need no meshes."""
        return cls(text, mesh_dir=mesh_dir)

    def __repr__(self) -> str:
        return f"KinematicTree({self.source!r}, links={len(self.links)}, joints={self.joint_names})"

    @property
    def n_joints(self) -> int:
        """``k``, the length of ``theta``."""
        return len(self.movable)

    # --- forward kinematics ---------------------------------------------------------------------

    def link_poses(self, theta: Tensor | None) -> Tensor:
        """``T_obj_link [..., n_links, 4, 4]`` for ``theta [..., k]``, in ``links`` order.

        dtype and device follow ``theta``; differentiable in ``theta``; values outside the limits
        are computed as given (the limits are enforced by :meth:`joint_vector`). An object without
        joints (only fixed ones) also takes ``theta=None``, the empty configuration (float64 poses).
        """
        if theta is None and self.n_joints == 0:
            theta = torch.zeros(0, dtype=torch.float64)
        if not isinstance(theta, Tensor) or not theta.is_floating_point():
            raise ValueError(f"theta must be a floating-point tensor, got {_describe(theta)}")
        if theta.ndim == 0 or theta.shape[-1] != self.n_joints:
            raise ValueError(
                f"theta must have shape [..., {self.n_joints}] (joints {self.joint_names}), got {list(theta.shape)}"
            )
        batch = theta.shape[:-1]
        origins = self._origins.to(theta)
        axes = self._axes.to(theta)
        poses = [torch.eye(4, dtype=theta.dtype, device=theta.device).expand(*batch, 4, 4)]
        for i, joint in enumerate(self.joints):
            origin = origins[i]
            if joint.type == "fixed":
                local = origin
            elif joint.type == "prismatic":
                shift = origin[:3, :3] @ axes[i]
                t = origin[:3, 3] + self._value(theta, i)[..., None] * shift
                local = make_pose(origin[:3, :3].expand(*batch, 3, 3), t)
            else:
                R = origin[:3, :3] @ _rotation_about(axes[i], self._value(theta, i))
                local = make_pose(R, origin[:3, 3].expand(*batch, 3))
            poses.append(poses[self._parent_index[i]] @ local)
        return torch.stack(poses, dim=-3)

    def _value(self, theta: Tensor, i: int) -> Tensor:
        """Joint ``i``'s value ``[...]``: its coordinate of ``theta``, or its mimic of one."""
        value = theta[..., self._theta_index[i]]
        multiplier, offset = self._mimic[i]
        return value if (multiplier, offset) == (1.0, 0.0) else value * multiplier + offset

    def part_poses(self, theta: Tensor | None) -> Tensor:
        """``T_obj_part [..., n_parts, 4, 4]``: the pose of each part's top link."""
        return self.link_poses(theta)[..., self._part_link_index, :, :]

    # --- configurations -------------------------------------------------------------------------

    def mid_configuration(self) -> Tensor:
        """``[k]`` float64: every joint half-way between its limits (0 for continuous joints)."""
        return (self.lower + self.upper) / 2

    def joint_vector(
        self,
        joints: Mapping[str, float] | None,
        *,
        fill_mid: bool = True,
        field: str = "joints",
        error: type[InputError] = InputError,
    ) -> Tensor:
        """``{name: value}`` to ``theta [k]`` float64, checked by :func:`narf_core.checks.check_joints`.

        Joints left out take their mid value when ``fill_mid`` (else that is an error). Raises
        ``error`` (an :class:`~narf_core.checks.InputError`) naming ``field`` and the joint.
        """
        values = check_joints(self.movable, joints, field, complete=not fill_mid, error=error)
        theta = self.mid_configuration()
        for i, name in enumerate(self.joint_names):
            if name in values:
                theta[i] = values[name]
        return theta

    def surface_speeds(self, points: Mapping[str, np.ndarray], theta: Tensor | None = None) -> Tensor:
        """``[k]`` float64: how far each joint moves the surface, in metres per unit of the joint (per
        radian or per metre): the root mean square speed of the surface points ``points`` (``{link: [n, 3]}``,
        link frame) that the joint moves, at ``theta [k]`` (mid-range if None), by central differences.
        A prismatic joint moves its points at 1; a revolute one at their distance from its axis, which is
        short for a small part at the end of a chain: there the same surface error is a larger angle.
        0 where the joint moves no point."""
        speed = self.point_speeds(points, theta)
        moving = speed > _SPEED_STEP
        return ((speed**2 * moving).sum(-1) / moving.sum(-1).clamp_min(1)).sqrt()

    def moved_points(self, points: Mapping[str, np.ndarray], theta: Tensor | None = None) -> Tensor:
        """``[k, N]`` bool: which of the surface points ``points`` (as :meth:`point_speeds` orders them) each
        joint moves, at ``theta [k]`` (mid-range if None)."""
        return self.point_speeds(points, theta) > _SPEED_STEP

    def point_speeds(self, points: Mapping[str, np.ndarray], theta: Tensor | None = None) -> Tensor:
        """``[k, N]`` float64: each joint's speed (metres per unit of the joint) at each of the surface points
        ``points`` (``{link: [n, 3]}``, link frame; ``N`` of them, in the order of :attr:`links`), at
        ``theta [k]`` (mid-range if None), by central differences; 0 where the joint does not move it."""
        theta = self.mid_configuration() if theta is None else theta.detach().to(torch.float64)
        step = _SPEED_STEP * torch.eye(self.n_joints, dtype=torch.float64)
        poses = self.link_poses(torch.cat([theta + step, theta - step]))  # [2k, links, 4, 4]
        moved = []
        for i, link in enumerate(self.links):
            own = torch.as_tensor(np.asarray(points.get(link, np.zeros((0, 3)))), dtype=torch.float64).reshape(-1, 3)
            moved.append(own @ poses[:, i, :3, :3].transpose(-1, -2) + poses[:, i, None, :3, 3])  # [2k, n, 3]
        moved = torch.cat(moved, 1)
        return (moved[: self.n_joints] - moved[self.n_joints :]).norm(dim=-1) / (2 * _SPEED_STEP)

    def joint_dict(self, theta: Tensor) -> dict[str, float]:
        """``theta [k]`` to ``{name: value}`` in URDF file order."""
        if tuple(theta.shape) != (self.n_joints,):
            raise ValueError(
                f"theta must have shape [{self.n_joints}] (joints {self.joint_names}), got {list(theta.shape)}"
            )
        return {name: float(v) for name, v in zip(self.joint_names, theta.tolist())}

    # --- geometry -------------------------------------------------------------------------------

    def visual_meshes(self) -> dict[str, trimesh.Trimesh]:
        """Per link with visuals, all its ``<visual>`` geometry merged into one mesh in the link frame.

        Meshes (with their ``scale``), boxes, cylinders and spheres, each placed by its ``origin``.
        Geometry only: materials are not kept. Links without visuals are left out.
        """
        if self._meshes is None:
            self._meshes = {
                name: _merge(name, link.visuals, self.mesh_dir, self.source)
                for name in self.links
                if (link := self._robot_links[name]).visuals
            }
        return {name: mesh.copy() for name, mesh in self._meshes.items()}

    def mesh_files(self) -> dict[str, Path]:
        """Every ``<mesh filename=...>`` of the links (visual and collision) and the file it resolves to."""
        if self.mesh_dir is None:
            return {}
        files = {}
        for name, link in self._robot_links.items():
            for element in [*link.visuals, *link.collisions]:
                mesh = None if element.geometry is None else element.geometry.mesh
                if mesh is not None:
                    files[mesh.filename] = resolve_mesh(mesh.filename, self.mesh_dir, link=name, source=self.source)
        return files

    def sample_points(self, n_per_link: int = 500, seed: int = 0) -> dict[str, np.ndarray]:
        """``{link: [n_per_link, 3]}`` float64 points, uniform on each link's visual surface (link frame)."""
        if n_per_link <= 0:
            raise ValueError(f"n_per_link must be positive, got {n_per_link}")
        meshes = self.visual_meshes()
        return {
            name: np.asarray(trimesh.sample.sample_surface(mesh, n_per_link, seed=seed + i)[0], np.float64)
            for i, (name, mesh) in enumerate(meshes.items())
        }

    def dense_points(self, spacing_m: float = DENSE_SPACING_M, most_per_link: int = DENSE_MOST_PER_LINK,
                     seed: int = 0) -> dict[str, np.ndarray]:
        """``{link: [n, 3]}`` float64 points, uniform on each link's visual surface (link frame), about
        ``spacing_m`` apart: a link's area over ``spacing_m²`` of them, at least 500 and at most
        ``most_per_link``."""
        if not spacing_m > 0 or most_per_link < 500:
            raise ValueError(f"spacing_m must be > 0 and most_per_link >= 500, got {spacing_m} and {most_per_link}")
        meshes = self.visual_meshes()
        return {
            name: np.asarray(trimesh.sample.sample_surface(
                mesh, int(np.clip(mesh.area / spacing_m**2, 500, most_per_link)), seed=seed + i)[0], np.float64)
            for i, (name, mesh) in enumerate(meshes.items())
        }

    def bounds(self) -> np.ndarray:
        """``[2, 3]`` (min, max) object-frame box holding every link's visual over the joint range.

        Each link's convex hull vertices (its origin if it has no visual) are moved by FK at sampled
        configurations: prismatic joints at their limits, rotating joints every 10 degrees from limit
        to limit; the full grid if it has at most 4096 configurations, else every corner of the
        joint box (up to 4096) and random configurations. A 2% margin of the diagonal covers the
        sampling.
        """
        meshes = self.visual_meshes()
        poses = self.link_poses(torch.as_tensor(self._bounds_configurations())).numpy()  # [n, links, 4, 4]
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        for i, name in enumerate(self.links):
            vertices = meshes[name].convex_hull.vertices if name in meshes else np.zeros((1, 3))
            moved = vertices @ poses[:, i, :3, :3].transpose(0, 2, 1) + poses[:, i, None, :3, 3]  # [n, m, 3]
            low = np.minimum(low, moved.min((0, 1)))
            high = np.maximum(high, moved.max((0, 1)))
        margin = _BOUNDS_MARGIN * max(float(np.linalg.norm(high - low)), 1e-3)
        return np.stack([low - margin, high + margin])

    def _bounds_configurations(self) -> np.ndarray:
        """``[n, k]`` configurations that sweep the joint box (see :meth:`bounds`)."""
        values = []
        for joint in self.movable:
            span = joint.upper - joint.lower
            steps = 1 if joint.type == "prismatic" else max(1, math.ceil(span / _BOUNDS_ANGLE_STEP))
            values.append(np.linspace(joint.lower, joint.upper, steps + 1))
        if math.prod(len(v) for v in values) <= _BOUNDS_MAX_CONFIGS:
            return np.array(list(itertools.product(*values)), dtype=np.float64)  # [n, k], also for k = 0
        all_corners = itertools.product(*zip(self.lower.tolist(), self.upper.tolist()))
        corners = np.array(list(itertools.islice(all_corners, _BOUNDS_MAX_CONFIGS)))
        rng = np.random.default_rng(0)
        lower, upper = self.lower.numpy(), self.upper.numpy()
        random = lower + (upper - lower) * rng.random((_BOUNDS_MAX_CONFIGS, self.n_joints))
        return np.concatenate([corners, random])


# --- parsing ------------------------------------------------------------------------------------


def _parse_robot(text: str, source: str) -> yourdfpy.Robot:
    """Strict XML parse (yourdfpy would silently 'recover' broken XML), then yourdfpy's model."""
    try:
        root = ET.fromstring(text.encode())
    except ET.ParseError as e:
        raise _error(source, f"not valid XML: {e}") from e
    if root.tag != "robot":
        raise _error(source, f"the root element is <{root.tag}>, expected <robot>")
    try:
        return yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=False, load_meshes=False).robot
    except (KeyError, AttributeError, ValueError, TypeError, IndexError) as e:
        detail = f"missing attribute {e}" if isinstance(e, KeyError) else f"{e.__class__.__name__}: {e}"
        raise _error(source, f"malformed URDF ({detail})") from e


def _make_joint(j: yourdfpy.Joint, links: set[str], source: str) -> Joint:
    where = f"joint {j.name!r}"
    if j.type not in SUPPORTED_TYPES:
        raise _error(source, f"{where} has type {j.type!r}; supported: {', '.join(SUPPORTED_TYPES)}")
    mimic = None
    if j.mimic is not None:
        if j.type == "fixed":
            raise _error(source, f"{where} is fixed and cannot mimic {j.mimic.joint!r}")
        multiplier = 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier)
        offset = 0.0 if j.mimic.offset is None else float(j.mimic.offset)
        if not (math.isfinite(multiplier) and math.isfinite(offset)):
            raise _error(source, f"{where} mimics {j.mimic.joint!r} with a non-finite multiplier or offset")
        if multiplier == 0:
            raise _error(source, f"{where} mimics {j.mimic.joint!r} with multiplier 0, so it cannot move; "
                                 "make it a fixed joint")
        mimic = (str(j.mimic.joint), multiplier, offset)
    for role, link in (("parent", j.parent), ("child", j.child)):
        if link not in links:
            raise _error(source, f"{where} names {role} link {link!r}, which is not a <link>")
    origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
    axis = np.asarray(j.axis, dtype=np.float64)
    if axis.shape != (3,) or not np.isfinite(axis).all():
        raise _error(source, f"{where} has axis {axis.tolist()}; it must be 3 finite numbers")
    if j.type != "fixed" and abs(np.linalg.norm(axis) - 1) > _AXIS_NORM_TOLERANCE:
        # URDF asks for unit axes; tools disagree on others (pybullet moves prismatic joints by |axis| q).
        length = f"{np.linalg.norm(axis):.6g}"
        raise _error(source, f"{where} has axis {axis.tolist()} of length {length}; it must be a unit vector")
    if not np.isfinite(origin).all():
        raise _error(source, f"{where} has a non-finite origin")
    if j.type == "continuous":
        lower, upper = -math.pi, math.pi
    elif j.type == "fixed" or mimic is not None:
        lower, upper = 0.0, 0.0  # a mimic joint's range is its source's, set by _resolve_mimics
    else:
        if j.limit is None or j.limit.lower is None or j.limit.upper is None:
            raise _error(source, f"{where} ({j.type}) needs <limit lower=... upper=...>")
        lower, upper = float(j.limit.lower), float(j.limit.upper)
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise _error(
                source,
                f"{where} has limits [{lower}, {upper}]; they must be finite with lower < upper "
                "(a joint that cannot move is a fixed joint)",
            )
    origin.setflags(write=False)
    if j.type != "fixed":
        axis = axis / np.linalg.norm(axis)
    axis.setflags(write=False)
    return Joint(j.name, j.type, j.parent, j.child, origin, axis, lower, upper, mimic)


def _resolve_mimics(joints: list[Joint], source: str) -> list[Joint]:
    """``joints`` with each mimic joint's limits set to its source's range mapped through it."""
    by_name = {j.name: j for j in joints}
    out = []
    for joint in joints:
        if joint.mimic is not None:
            name, multiplier, offset = joint.mimic
            src = by_name.get(name)
            if src is None or not src.is_actuated:
                what = "no joint" if src is None else ("a mimic joint" if src.mimic else f"a {src.type} joint")
                raise _error(source, f"joint {joint.name!r} mimics {name!r}, which is {what}; "
                                     "the source must be a revolute, continuous or prismatic joint")
            ends = sorted((multiplier * src.lower + offset, multiplier * src.upper + offset))
            joint = replace(joint, lower=ends[0], upper=ends[1])
        out.append(joint)
    return out


def _topological_order(links: list[str], joints: list[Joint], source: str) -> tuple[str, list[Joint]]:
    """The root link and the joints depth first from it (children in file order)."""
    parent_joint: dict[str, Joint] = {}
    for joint in joints:
        if joint.child in parent_joint:
            both = f"{parent_joint[joint.child].name!r} and {joint.name!r}"
            raise _error(source, f"link {joint.child!r} is the child of two joints: {both}")
        parent_joint[joint.child] = joint
    roots = [name for name in links if name not in parent_joint]
    if len(roots) != 1:
        raise _error(source, f"expected exactly one root link (a link that is no joint's child), found {roots}")
    children: dict[str, list[Joint]] = {name: [] for name in links}
    for joint in joints:
        children[joint.parent].append(joint)
    ordered: list[Joint] = []
    stack = list(reversed(children[roots[0]]))
    while stack:
        joint = stack.pop()
        ordered.append(joint)
        stack.extend(reversed(children[joint.child]))
    if len(ordered) != len(joints):
        stray = sorted(set(links) - {roots[0]} - {j.child for j in ordered})
        raise _error(source, f"links {stray} are not connected to the root {roots[0]!r} (a cycle of joints?)")
    return roots[0], ordered


# --- meshes -------------------------------------------------------------------------------------


def resolve_mesh(filename: str, mesh_dir: str | Path, *, link: str = "?", source: str = "<urdf string>") -> Path:
    """The file a ``<mesh filename=...>`` names: a path relative to ``mesh_dir`` (the URDF's folder),
    an absolute path, ``file://...`` or ``package://<pkg>/...`` (the package is a folder named
    ``<pkg>`` at or above ``mesh_dir``, else ``mesh_dir`` itself)."""
    base = Path(mesh_dir).resolve()
    if filename.startswith("file://"):
        candidates = [Path(filename[len("file://"):])]
    elif filename.startswith("package://"):
        package, _, rest = filename[len("package://"):].partition("/")
        candidates = [d / rest for d in (base, *base.parents) if d.name == package]
        candidates.append(base / rest)
    else:
        candidates = [base / filename]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise _error(source, f"link {link!r}: mesh file {filename!r} not found (looked in {mesh_dir})")


def _merge(link: str, visuals: list[yourdfpy.Visual], mesh_dir: Path | None, source: str) -> trimesh.Trimesh:
    parts = []
    for visual in visuals:
        mesh = _geometry_mesh(link, visual.geometry, mesh_dir, source)
        if visual.origin is not None:
            mesh.apply_transform(visual.origin)
        parts.append(mesh)
    return trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0]


def _geometry_mesh(link: str, geometry: yourdfpy.Geometry, mesh_dir: Path | None, source: str) -> trimesh.Trimesh:
    where = f"link {link!r}"
    if geometry is None:
        raise _error(source, f"{where} has a <visual> without <geometry>")
    if geometry.box is not None:
        return trimesh.creation.box(extents=geometry.box.size)
    if geometry.cylinder is not None:
        return trimesh.creation.cylinder(radius=geometry.cylinder.radius, height=geometry.cylinder.length, sections=32)
    if geometry.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=3, radius=geometry.sphere.radius)
    if geometry.mesh is None:
        raise _error(source, f"{where} has a <geometry> that is none of box, cylinder, sphere, mesh")
    filename = geometry.mesh.filename
    if mesh_dir is None:
        raise _error(source, f"{where} uses mesh {filename!r} but no mesh folder was given")
    path = resolve_mesh(filename, mesh_dir, link=link, source=source)
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for corrupt files
        raise _error(source, f"{where}: cannot load mesh {str(path)!r} ({e.__class__.__name__}: {e})") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise _error(source, f"{where}: mesh {str(path)!r} has no triangles")
    if geometry.mesh.scale is not None:
        scale = np.broadcast_to(np.asarray(geometry.mesh.scale, dtype=np.float64), (3,))
        mesh.apply_transform(np.diag([*scale, 1.0]))
    return mesh


# --- small helpers ------------------------------------------------------------------------------


def _rotation_about(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation ``[..., 3, 3]`` by ``angle [...]`` about the unit ``axis [3]`` (Rodrigues, exact)."""
    k = skew(axis)
    s = torch.sin(angle)[..., None, None]
    one_minus_c = 2 * torch.sin(angle / 2)[..., None, None] ** 2  # 1 - cos, without cancellation
    return torch.eye(3, dtype=axis.dtype, device=axis.device) + s * k + one_minus_c * (k @ k)


def _describe(value: object) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:60] + '...' if len(text) > 60 else text}"
