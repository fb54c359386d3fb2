"""A second renderer for test data: the frames of a dataset re-rendered with Mitsuba 3's path tracer.

The same object, poses and configurations as the source dataset (pybullet's TinyRenderer drew it),
now under randomised lights (a coloured environment plus area, point or sun lights with colour
temperature and intensity), glossy materials, a textured ground plane, clutter around the tool and
the shadows they cast. The depth image holds everything the camera sees (table and clutter too, as
a real sensor's would); the labels mark the tool's *visible* pixels per link. The faults a real
camera, depth sensor and segmenter add come after, from :mod:`narf_core.data.synth.faults`, one
dataset per named condition.

Cameras: docs/design.md §2's OpenCV camera becomes Mitsuba's ``perspective`` sensor, whose local frame has
x left and y up: ``to_world = T_obj_cam @ diag(-1, -1, 1, 1)``, the field of view along x from
``fx`` and the principal point as an offset of ``-(c - size / 2) / size`` (Mitsuba's sign is the
opposite of K's). Depth and labels come from a second pass with Mitsuba's ``aov`` integrator at
exactly the pixel centres (a stratified sampler without jitter, box filter): the hit position,
moved into the camera frame, gives z-depth along the optical axis (not the ray length), and the
shape index gives the link. Only square pixels (``fx == fy``) and zero skew are supported.

Layout written by :func:`restyle`::

    OUT/renders/<id>.npz       the path-traced frame: linear RGB, z-depth, visible labels (a cache)
    OUT/<condition>/           one dataset per condition (docs/design.md §3); clean/ holds the fault-free
                               depth and labels; scene.json's generator records the condition,
                               its fault options and, per frame, the drawn scene and fault values

Never imported by the service; needs the ``realism`` extra (``mitsuba``).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from narf_core.data.dataset import Dataset, DatasetWriter, FrameImages, read_urdf
from narf_core.data.synth import faults
from narf_core.data.synth.bar import occlude_linear
from narf_core.geometry import Pinhole
from narf_core.kinematics import KinematicTree

VARIANT = "scalar_rgb"
_CV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV camera axes -> Mitsuba's (x left, y up)
_PLANE_GAP = 1e-3  # metres between the object's lowest point and the ground plane
_PLANE_HALF = 2.0  # metres


class RestyleError(ValueError):
    """Bad input to the restyler (missing extra, unsupported camera, unknown frames)."""


def mitsuba():
    """The ``mitsuba`` module with the CPU variant set, or a :class:`RestyleError` naming the extra."""
    try:
        import mitsuba as mi
    except ImportError:
        raise RestyleError(
            "the mitsuba renderer is not installed; install the extra: pip install 'narf[realism]'"
        ) from None
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


@dataclass
class Render:
    """A path-traced frame: ``linear`` RGB float32 ``[H, W, 3]``, ``depth`` z-depth float32 metres
    ``[H, W]`` (0 = nothing hit), ``labels`` uint8 ``[H, W]`` (the tool's visible pixels, 1 + link)
    and ``scene`` (the drawn lights, materials and clutter, JSON-able)."""

    linear: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    scene: dict


# ------------------------------------------------------------------------------------------------
# camera


def check_camera(camera: Pinhole) -> np.ndarray:
    """``camera``'s K as float64, or :class:`RestyleError` if Mitsuba cannot reproduce it (it has
    square pixels and no skew)."""
    K = camera.K.detach().double().cpu().numpy()
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-9:
        raise RestyleError(f"the Mitsuba camera needs square pixels (fx = fy) and no skew, got K = {K.tolist()}")
    return K


def sensor(camera: Pinhole, T_cam_obj: np.ndarray, *, spp: int, centres: bool) -> dict:
    """Mitsuba's perspective sensor for an OpenCV ``camera`` at ``T_cam_obj [4, 4]`` (object frame =
    Mitsuba's world). ``centres``: one sample at each pixel centre (for depth and labels)."""
    mi = mitsuba()
    K = check_camera(camera)
    w, h = camera.width, camera.height
    T_obj_cam = np.linalg.inv(np.asarray(T_cam_obj, dtype=np.float64))
    sampler = {"type": "stratified", "sample_count": 1, "jitter": False} if centres else {
        "type": "independent", "sample_count": int(spp)}
    return {
        "type": "perspective",
        "fov": float(np.degrees(2 * np.arctan(w / (2 * K[0, 0])))),
        "fov_axis": "x",
        "principal_point_offset_x": float(-(K[0, 2] - w / 2) / w),
        "principal_point_offset_y": float(-(K[1, 2] - h / 2) / h),
        "near_clip": 0.005,
        "far_clip": 100.0,
        "to_world": mi.ScalarTransform4f((T_obj_cam @ _CV_TO_MITSUBA).tolist()),
        "film": {"type": "hdrfilm", "width": w, "height": h, "pixel_format": "rgb",
                 "rfilter": {"type": "box"} if centres else {"type": "gaussian", "stddev": 0.4}},
        "sampler": sampler,
    }


# ------------------------------------------------------------------------------------------------
# the object


def _obj_material(mesh: Path) -> tuple[list[float], Path | None]:
    """The diffuse colour and texture of an OBJ's first material (``Kd``, ``map_Kd``); grey without one."""
    colour, texture = [0.6, 0.6, 0.6], None
    if mesh.suffix.lower() != ".obj":
        return colour, texture
    libs = [line.split(None, 1)[1].strip() for line in mesh.read_text(errors="replace").splitlines()
            if line.startswith("mtllib ")]
    for lib in libs:
        path = mesh.parent / lib
        if not path.is_file():
            continue
        for line in path.read_text(errors="replace").splitlines():
            key, _, value = line.strip().partition(" ")
            if key == "Kd":
                colour = [float(v) for v in value.split()[:3]]
            elif key == "map_Kd" and (mesh.parent / value.strip()).is_file():
                texture = mesh.parent / value.strip()
        break
    return colour, texture


@dataclass
class _Visual:
    link: str
    mesh: Path  # a file Mitsuba reads (obj or ply)
    T_link_visual: np.ndarray  # [4, 4], scale included
    colour: list[float]
    texture: Path | None


def object_visuals(urdf_path: Path, scratch: Path) -> list[_Visual]:
    """Every ``<visual>`` of the URDF as a mesh file with its link and placement; primitives and
    meshes in formats Mitsuba does not read are converted to PLY in ``scratch``."""
    import trimesh
    import yourdfpy

    from narf_core.kinematics import resolve_mesh

    robot = yourdfpy.URDF.load(str(urdf_path), load_meshes=False, build_scene_graph=False).robot
    visuals = []
    for link in robot.links:
        for k, visual in enumerate(link.visuals):
            origin = np.eye(4) if visual.origin is None else np.asarray(visual.origin, dtype=np.float64)
            g = visual.geometry
            colour = [0.6, 0.6, 0.6]
            if visual.material is not None and visual.material.color is not None:
                colour = [float(c) for c in visual.material.color.rgba[:3]]
            texture = None
            if g.mesh is not None:
                path = resolve_mesh(g.mesh.filename, Path(urdf_path).parent, link=link.name, source=str(urdf_path))
                scale = np.ones(3) if g.mesh.scale is None else np.broadcast_to(np.asarray(g.mesh.scale, float), 3)
                origin = origin @ np.diag([*scale, 1.0])
                if path.suffix.lower() == ".obj":
                    colour, texture = _obj_material(path)
                elif path.suffix.lower() != ".ply":
                    out = scratch / f"{link.name}_{k}.ply"
                    trimesh.load(path, force="mesh").export(out)
                    path = out
            else:
                if g.box is not None:
                    mesh = trimesh.creation.box(extents=g.box.size)
                elif g.cylinder is not None:
                    mesh = trimesh.creation.cylinder(radius=g.cylinder.radius, height=g.cylinder.length)
                elif g.sphere is not None:
                    mesh = trimesh.creation.icosphere(radius=g.sphere.radius)
                else:
                    continue
                path = scratch / f"{link.name}_{k}.ply"
                mesh.export(path)
            visuals.append(_Visual(link.name, path, origin, colour, texture))
    return visuals


def _lowest_point(tree: KinematicTree, link_poses: dict[str, np.ndarray]) -> float:
    """The object's lowest z (object frame) in the configuration whose link poses are given."""
    low = np.inf
    for name, mesh in tree.visual_meshes().items():
        v = np.asarray(mesh.vertices) @ link_poses[name][:3, :3].T + link_poses[name][:3, 3]
        low = min(low, float(v[:, 2].min()))
    return 0.0 if not np.isfinite(low) else low


# ------------------------------------------------------------------------------------------------
# the scene around it: lights, ground, clutter


def colour_temperature(kelvin: float) -> list[float]:
    """Linear RGB of a black body at ``kelvin`` (1000-40000 K), scaled to luminance 1 (Tanner
    Helland's fit of the CIE data, then sRGB-decoded)."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = 99.4708025861 * np.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * np.log(t - 10) - 305.0447927307)
    srgb = np.clip(np.array([r, g, b]) / 255.0, 0, 1)
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return (linear / max(float(linear @ [0.2126, 0.7152, 0.0722]), 1e-6)).tolist()


def ground_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A tileable procedural surface, uint8 ``[size, size, 3]``: wood grain, speckled laminate or
    woven cloth, in a random hue."""
    y, x = np.mgrid[0:size, 0:size] / size
    kind = rng.integers(3)
    low = np.zeros((size, size))
    for k in (2, 4, 8):
        a, b = rng.integers(1, k + 1, 2)
        low += np.sin(2 * np.pi * (a * x + b * y) + rng.uniform(0, 2 * np.pi)) / k
    if kind == 0:
        pattern = 0.5 + 0.5 * np.sin(2 * np.pi * (10 * y + 0.6 * low))
    elif kind == 1:
        pattern = 0.5 + 0.25 * low + 0.25 * rng.random((size, size))
    else:
        pattern = 0.5 + 0.25 * np.sign(np.sin(2 * np.pi * 24 * x)) * np.sign(np.sin(2 * np.pi * 24 * y)) + 0.15 * low
    base = rng.uniform(0.15, 0.85, 3)
    shade = 0.6 + 0.4 * np.clip(pattern, 0, 1)
    return np.clip(255 * shade[..., None] * base, 0, 255).astype(np.uint8)


def _hides(eye: np.ndarray, centre: np.ndarray, radius: float, blocker: np.ndarray, size: float) -> bool:
    """Whether a ball (``blocker``, ``size``) can hide part of the ball (``centre``, ``radius``) from ``eye``."""
    to_tool, to_blocker = centre - eye, blocker - eye
    d_tool, d_blocker = float(np.linalg.norm(to_tool)), float(np.linalg.norm(to_blocker))
    if d_blocker <= size or d_tool <= radius:
        return True
    if d_blocker - size > d_tool + radius:
        return False
    angle = np.arccos(np.clip(to_tool @ to_blocker / (d_tool * d_blocker), -1, 1))
    return bool(angle < np.arcsin(min(radius / d_tool, 1)) + np.arcsin(min(size / d_blocker, 1)))


def _look_at(mi, origin: np.ndarray, target: np.ndarray) -> Any:
    up = [0, 0, 1] if abs((target - origin)[2]) < 0.99 * np.linalg.norm(target - origin) else [0, 1, 0]
    return mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=target.tolist(), up=up)


def scene_dict(
    visuals: list[_Visual],
    link_poses: dict[str, np.ndarray],
    floor_z: float,
    centre: np.ndarray,
    radius: float,
    rng: np.random.Generator,
    scratch: Path,
    eye: np.ndarray | None = None,
) -> tuple[dict, dict]:
    """Mitsuba's scene (without sensor and integrator) and a JSON record of what was drawn.

    Tool shapes are named ``tool:<index>`` (index into ``visuals``); lights and clutter are drawn
    from ``rng``: a coloured constant environment, 1-2 of area/point/sun lights of 2700-7500 K,
    glossy plastic on the tool (roughness 0.05-0.4), a textured ground plane and 2-6 boxes,
    cylinders and spheres on it, 1-3.5 object radii from the tool's centre, none of them between
    the tool and the camera at ``eye`` (object frame; ``[3]``, or ``[n, 3]`` for every camera of a
    sequence): occlusion is the faults' business.
    """
    eyes = None if eye is None else np.atleast_2d(np.asarray(eye, dtype=np.float64))
    mi = mitsuba()
    T = mi.ScalarTransform4f
    scene: dict[str, Any] = {"type": "scene"}
    record: dict[str, Any] = {"lights": [], "clutter": []}
    roughness = float(rng.uniform(0.05, 0.4))
    record["tool_roughness"] = roughness
    for i, v in enumerate(visuals):
        reflectance = (
            {"type": "bitmap", "filename": str(v.texture)} if v.texture else {"type": "rgb", "value": v.colour}
        )
        scene[f"tool:{i}"] = {
            "type": "obj" if v.mesh.suffix.lower() == ".obj" else "ply",
            "filename": str(v.mesh),
            "to_world": T((link_poses[v.link] @ v.T_link_visual).tolist()),
            "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": roughness,
                     "diffuse_reflectance": reflectance},
        }
    texture = scratch / "ground.png"
    Image.fromarray(ground_texture(rng)).save(texture)
    tiles = float(rng.uniform(4, 12))
    scene["ground"] = {
        "type": "rectangle",
        "to_world": T().translate([float(centre[0]), float(centre[1]), floor_z]).scale(_PLANE_HALF),
        "bsdf": {"type": "roughplastic", "alpha": float(rng.uniform(0.2, 0.6)),
                 "diffuse_reflectance": {"type": "bitmap", "filename": str(texture),
                                         "to_uv": T().scale([tiles, tiles, 1])}},
    }
    for i in range(int(rng.integers(2, 7))):
        kind = ["cube", "cylinder", "sphere"][rng.integers(3)]
        for _ in range(20):  # redraw a place that hides the tool
            size = float(rng.uniform(0.3, 1.2) * radius)
            distance = float(rng.uniform(1.0, 3.5) * radius)
            angle = float(rng.uniform(0, 2 * np.pi))
            x, y = centre[0] + distance * np.cos(angle), centre[1] + distance * np.sin(angle)
            blocker = np.array([x, y, floor_z + size])
            if eyes is None or not any(_hides(e, centre, radius, blocker, 1.5 * size) for e in eyes):
                break
        else:
            continue
        colour = rng.uniform(0.05, 0.9, 3).tolist()
        if kind == "cube":
            height = size * float(rng.uniform(0.3, 1.5))
            to_world = T().translate([x, y, floor_z + height / 2]).rotate([0, 0, 1], float(rng.uniform(0, 360))).scale(
                [size / 2, size * float(rng.uniform(0.3, 1.0)) / 2, height / 2])
        elif kind == "cylinder":
            height = size * float(rng.uniform(0.5, 2.0))
            to_world = T().translate([x, y, floor_z]).scale([size / 2, size / 2, height])
        else:
            to_world = T().translate([x, y, floor_z + size / 2]).scale(size / 2)
        scene[f"clutter:{i}"] = {"type": kind, "to_world": to_world,
                                 "bsdf": {"type": "roughplastic", "alpha": float(rng.uniform(0.05, 0.5)),
                                          "diffuse_reflectance": {"type": "rgb", "value": colour}}}
        record["clutter"].append({"kind": kind, "size_m": size, "distance_m": distance, "colour": colour})
    kelvin = float(rng.uniform(4000, 12000))
    ambient = float(rng.uniform(0.05, 0.4))
    sky = (np.array(colour_temperature(kelvin)) * ambient).tolist()
    scene["environment"] = {"type": "constant", "radiance": {"type": "rgb", "value": sky}}
    record["lights"].append({"kind": "environment", "kelvin": kelvin, "radiance": ambient})
    for i in range(int(rng.integers(1, 3))):
        kind = ["area", "point", "sun"][rng.integers(3)]
        kelvin = float(rng.uniform(2700, 7500))
        elevation, azimuth = np.radians(rng.uniform(25, 80)), rng.uniform(0, 2 * np.pi)
        direction = np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        distance = float(rng.uniform(0.6, 1.5))
        position = centre + distance * direction
        colour = np.array(colour_temperature(kelvin))
        if kind == "area":
            size = float(rng.uniform(0.1, 0.5))
            power = float(rng.uniform(1.0, 4.0)) * distance**2 / size**2
            radiance = {"type": "rgb", "value": (colour * power).tolist()}
            to_world = _look_at(mi, position, centre) @ T().scale(size / 2)
            scene[f"light:{i}"] = {"type": "rectangle", "to_world": to_world,
                                   "emitter": {"type": "area", "radiance": radiance}}
        elif kind == "point":
            power = float(rng.uniform(1.0, 4.0)) * distance**2
            scene[f"light:{i}"] = {"type": "point", "position": position.tolist(),
                                   "intensity": {"type": "rgb", "value": (colour * power).tolist()}}
        else:
            power = float(rng.uniform(1.0, 4.0))
            scene[f"light:{i}"] = {"type": "directional", "direction": (-direction).tolist(),
                                   "irradiance": {"type": "rgb", "value": (colour * power).tolist()}}
        record["lights"].append({"kind": kind, "kelvin": kelvin, "power": power, "distance_m": distance,
                                 "elevation_deg": float(np.degrees(elevation)),
                                 "azimuth_deg": float(np.degrees(azimuth))})
    return scene, record


# ------------------------------------------------------------------------------------------------
# rendering a frame


@dataclass
class Shared:
    """One scene for every frame of a sequence: drawn from ``seed``, the ground at ``floor`` (object
    frame, under the object in every frame's configuration), no clutter between the tool and any camera
    position in ``eyes [n, 3]`` (object frame)."""

    seed: tuple[int, ...]
    floor: float
    eyes: np.ndarray


class Restyler:
    """Renders frames of one object with Mitsuba; see the module docstring for the conventions.

    Args:
        urdf_path: the object (a dataset's ``object.urdf``).
        links: the label order (a dataset's ``links``).
        spp: path-tracing samples per pixel of the RGB pass.
    """

    def __init__(self, urdf_path: Path, links: list[str], spp: int = 32) -> None:
        mitsuba()
        if spp < 1:
            raise RestyleError(f"spp must be >= 1, got {spp}")
        self.urdf_path, self.links, self.spp = Path(urdf_path), list(links), int(spp)
        self.tree = KinematicTree.from_urdf(self.urdf_path)
        self._scratch = tempfile.TemporaryDirectory(prefix="narf-restyle-")
        self.visuals = object_visuals(self.urdf_path, Path(self._scratch.name))
        self._label = np.array([1 + self.links.index(v.link) if v.link in self.links else 0 for v in self.visuals],
                               dtype=np.uint8)
        box = self.tree.bounds()
        self.centre = (box[0] + box[1]) / 2
        self.radius = 0.5 * float(np.linalg.norm(box[1] - box[0]))

    def close(self) -> None:
        self._scratch.cleanup()

    def __enter__(self) -> Restyler:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def floor(self, joints: dict[str, float]) -> float:
        """The ground plane's height (object frame): just under the object in configuration ``joints``."""
        poses = self.tree.link_poses(self.tree.joint_vector(joints)).numpy()
        return _lowest_point(self.tree, {name: poses[i] for i, name in enumerate(self.tree.links)}) - _PLANE_GAP

    def render(
        self,
        camera: Pinhole,
        T_cam_obj: np.ndarray,
        joints: dict[str, float],
        seed: tuple[int, ...],
        shared: Shared | None = None,
    ) -> Render:
        """One frame: the RGB pass (path tracing, ``spp`` samples) and the AOV pass (pixel centres).

        Without ``shared`` the scene (lights, materials, ground, clutter) and the path tracer's samples
        are drawn from ``seed``; with it, the scene from ``shared.seed`` on ``shared.floor``, clear of
        every camera in ``shared.eyes`` (one scene for all frames of a sequence), the samples from ``seed``."""
        mi = mitsuba()
        rng = np.random.default_rng(list(seed))
        theta = self.tree.joint_vector(joints)
        poses = self.tree.link_poses(theta).numpy()
        link_poses = {name: poses[i] for i, name in enumerate(self.tree.links)}
        with tempfile.TemporaryDirectory(dir=self._scratch.name) as scratch:
            if shared is None:
                eye = np.linalg.inv(np.asarray(T_cam_obj, dtype=np.float64))[:3, 3]
                shapes, record = scene_dict(self.visuals, link_poses, _lowest_point(self.tree, link_poses) - _PLANE_GAP,
                                            self.centre, self.radius, rng, Path(scratch), eye)
            else:
                shapes, record = scene_dict(self.visuals, link_poses, shared.floor, self.centre, self.radius,
                                            np.random.default_rng(list(shared.seed)), Path(scratch), shared.eyes)
            rgb_scene = mi.load_dict({**shapes, "sensor": sensor(camera, T_cam_obj, spp=self.spp, centres=False),
                                      "integrator": {"type": "path", "max_depth": 6}})
            linear = np.array(mi.render(rgb_scene, seed=int(rng.integers(2**31))), dtype=np.float32)[..., :3]
            aov_scene = mi.load_dict({**shapes, "sensor": sensor(camera, T_cam_obj, spp=1, centres=True),
                                      "integrator": {"type": "aov", "aovs": "pp:position,si:shape_index"}})
            aov = np.array(mi.render(aov_scene), dtype=np.float64)
            ids = [shape.id() for shape in aov_scene.shapes()]
        label_of = {name: int(self._label[int(name.split(":")[1])]) for name in ids if name.startswith("tool:")}
        depth, labels = depth_and_labels(aov, T_cam_obj, ids, label_of)
        return Render(np.ascontiguousarray(np.nan_to_num(linear, nan=0.0, posinf=0.0)), depth, labels, record)


def depth_and_labels(
    aov: np.ndarray, T_cam_obj: np.ndarray, shape_ids: list[str], label_of: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """z-depth float32 ``[H, W]`` (0 = nothing hit) and labels uint8 ``[H, W]`` from the AOV pass.

    ``aov [H, W, 4]`` holds the hit position (object frame) and Mitsuba's shape index (1-based
    into ``shape_ids``, the scene's ``shapes()`` ids; 0 = nothing hit); ``label_of`` maps a shape id
    to its label (shapes not in it are background). The depth is the position's z in the camera
    frame: along the optical axis, not the length of the ray.
    """
    position, index = aov[..., :3].astype(np.float64), np.round(aov[..., 3]).astype(np.int64)
    T = np.asarray(T_cam_obj, dtype=np.float64)
    z = position @ T[2, :3] + T[2, 3]
    depth = np.where(index > 0, z, 0.0).astype(np.float32)
    lut = np.zeros(len(shape_ids) + 1, dtype=np.uint8)
    for k, name in enumerate(shape_ids):
        lut[k + 1] = label_of.get(name, 0)
    return depth, lut[np.clip(index, 0, len(shape_ids))]


# ------------------------------------------------------------------------------------------------
# a dataset, restyled


def _cached_render(restyler: Restyler, cache: Path, key: dict, camera: Pinhole, frame, seed: int,
                   shared: Shared | None) -> Render:
    path = cache / f"{frame.id:06d}.npz"
    stamp = json.dumps(key, sort_keys=True)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) == stamp:
                return Render(z["linear"], z["depth"], z["labels"], json.loads(str(z["scene"])))
    render = restyler.render(camera, frame.T_cam_obj, frame.joints, (seed, frame.id), shared)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, linear=render.linear.astype(np.float16), depth=render.depth, labels=render.labels,
                        scene=json.dumps(render.scene), key=stamp)
    tmp.replace(path)
    render.linear = render.linear.astype(np.float16).astype(np.float32)  # as the cache gives it back next time
    return render


def restyle(
    source: str | Path,
    out: str | Path,
    *,
    conditions: tuple[str, ...] = ("lighting",),
    size: tuple[int, int] | None = None,
    seed: int = 0,
    spp: int = 32,
    splits: tuple[str, ...] | None = None,
    frame_ids: list[int] | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> dict[str, Path]:
    """Re-render frames of the dataset ``source`` with Mitsuba and write ``out/<condition>/`` for each
    condition (:data:`faults.CONDITIONS`); returns ``{condition: dataset folder}``.

    ``size`` ``(W, H)`` scales the camera (default: the source's); ``splits`` and ``frame_ids``
    choose frames (default: all). Deterministic from ``seed``: the scene of a frame depends only on
    ``(seed, frame id)``, its faults on ``(seed, frame id, effect)``. A sequence (every frame with a
    ``time``, as ``narf synth --sequence`` writes) stays one: one scene for all its frames (a camera
    moving through one room), one exposure and white-balance error (one camera's) and one occluder that
    moves round the tool with time (:func:`faults.apply_faults`), the time stamps kept; the path tracer's
    samples and the other faults are drawn per frame. A sequence synthesised with events keeps its own
    occluding bar where pybullet drew it (:func:`sequence_bars`), before the faults. Path-traced frames are cached
    in ``out/renders/`` and reused by later calls with the same size, spp and seed. A condition's
    folder that already holds a dataset is replaced only with ``overwrite``.
    """
    if not conditions:
        raise RestyleError("name at least one condition")
    for name in conditions:
        faults.condition(name)
    if spp < 1:
        raise RestyleError(f"spp must be >= 1, got {spp}")
    dataset = Dataset.open(source)
    camera = dataset.camera if size is None else dataset.camera.scaled(int(size[0]), int(size[1]))
    check_camera(camera)
    every = dataset.frames()  # a sequence's scene is the whole sequence's, whichever frames are drawn now
    frames = every
    if splits is not None:
        frames = [f for f in frames if f.split in splits]
    if frame_ids is not None:
        known = {f.id for f in frames}
        unknown = sorted(set(frame_ids) - known)
        if unknown:
            raise RestyleError(f"frames {unknown[:5]} are not in {dataset.root} (or not in the chosen splits)")
        frames = [f for f in frames if f.id in set(frame_ids)]
    if not frames:
        raise RestyleError(f"no frames to restyle in {dataset.root}")
    out = Path(out)
    targets = {name: out / name for name in conditions}
    for name, root in targets.items():
        if (root / "scene.json").exists() and not overwrite:
            raise FileExistsError(f"{root}: already holds a dataset; pass overwrite to replace it")
    cache = out / "renders"
    cache.mkdir(parents=True, exist_ok=True)
    key = {"source": str(dataset.root.resolve()), "size": [camera.width, camera.height], "spp": spp, "seed": seed,
           "variant": VARIANT}
    is_sequence = all(f.time is not None for f in every)
    if is_sequence:
        key["scene"] = "sequence"
    bars = sequence_bars(dataset)
    urdf = read_urdf(dataset.urdf_path)
    fx = float(camera.K[0, 0])
    generator = {"restyle": {"source": str(dataset.root), "renderer": f"mitsuba {_mitsuba_version()} ({VARIANT})",
                             "spp": spp, "seed": seed, "size": [camera.width, camera.height],
                             "source_frames": [f.id for f in frames], "faults_version": faults.VERSION,
                             "scene_per": "sequence" if is_sequence else "frame"}}
    writers = {}
    for name, root in targets.items():
        source_generator = {k: v for k, v in dataset.generator.items() if k != "clean_frames"}
        g = {**generator, "condition": name, "faults": faults.condition(name).to_json(), "source": source_generator,
             "frames": []}
        writers[name] = DatasetWriter(root, urdf, camera, g, overwrite=overwrite)
    from tqdm import tqdm

    with Restyler(dataset.urdf_path, dataset.links, spp) as restyler:
        shared = None
        if is_sequence:
            eyes = np.stack([np.linalg.inv(np.asarray(f.T_cam_obj, dtype=np.float64))[:3, 3] for f in every])
            shared = Shared((seed,), min(restyler.floor(f.joints) for f in every), eyes)
        for frame in tqdm(frames, desc="restyle", unit="frame", disable=not progress):
            render = _cached_render(restyler, cache, key, camera, frame, seed, shared)
            linear, depth, labels = render.linear, render.depth, render.labels
            if frame.id in bars:
                linear, depth, labels = occlude_linear(linear, depth, labels, *bars[frame.id])
            for name, writer in writers.items():
                f = faults.apply_faults(linear, depth, labels, faults.condition(name),
                                        (seed, frame.id), fx, sequence_seed=(seed,) if is_sequence else None,
                                        time=frame.time or 0.0)
                clean = (FrameImages(f.rgb, f.clean_depth, f.clean_labels), frame.T_cam_obj, frame.joints)
                added = writer.add(frame.split, FrameImages(f.rgb, f.depth, f.labels), frame.T_cam_obj, frame.joints,
                                   clean=clean, time=frame.time)
                writer.generator["frames"].append({"id": added.id, "source_id": frame.id, "scene": render.scene,
                                                   "faults": f.info})
    for writer in writers.values():
        writer.close()
    return targets


def sequence_bars(dataset: Dataset) -> dict[int, tuple[float, float]]:
    """``{frame id: (centre x as a fraction of the width, depth m)}``: the occluding bar that ``narf synth
    --sequence`` drew into the frames of a sequence with events (:mod:`narf_core.data.synth.bar`); empty for any
    other dataset. A sequence with events that does not record its bar (synthesised before it was recorded) is
    refused: its restyled frames would lack the occluder its pybullet frames show."""
    sequence = dataset.generator.get("sequence") or {}
    if not sequence.get("events"):
        return {}
    per_frame, frames = sequence.get("per_frame") or [], dataset.frames()
    if len(per_frame) != len(frames) or any("occluder" not in p for p in per_frame):
        raise RestyleError(f"{dataset.root}: a sequence with events that does not record its occluder (made by an "
                           "older narf); synthesise it again")
    return {f.id: (float(p["occluder"]["x"]), float(p["occluder"]["z"]))
            for f, p in zip(frames, per_frame) if p["occluder"] is not None}


def _mitsuba_version() -> str:
    return str(mitsuba().__version__)
