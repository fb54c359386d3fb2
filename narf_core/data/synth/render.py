"""Ground-truth images of an articulated object from pybullet's CPU renderer (TinyRenderer).

One ``getCameraImage`` call gives RGB, the depth buffer and a per-link segmentation. This module
turns them into the dataset's conventions (docs/design.md §2): an OpenCV camera ``K`` becomes an OpenGL
projection that samples every pixel at its centre, the non-linear depth buffer becomes metric
z-depth (0 = no return), and pybullet's packed segmentation becomes labels ``1 + i`` for link ``i``
of the URDF's link list (0 = background, including the optional table).

The object's URDF root frame is the world frame, so ``T_cam_obj`` is the view transform.
"""

from __future__ import annotations

import logging
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yourdfpy
from PIL import Image

from narf_core.data.dataset import FrameImages, UrdfError, UrdfInfo
from narf_core.checks import JointSpec, check_joints
from narf_core.geometry import Pinhole
from narf_core.kinematics import resolve_mesh

log = logging.getLogger(__name__)


@contextmanager
def _native_output(fd: int, what: str) -> Iterator[list[str]]:
    """Capture what C code (pybullet's printf, b3Warning, b3Error) writes to file descriptor ``fd``
    (1 or 2) so that stdout stays clean for ``--json`` and stderr for one-line errors. The text is
    sent to this module's debug log and appended to the yielded list when the block ends."""
    captured: list[str] = []
    (sys.stdout if fd == 1 else sys.stderr).flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), fd)
        try:
            yield captured
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode(errors="replace").strip()
            if text:
                log.debug("pybullet output while %s:\n%s", what, text)
            captured.append(text)


def _pybullet_messages(text: str) -> str:
    """pybullet's b3Error/b3Warning output as one line."""
    return " ".join(re.sub(r"b3(Error|Warning)\[[^\]]*\]:", " ", text).split())


with _native_output(2, "importing pybullet"):  # it prints its build time
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera (y down, z forward) -> OpenGL (y up, z back)
_TABLE_HALF_SIZE = 1.5  # metres; the table fills the view of every camera the generator samples
_TABLE_TILE = 0.4  # metres of table per texture repeat
_TABLE_GAP = 1e-3  # metres between the object's lowest point and the table (no z-fighting)


def opengl_projection(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """The OpenGL projection ``[4, 4]`` under which TinyRenderer samples pixel ``(u, v)`` at the
    OpenCV pixel centre ``(u + 0.5, v + 0.5)`` of camera ``K [3, 3]`` (skew allowed).

    TinyRenderer samples the viewport at integer coordinates (pixel corners) and flips rows (its
    row 0 is the top), so the textbook matrix is half a pixel off in both axes: the principal point
    enters as ``(cx - 0.5, cy + 0.5)``. Depth maps ``[near, far]`` to the buffer's ``[0, 1]``.
    """
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    fx, s, cx = K[0, 0], K[0, 1], K[0, 2] - 0.5
    fy, cy = K[1, 1], K[1, 2] + 0.5
    P = np.zeros((4, 4))
    P[0, 0], P[0, 1], P[0, 2] = 2 * fx / width, -2 * s / width, (width - 2 * cx) / width
    P[1, 1], P[1, 2] = 2 * fy / height, (2 * cy - height) / height
    P[2, 2], P[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
    P[3, 2] = -1.0
    return P


def opengl_view(T_cam_world: np.ndarray) -> np.ndarray:
    """The OpenGL view matrix ``[4, 4]`` of an OpenCV camera with pose ``T_cam_world [4, 4]``."""
    return _GL_FROM_CV @ T_cam_world


def depth_buffer_to_z(buffer: np.ndarray, near: float, far: float) -> np.ndarray:
    """Non-linear depth buffer values in ``[0, 1]`` (any shape) to metric z-depth (float64)."""
    buffer = np.asarray(buffer, dtype=np.float64)
    return far * near / (far - (far - near) * buffer)


def split_segmentation(seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pybullet's packed segmentation (``ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX``) to
    ``(body id, link index)``, both int64 of the same shape. The value packs
    ``(link index + 1) << 24 | body id`` with link index -1 for a body's root link; a pixel that
    sees nothing is -1 and comes back as body -1."""
    seg = np.asarray(seg, dtype=np.int64)
    hit = seg >= 0
    body = np.where(hit, seg & 0xFFFFFF, -1)
    link = np.where(hit, (seg >> 24) - 1, -1)
    return body, link


@dataclass(frozen=True)
class Lighting:
    """TinyRenderer's light: ``direction`` (towards the light, object frame) and the Phong terms."""

    direction: tuple[float, float, float] = (0.4, -0.3, 1.0)
    ambient: float = 0.55
    diffuse: float = 0.45
    specular: float = 0.1
    shadow: bool = False


def _periodic_noise(rng: np.random.Generator, cells: int, size: int) -> np.ndarray:
    """Smooth noise ``[size, size]`` that tiles: a random ``cells x cells`` lattice, bilinearly
    interpolated with wrap-around."""
    lattice = rng.normal(size=(cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(int)
    f = t - i0
    i1 = (i0 + 1) % cells
    rows = lattice[i0] * (1 - f)[:, None] + lattice[i1] * f[:, None]
    return rows[:, i0] * (1 - f)[None, :] + rows[:, i1] * f[None, :]


def table_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A tileable procedural wood-grain texture, uint8 ``[size, size, 3]``."""
    y, x = np.mgrid[0:size, 0:size] / size
    warp = _periodic_noise(rng, 4, size) + 0.3 * _periodic_noise(rng, 16, size)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (9 * y + 0.5 * warp + 0.15 * np.sin(2 * np.pi * x)))
    fine = 0.05 * _periodic_noise(rng, 64, size)
    shade = np.clip(0.72 + 0.18 * grain**3 + fine, 0, 1)
    base = np.array([182.0, 134.0, 90.0])
    return np.clip(shade[..., None] * base, 0, 255).astype(np.uint8)


class BulletScene:
    """An articulated object (and an optional textured table) in a headless pybullet world.

    Args:
        urdf: the object (:func:`~narf_core.data.dataset.read_urdf`); its root frame is the world.
        background: add a textured table under the object (labelled background, with depth).
        lighting: the light, fixed in the object frame.
        texture_seed: seed of the table's procedural texture.

    Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        urdf: UrdfInfo,
        *,
        background: bool = False,
        lighting: Lighting = Lighting(),
        texture_seed: int = 0,
    ) -> None:
        self.urdf = urdf
        self.links = urdf.links
        self.joints = urdf.joints
        self.lighting = lighting
        with _native_output(1, "connecting"):
            self._p = BulletClient(connection_mode=pybullet.DIRECT)
        try:
            with _native_output(1, f"loading {urdf.path}") as output:
                self._body = self._p.loadURDF(str(urdf.path), useFixedBase=True)
        except pybullet.error:
            self.close()
            messages = _pybullet_messages(output[0])
            raise UrdfError(f"{urdf.path}: pybullet cannot load it: {messages}") from None
        self._joint_index: dict[str, int] = {}
        label_of = {name: 1 + i for i, name in enumerate(urdf.links)}
        lut = np.zeros(self._p.getNumJoints(self._body) + 1, dtype=np.uint8)
        lut[0] = label_of[self._p.getBodyInfo(self._body)[0].decode()]
        for j in range(self._p.getNumJoints(self._body)):
            info = self._p.getJointInfo(self._body, j)
            self._joint_index[info[1].decode()] = j
            lut[j + 1] = label_of[info[12].decode()]
        self._label_lut = lut  # pybullet link index + 1 -> label
        # resetBasePositionAndOrientation places the root's *inertial* frame: put it where the
        # root's inertial frame is when the URDF frame is the world frame.
        inertial_pos, inertial_orn = self._p.getDynamicsInfo(self._body, -1)[3:5]
        self._p.resetBasePositionAndOrientation(self._body, inertial_pos, inertial_orn)
        self._model = yourdfpy.URDF.load(
            str(urdf.path),
            load_meshes=True,
            build_scene_graph=True,
            filename_handler=lambda fname: str(resolve_mesh(fname, urdf.path.parent, source=str(urdf.path))),
        )
        self._table = self._add_table(np.random.default_rng(texture_seed)) if background else None
        self.configuration: dict[str, float] = {}
        self.set_configuration({j["name"]: 0.5 * (j["lower"] + j["upper"]) for j in self.joints})

    def __enter__(self) -> BulletScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect from pybullet."""
        self._p.disconnect()

    def set_configuration(self, joints: dict[str, float]) -> None:
        """Set every actuated joint (``{name: value}``, within limits); mimic joints follow."""
        joints = check_joints([JointSpec(**j) for j in self.joints], joints, "configuration", complete=True)
        values = dict(joints)
        for name, (source, multiplier, offset) in self.urdf.mimics.items():
            values[name] = multiplier * joints[source] + offset
        for name, value in values.items():
            self._p.resetJointState(self._body, self._joint_index[name], float(value))
        self._model.update_cfg({name: float(joints[name]) for name in self._model.actuated_joint_names})
        self.configuration = dict(joints)
        self._bounds = np.asarray(self._model.scene.bounds, dtype=np.float64)
        if self._table is not None:
            z = self._bounds[0, 2] - _TABLE_GAP
            self._p.resetBasePositionAndOrientation(self._table, [0.0, 0.0, z], [0.0, 0.0, 0.0, 1.0])

    def bounds(self) -> np.ndarray:
        """The object's axis-aligned box ``[2, 3]`` (min, max) in its frame at the current configuration."""
        return self._bounds.copy()

    def render(self, camera: Pinhole, T_cam_obj: np.ndarray, supersample: int = 1) -> FrameImages:
        """RGB uint8 ``[H, W, 3]``, metric z-depth float32 ``[H, W]`` (0 = no return) and labels
        uint8 ``[H, W]`` of the object seen by ``camera`` from ``T_cam_obj [4, 4]``.

        ``supersample`` (odd) renders ``s x s`` samples per pixel, as a camera integrates light over
        its pixel area: the colour is the mean of the samples that carry the pixel's label (no
        bleeding across silhouettes), while labels and depth are the centre sample's, which lies
        exactly on the pixel centre, so they stay exact. TinyRenderer samples textures at a point
        without filtering; without supersampling, texture detail finer than a pixel turns into
        aliasing that no view-consistent model can reproduce.
        """
        if supersample < 1 or supersample % 2 == 0:
            raise ValueError(f"supersample must be a positive odd number, got {supersample}")
        T_cam_obj = np.asarray(T_cam_obj, dtype=np.float64)
        if T_cam_obj.shape != (4, 4) or not np.isfinite(T_cam_obj).all():
            raise ValueError(f"T_cam_obj must be a finite 4x4 matrix, got shape {list(T_cam_obj.shape)}")
        s = supersample
        rgb, depth, labels = self._render_samples(camera.scaled(camera.width * s, camera.height * s), T_cam_obj)
        if s == 1:
            return FrameImages(rgb, depth, labels)
        h, w = camera.height, camera.width
        centre_labels = labels[s // 2 :: s, s // 2 :: s]
        same = (labels.reshape(h, s, w, s) == centre_labels[:, None, :, None])[..., None]
        blocks = rgb.reshape(h, s, w, s, 3).astype(np.float64)
        mean = (blocks * same).sum((1, 3)) / same.sum((1, 3))
        return FrameImages(
            np.ascontiguousarray(np.round(mean).astype(np.uint8)),
            np.ascontiguousarray(depth[s // 2 :: s, s // 2 :: s]),
            np.ascontiguousarray(centre_labels),
        )

    def _render_samples(self, camera: Pinhole, T_cam_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One TinyRenderer call: RGB, z-depth and labels at ``camera``'s resolution."""
        K = camera.K.detach().double().cpu().numpy()
        near, far = self._clip_range(T_cam_obj)
        view = opengl_view(T_cam_obj)
        proj = opengl_projection(K, camera.width, camera.height, near, far)
        light = self.lighting
        _, _, rgba, buffer, seg = self._p.getCameraImage(
            camera.width,
            camera.height,
            viewMatrix=view.T.reshape(-1).tolist(),  # column-major
            projectionMatrix=proj.T.reshape(-1).tolist(),
            lightDirection=list(light.direction),
            lightAmbientCoeff=light.ambient,
            lightDiffuseCoeff=light.diffuse,
            lightSpecularCoeff=light.specular,
            shadow=int(light.shadow),
            renderer=pybullet.ER_TINY_RENDERER,
            flags=pybullet.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
        )
        shape = (camera.height, camera.width)
        body, link = split_segmentation(np.reshape(seg, shape))
        on_object = body == self._body
        labels = np.where(on_object, self._label_lut[link + 1], 0).astype(np.uint8)
        z = depth_buffer_to_z(np.reshape(buffer, shape), near, far)
        depth = np.where(body >= 0, z, 0.0).astype(np.float32)
        rgb = np.ascontiguousarray(np.reshape(rgba, (*shape, 4))[..., :3], dtype=np.uint8)
        return rgb, depth, labels

    def _clip_range(self, T_cam_obj: np.ndarray) -> tuple[float, float]:
        """Near and far planes around the object's bounding sphere (and the table, if any)."""
        centre = self._bounds.mean(0)
        radius = 0.5 * float(np.linalg.norm(self._bounds[1] - self._bounds[0])) + 1e-3
        eye = -T_cam_obj[:3, :3].T @ T_cam_obj[:3, 3]
        distance = float(np.linalg.norm(eye - centre))
        near = max(1e-3, 0.5 * (distance - radius))
        far = distance + radius + (2 * np.sqrt(2) * _TABLE_HALF_SIZE if self._table is not None else 0.01)
        return near, far

    def _add_table(self, rng: np.random.Generator) -> int:
        """A textured square plane, labelled background; moved under the object per configuration."""
        h, uv = _TABLE_HALF_SIZE, 2 * _TABLE_HALF_SIZE / _TABLE_TILE
        obj = (
            f"v {-h} {-h} 0\nv {h} {-h} 0\nv {h} {h} 0\nv {-h} {h} 0\n"
            f"vt 0 0\nvt {uv} 0\nvt {uv} {uv}\nvt 0 {uv}\nvn 0 0 1\n"
            "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n"
        )
        with tempfile.TemporaryDirectory(prefix="narf-table-") as tmp:
            (Path(tmp) / "table.obj").write_text(obj)
            Image.fromarray(table_texture(rng)).save(Path(tmp) / "table.png")
            with _native_output(1, "creating the table"):
                shape = self._p.createVisualShape(pybullet.GEOM_MESH, fileName=str(Path(tmp) / "table.obj"))
                table = self._p.createMultiBody(baseMass=0, baseVisualShapeIndex=shape)
                texture = self._p.loadTexture(str(Path(tmp) / "table.png"))
        self._p.changeVisualShape(table, -1, textureUniqueId=texture, rgbaColor=[1, 1, 1, 1])
        return table
