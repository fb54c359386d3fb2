"""The dataset format of docs/design.md §3: reading and validating it, writing it, and its URDF.

A dataset is a folder::

    object.urdf, meshes/...     the object (every mesh, material and texture it references)
    scene.json                  camera, links (label order), joints, frames, generator provenance
                                (a sequence's frames carry "time" in seconds, in time order)
    rgb/000000.png              sRGB uint8
    depth/000000.png            uint16 millimetres, 0 = no return (or .npy float32 metres)
    labels/000000.png           uint8, 0 = background, 1 + i = link i of "links"

:meth:`Dataset.open` validates everything it reads and raises :class:`DatasetError` naming the exact
file or JSON field that is wrong; :class:`DatasetWriter` writes the same format. When a generator
adds label noise, the clean ground truth is kept beside it (``clean/`` images and
``generator.clean_frames``) and ``Dataset.open(root, clean=True)`` reads that instead.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import torch
from PIL import Image

from narf_core.checks import InputError, JointSpec, check_joints, check_pose
from narf_core.depth import DEPTH_MM_MAX, depth_to_mm, mm_to_depth
from narf_core.geometry import Pinhole
from narf_core.kinematics import KinematicTree, UrdfError  # noqa: F401  (UrdfError: the one URDF error)

SPLITS = ("train", "test", "novel")
JOINT_TYPES = ("revolute", "prismatic", "continuous")
SCENE_FILE = "scene.json"
URDF_FILE = "object.urdf"
MESH_DIR = "meshes"
MAX_LINKS = 255  # labels are uint8 with 0 for the background

_MTL_MAPS = ("map_kd", "map_ka", "map_ks", "map_d", "map_bump", "bump", "norm")  # MTL keys naming textures


class DatasetError(ValueError):
    """A dataset on disk is malformed; the message names the file or JSON field that is wrong."""


@dataclass
class Frame:
    """One labelled view. Image paths are relative to the dataset root (POSIX separators)."""

    id: int
    rgb: str
    depth: str | None
    labels: str
    T_cam_obj: np.ndarray  # [4, 4] float64
    joints: dict[str, float]
    split: str
    time: float | None = None  # seconds, in sequences (frames in time order); None elsewhere

    def to_json(self) -> dict[str, Any]:
        out = {
            "id": self.id,
            "rgb": self.rgb,
            "depth": self.depth,
            "labels": self.labels,
            "T_cam_obj": np.asarray(self.T_cam_obj, dtype=np.float64).tolist(),
            "joints": {name: float(value) for name, value in self.joints.items()},
            "split": self.split,
        }
        if self.time is not None:
            out["time"] = float(self.time)
        return out


@dataclass
class FrameImages:
    """The images of one frame: ``rgb`` uint8 ``[H, W, 3]``, ``depth`` float32 metres ``[H, W]``
    (0 = no return) or ``None``, ``labels`` uint8 ``[H, W]``."""

    rgb: np.ndarray
    depth: np.ndarray | None
    labels: np.ndarray


# --------------------------------------------------------------------------------------------
# URDF: what the dataset needs to know of it, and copying it with its meshes


@dataclass(frozen=True)
class UrdfInfo:
    """The parts of a URDF the dataset format uses, read by :class:`~narf_core.kinematics.KinematicTree`
    (the one URDF reader, with its rules for joints, limits and mimic joints).

    ``links`` in the order the file lists them (this is the label order); ``joints`` the actuated
    joints as ``{"name", "type", "lower", "upper"}`` (continuous joints get ``[-pi, pi]``);
    ``mimics`` maps a mimicking joint to ``(source joint, multiplier, offset)``; ``meshes`` maps each
    mesh ``filename`` attribute to the file it resolves to.
    """

    path: Path
    name: str
    links: list[str]
    joints: list[dict[str, Any]]
    mimics: dict[str, tuple[str, float, float]]
    meshes: dict[str, Path]


def read_urdf(path: str | os.PathLike) -> UrdfInfo:
    """Parse a URDF with :class:`~narf_core.kinematics.KinematicTree` and resolve its mesh files.

    Raises :class:`UrdfError` for anything the tree refuses, a mesh that does not resolve to a
    file, or more links than labels can hold.
    """
    path = Path(path)
    tree = KinematicTree.from_urdf(path, load_meshes=False)
    if len(tree.links) > MAX_LINKS:
        raise UrdfError(f"{path}: {len(tree.links)} links, labels hold at most {MAX_LINKS}")
    joints = [{"name": j.name, "type": j.type, "lower": j.lower, "upper": j.upper} for j in tree.movable]
    mimics = {j.name: j.mimic for j in tree.mimics}
    return UrdfInfo(path, tree.name or path.stem, tree.links_in_file, joints, mimics, tree.mesh_files())


def mesh_assets(mesh: Path) -> list[Path]:
    """A mesh file and the files it pulls in: an OBJ's ``mtllib`` and the textures those name."""
    files = [mesh]
    if mesh.suffix.lower() != ".obj":
        return files
    for mtl_name in _directives(mesh, ("mtllib",)):
        mtl = mesh.parent / mtl_name
        if not mtl.is_file():
            raise UrdfError(f"{mesh}: material library '{mtl_name}' not found")
        files.append(mtl)
        for texture_name in _directives(mtl, _MTL_MAPS):
            texture = mtl.parent / texture_name
            if not texture.is_file():
                raise UrdfError(f"{mtl}: texture '{texture_name}' not found")
            files.append(texture)
    return files


def copy_urdf(info: UrdfInfo, root: Path) -> Path:
    """Copy a URDF into ``root/object.urdf`` with every mesh asset under ``root/meshes/``.

    Assets keep their layout relative to their common folder, so the relative references inside
    OBJ and MTL files stay valid; the URDF's mesh filenames are rewritten to the copies.
    """
    sources = {mesh: mesh_assets(mesh) for mesh in set(info.meshes.values())}
    every = sorted({f.resolve() for files in sources.values() for f in files})
    common = Path(os.path.commonpath([f.parent for f in every])) if every else None
    renamed: dict[Path, str] = {}
    for f in every:
        rel = PurePosixPath(MESH_DIR, *f.relative_to(common).parts)  # type: ignore[arg-type]
        dest = root / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, dest)
        renamed[f] = str(rel)
    tree = ET.parse(info.path)
    for mesh in (m for link in tree.getroot().findall("link") for m in link.iter("mesh")):
        mesh.set("filename", renamed[info.meshes[mesh.get("filename", "")].resolve()])
    out = root / URDF_FILE
    tree.write(out, encoding="utf-8", xml_declaration=True)
    return out


def _directives(path: Path, keys: tuple[str, ...]) -> list[str]:
    """The arguments of lines starting with one of ``keys`` in an OBJ/MTL file (options skipped)."""
    found = []
    for line in path.read_text(errors="replace").splitlines():
        parts = line.split()
        if parts and parts[0].lower() in keys:
            args = [a for a in parts[1:] if not a.startswith("-") and not re.fullmatch(r"[-+0-9.eE]+", a)]
            if args:
                found.append(args[-1])
    return found


# --------------------------------------------------------------------------------------------
# images


def write_png_rgb(path: Path, rgb: np.ndarray) -> None:
    """``rgb`` uint8 ``[H, W, 3]`` as an 8-bit RGB PNG."""
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), mode="RGB").save(path)


def write_png_labels(path: Path, labels: np.ndarray) -> None:
    """``labels`` uint8 ``[H, W]`` as an 8-bit grey PNG."""
    Image.fromarray(np.ascontiguousarray(labels, dtype=np.uint8), mode="L").save(path)


def write_png_depth(path: Path, depth: np.ndarray) -> None:
    """Metric depth float ``[H, W]`` as a uint16 millimetre PNG (:func:`narf_core.depth.depth_to_mm`:
    ROS 16UC1, 0 = no return, saturating beyond 65.535 m)."""
    Image.fromarray(depth_to_mm(depth)).save(path)


def read_depth(path: Path) -> np.ndarray:
    """A depth image as float32 metres ``[H, W]``: 16-bit PNG in millimetres or ``.npy`` metres."""
    if path.suffix.lower() == ".npy":
        depth = np.load(path, allow_pickle=False)
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
            raise DatasetError(f"{path}: expected a 2-D float array of metres, got {_describe(depth)}")
        depth = depth.astype(np.float32)
        if not np.isfinite(depth).all() or (depth < 0).any():
            raise DatasetError(f"{path}: depth must be finite and >= 0")
        return depth
    with _open_image(path) as im:
        if im.mode not in ("I;16", "I;16B", "I"):
            raise DatasetError(f"{path}: depth PNG must be 16-bit millimetres, got mode {im.mode}")
        mm = np.asarray(im).astype(np.int64)
    if mm.min(initial=0) < 0 or mm.max(initial=0) > DEPTH_MM_MAX:
        raise DatasetError(f"{path}: depth values outside the uint16 range")
    return mm_to_depth(mm)


def _open_image(path: Path) -> Image.Image:
    try:
        im = Image.open(path)
        im.load()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: not a readable image ({e})") from None
    return im


# --------------------------------------------------------------------------------------------
# reading


class Dataset:
    """A dataset opened from disk; ``scene.json`` is fully validated by :meth:`open`.

    Attributes: ``root``, ``urdf_path``, ``camera`` (:class:`~narf_core.geometry.Pinhole`, float32
    ``K``), ``links`` (label order), ``joints`` (``{"name", "type", "lower", "upper"}``),
    ``generator`` (provenance, ``{}`` if none), ``clean`` (whether these are the clean frames).
    """

    def __init__(
        self,
        root: Path,
        camera: Pinhole,
        links: list[str],
        joints: list[dict[str, Any]],
        frames: list[Frame],
        generator: dict[str, Any],
        clean: bool,
    ) -> None:
        self.root = root
        self.urdf_path = root / URDF_FILE
        self.camera = camera
        self.links = links
        self.joints = joints
        self.generator = generator
        self.clean = clean
        self._frames = frames

    @classmethod
    def open(cls, root: str | os.PathLike, *, clean: bool = False) -> Dataset:
        """Open and validate the dataset at ``root``.

        With ``clean=True`` the frames are the generator's noise-free ground truth
        (``generator.clean_frames``) where the dataset has label noise, the written frames otherwise.
        """
        root = Path(root)
        scene_path = root / SCENE_FILE
        if not root.is_dir():
            raise DatasetError(f"{root}: not a dataset folder (no such directory)")
        if not scene_path.is_file():
            raise DatasetError(f"{scene_path}: file not found")
        try:
            scene = json.loads(scene_path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DatasetError(f"{scene_path}: not valid JSON ({e})") from None
        v = _Validator(scene_path)
        v.require(isinstance(scene, dict), "", "must be a JSON object")
        camera = v.camera(scene.get("camera"))
        links = v.links(scene.get("links"))
        joints = v.joints(scene.get("joints"))
        _check_against_urdf(root / URDF_FILE, links, joints)
        generator = scene.get("generator", {})
        v.require(isinstance(generator, dict), "generator", "must be an object")
        frames = v.frames(root, scene.get("frames"), "frames", joints)
        if clean and "clean_frames" in generator:
            frames = v.frames(root, generator["clean_frames"], "generator.clean_frames", joints)
        return cls(root, camera, links, joints, frames, generator, clean)

    @property
    def noisy(self) -> bool:
        """Whether the written labels carry generator noise (then ``clean=True`` differs)."""
        return "clean_frames" in self.generator

    def __len__(self) -> int:
        return len(self._frames)

    def frames(self, split: str | None = None) -> list[Frame]:
        """All frames, or those of one split (``train``, ``test`` or ``novel``), in id order."""
        if split is None:
            return list(self._frames)
        if split not in SPLITS:
            raise ValueError(f"unknown split '{split}'; expected one of {', '.join(SPLITS)}")
        return [f for f in self._frames if f.split == split]

    def load(self, frame: Frame) -> FrameImages:
        """Read a frame's images, checking their modes, sizes (against the camera) and label range."""
        size = (self.camera.width, self.camera.height)
        rgb_path = self.root / frame.rgb
        with _open_image(rgb_path) as im:
            if im.mode not in ("RGB", "RGBA"):
                raise DatasetError(f"{rgb_path}: expected an 8-bit RGB image, got mode {im.mode}")
            _check_size(rgb_path, im.size, size)
            rgb = np.asarray(im.convert("RGB"))
        labels_path = self.root / frame.labels
        with _open_image(labels_path) as im:
            if im.mode not in ("L", "P"):
                raise DatasetError(f"{labels_path}: expected an 8-bit label image, got mode {im.mode}")
            _check_size(labels_path, im.size, size)
            labels = np.asarray(im, dtype=np.uint8)
        if labels.max(initial=0) > len(self.links):
            raise DatasetError(
                f"{labels_path}: label {labels.max()} but scene.json lists only {len(self.links)} links"
            )
        depth = None
        if frame.depth is not None:
            depth_path = self.root / frame.depth
            if not depth_path.is_file():
                raise DatasetError(f"{depth_path}: file not found")
            depth = read_depth(depth_path)
            _check_size(depth_path, depth.shape[::-1], size)
        return FrameImages(rgb, depth, labels)


def _check_size(path: Path, got: tuple[int, int], expected: tuple[int, int]) -> None:
    if tuple(got) != tuple(expected):
        raise DatasetError(
            f"{path}: image is {got[0]}x{got[1]} but the camera in scene.json is {expected[0]}x{expected[1]}"
        )


def _check_against_urdf(urdf_path: Path, links: list[str], joints: list[dict[str, Any]]) -> None:
    """scene.json's links and joints must be the URDF's."""
    if not urdf_path.is_file():
        raise DatasetError(f"{urdf_path}: file not found")
    try:
        info = read_urdf(urdf_path)
    except UrdfError as e:
        raise DatasetError(str(e)) from None
    missing = [name for name in links if name not in info.links]
    if missing:
        raise DatasetError(f"{urdf_path.parent / SCENE_FILE}: links {missing} are not in {urdf_path.name}")
    by_name = {j["name"]: j for j in info.joints}
    for i, joint in enumerate(joints):
        ref = by_name.get(joint["name"])
        where = f"{urdf_path.parent / SCENE_FILE}: joints[{i}]"
        if ref is None:
            raise DatasetError(f"{where}: '{joint['name']}' is not an actuated joint of {urdf_path.name}")
        if ref["type"] != joint["type"] or not (
            math.isclose(ref["lower"], joint["lower"], abs_tol=1e-9)
            and math.isclose(ref["upper"], joint["upper"], abs_tol=1e-9)
        ):
            raise DatasetError(f"{where}: '{joint['name']}' does not match {urdf_path.name} ({ref})")


class _Validator:
    """Checks of scene.json fields; each failure names the file and the JSON path."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def require(self, ok: bool, field: str, message: str) -> None:
        if not ok:
            raise DatasetError(f"{self.path}: {field + ': ' if field else ''}{message}")

    def number(self, value: Any, field: str) -> float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        self.require(ok, field, f"expected a finite number, got {value!r}")
        return float(value)

    def integer(self, value: Any, field: str, minimum: int) -> int:
        ok = isinstance(value, int) and not isinstance(value, bool) and value >= minimum
        self.require(ok, field, f"expected an integer >= {minimum}, got {value!r}")
        return value

    def choice(self, value: Any, field: str, choices: tuple[str, ...]) -> str:
        self.require(value in choices, field, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def matrix(self, value: Any, field: str, rows: int, cols: int) -> np.ndarray:
        ok = isinstance(value, list) and len(value) == rows
        ok = ok and all(isinstance(row, list) and len(row) == cols for row in value)
        self.require(ok, field, f"expected a {rows}x{cols} array of numbers")
        return np.array(
            [[self.number(x, f"{field}[{i}][{j}]") for j, x in enumerate(row)] for i, row in enumerate(value)]
        )

    def camera(self, value: Any) -> Pinhole:
        self.require(isinstance(value, dict), "camera", "missing or not an object")
        K = self.matrix(value.get("K"), "camera.K", 3, 3)
        self.require(K[0, 0] > 0 and K[1, 1] > 0, "camera.K", "focal lengths K[0][0], K[1][1] must be > 0")
        upper = K[1, 0] == 0 and (K[2] == [0, 0, 1]).all()
        self.require(upper, "camera.K", "must be upper triangular with K[2] = [0, 0, 1]")
        width = self.integer(value.get("width"), "camera.width", 1)
        height = self.integer(value.get("height"), "camera.height", 1)
        return Pinhole(torch.tensor(K, dtype=torch.float32), width, height)

    def links(self, value: Any) -> list[str]:
        ok = isinstance(value, list) and value and all(isinstance(x, str) and x for x in value)
        self.require(bool(ok), "links", "expected a non-empty list of link names")
        self.require(len(set(value)) == len(value), "links", "link names must be unique")
        self.require(len(value) <= MAX_LINKS, "links", f"{len(value)} links; labels hold at most {MAX_LINKS}")
        return list(value)

    def joints(self, value: Any) -> list[dict[str, Any]]:
        self.require(isinstance(value, list), "joints", "expected a list (empty for a rigid object)")
        joints = []
        for i, j in enumerate(value):
            field = f"joints[{i}]"
            self.require(isinstance(j, dict), field, "expected an object")
            name = j.get("name")
            self.require(isinstance(name, str) and bool(name), f"{field}.name", "expected a joint name")
            kind = self.choice(j.get("type"), f"{field}.type", JOINT_TYPES)
            lower = self.number(j.get("lower"), f"{field}.lower")
            upper = self.number(j.get("upper"), f"{field}.upper")
            self.require(lower < upper, field, f"lower {lower} must be < upper {upper}")
            joints.append({"name": name, "type": kind, "lower": lower, "upper": upper})
        names = [j["name"] for j in joints]
        self.require(len(set(names)) == len(names), "joints", "joint names must be unique")
        return joints

    def frames(self, root: Path, value: Any, field: str, joints: list[dict[str, Any]]) -> list[Frame]:
        self.require(isinstance(value, list), field, "expected a list of frames")
        frames, ids = [], set()
        for i, f in enumerate(value):
            here = f"{field}[{i}]"
            self.require(isinstance(f, dict), here, "expected an object")
            fid = self.integer(f.get("id"), f"{here}.id", 0)
            self.require(fid not in ids, f"{here}.id", f"duplicate id {fid}")
            ids.add(fid)
            rgb = self.image_path(root, f.get("rgb"), f"{here}.rgb")
            labels = self.image_path(root, f.get("labels"), f"{here}.labels")
            depth = None if f.get("depth") is None else self.image_path(root, f["depth"], f"{here}.depth")
            T = self.pose(f.get("T_cam_obj"), f"{here}.T_cam_obj")
            config = self.configuration(f.get("joints"), f"{here}.joints", joints)
            split = self.choice(f.get("split"), f"{here}.split", SPLITS)
            stamp = None if f.get("time") is None else self.number(f["time"], f"{here}.time")
            frames.append(Frame(fid, rgb, depth, labels, T, config, split, stamp))
        return sorted(frames, key=lambda fr: fr.id)

    def image_path(self, root: Path, value: Any, field: str) -> str:
        self.require(isinstance(value, str) and bool(value), field, "expected a relative file path")
        rel = PurePosixPath(value)
        inside = not rel.is_absolute() and ".." not in rel.parts
        self.require(inside, field, f"'{value}' must be relative to the dataset, inside it")
        self.require((root / rel).is_file(), field, f"file '{value}' not found")
        return value

    def pose(self, value: Any, field: str) -> np.ndarray:
        try:
            return check_pose(self.matrix(value, field, 4, 4), field)
        except InputError as e:
            raise DatasetError(f"{self.path}: {e}") from None

    def configuration(self, value: Any, field: str, joints: list[dict[str, Any]]) -> dict[str, float]:
        self.require(isinstance(value, dict), field, "expected an object {joint name: value}")
        try:
            return check_joints([JointSpec(**j) for j in joints], value, field, complete=True)
        except InputError as e:
            raise DatasetError(f"{self.path}: {e}") from None


# --------------------------------------------------------------------------------------------
# writing


_OWN_ENTRIES = {SCENE_FILE, SCENE_FILE + ".tmp", URDF_FILE, MESH_DIR, "rgb", "depth", "labels", "clean"}


def _describe(array: np.ndarray) -> str:
    return f"{array.dtype} {list(array.shape)}"


def _prepare_folder(root: Path, overwrite: bool) -> None:
    """Create ``root``, or empty it when ``overwrite`` and it holds nothing but a dataset's entries."""
    if root.exists() and not root.is_dir():
        raise NotADirectoryError(f"{root}: exists and is not a folder")
    entries = sorted(p.name for p in root.iterdir()) if root.exists() else []
    if entries:
        foreign = [name for name in entries if name not in _OWN_ENTRIES]
        if not overwrite:
            raise FileExistsError(f"{root}: folder is not empty; choose a new folder or pass overwrite")
        if foreign:
            raise FileExistsError(f"{root}: will not overwrite a folder holding {foreign[:3]}")
        for name in entries:
            path = root / name
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()
    root.mkdir(parents=True, exist_ok=True)
    probe = root / ".write-test"
    probe.touch()
    probe.unlink()


class DatasetWriter:
    """Writes a dataset folder frame by frame; :meth:`close` writes ``scene.json`` last.

    Use as a context manager; ``scene.json`` is only written when the block exits cleanly, so an
    interrupted run never leaves a dataset that :meth:`Dataset.open` accepts.

    Args:
        root: the dataset folder; created if missing. An existing folder must be empty, or hold
            only a dataset's entries and ``overwrite`` be set (then it is emptied first).
        urdf: the object's URDF (:func:`read_urdf`); copied with its meshes.
        camera: the camera of every frame.
        generator: provenance stored as scene.json's ``generator`` block.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        urdf: UrdfInfo,
        camera: Pinhole,
        generator: dict[str, Any] | None = None,
        *,
        overwrite: bool = False,
    ) -> None:
        self.root = Path(root)
        _prepare_folder(self.root, overwrite)
        copy_urdf(urdf, self.root)
        self.urdf = urdf
        self.camera = camera
        self.generator = dict(generator or {})
        self.frames: list[Frame] = []
        self.clean_frames: list[Frame] = []
        self._any_clean = False

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    def add(
        self,
        split: str,
        images: FrameImages,
        T_cam_obj: np.ndarray,
        joints: dict[str, float],
        *,
        clean: tuple[FrameImages, np.ndarray, dict[str, float]] | None = None,
        time: float | None = None,
    ) -> Frame:
        """Write one frame's images and record it; returns the :class:`Frame`.

        ``time`` (seconds) stamps the frames of a sequence.

        ``clean`` is the noise-free ``(images, T_cam_obj, joints)`` when the written labels carry
        generator noise; its ``depth`` and ``labels`` go under ``clean/`` (``rgb`` is shared).
        """
        if split not in SPLITS:
            raise ValueError(f"unknown split '{split}'; expected one of {', '.join(SPLITS)}")
        self._check_images(images)
        fid = len(self.frames)
        frame = self._write(fid, split, images, T_cam_obj, joints, prefix="")
        frame.time = time
        self.frames.append(frame)
        if clean is None:
            self.clean_frames.append(frame)
        else:
            self._check_images(clean[0])
            self._any_clean = True
            clean_images, clean_T, clean_joints = clean
            self.clean_frames.append(
                self._write(fid, split, clean_images, clean_T, clean_joints, prefix="clean/", rgb=frame.rgb)
            )
        return frame

    def close(self) -> Path:
        """Write ``scene.json`` (atomically) and return its path."""
        generator = dict(self.generator)
        if self._any_clean:
            generator["clean_frames"] = [f.to_json() for f in self.clean_frames]
        scene = {
            "camera": {
                "K": self.camera.K.double().tolist(),
                "width": self.camera.width,
                "height": self.camera.height,
            },
            "links": self.urdf.links,
            "joints": self.urdf.joints,
            "frames": [f.to_json() for f in self.frames],
            "generator": generator,
        }
        path = self.root / SCENE_FILE
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(scene, indent=1))
        tmp.replace(path)
        return path

    def _check_images(self, images: FrameImages) -> None:
        h, w = self.camera.height, self.camera.width
        if images.rgb.shape != (h, w, 3) or images.rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8 [{h}, {w}, 3], got {_describe(images.rgb)}")
        if images.labels.shape != (h, w) or images.labels.dtype != np.uint8:
            raise ValueError(f"labels must be uint8 [{h}, {w}], got {_describe(images.labels)}")
        if images.labels.max(initial=0) > len(self.urdf.links):
            raise ValueError(f"label {images.labels.max()} but the object has {len(self.urdf.links)} links")
        if images.depth is not None and images.depth.shape != (h, w):
            raise ValueError(f"depth must be [{h}, {w}], got {list(images.depth.shape)}")
        if images.depth is not None and (not np.isfinite(images.depth).all() or (images.depth < 0).any()):
            raise ValueError("depth must be finite and >= 0 metres (0 = no return)")

    def _write(
        self,
        fid: int,
        split: str,
        images: FrameImages,
        T_cam_obj: np.ndarray,
        joints: dict[str, float],
        prefix: str,
        rgb: str | None = None,
    ) -> Frame:
        name = f"{fid:06d}.png"
        if rgb is None:
            rgb = f"{prefix}rgb/{name}"
            (self.root / rgb).parent.mkdir(parents=True, exist_ok=True)
            write_png_rgb(self.root / rgb, images.rgb)
        labels = f"{prefix}labels/{name}"
        (self.root / labels).parent.mkdir(parents=True, exist_ok=True)
        write_png_labels(self.root / labels, images.labels)
        depth = None
        if images.depth is not None:
            depth = f"{prefix}depth/{name}"
            (self.root / depth).parent.mkdir(parents=True, exist_ok=True)
            write_png_depth(self.root / depth, images.depth)
        return Frame(fid, rgb, depth, labels, np.asarray(T_cam_obj, dtype=np.float64), dict(joints), split)
