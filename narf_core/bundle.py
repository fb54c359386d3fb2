"""The model bundle: one safetensors file per object (docs/design.md §6), and the model it loads into.

A bundle holds tensors only (never pickle):
  ``field.*``              the configuration field F(x, d, θ), unless it is an articulated field copied
                           from the part fields (``field_from_parts`` in the metadata): then it is
                           rebuilt from them at load and the part fields are stored once
  ``grid``                 its occupancy grid, valid for every θ in the limits (bits, packed)
  ``part.<i>.*``           the part fields, if the bundle keeps them (render mode ``parts``)
  ``part_grid.<i>``        their occupancy grids (bits, packed)
  ``points.<link>``        surface points per link, in the link frame, for ADD
  ``dense.<link>``         denser surface points per link (link frame) that depth is fitted to; a bundle
                           saved without them loads, and the fit uses ``points.*``
and one JSON document in the safetensors metadata under ``"narf"``: format and version, object
name, links, joints with limits, bounds, field architectures and hyper-parameters, the URDF text
(for FK), training provenance and metrics, the render modes' measurement (``mode_measurement``,
narf_core/modes.py), and ``checksum``: the SHA-256 of the tensors (see
:func:`tensors_digest`), written at save and verified at load. A bundle whose tensors do not match
it, or that holds a non-finite weight, is refused; one saved before checksums existed loads with the
finiteness check only (load and save it again to add one).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field as dataclass_field
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor

from narf_core.checks import InputError, JointSpec, check_number
from narf_core.fields import ArticulatedField, make_field
from narf_core.fields.composed import ComposedField, compose_parts
from narf_core.diameter import object_diameter
from narf_core.geometry import Pinhole, Rays
from narf_core.kinematics import KinematicTree
from narf_core.modes import MODES, RECORD_KEY, choose_mode
from narf_core.render import OccupancyGrid, RenderOutput, march_samples, render_image, render_rays
from narf_core.sampling import Samples

FORMAT = "narf-bundle"
FORMAT_VERSION = 3  # 3: an articulated field copied from the part fields is stored as those parts only
READ_VERSIONS = (2, 3)  # 2 (occupancy grids as packed bits, their shapes in the metadata) still loads
CHECKSUM_ALGORITHM = "sha256"
STEPS_PER_DIAGONAL = 256


def march_step(aabb: Tensor) -> float:
    """The ray-marching interval (metres) of a model whose box is ``aabb [2, 3]``: its diagonal /
    :data:`STEPS_PER_DIAGONAL`, used in training and by every render of the trained model."""
    return float((aabb[1] - aabb[0]).norm()) / STEPS_PER_DIAGONAL


class BundleError(ValueError):
    """A bundle file that cannot be used: missing, corrupt, foreign or of another version."""


def resolve_device(device: str | torch.device) -> torch.device:
    """The torch device named ``device`` (``cpu``, ``cuda`` or ``cuda:N``), if this machine has it.

    A ValueError says why not (an unknown name, a torch built without CUDA, no such GPU), so that the
    CLI, the benchmarks and the service refuse a device in one line before loading anything.
    """
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device {device!r}: not a torch device (use 'cpu', 'cuda' or 'cuda:N')") from None
    if resolved.type == "cpu":
        return resolved
    if resolved.type != "cuda":
        raise ValueError(f"device {device!r}: only 'cpu' and 'cuda' are supported")
    if not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: this torch ({torch.__version__}) sees no CUDA device")
    count = torch.cuda.device_count()
    if resolved.index is not None and resolved.index >= count:
        raise ValueError(f"device {device!r}: this machine has {count} CUDA device(s)")
    return resolved


@dataclass
class NarfModel:
    """A trained object: the configuration field, optionally its part fields, and its kinematics.

    ``field`` is any field callable ``(x [n,3], d [n,3], θ [n,k]) -> (σ [n], rgb [n,3])`` (a trained
    :class:`~narf_core.fields.base.RadianceField` in practice); ``grid`` is its occupancy grid over
    the object box, valid for every θ within the limits. ``sample_points`` (500 a link) are the model points
    of ADD and the refiner's geometric checks; ``dense_points`` (:meth:`~narf_core.kinematics.KinematicTree.
    dense_points`, a few millimetres apart) are what a depth image's points are fitted to, empty in a bundle
    saved before they were kept (the fit then uses ``sample_points``).
    """

    name: str
    kinematics: KinematicTree
    field: torch.nn.Module
    grid: OccupancyGrid
    part_fields: list[torch.nn.Module] | None = None
    part_grids: list[OccupancyGrid] | None = None
    metadata: dict = dataclass_field(default_factory=dict)
    step: float | None = None
    sample_points: dict[str, np.ndarray] = dataclass_field(default_factory=dict)
    dense_points: dict[str, np.ndarray] = dataclass_field(default_factory=dict)

    def __post_init__(self) -> None:
        kin = self.kinematics
        self.links = list(kin.links)
        self.joints = [JointSpec(j.name, j.type, float(j.lower), float(j.upper)) for j in kin.movable]
        self.lower = kin.lower.to(torch.float32)
        self.upper = kin.upper.to(torch.float32)
        self.aabb = self.grid.aabb.to(torch.float32)
        if self.step is None:
            self.step = march_step(self.aabb)
        if not self.sample_points:  # built from a URDF with its meshes (training), not loaded
            self.sample_points = kin.sample_points()
            self.dense_points = self.dense_points or kin.dense_points()
        points = np.concatenate(list(self.sample_points.values())) if self.sample_points else np.zeros((0, 3))
        self.diameter = float(self.metadata.get("diameter") or _diameter(points, kin, self.sample_points))

    @property
    def has_parts(self) -> bool:
        return bool(self.part_fields)

    def joint_vector(self, joints: Mapping[str, float] | None, *, field: str = "joints") -> Tensor:
        """θ ``[k]`` (float32) from ``{name: value}``; missing joints at mid-range.

        Raises :class:`~narf_core.checks.InputError` naming ``field`` and an unknown joint, a
        non-finite value or one outside its limits.
        """
        return self.kinematics.joint_vector(joints, field=field).to(torch.float32)

    def joint_dict(self, theta: Tensor) -> dict[str, float]:
        return self.kinematics.joint_dict(theta)

    def _field_for(self, mode: str, theta: Tensor):
        """The field and occupancy to render in ``mode`` at ``θ [k]``.

        ``parts`` composes the part fields at the part poses FK gives for ``θ [k]`` (differentiable
        in ``θ``); the composition is its own occupancy grid, so empty space is skipped there too.
        With one ``θ`` per ray (``[n, k]``), FK runs per sample instead. ``narf`` marches the
        model's grid, or for a field with FK inside (the articulated field) its part grids posed at
        ``θ`` (``field.occupancy(θ)``), which are tight at every configuration. ``auto``: the mode
        :func:`~narf_core.modes.choose_mode` picks for this model.
        """
        if mode == "auto":
            mode = choose_mode(self, mode)[0]
        if mode == "narf":
            posed = getattr(self.field, "occupancy", None)  # a field with FK inside: its parts' grids posed at θ
            return self.field, (posed(theta) if callable(posed) else self.grid)
        if mode == "parts":
            if not self.has_parts:
                raise ValueError(f"model {self.name!r} has no part fields: render mode 'parts' is unavailable")
            if theta.dim() == 2:  # one θ per ray (several starts in one batch): FK per sample
                return ComposedField(self.part_fields, self.part_grids, self.kinematics.part_poses), None
            composition = compose_parts(self.part_fields, self.part_grids, self.kinematics.part_poses(theta).to(torch.float32))
            return composition, composition
        raise ValueError(f"unknown render mode {mode!r}; expected one of {', '.join(MODES)}")

    def render_rays(
        self,
        rays_obj: Rays,
        theta: Tensor,
        *,
        mode: str = "narf",
        outputs: tuple[str, ...] = ("rgb",),
        background: float = 0.0,
        t_range: tuple[Tensor, Tensor] | None = None,
    ) -> RenderOutput:
        """Render rays given in the object frame at configuration ``θ [k]``; differentiable.
        ``t_range``: ``(near [n], far [n])``, march only that band of each ray (see :func:`render_rays`)."""
        field, grid = self._field_for(mode, theta)
        return render_rays(
            field, rays_obj, self.aabb, theta=theta, grid=grid, step=self.step, outputs=outputs, background=background,
            t_range=t_range,
        )

    def march(
        self, rays_obj: Rays, theta: Tensor, *, mode: str = "narf", t_range: tuple[Tensor, Tensor] | None = None
    ) -> tuple[object, Samples]:
        """The field of ``mode`` at ``θ`` (``[k]`` or ``[n, k]``) and the samples a differentiable
        :meth:`render_rays` of these arguments composites (:func:`~narf_core.render.march_samples`)."""
        field, grid = self._field_for(mode, theta)
        return field, march_samples(field, rays_obj, self.aabb, theta=theta, grid=grid, step=self.step, t_range=t_range)

    def render(
        self,
        T_cam_obj: Tensor,
        theta: Tensor,
        camera: Pinhole,
        *,
        outputs: tuple[str, ...] = ("rgb",),
        mode: str = "narf",
    ) -> dict[str, Tensor]:
        """Images of the object at pose ``T_cam_obj [4,4]`` and ``θ [k]``.

        Returns the asked outputs: ``rgb [H,W,3]`` in [0, 1], ``depth [H,W]`` (metres, 0 = no return),
        ``opacity [H,W]``, on the model's device (the inputs may be on any).
        """
        device = self.aabb.device
        theta = theta.to(device, torch.float32)
        field, grid = self._field_for(mode, theta)
        with torch.no_grad():
            return render_image(
                field,
                Pinhole(camera.K.to(device, torch.float32), camera.width, camera.height),
                T_cam_obj.to(device, torch.float32),
                theta=theta,
                aabb=self.aabb,
                grid=grid,
                outputs=outputs,
                step=self.step,
            )

    def describe(self) -> dict:
        """JSON-able description: links, joints and limits, bounds, metrics, the modes and the one
        ``auto`` picks with its reason and measurement (the service's ``/v1/models`` answers are made of it)."""
        return {
            "name": self.name,
            "links": list(self.links),
            "joints": [dataclasses.asdict(j) for j in self.joints],
            "bounds": self.aabb.tolist(),
            "diameter": self.diameter,
            "modes": ["narf", "parts"] if self.has_parts else ["narf"],
            "auto_mode": dict(zip(("mode", "reason"), choose_mode(self, "auto"))),
            RECORD_KEY: self.metadata.get(RECORD_KEY),
            "field": self.metadata.get("field") or {},
            "metrics": self.metadata.get("metrics") or {},
            "provenance": self.metadata.get("provenance") or {},
        }


def _diameter(points: np.ndarray, kin: KinematicTree, sample_points: dict[str, np.ndarray]) -> float:
    """Largest distance between surface points of the object at mid-range θ."""
    if len(points) == 0:
        return 0.0
    poses = kin.link_poses(kin.mid_configuration()).numpy()
    world = [p @ poses[kin.links.index(name), :3, :3].T + poses[kin.links.index(name), :3, 3] for name, p in sample_points.items()]
    return float(object_diameter(np.concatenate(world)))


def with_dense_points(model: NarfModel, urdf: str | Path) -> NarfModel:
    """``model`` with the ``dense_points`` of the meshes that ``urdf`` (a file whose meshes lie beside it) names,
    for a bundle saved before they were kept. The meshes must be those the model was trained on: their 500
    points a link, drawn as at training, must come out as the bundle's ``sample_points`` (float32 rounding), else
    :class:`BundleError` names the first link that differs."""
    kin = KinematicTree.from_urdf(urdf)
    if list(kin.links) != list(model.links):
        raise BundleError(f"{urdf}: its links {list(kin.links)} are not the model's {list(model.links)}")
    points = kin.sample_points()
    for name, own in model.sample_points.items():
        theirs = points.get(name)
        if theirs is None or theirs.shape != own.shape or not np.allclose(theirs, own, rtol=0, atol=1e-6):
            raise BundleError(f"{urdf}: link {name!r}'s meshes are not the ones {model.name!r} was trained on")
    return dataclasses.replace(model, dense_points=kin.dense_points())


def save_bundle(path: str | Path, model: NarfModel) -> Path:
    """Write ``model`` to ``path`` atomically (a temporary file renamed into place)."""
    path = Path(path)
    tensors: dict[str, Tensor] = {}
    from_parts = _field_from_parts(model)
    for key, value in ({} if from_parts else model.field.state_dict()).items():
        tensors[f"field.{key}"] = value
    tensors["grid"] = _pack_bits(model.grid.occupancy)
    part_meta = []
    for i, (pf, pg) in enumerate(zip(model.part_fields or [], model.part_grids or [])):
        for key, value in pf.state_dict().items():
            tensors[f"part.{i}.{key}"] = value
        tensors[f"part_grid.{i}"] = _pack_bits(pg.occupancy)
        part_meta.append({"field": pf.config(), "grid_aabb": pg.aabb.tolist(), "grid_shape": list(pg.occupancy.shape)})
    for link, pts in model.sample_points.items():
        tensors[f"points.{link}"] = torch.as_tensor(pts, dtype=torch.float32)
    for link, pts in model.dense_points.items():
        tensors[f"dense.{link}"] = torch.as_tensor(pts, dtype=torch.float32)
    meta = {
        **{k: v for k, v in model.metadata.items() if k not in ("format", "version")},
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "name": model.name,
        "links": model.links,
        "joints": [j.__dict__ for j in model.joints],
        "bounds": model.aabb.tolist(),
        "step": model.step,
        "diameter": model.diameter,
        "field": model.field.config(),
        "field_from_parts": from_parts,
        "grid_aabb": model.grid.aabb.tolist(),
        "grid_shape": list(model.grid.occupancy.shape),
        "grid_theta_range": None if model.grid.theta_range is None else model.grid.theta_range.tolist(),
        "parts": part_meta,
        "part_links": model.kinematics.parts,
        "urdf": model.kinematics.urdf_text,
    }
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    meta["checksum"] = {"algorithm": CHECKSUM_ALGORITHM, "tensors": tensors_digest(tensors)}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata={"narf": json.dumps(meta)})
        os.chmod(tmp, 0o644)  # mkstemp makes it private; a bundle is meant to be read by services
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_metadata(path: str | Path) -> dict:
    """The bundle's JSON metadata, checked for format and version, without loading weights."""
    path = Path(path)
    if path.is_dir():
        raise BundleError(f"{path}: is a folder, not a model file")
    if not path.is_file():
        raise BundleError(f"{path}: no such model file")
    try:
        with open(path, "rb") as f:
            header_len = int.from_bytes(f.read(8), "little")
            header = json.loads(f.read(header_len)) if 0 < header_len < 100_000_000 else None
    except (ValueError, OSError) as e:
        raise BundleError(f"{path}: not a NARF model bundle ({_one_line(e)})") from None
    if header is None:
        reason = "the file is empty" if path.stat().st_size == 0 else "no safetensors header"
        raise BundleError(f"{path}: not a NARF model bundle ({reason})")
    narf = header.get("__metadata__") if isinstance(header, dict) else None
    if not isinstance(narf, dict) or "narf" not in narf:
        raise BundleError(f"{path}: not a NARF model bundle (a safetensors file without 'narf' metadata)")
    try:
        meta = json.loads(narf["narf"])
    except (ValueError, TypeError) as e:
        raise BundleError(f"{path}: not a NARF model bundle (its 'narf' metadata is not JSON: {_one_line(e)})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else meta
        raise BundleError(f"{path}: not a NARF model bundle (format {found!r})")
    if meta.get("version") not in READ_VERSIONS:
        raise BundleError(
            f"{path}: bundle format version {meta.get('version')!r} is not supported "
            f"(this NARF reads {FORMAT_VERSION} and the older {', '.join(map(str, READ_VERSIONS[:-1]))})"
        )
    return meta


def load_bundle(path: str | Path, device: str | torch.device = "cpu") -> NarfModel:
    """Load a ``.narf`` bundle onto ``device`` (:func:`resolve_device`); raises :class:`BundleError`
    with the reason if it cannot be used."""
    device = resolve_device(device)
    meta = read_metadata(path)
    try:
        tensors = load_file(str(path), device=str(device))
    except (SafetensorError, OSError, ValueError) as e:
        raise BundleError(f"{path}: corrupt model bundle ({_one_line(e)})") from None
    verify_tensors(path, meta, tensors)
    try:
        _check_training_camera(meta.get("training_camera"))
        kin = KinematicTree.from_urdf_string(meta["urdf"])
        theta_range = meta.get("grid_theta_range")
        grid = OccupancyGrid(
            torch.tensor(meta["grid_aabb"], device=device),
            _unpack_bits(tensors["grid"], meta["grid_shape"]),
            None if theta_range is None else torch.tensor(theta_range, device=device),
        )
        part_fields, part_grids = [], []
        for i, part in enumerate(meta.get("parts", [])):
            part_fields.append(_load_module(part["field"], tensors, f"part.{i}.", device))
            occupancy = _unpack_bits(tensors[f"part_grid.{i}"], part["grid_shape"])
            part_grids.append(OccupancyGrid(torch.tensor(part["grid_aabb"], device=device), occupancy))
        if meta.get("field_from_parts"):
            field = _articulated_from_parts(meta["field"], kin, part_fields, part_grids, device)
        else:
            field = _load_module(meta["field"], tensors, "field.", device)
        points = {k[len("points."):]: v.cpu().numpy() for k, v in tensors.items() if k.startswith("points.")}
        dense = {k[len("dense."):]: v.cpu().numpy() for k, v in tensors.items() if k.startswith("dense.")}
        return NarfModel(
            name=str(meta["name"]),
            kinematics=kin,
            field=field,
            grid=grid,
            part_fields=part_fields or None,
            part_grids=part_grids or None,
            metadata=meta,
            step=meta.get("step"),
            sample_points=points,
            dense_points=dense,
        )
    except (KeyError, RuntimeError, TypeError, ValueError) as e:  # ValueError: UrdfError, bad field config or grid
        raise BundleError(f"{path}: incomplete or inconsistent model bundle ({_one_line(e)})") from None


def _check_training_camera(camera) -> None:
    """``metadata["training_camera"]`` (``narf train``'s record of the views' camera, read by the tracker's
    uncertainty) absent, or positive sizes and focal lengths; ``ValueError`` naming what is wrong."""
    if camera is None:
        return
    keys = ("width", "height", "fx", "fy")
    try:
        good = isinstance(camera, Mapping) and all(check_number(camera.get(k), k) > 0 for k in keys)
    except InputError:  # not a finite number
        good = False
    if not good:
        raise ValueError(f"training_camera must hold positive numbers {', '.join(keys)}, got {camera!r}")


def tensors_digest(tensors: Mapping[str, Tensor]) -> str:
    """SHA-256 (hex) over the tensors in key order: each key, dtype, shape and raw bytes."""
    digest = hashlib.sha256()
    for key in sorted(tensors):
        t = tensors[key].detach().cpu().contiguous()
        digest.update(f"{key}\0{t.dtype}\0{list(t.shape)}\0".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()


def verify_tensors(path: str | Path, meta: Mapping, tensors: Mapping[str, Tensor]) -> None:
    """:class:`BundleError` unless the tensors match the metadata's checksum (when it has one) and
    every floating-point tensor is finite."""
    checksum = meta.get("checksum")
    if checksum is not None:
        if not isinstance(checksum, dict) or checksum.get("algorithm") != CHECKSUM_ALGORITHM:
            raise BundleError(f"{path}: unsupported checksum {checksum!r} (this NARF verifies {CHECKSUM_ALGORITHM})")
        if tensors_digest(tensors) != checksum.get("tensors"):
            raise BundleError(f"{path}: checksum mismatch: the weights changed after the bundle was saved")
    for key in sorted(tensors):
        t = tensors[key]
        if t.is_floating_point():
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                raise BundleError(f"{path}: non-finite weights in {key} ({bad} of {t.numel()} values)")


def _pack_bits(occupancy: Tensor) -> Tensor:
    """A bool grid of any shape as ``uint8 [ceil(numel / 8)]`` (row-major, big-endian bits)."""
    return torch.from_numpy(np.packbits(occupancy.detach().cpu().numpy().reshape(-1)))


def _unpack_bits(packed: Tensor, shape) -> Tensor:
    """The bool grid of ``shape`` that :func:`_pack_bits` packed; ``ValueError`` if the sizes disagree."""
    shape = tuple(int(s) for s in shape)
    count = int(np.prod(shape))
    if packed.dtype != torch.uint8 or packed.dim() != 1 or packed.numel() != -(-count // 8):
        raise ValueError(f"a packed occupancy grid of shape {shape} needs {-(-count // 8)} bytes, got {tuple(packed.shape)}")
    bits = np.unpackbits(packed.cpu().numpy(), count=count).reshape(shape)
    return torch.from_numpy(bits.astype(bool)).to(packed.device)


def _one_line(error: BaseException) -> str:
    """``Type: message`` on one line (torch's state-dict errors span several)."""
    return f"{type(error).__name__}: {' '.join(str(error).split())}"


def _field_from_parts(model: NarfModel) -> bool:
    """Whether ``model.field`` is the articulated field its part fields and grids rebuild, weight for weight
    (as ``narf train`` makes it): then the bundle stores the parts only. A field changed after the copy
    (or of another kind) is stored whole."""
    if not model.has_parts or model.field.config().get("arch") != "articulated":
        return False
    try:
        rebuilt = ArticulatedField.from_parts(model.kinematics, model.part_fields, model.part_grids, model.field.aabb.cpu())
    except ValueError:  # parts of another architecture or hyper-parameters
        return False
    ours, theirs = rebuilt.state_dict(), model.field.state_dict()
    return (
        rebuilt.config() == model.field.config()
        and ours.keys() == theirs.keys()
        and all(torch.equal(ours[k], theirs[k].detach().cpu()) for k in ours)
    )


def _articulated_from_parts(config: dict, kin: KinematicTree, part_fields, part_grids, device) -> torch.nn.Module:
    """The articulated field a bundle stores as its part fields (``field_from_parts``), checked against its ``config``."""
    field = ArticulatedField.from_parts(kin, part_fields, part_grids, torch.tensor(config["aabb"], device=device))
    if json.loads(json.dumps(field.config())) != config:
        raise ValueError("the articulated field rebuilt from the part fields differs from the bundle's field config")
    return field.to(device).eval().requires_grad_(False)


def _load_module(config: dict, tensors: dict[str, Tensor], prefix: str, device) -> torch.nn.Module:
    module = make_field(config).to(device)
    state = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    module.load_state_dict(state)
    return module.eval().requires_grad_(False)  # inference only: the refiner needs no weight gradients
