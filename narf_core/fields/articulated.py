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
(one ``grid_sample``) for all parts' planes, one FK per configuration, every lookup coordinate of a
sample (cell units in each part grid, texel coordinates in each part's tiles) from one matrix product
(they are affine in ``x`` at a given ``θ``), and each ray marched only from where it enters the
first of the parts' occupied boxes to where it leaves the last (:meth:`PosedGridRays.span`).

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

from narf_core.fields.base import SIGMA_MAX_LOG, RadianceField, activated_jacobian, trunc_exp
from narf_core.fields.encodings import _EDGE_SHRINK, in_texel_step  # the same border shrink as K-planes' lookups
from narf_core.fields.kplanes import KPlanesField
from narf_core.geometry import box_corners, invert_pose, make_pose, skew, transform_points
from narf_core.occupancy import OccupancyGrid, needs_theta_grad, one_configuration
from narf_core.sampling import ray_aabb

JOINT_TYPES = ("fixed", "revolute", "continuous", "prismatic")
_BOX_MARGIN = 0.01  # cells: a part's occupied box is grown by this, so float rounding never clips an occupied sample
_BLOCK = 4  # cells per block (per axis) of the coarse part grids a ray's span is narrowed with
_SPAN_SAMPLES = 128  # at most this many coarse samples per ray; a longer span keeps its boxes' bounds
_MAX_RUNS = 64  # configurations mapped run by run (one FK each); rows of more are mapped one by one


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
        self._pose_cache: dict[tuple, Tensor] = {}  # (θ, device) -> T_part_obj [p, 4, 4]

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
        return self._chain(theta, derivatives=False)[0]

    def _chain(self, theta: Tensor, derivatives: bool) -> tuple[Tensor, Tensor | None]:
        """``T_obj_part [..., p, 4, 4]`` for ``θ [..., k]`` and, with ``derivatives``, ``∂T_obj_part / ∂θ_j
        [..., k, p, 4, 4]``: the chain's forward kinematics, joint by joint (a joint's local pose depends on
        its own coordinate alone, through its mimic multiplier)."""
        theta = theta.to(self.origins.dtype)
        batch, k = theta.shape[:-1], theta.shape[-1]
        poses = [torch.eye(4, dtype=theta.dtype, device=theta.device).expand(*batch, 4, 4)]  # T_obj_link
        grads = [theta.new_zeros(*batch, k, 4, 4)] if derivatives else []  # ∂T_obj_link / ∂θ_j
        chain = self.chain
        for i, kind in enumerate(chain["types"]):
            origin, parent, dlocal = self.origins[i], chain["parents"][i], None
            if kind == "fixed":
                local = origin.expand(*batch, 4, 4)
            else:
                m, o = chain["mimic"][i]
                q = theta[..., chain["theta_index"][i]] * m + o
                if kind == "prismatic":
                    direction = origin[:3, :3] @ self.axes[i]
                    local = make_pose(origin[:3, :3].expand(*batch, 3, 3), origin[:3, 3] + q[..., None] * direction)
                    if derivatives:
                        dlocal = theta.new_zeros(*batch, 4, 4)
                        dlocal[..., :3, 3] = m * direction
                else:
                    rotation = _rotation_about(self.axes[i], q)
                    local = make_pose(origin[:3, :3] @ rotation, origin[:3, 3].expand(*batch, 3))
                    if derivatives:
                        dlocal = theta.new_zeros(*batch, 4, 4)
                        dlocal[..., :3, :3] = m * (origin[:3, :3] @ skew(self.axes[i]) @ rotation)
            poses.append(poses[parent] @ local)
            if derivatives:
                grad = grads[parent] @ local[..., None, :, :]
                if dlocal is not None:
                    j = chain["theta_index"][i]
                    grad = grad.clone()
                    grad[..., j, :, :] += poses[parent] @ dlocal
                grads.append(grad)
        links = chain["part_links"]
        T = torch.stack([poses[i] for i in links], dim=-3)
        return T, (torch.stack([grads[i] for i in links], dim=-3) if derivatives else None)

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
            lookup = _PartLookup(grids)
            state = self._grids_state = (key, grids, lookup, self._lookup_coordinates(lookup))
        return state

    def _lookup_coordinates(self, lookup: _PartLookup) -> Tensor:
        """``C [p, 4, 3 + 2N]``: a point ``xp`` in part ``i``'s frame (homogeneous, ``[4]``) to, by ``xp @
        C[i]``, its cell units in the part's padded grid (3) and its ``grid_sample`` coordinates in the
        part's tile of each of the atlas's ``N`` planes (``N`` pairs ``(u, v)``). Both are affine in
        ``xp``, so a sample's every lookup coordinate is one product with ``T_part_obj(θ)`` folded in."""
        n_planes = self.atlas.shape[0]
        scale, shift = lookup.scale.double(), lookup.shift.double()  # [p, 3]: metres -> cell units
        device = lookup.scale.device
        axes = torch.tensor([[0, 1], [0, 2], [1, 2]] * (n_planes // 3), device=device)  # [N, 2]: the plane's (u, v) axes
        # cell units -> normalised box coordinates -> shrunk -> the tile's grid coordinates, per (plane, u|v)
        z_scale, z_shift = lookup.z_scale.double()[:, axes], lookup.z_shift.double()[:, axes]  # [p, N, 2]
        tile_scale, tile_shift = self._tile_scale.double(), self._tile_shift.double()
        gain = z_scale * _EDGE_SHRINK * tile_scale  # grid = cell * gain + bias
        bias = (z_shift * _EDGE_SHRINK + 1) * tile_scale + tile_shift
        p = lookup.scale.shape[0]
        C = torch.zeros(p, 4, 3 + 2 * n_planes, dtype=torch.float64, device=device)
        C[:, [0, 1, 2], [0, 1, 2]] = scale
        C[:, 3, :3] = shift
        for a in range(3):  # the columns of the planes' coordinates that follow axis a
            on = (axes == a).reshape(-1)  # [2N]
            C[:, a, 3:][:, on] = (scale[:, a, None] * gain.reshape(p, -1))[:, on]
            C[:, 3, 3:][:, on] = (shift[:, a, None] * gain.reshape(p, -1) + bias.reshape(p, -1))[:, on]
        return C.float().to(self.atlas.device)

    def part_from_object(self, theta: Tensor | None, n: int) -> Tensor:
        """``T_part_obj``: ``[p,4,4]`` for a shared ``θ`` (``[k]``, or rows that are one), else ``[n,p,4,4]``.

        Rows are one ``θ`` where :func:`~narf_core.occupancy.one_configuration` says so; without gradients
        the poses of the last ``_MAX_RUNS`` shared ``θ`` are reused (a render asks once per round, for each
        of its configurations)."""
        theta = self._check_theta(theta, n)
        if theta.dim() == 2 and one_configuration(theta):
            theta = theta[0] if n else theta.new_zeros(self.n_theta)
        cacheable = theta.dim() == 1 and not needs_theta_grad(theta)
        if cacheable:
            key = (tuple(theta.tolist()), str(theta.device))
            if key in self._pose_cache:
                return self._pose_cache[key]
        T = invert_pose(self.part_poses(theta))
        if cacheable:
            if len(self._pose_cache) >= _MAX_RUNS:
                self._pose_cache.clear()
            self._pose_cache[key] = T
        return T

    def _check_theta(self, theta: Tensor | None, n: int) -> Tensor:
        k = self.n_theta
        if theta is None:
            raise ValueError(f"this field needs a configuration theta with {k} values, got None")
        if theta.shape not in ((k,), (n, k)):
            raise ValueError(f"theta must be [{k}] or [{n}, {k}], got shape {tuple(theta.shape)}")
        return theta

    def lookup_coordinates(self, x: Tensor, theta: Tensor | None, columns: slice = slice(None), translate: bool = True) -> Tensor:
        """``x [n, 3]`` (object frame; directions with ``translate=False``) to their lookup coordinates in
        every part (:meth:`_lookup_coordinates`, its ``columns``) at ``θ`` (``[k]``, or ``[n, k]`` one per
        row): ``[n, p, K]``.

        A render's rows come in runs of one configuration (its samples ray after ray, a start's rays
        together): each run is one matrix product with the maps of its ``θ``, the FK once per run, and
        rows of more than ``_MAX_RUNS`` configurations are mapped one by one. Where ``θ`` needs a
        gradient, each row gets its own ``∂/∂θ`` from the term ``(θ_row - θ_run) ∂A/∂θ``, zero in value,
        with the maps' derivative at the run's ``θ`` (:meth:`_pose_derivatives`): a Gauss-Newton
        Jacobian needs every ray's derivative, not the run's total."""
        n = x.shape[0]
        theta = self._check_theta(theta, n)
        C = self._grid_state()[3][..., columns].to(x.dtype)
        if theta.dim() == 1 or n == 0 or theta.stride(0) == 0:  # one θ for all rows (an expanded one: its gradient sums)
            return _affine(x, self.part_from_object(theta, n).to(x.dtype).transpose(-1, -2) @ C, translate)
        starts = _runs(theta.detach())
        if starts is None:  # many configurations: the FK per row
            return _affine(x, self.part_from_object(theta, n).to(x.dtype).transpose(-1, -2) @ C, translate)
        values = theta.detach()[starts[:-1]]  # [U, k]
        spans = list(zip(starts[:-1], starts[1:]))
        maps = [self.part_from_object(v, 1).to(x.dtype).transpose(-1, -2) @ C for v in values]  # U x [p, 4, K]
        out = torch.cat([_affine(x[a:b], A, translate) for (a, b), A in zip(spans, maps)])
        if not needs_theta_grad(theta):
            return out
        dmaps = self._pose_derivatives(values).to(x.dtype).transpose(-1, -2) @ C  # [U, k, p, 4, K]
        x0 = x.detach()
        term = torch.cat([torch.stack([_affine(x0[a:b], dA, translate) for dA in dmaps[u]], -1)  # [m, p, K, k]
                          for u, (a, b) in enumerate(spans)])
        delta = (theta - theta.detach()).to(x.dtype)  # zero, with ∂/∂θ = 1 in every row
        return out + (term * delta[:, None, None, :]).sum(-1)

    def lookup_tangents(self, x: Tensor, theta: Tensor, sample: Tensor, part: Tensor, columns: slice = slice(None)) -> Tensor:
        """``∂/∂(x, θ)`` of :meth:`lookup_coordinates` (its ``columns``) of the samples ``sample [m]`` in the parts
        ``part [m]`` (rows of ``x [n, 3]``, ``θ [k]`` or ``[n, k]``): ``[m, K, 3 + k]``, exact (the coordinates
        are affine in ``x`` at a ``θ``; the ``θ`` columns from the chain's derivatives)."""
        n = x.shape[0]
        theta = self._check_theta(theta, n).detach()
        C = self._grid_state()[3][..., columns].to(x.dtype)
        if theta.dim() == 1 or n == 0 or theta.stride(0) == 0:
            values, run = theta.reshape(-1, self.n_theta)[:1], torch.zeros_like(sample)
        else:
            starts = _runs(theta)
            if starts is None:  # many configurations: one run per row
                values, run = theta, sample
            else:
                values = theta[starts[:-1]]
                run = torch.searchsorted(torch.tensor(starts[1:-1], device=x.device), sample, right=True)
        linear = invert_pose(self.part_poses(values)).to(x.dtype).transpose(-1, -2) @ C  # [U, p, 4, K]
        dmaps = self._pose_derivatives(values).to(x.dtype).transpose(-1, -2) @ C  # [U, k, p, 4, K]
        along_x = linear[run, part, :3].transpose(1, 2)  # [m, K, 3]: the coordinates' change per metre
        point = torch.cat([x[sample], x.new_ones(len(sample), 1)], 1)  # [m, 4]
        along_theta = torch.einsum("md,mjdK->mKj", point, dmaps[run, :, part])  # [m, K, k]
        return torch.cat([along_x, along_theta], -1)

    def _pose_derivatives(self, values: Tensor) -> Tensor:
        """``∂T_part_obj / ∂θ_j [U, k, p, 4, 4]`` at each configuration of ``values [U, k]``, from the chain's
        (:meth:`_chain`) by ``∂T⁻¹ = -T⁻¹ ∂T T⁻¹``; in closed form, as torch's forward mode would import its
        compiler stack (about half a second) into every estimating process."""
        T, dT = self._chain(values, derivatives=True)
        T_part_obj = invert_pose(T)[:, None]  # [U, 1, p, 4, 4]
        return -T_part_obj @ dT @ T_part_obj

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
        coords = self.lookup_coordinates(x, theta)  # [n, p, 3 + 2N]
        occupied = self.part_lookup().occupied_cells(coords[..., :3])  # [n, p]
        part, sample = occupied.t().nonzero(as_tuple=True)  # (sample, part) pairs grouped by part
        if sample.numel() == 0:
            return sigma, weighted
        features = self._plane_features(coords[..., 3:][sample, part].to(self.atlas.dtype))  # [m, F * S]
        counts = occupied.sum(0).tolist()
        out = torch.cat([self.decoders[i](f) for i, f in enumerate(features.split(counts)) if f.shape[0]])
        raw = out[:, 0]
        s = (trunc_exp(raw) if torch.is_grad_enabled() else raw.clamp(max=SIGMA_MAX_LOG).exp_()).to(x.dtype)
        sigma = sigma.index_add(0, sample, s)
        if color:
            weighted = weighted.index_add(0, sample, s[:, None] * torch.sigmoid(out[:, 1:]).to(x.dtype))
        return sigma, weighted

    def _plane_features(self, uv: Tensor) -> Tensor:
        """K-planes features ``[m, F * S]`` of samples at atlas coordinates ``uv [m, 2N]`` (their ``grid_sample``
        coordinates in their part's tile of each plane, :meth:`_lookup_coordinates`)."""
        n_planes = self.atlas.shape[0]
        grid = uv.reshape(-1, n_planes, 2).transpose(0, 1)[:, None]  # [N, 1, m, 2]
        atlas = self.atlas.permute(0, 3, 1, 2)  # [N, F, rows, width] over channels-last memory
        out = F.grid_sample(atlas, grid, mode="bilinear", padding_mode="border", align_corners=True)[:, :, 0]  # [N, F, m]
        out = out.reshape(-1, 3, self.features, out.shape[-1])  # [S, 3, F, m]
        return (out[:, 0] * out[:, 1] * out[:, 2]).reshape(-1, out.shape[-1]).t()

    supports_jacobian = True  # view-independent: :meth:`jacobian` serves

    @torch.no_grad()
    def jacobian(self, x: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
        """The field and its derivatives at ``x [n, 3]`` (object frame), ``θ [k]`` or ``[n, k]``: ``values
        [n, 4]`` (``σ``, colour) and ``∂values/∂(x, θ) [n, 4, 3 + k]``; no graph.

        Reverse mode gives a sample's derivatives one output at a time (a backward pass through the planes
        and decoders per output, four in all). Here every column is one difference in the lookup coordinates
        along their exact tangent (:meth:`lookup_tangents`) that keeps every lookup between the same two
        texel centres (:func:`~narf_core.fields.encodings.in_texel_step`: the bilinear lookup is linear
        there, so the difference is its derivative), with each sample's parts fixed as at ``x`` (the
        occupancy's cut is not differentiated, as reverse mode does not differentiate it either): the planes
        and decoders evaluated once at ``1 + 3 + k`` coordinate sets; ``σ = exp(raw)`` and the sigmoid's
        colour are differentiated in closed form."""
        n, k = x.shape[0], self.n_theta
        values, derivatives = x.new_zeros(n, 4), x.new_zeros(n, 4, 3 + k)
        if n == 0:
            return values, derivatives
        theta = self._check_theta(theta, n)
        coords = self.lookup_coordinates(x, theta)  # [n, p, 3 + 2N]
        occupied = self.part_lookup().occupied_cells(coords[..., :3])  # [n, p]
        part, sample = occupied.t().nonzero(as_tuple=True)  # (sample, part) pairs grouped by part
        if sample.numel() == 0:
            return values, derivatives
        uv = coords[..., 3:][sample, part]  # [m, 2N]
        tangents = self.lookup_tangents(x, theta, sample, part, slice(3, None))  # [m, 2N, 3 + k]
        rows, width = self.atlas.shape[1:3]
        per_texel = uv.new_tensor([(width - 1) / 2, (rows - 1) / 2]).repeat(uv.shape[1] // 2)  # texels per unit, u and v
        texel, rate = (uv + 1) * per_texel, tangents * per_texel[:, None]
        step = torch.stack([in_texel_step(texel, rate[..., j]) for j in range(3 + k)], 1)  # [m, 3 + k]
        shifted = uv[None] + step.t()[..., None] * tangents.permute(2, 0, 1)  # [3 + k, m, 2N]
        stacked = torch.cat([uv[None], shifted])  # [T, m, 2N]
        T, m = stacked.shape[:2]
        features = self._plane_features(stacked.reshape(T * m, -1).to(self.atlas.dtype)).reshape(T, m, -1)
        counts = occupied.sum(0).tolist()
        raw = torch.cat([self.decoders[i](f.reshape(-1, f.shape[-1])).reshape(T, -1, 4)
                         for i, f in enumerate(features.split(counts, dim=1)) if f.shape[1]], dim=1).to(x.dtype)
        draw = ((raw[1:] - raw[:1]) / step.t()[..., None]).permute(1, 2, 0)  # [m, 4, 3 + k]
        s, c, ds, dc = activated_jacobian(raw[0], draw)  # each pair's density and colour, [m, 3 + k], [m, 3, 3 + k]
        sigma = x.new_zeros(n).index_add(0, sample, s)
        weighted = x.new_zeros(n, 3).index_add(0, sample, s[:, None] * c)
        dsigma = x.new_zeros(n, 3 + k).index_add(0, sample, ds)
        dweighted = x.new_zeros(n, 3, 3 + k).index_add(0, sample, ds[:, None] * c[..., None] + s[:, None, None] * dc)
        inverse = torch.where(sigma > 0, 1 / sigma.clamp_min(1e-30), 0.0)  # the density-weighted mean colour
        colour = weighted * inverse[:, None]
        dcolour = (dweighted - colour[..., None] * dsigma[:, None]) * inverse[:, None, None]
        return torch.cat([sigma[:, None], colour], 1), torch.cat([dsigma[:, None], dcolour], 1)

    def forward(self, x: Tensor, d: Tensor, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        sigma, weighted = self._evaluate(x, theta, True)
        if not torch.is_grad_enabled():  # where σ = 0 no part holds density, so the weighted sum is 0 too
            return sigma, weighted.div_(sigma.clamp_min(1e-30)[:, None])
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

    def __init__(self, grids: Sequence[OccupancyGrid], coarse: bool = True) -> None:
        self.flat = torch.cat([F.pad(g.occupancy, (1, 1, 1, 1, 1, 1)).reshape(-1) for g in grids])
        # blocks of _BLOCK^3 cells, occupied where any cell of theirs or of a neighbouring block is
        self.coarse = _PartLookup([_blocks(g) for g in grids], coarse=False) if coarse else None
        device = self.flat.device
        cells = torch.tensor([g.resolution for g in grids], dtype=torch.float32, device=device)  # [p, 3]
        lo = torch.stack([g.aabb[0] for g in grids])  # [p, 3]
        self.scale = cells / (torch.stack([g.aabb[1] for g in grids]) - lo)
        self.shift = 1 - lo * self.scale  # cell units of the padded grid: x * scale + shift
        self.z_scale, self.z_shift = 2 / cells, -2 / cells - 1  # cell units -> [-1, 1] over the box
        padded = cells.long() + 2
        # the last cell, the flat table's strides [p, 3] and each part's first cell [p], in float32 like the lookups'
        # sums (exact: the table has fewer than 2^24 cells)
        self.top = (padded - 1).float()
        self.strides = torch.stack([padded[:, 1] * padded[:, 2], padded[:, 2], padded.new_ones(len(grids))], -1).float()
        self.offset = torch.cat([padded.new_zeros(1), padded.prod(-1).cumsum(0)[:-1]]).float()
        if self.flat.numel() >= 1 << 24:
            raise ValueError(f"at most 2^24 cells in all part grids together, got {self.flat.numel()}")
        self._axes = [(top.long().tolist(), size.tolist(), int(o)) for top, size, o in zip(self.top, padded, self.offset)]
        self.boxes = torch.stack([_occupied_cells_box(g.occupancy) for g in grids], 1)  # [2, p, 3], padded cell units
        if self.coarse is not None:  # cell units -> the coarse grids' (block) units: c * ratio + offset, [p, 3]
            self.to_coarse = (self.coarse.scale / self.scale, self.coarse.shift - self.shift * self.coarse.scale / self.scale)

    def occupied_cells(self, c: Tensor) -> Tensor:
        """``c [..., p, 3]`` in cell units -> ``[..., p]``: in an occupied cell of the part's grid (the flat index
        summed in float32, two products where a sum over an axis of three costs more)."""
        cell = torch.minimum(c.floor().clamp_(min=0), self.top)
        flat = torch.addcmul(self.offset, cell[..., 0], self.strides[:, 0]).addcmul_(cell[..., 1], self.strides[:, 1])
        return self.flat[flat.add_(cell[..., 2]).int()]

    def occupied_along(self, c: Tensor, cd: Tensor, t: Tensor) -> Tensor:
        """``[m, w]``: the points ``c + t cd`` (``c``, ``cd [m, p, 3]`` rays in each part grid's cell units,
        ``t [m, w]``) in an occupied cell of any part: one contiguous ``[m, w]`` pass per part and axis."""
        hit = None
        for i, (top, padded, offset) in enumerate(self._axes):
            flat = None
            for a in range(3):  # the flat index, row-major: ((i_x * n_y) + i_y) * n_z + i_z
                cell = torch.addcmul(c[:, i, a : a + 1], t, cd[:, i, a : a + 1]).floor_().clamp_(0, top[a])
                flat = cell if flat is None else flat.mul_(padded[a]).add_(cell)
            occupied = self.flat[flat.add_(offset).int()]  # exact in float32: the table has fewer than 2^24 cells
            hit = occupied if hit is None else hit.logical_or_(occupied)
        return hit


def _changes(theta: Tensor) -> Tensor:
    """``[n - 1]``: where row ``i + 1`` of ``theta [n, k]`` differs from row ``i`` (a new run starts)."""
    return (theta[1:] != theta[:-1]).any(-1)


def _runs(theta: Tensor) -> list[int] | None:
    """Where the runs of equal rows of ``theta [n, k]`` start, with ``n`` last; ``None`` for more than
    ``_MAX_RUNS`` runs."""
    change = _changes(theta)
    if int(change.sum()) >= _MAX_RUNS:
        return None
    return [0, *(change.nonzero()[:, 0] + 1).tolist(), theta.shape[0]]


def _distinct_rows(theta: Tensor) -> Tensor:
    """The distinct rows of ``theta [n, k]``, sorted. Rays come in runs of one θ (one per start): the
    runs' first rows, then ``torch.unique`` over those few (over all ``n`` rows it sorts them all)."""
    first = torch.ones(theta.shape[0], dtype=torch.bool, device=theta.device)
    first[1:] = _changes(theta)
    return torch.unique(theta[first], dim=0)


def _affine(x: Tensor, A: Tensor, translate: bool = True) -> Tensor:
    """``x [n,3]`` mapped by each part's affine map ``A [p, 4, K]`` (or one per row, ``[n, p, 4, K]``; rows
    ``x, y, z, 1``) -> ``[n, p, K]``; ``translate=False`` for directions. A shared map is one matrix product."""
    if A.dim() == 3:
        W = A[:, :3].transpose(0, 1).reshape(3, -1)  # [3, p * K]
        out = torch.addmm(A[:, 3].reshape(-1), x, W) if translate else x @ W
        return out.reshape(x.shape[0], A.shape[0], A.shape[-1])  # K explicit: x may have no rows
    out = torch.einsum("nj,npjk->npk", x, A[..., :3, :])
    return out + A[..., 3, :] if translate else out


def _blocks(grid: OccupancyGrid) -> OccupancyGrid:
    """``grid`` in blocks of :data:`_BLOCK` cells per axis, over its box grown to whole blocks and by one
    more block on every side; a block is occupied where it or one of its 26 neighbours holds an occupied cell."""
    occupancy = F.pad(F.max_pool3d(grid.occupancy[None, None].float(), _BLOCK, ceil_mode=True), (1, 1, 1, 1, 1, 1))
    occupancy = F.max_pool3d(occupancy, 3, stride=1, padding=1)[0, 0] > 0
    size = grid.cell_size * _BLOCK
    lo = grid.aabb[0] - size
    return OccupancyGrid(torch.stack([lo, lo + size * torch.tensor(occupancy.shape, device=lo.device)]), occupancy)


def _occupied_cells_box(occupancy: Tensor) -> Tensor:
    """``[2, 3]``: the box around the occupied cells of ``occupancy [Rx, Ry, Rz]`` in cell units of the
    grid padded by one cell, grown by :data:`_BOX_MARGIN` cells; empty (lower > upper) if none is occupied."""
    nz = occupancy.nonzero()
    if nz.shape[0] == 0:
        return torch.tensor([[math.inf] * 3, [-math.inf] * 3], device=occupancy.device)
    return torch.stack([nz.amin(0) + 1 - _BOX_MARGIN, nz.amax(0) + 2 + _BOX_MARGIN]).float()


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
        self._bounds: tuple[tuple, Tensor] | None = None  # (shared θ, its box): a render asks twice for it

    def _part_from_object(self, theta: Tensor | None) -> Tensor:
        """``T_part_obj`` ``[p,4,4]`` (a shared θ) or ``[m,p,4,4]`` (one per point or ray)."""
        theta = self.theta if theta is None else theta.detach()
        return self.field.part_from_object(theta, theta.shape[0] if theta.dim() == 2 else 1)

    def occupied(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        theta = self.theta if theta is None else theta.detach()
        cells = self.field.lookup_coordinates(x, theta, slice(0, 3))  # cell units, as the field looks up
        return self.field.part_lookup().occupied_cells(cells).any(-1)

    def occupied_near(self, x: Tensor, theta: Tensor | None = None) -> Tensor:
        """``x [n,3]`` -> ``[n]`` bool: in an occupied block of the coarse part grids (``_BLOCK`` cells a side,
        each dilated by a block): every point :meth:`occupied` holds, and every point within a block of one
        along each axis of its part's grid."""
        theta = self.theta if theta is None else theta.detach()
        lookup = self.field.part_lookup()
        ratio, offset = lookup.to_coarse
        cells = self.field.lookup_coordinates(x, theta, slice(0, 3))
        return lookup.coarse.occupied_cells(cells * ratio + offset).any(-1)

    def bounds(self, theta: Tensor | None = None) -> Tensor | None:
        """The object-frame box around the posed parts' tight boxes (over every ray's ``θ`` if per ray)."""
        shared = (self.theta if theta is None else theta).detach()
        if shared.dim() == 2:
            shared = _distinct_rows(shared)
            shared = shared[0] if shared.shape[0] == 1 else shared  # one θ on every ray: one box, kept
        key = tuple(shared.tolist()) if shared.dim() == 1 else None
        if key is not None and self._bounds is not None and self._bounds[0] == key:
            return self._bounds[1]
        grids = self.field.part_grids()
        boxes = [(i, grid.bounds()) for i, grid in enumerate(grids)]
        boxes = [(i, box) for i, box in boxes if box is not None]
        if not boxes:
            return None
        T = invert_pose(self._part_from_object(shared)).reshape(-1, len(grids), 4, 4)
        index = [i for i, _ in boxes]
        corners = transform_points(T[:, index, None], torch.stack([box_corners(box) for _, box in boxes])).reshape(-1, 3)
        box = torch.stack([corners.amin(0), corners.amax(0)])
        if key is not None:
            self._bounds = (key, box)
        return box

    def along(self, origins: Tensor, directions: Tensor, theta: Tensor | None = None) -> PosedGridRays:
        theta = self.theta if theta is None else theta.detach()
        cells = slice(0, 3)  # cell units
        c = self.field.lookup_coordinates(origins, theta, cells)  # [m, p, 3]
        cd = self.field.lookup_coordinates(directions, theta, cells, translate=False)
        return PosedGridRays(self.field.part_lookup(), c.float(), cd.float())


class PosedGridRays:
    """:class:`~narf_core.occupancy.RayOccupancy` of :class:`PosedGrids`: the rays in every part grid's cell
    units (``c``, ``cd [m, p, 3]``), so a marching round is one lookup for all parts."""

    def __init__(self, lookup: _PartLookup, c: Tensor, cd: Tensor) -> None:
        self.lookup, self.c, self.cd = lookup, c, cd

    def span(self) -> tuple[Tensor, Tensor]:
        """``(near [m], far [m])``: each ray meets occupied cells only between these distances (``near >
        far`` for a ray that meets none).

        First the union of its segments through the parts' occupied boxes; then, within it, the first and
        last of its samples that fall in occupied blocks of the coarse part grids (``_BLOCK`` cells a
        side, each dilated by a block), taken so that no sample moves more than one block along any
        axis of any part from the last: an occupied cell of the ray lies within half a sample spacing
        of a sample in an occupied (dilated) block, so nothing occupied falls outside the span."""
        near, far, hit = ray_aabb(self.c, self.cd, self.lookup.boxes)  # [m, p] each, every part's box in its grid
        near = torch.where(hit, near, math.inf).amin(-1)
        far = torch.where(hit, far, -math.inf).amax(-1)
        coarse, (ratio, offset) = self.lookup.coarse, self.lookup.to_coarse
        cd = self.cd * ratio  # the rays in the coarse grids' block units
        spacing = 1 / cd.abs().flatten(1).amax(1).clamp_min(1e-12)  # [m]: at most one block per sample
        count = torch.ceil((far - near) / spacing).nan_to_num(0, 0, 0).clamp_min(0)  # samples over each span
        count = torch.where(count > _SPAN_SAMPLES, 0, count)  # a longer span keeps its boxes' bounds
        most = int(count.max()) if count.numel() else 0
        if most == 0:
            return near, far
        t = near[:, None] + (torch.arange(most, dtype=near.dtype, device=near.device) + 0.5) * spacing[:, None]  # [m, most]
        blocks = coarse.occupied_along(self.c * ratio + offset, cd, t.nan_to_num(0, 0, 0))
        blocks &= torch.arange(most, device=near.device) < count[:, None]
        first = torch.where(blocks, t, math.inf).amin(1) - spacing / 2
        last = torch.where(blocks, t, -math.inf).amax(1) + spacing / 2
        refined = count > 0
        return torch.where(refined, torch.maximum(near, first), near), torch.where(refined, torch.minimum(far, last), far)

    def __call__(self, t: Tensor) -> Tensor:
        return self.lookup.occupied_along(self.c, self.cd, t.float())

    def select(self, keep: Tensor) -> PosedGridRays:
        return PosedGridRays(self.lookup, self.c[keep], self.cd[keep])
