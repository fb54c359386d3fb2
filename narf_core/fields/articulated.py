"""The articulated configuration field: part features looked up in each part's own frame at ``θ``.

One module ``F(x, d, θ)`` that holds the object's forward kinematics (the joint chain as a few matrix
products: no URDF is needed at inference), K-planes features and a small decoder per rigid part
(over the part's box, in its frame) and each part's occupancy grid. A sample ``x`` (object frame)
is moved into every part's frame by ``T_part_obj(θ)``; a part is evaluated only where the sample
falls in its occupied cells, so the assignment of samples to parts is explicit and exact at every
``θ``; densities add and the colour is the density-weighted mean (the composition of
docs/design.md §4.2). Nothing is a product over joint axes, so the field is as accurate with
several joints as with one, and its occupancy (:class:`PosedGrids`: the part grids posed by FK at
``θ``) is tight at every configuration instead of a union over a bin of configurations. What makes
it cheaper than composing separate part fields: one lookup table for all part grids, one atlas
(one ``grid_sample``) for all parts' planes, one FK per configuration.

:meth:`ArticulatedField.from_parts` copies trained K-planes part fields into it (seconds, no
distillation stage); :func:`chain_spec` turns a :class:`~narf_core.kinematics.KinematicTree` into
the JSON-able chain the field's config stores.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from narf_core.fields.base import RadianceField, trunc_exp
from narf_core.fields.encodings import _EDGE_SHRINK  # the same border shrink as K-planes' lookups
from narf_core.fields.kplanes import KPlanesField
from narf_core.geometry import box_corners, invert_pose, make_pose, skew, transform_points
from narf_core.occupancy import OccupancyGrid

JOINT_TYPES = ("fixed", "revolute", "continuous", "prismatic")


def chain_spec(kin) -> dict:
    """The joint chain of ``kin`` (a :class:`~narf_core.kinematics.KinematicTree`) as JSON-able lists.

    ``types``, ``parents`` (index into the links, root = 0, parents first), ``theta_index`` (the
    coordinate of ``θ`` that drives the joint, -1 if fixed), ``mimic`` (``[multiplier, offset]``),
    ``origins`` (``T_parent_child`` at zero, 4x4), ``axes`` (unit, joint frame) per joint, and
    ``part_links``: the link index of each part's top link.
    """
    link_index = {name: i for i, name in enumerate(kin.links)}
    theta_index = {name: i for i, name in enumerate(kin.joint_names)}
    joints = kin.joints
    return {
        "types": [j.type for j in joints],
        "parents": [link_index[j.parent] for j in joints],
        "theta_index": [theta_index.get(j.name if j.mimic is None else j.mimic[0], -1) for j in joints],
        "mimic": [[1.0, 0.0] if j.mimic is None else [float(j.mimic[1]), float(j.mimic[2])] for j in joints],
        "origins": [np.asarray(j.origin, dtype=np.float64).tolist() for j in joints],
        "axes": [np.asarray(j.axis, dtype=np.float64).tolist() for j in joints],
        "part_links": [link_index[name] for name in kin.part_names],
    }


def _rotation_about(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation ``[..., 3, 3]`` by ``angle [...]`` about the unit ``axis [3]`` (Rodrigues, as
    :mod:`narf_core.kinematics` computes it; the field does not import the URDF reader)."""
    k = skew(axis)
    s = torch.sin(angle)[..., None, None]
    one_minus_c = 2 * torch.sin(angle / 2)[..., None, None] ** 2
    return torch.eye(3, dtype=axis.dtype, device=axis.device) + s * k + one_minus_c * (k @ k)


class ArticulatedField(RadianceField):
    """``(x [n,3], d [n,3], θ [n,k] | [k]) -> (σ [n], rgb [n,3])``: part K-planes posed by FK inside.

    Each part ``i`` has K-planes features over its box (the ``xy``, ``xz``, ``yz`` planes at each
    scale, sized like :class:`~narf_core.fields.kplanes.KPlanesField`'s so that cells are about
    cubic) and its own decoder (``layers`` ReLU layers of ``hidden`` units, then the raw density
    and three colour logits). The planes of every part and scale are tiles of one atlas, so one
    lookup serves every sample of every part; each part's occupancy grid decides which parts a
    sample belongs to (usually one; densities add where several overlap).

    Args:
        aabb: ``[2,3]`` object-frame box over the joint range (metres).
        theta_lower, theta_upper: ``[k]`` joint limits, ``k >= 1``.
        chain: the joint chain (:func:`chain_spec`).
        part_aabbs: ``[p, 2, 3]`` each part's box (metres, part frame).
        grid_shapes: ``[Rx, Ry, Rz]`` per part: its occupancy grid over its box (a buffer; every
            cell occupied until trained values are loaded).
        resolution, features, hidden, layers: as for :class:`~narf_core.fields.kplanes.KPlanesField`.
    """

    def __init__(
        self,
        aabb,
        theta_lower=None,
        theta_upper=None,
        *,
        chain: dict,
        part_aabbs: Sequence,
        grid_shapes: Sequence[Sequence[int]],
        resolution: Sequence[int] = (64, 128),
        features: int = 16,
        hidden: int = 64,
        layers: int = 2,
    ) -> None:
        super().__init__(aabb, theta_lower, theta_upper)
        if self.n_theta == 0:
            raise ValueError("an articulated field needs joint limits (theta_lower, theta_upper) for k >= 1 joints")
        self.chain = _check_chain(chain, self.n_theta)
        p = len(self.chain["part_links"])
        if not len(part_aabbs) == len(grid_shapes) == p:
            raise ValueError(
                f"need one box and one grid shape per part: the chain has {p} parts, got {len(part_aabbs)} boxes "
                f"and {len(grid_shapes)} grid shapes"
            )
        self.resolution = [int(r) for r in resolution]
        if not self.resolution or min(self.resolution) < 2:
            raise ValueError(f"resolution needs one entry >= 2 per scale, got {self.resolution}")
        if features < 1 or hidden < 1 or layers < 1:
            raise ValueError(f"features, hidden and layers must be >= 1, got {features}, {hidden}, {layers}")
        self.features, self.hidden, self.layers = int(features), int(hidden), int(layers)
        self.grid_shapes = [[int(r) for r in shape] for shape in grid_shapes]
        for i, shape in enumerate(self.grid_shapes):
            if len(shape) != 3 or min(shape) < 1:
                raise ValueError(f"grid_shapes[{i}] must be 3 positive cell counts, got {shape}")
        boxes = torch.stack([_as_part_box(box, i) for i, box in enumerate(part_aabbs)])
        self.register_buffer("part_aabbs", boxes)

        # planes: n = scale * 3 + pair, pairs (x, y), (x, z), (y, z). The atlas is [N, rows, columns, F]
        # (channels last: the fast bilinear lookup on CPU); part i owns the columns from start_i, as
        # many as its widest plane, and its plane n is the tile atlas[n, :rows_in, start_i : start_i + cols_in]
        # (rows follow the pair's second axis).
        sizes = torch.tensor([[_plane_sizes(r, box) for r in self.resolution] for box in boxes])  # [p, S, 3]
        rows = sizes[:, :, [1, 2, 2]].reshape(p, -1)  # [p, N]
        cols = sizes[:, :, [0, 0, 1]].reshape(p, -1)
        n_planes, height = 3 * len(self.resolution), int(rows.max())
        widths = cols.amax(1)
        start = torch.cat([torch.zeros(1, dtype=widths.dtype), widths.cumsum(0)[:-1]])  # [p]
        self.atlas = nn.Parameter(torch.zeros(n_planes, height, int(widths.sum()), self.features))
        total = int(widths.sum()) - 1
        scale = torch.stack([(cols - 1) / total, (rows - 1) / (height - 1)], -1)  # [p, N, 2]: grid = (uv + 1) * scale + shift
        shift = torch.stack([(2 * start[:, None] / total - 1).expand(p, n_planes), -torch.ones(p, n_planes)], -1)
        self.register_buffer("_tile_scale", scale.float(), persistent=False)
        self.register_buffer("_tile_shift", shift.float(), persistent=False)
        self._tiles = [[(int(rows[i, n]), slice(int(start[i]), int(start[i] + cols[i, n]))) for n in range(n_planes)] for i in range(p)]
        self.decoders = nn.ModuleList(_decoder(self.features * len(self.resolution), self.hidden, self.layers) for _ in range(p))

        for i, shape in enumerate(self.grid_shapes):
            self.register_buffer(f"grid_{i}", torch.ones(shape, dtype=torch.uint8))
        self.register_buffer("origins", torch.tensor(self.chain["origins"], dtype=torch.float32).reshape(-1, 4, 4), persistent=False)
        self.register_buffer("axes", torch.tensor(self.chain["axes"], dtype=torch.float32).reshape(-1, 3), persistent=False)
        self._grids_state: tuple | None = None  # (buffer key, part grids, their lookup table), replaced whole
        self._pose_cache: tuple[tuple, Tensor] | None = None

    @property
    def n_parts(self) -> int:
        return len(self.grid_shapes)

    @classmethod
    @torch.no_grad()
    def from_parts(cls, kin, part_fields: Sequence[KPlanesField], part_grids: Sequence[OccupancyGrid], aabb) -> ArticulatedField:
        """The field of trained K-planes ``part_fields`` (view-independent, one architecture) and their
        ``part_grids`` on the kinematics ``kin``; weights copied, so it renders what their composition renders."""
        configs = [f.config() for f in part_fields]
        shared = {key: configs[0].get(key) for key in ("resolution", "features", "hidden", "layers")}
        for i, c in enumerate(configs):
            if c.get("arch") != "kplanes" or c.get("dir_degree", 0) != 0 or c.get("theta_lower") is not None:
                raise ValueError(f"part field {i} must be a view-independent K-planes part field, got {c.get('arch')!r}")
            if {key: c.get(key) for key in shared} != shared:
                raise ValueError(f"part field {i} has other hyper-parameters than part field 0: {c} vs {shared}")
        field = cls(
            aabb, kin.lower.tolist(), kin.upper.tolist(), chain=chain_spec(kin),
            part_aabbs=[f.aabb.tolist() for f in part_fields], grid_shapes=[list(g.resolution) for g in part_grids], **shared,
        )
        for i, (part, grid) in enumerate(zip(part_fields, part_grids)):
            if not torch.allclose(grid.aabb, part.aabb):
                raise ValueError(f"part grid {i} covers {grid.aabb.tolist()}, not its field's box {part.aabb.tolist()}")
            for n, plane in enumerate(part.planes):
                rows, cols = field._tiles[i][n]
                field.atlas[n, :rows, cols] = plane
            field.decoders[i].load_state_dict({**{f"{k}": v for k, v in part.decoder.state_dict().items()},
                                               **{f"{len(part.decoder)}.{k}": v for k, v in part.head.state_dict().items()}})
            getattr(field, f"grid_{i}").copy_(grid.occupancy.to(torch.uint8))
        return field

    # --- kinematics and occupancy ---------------------------------------------------------------

    def part_poses(self, theta: Tensor) -> Tensor:
        """``T_obj_part [..., p, 4, 4]`` for ``θ [..., k]`` (float32): the chain's forward kinematics."""
        theta = theta.to(self.origins.dtype)
        batch = theta.shape[:-1]
        poses = [torch.eye(4, dtype=theta.dtype, device=theta.device).expand(*batch, 4, 4)]
        chain = self.chain
        for i, kind in enumerate(chain["types"]):
            origin = self.origins[i]
            if kind == "fixed":
                local = origin.expand(*batch, 4, 4)
            else:
                m, o = chain["mimic"][i]
                q = theta[..., chain["theta_index"][i]] * m + o
                if kind == "prismatic":
                    local = make_pose(origin[:3, :3].expand(*batch, 3, 3), origin[:3, 3] + q[..., None] * (origin[:3, :3] @ self.axes[i]))
                else:
                    local = make_pose(origin[:3, :3] @ _rotation_about(self.axes[i], q), origin[:3, 3].expand(*batch, 3))
            poses.append(poses[chain["parents"][i]] @ local)
        return torch.stack([poses[i] for i in chain["part_links"]], dim=-3)

    def part_grids(self) -> list[OccupancyGrid]:
        """Each part's occupancy grid (its frame), rebuilt when the grid buffers change."""
        return self._grid_state()[1]

    def part_lookup(self) -> _PartLookup:
        """Every part grid in one lookup table (:class:`_PartLookup`)."""
        return self._grid_state()[2]

    def _grid_state(self) -> tuple:
        buffers = [getattr(self, f"grid_{i}") for i in range(self.n_parts)]
        key = tuple((b.data_ptr(), b._version, str(b.device)) for b in buffers)
        state = self._grids_state
        if state is None or state[0] != key:
            grids = [OccupancyGrid(box, b.bool()) for box, b in zip(self.part_aabbs, buffers)]
            state = self._grids_state = (key, grids, _PartLookup(grids))
        return state

    def part_from_object(self, theta: Tensor | None, n: int) -> Tensor:
        """``T_part_obj``: ``[p,4,4]`` for a shared ``θ`` (``[k]``, or rows that are one), else ``[n,p,4,4]``.

        Without gradients, the last shared ``θ``'s poses are reused (a render asks once per round)."""
        k = self.n_theta
        if theta is None:
            raise ValueError(f"this field needs a configuration theta with {k} values, got None")
        if theta.shape not in ((k,), (n, k)):
            raise ValueError(f"theta must be [{k}] or [{n}, {k}], got shape {tuple(theta.shape)}")
        if theta.dim() == 2 and (n == 0 or theta.stride(0) == 0 or bool((theta == theta[:1]).all())):
            theta = theta[0] if n else theta.new_zeros(k)
        cacheable = theta.dim() == 1 and not (torch.is_grad_enabled() and theta.requires_grad)
        if cacheable:
            key = (tuple(theta.tolist()), str(theta.device))
            if self._pose_cache is not None and self._pose_cache[0] == key:
                return self._pose_cache[1]
        T = invert_pose(self.part_poses(theta))
        if cacheable:
            self._pose_cache = (key, T)
        return T

    def occupancy(self, theta: Tensor) -> PosedGrids:
        """The object-frame occupancy at ``θ [k]`` (or ``[n,k]``, one per ray): the part grids posed by FK."""
        return PosedGrids(self, theta)

    # --- the field ------------------------------------------------------------------------------

    def _evaluate(self, x: Tensor, theta: Tensor | None, color: bool) -> tuple[Tensor, Tensor | None]:
        """``σ [n]`` and (``color``) the density-weighted sum of the parts' colours ``[n, 3]`` at ``x [n,3]``."""
        n = x.shape[0]
        sigma = x.new_zeros(n)
        weighted = x.new_zeros(n, 3) if color else None
        if n == 0:
            return sigma, weighted
        T = self.part_from_object(theta, n).to(x.dtype)
        lookup = self.part_lookup()
        R, t = T[..., :3, :3], T[..., :3, 3]
        if T.dim() == 3:  # shared θ: all parts in one product, [n, p, 3]
            xp = (x @ R.transpose(-1, -2).permute(1, 0, 2).reshape(3, -1)).reshape(n, -1, 3) + t
        else:
            xp = torch.einsum("npij,nj->npi", R, x) + t
        c = lookup.cell_units(xp)  # [n, p, 3], differentiable
        occupied = lookup.occupied_cells(c)  # [n, p]
        part, sample = occupied.t().nonzero(as_tuple=True)  # (sample, part) pairs grouped by part
        if sample.numel() == 0:
            return sigma, weighted
        z = c[sample, part] * lookup.z_scale[part] + lookup.z_shift[part]  # [m, 3]: [-1, 1] over the part's box
        features = self._plane_features(z.to(self.atlas.dtype), part)  # [m, F * S]
        counts = occupied.sum(0).tolist()
        out = torch.cat([self.decoders[i](f) for i, f in enumerate(features.split(counts)) if f.shape[0]])
        s = trunc_exp(out[:, 0]).to(x.dtype)
        sigma = sigma.index_add(0, sample, s)
        if color:
            weighted = weighted.index_add(0, sample, s[:, None] * torch.sigmoid(out[:, 1:]).to(x.dtype))
        return sigma, weighted

    def _plane_features(self, z: Tensor, part: Tensor) -> Tensor:
        """K-planes features ``[m, F * S]`` of points ``z [m,3]`` (normalised in their part's box) of ``part [m]``."""
        n_planes = self.atlas.shape[0]
        z = z * _EDGE_SHRINK
        uv = torch.stack([z[:, [0, 0, 1] * (n_planes // 3)], z[:, [1, 2, 2] * (n_planes // 3)]], -1)  # [m, N, 2]
        grid = ((uv + 1) * self._tile_scale[part] + self._tile_shift[part]).transpose(0, 1)[:, None]  # [N, 1, m, 2]
        atlas = self.atlas.permute(0, 3, 1, 2)  # [N, F, rows, width] over channels-last memory
        out = F.grid_sample(atlas, grid, mode="bilinear", padding_mode="border", align_corners=True)[:, :, 0]  # [N, F, m]
        out = out.reshape(-1, 3, self.features, out.shape[-1])  # [S, 3, F, m]
        return (out[:, 0] * out[:, 1] * out[:, 2]).reshape(-1, out.shape[-1]).t()

    def forward(self, x: Tensor, d: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        sigma, weighted = self._evaluate(x, theta, True)
        return sigma, torch.where(sigma[:, None] > 0, weighted / sigma.clamp_min(1e-30)[:, None], 0.0)

    def density(self, x: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``σ [n]`` and, as features, the colour ``[n,3]`` (the parts are view-independent)."""
        return self.forward(x, torch.zeros_like(x), theta)

    def color(self, features: Tensor, d: Tensor) -> Tensor:
        return features

    def density_only(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        return self._evaluate(x, theta, False)[0]

    def config(self) -> dict:
        return {
            "arch": "articulated",
            "aabb": self.aabb.tolist(),
            "theta_lower": self.theta_lower.tolist(),
            "theta_upper": self.theta_upper.tolist(),
            "chain": self.chain,
            "part_aabbs": self.part_aabbs.tolist(),
            "grid_shapes": self.grid_shapes,
            "resolution": self.resolution,
            "features": self.features,
            "hidden": self.hidden,
            "layers": self.layers,
        }


def _plane_sizes(r: int, box: Tensor) -> list[int]:
    """Texels per axis of the planes at resolution ``r`` over ``box [2,3]`` (as K-planes sizes them)."""
    extent = box[1] - box[0]
    return [max(2, math.ceil(r * float(e / extent.max()) - 1e-6)) for e in extent]


def _decoder(width: int, hidden: int, layers: int) -> nn.Sequential:
    """``layers`` ReLU layers of ``hidden`` units, then the raw density and three colour logits."""
    mlp: list[nn.Module] = []
    for _ in range(layers):
        mlp += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    return nn.Sequential(*mlp, nn.Linear(hidden, 4))


def _as_part_box(box, i: int) -> Tensor:
    b = torch.as_tensor(box, dtype=torch.float32)
    if tuple(b.shape) != (2, 3) or not bool(torch.isfinite(b).all()) or not bool((b[1] > b[0]).all()):
        raise ValueError(f"part_aabbs[{i}] must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b.tolist()}")
    return b


class _PartLookup:
    """Every part grid in one flat table: ``occupied(xp [..., p, 3]) -> [..., p]`` in a few operations.

    Each grid is padded by one empty cell on every side, so a point outside its part's box reads an
    empty cell after clamping (no separate inside test).
    """

    def __init__(self, grids: Sequence[OccupancyGrid]) -> None:
        self.flat = torch.cat([F.pad(g.occupancy, (1, 1, 1, 1, 1, 1)).reshape(-1) for g in grids])
        cells = torch.tensor([g.resolution for g in grids], dtype=torch.float32)  # [p, 3]
        lo = torch.stack([g.aabb[0] for g in grids])  # [p, 3]
        self.scale = cells / (torch.stack([g.aabb[1] for g in grids]) - lo)
        self.shift = 1 - lo * self.scale  # cell units of the padded grid: x * scale + shift
        self.z_scale, self.z_shift = 2 / cells, -2 / cells - 1  # cell units -> [-1, 1] over the box
        padded = cells.long() + 2
        self.top = (padded - 1).int()
        self.strides = torch.stack([padded[:, 1] * padded[:, 2], padded[:, 2], torch.ones(len(grids), dtype=torch.long)], -1).int()
        self.offset = torch.cat([torch.zeros(1, dtype=torch.long), padded.prod(-1).cumsum(0)[:-1]]).int()  # [p]

    def cell_units(self, xp: Tensor) -> Tensor:
        """``xp [..., p, 3]`` (metres, each in its part's frame) in cell units of each part's padded grid."""
        return xp.float() * self.scale + self.shift

    def occupied_cells(self, c: Tensor) -> Tensor:
        """``c [..., p, 3]`` in cell units -> ``[..., p]``: in an occupied cell of the part's grid."""
        cell = torch.minimum(c.floor().clamp_(min=0).int(), self.top)
        return self.flat[(cell * self.strides).sum(-1, dtype=torch.int32) + self.offset]

    def occupied(self, xp: Tensor) -> Tensor:
        return self.occupied_cells(self.cell_units(xp))


def _check_chain(chain: dict, k: int) -> dict:
    """``chain`` (:func:`chain_spec`) checked for consistent lengths, known types and indices in range."""
    keys = ("types", "parents", "theta_index", "mimic", "origins", "axes", "part_links")
    if not isinstance(chain, dict) or any(key not in chain for key in keys):
        raise ValueError(f"chain must be a dict with {', '.join(keys)}")
    n = len(chain["types"])
    if any(len(chain[key]) != n for key in keys[:-1]):
        raise ValueError("chain: types, parents, theta_index, mimic, origins and axes need one entry per joint")
    for i, (kind, parent, index) in enumerate(zip(chain["types"], chain["parents"], chain["theta_index"])):
        if kind not in JOINT_TYPES:
            raise ValueError(f"chain: joint {i} has unknown type {kind!r}; expected one of {', '.join(JOINT_TYPES)}")
        if not 0 <= int(parent) <= i:
            raise ValueError(f"chain: joint {i}'s parent link {parent} does not come before it")
        if kind != "fixed" and not 0 <= int(index) < k:
            raise ValueError(f"chain: joint {i} is driven by theta[{index}], outside the {k} configuration values")
    if not chain["part_links"] or any(not 0 <= int(p) <= n for p in chain["part_links"]):
        raise ValueError(f"chain: part_links must index the {n + 1} links, got {chain['part_links']}")
    return {key: list(chain[key]) for key in keys}


class PosedGrids:
    """:class:`~narf_core.occupancy.Occupancy` of an :class:`ArticulatedField` at ``θ``: the union of its
    part grids, each posed by the field's FK.

    ``θ``: ``[k]``, or ``[n,k]`` (one per ray); a ``theta`` passed to a method (``[m,k]`` for the ``m``
    points or rays asked about) takes precedence. Along rays, each ray is moved into every part's
    grid once (a rigid motion keeps it a ray), and a marching round looks all parts up in one table.
    """

    def __init__(self, field: ArticulatedField, theta: Tensor) -> None:
        self.field = field
        self.theta = theta.detach()

    def _part_from_object(self, theta: Tensor | None) -> Tensor:
        """``T_part_obj`` ``[p,4,4]`` (a shared θ) or ``[m,p,4,4]`` (one per point or ray)."""
        theta = self.theta if theta is None else theta.detach()
        return self.field.part_from_object(theta, theta.shape[0] if theta.dim() == 2 else 1)

    def occupied(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        T = self._part_from_object(theta).to(x.dtype)
        equation = "pij,mj->mpi" if T.dim() == 3 else "mpij,mj->mpi"
        xp = torch.einsum(equation, T[..., :3, :3], x) + T[..., :3, 3]
        return self.field.part_lookup().occupied(xp).any(-1)

    def bounds(self, theta: Tensor | None = None) -> Tensor | None:
        """The object-frame box around the posed parts' tight boxes (over every ray's ``θ`` if per ray)."""
        grids = self.field.part_grids()
        boxes = [(i, grid.bounds()) for i, grid in enumerate(grids)]
        boxes = [(i, box) for i, box in boxes if box is not None]
        if not boxes:
            return None
        T = invert_pose(self._part_from_object(theta)).reshape(-1, len(grids), 4, 4)
        corners = torch.cat([transform_points(T[:, i, None], box_corners(box)[None]).reshape(-1, 3) for i, box in boxes])
        return torch.stack([corners.amin(0), corners.amax(0)])

    def along(self, origins: Tensor, directions: Tensor, theta: Tensor | None = None) -> PosedGridRays:
        T = self._part_from_object(theta).to(origins.dtype)
        equation = "pij,mj->mpi" if T.dim() == 3 else "mpij,mj->mpi"
        o = torch.einsum(equation, T[..., :3, :3], origins) + T[..., :3, 3]  # [m, p, 3]
        d = torch.einsum(equation, T[..., :3, :3], directions)
        lookup = self.field.part_lookup()
        return PosedGridRays(lookup, lookup.cell_units(o), d.float() * lookup.scale)


class PosedGridRays:
    """:class:`~narf_core.occupancy.RayOccupancy` of :class:`PosedGrids`: the rays in every part grid's cell
    units (``c``, ``cd [m, p, 3]``), so a marching round is one lookup for all parts."""

    def __init__(self, lookup: _PartLookup, c: Tensor, cd: Tensor) -> None:
        self.lookup, self.c, self.cd = lookup, c, cd

    def __call__(self, t: Tensor) -> Tensor:
        points = self.c[:, None] + t.float()[..., None, None] * self.cd[:, None]  # [m, w, p, 3]
        return self.lookup.occupied_cells(points).any(-1)

    def select(self, keep: Tensor) -> PosedGridRays:
        return PosedGridRays(self.lookup, self.c[keep], self.cd[keep])
