"""Synthetic datasets: views, splits, label noise, and writing them (``narf synth``).

:func:`synthesize` renders an articulated object (one of the procedural tools, or any URDF) with
pybullet from robot-head-like viewpoints and writes a dataset in the format of docs/design.md §3, with the
paper's splits (Table I): ``train`` (few configurations), ``test`` (the same configurations from
other viewpoints) and ``novel`` (configurations absent from ``train``).

Everything is deterministic from ``seed``: independent random streams drive the configurations,
the views of each split, the label noise and the table texture, so changing ``views`` changes
neither the configurations nor the noise model.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

import narf_core
from narf_core.data.dataset import DatasetWriter, FrameImages, UrdfInfo, read_urdf
from narf_core.data.synth import tools
from narf_core.data.synth.render import BulletScene
from narf_core.geometry import Pinhole, invert_pose, look_at, so3_exp

Configuration = dict[str, float]  # {joint name: value}

DEFAULT_VIEWS = 200
MIN_EVAL_VIEWS = 17  # the paper's estimation protocol uses 17 scenes
_MAX_VIEW_TRIES = 100
NOISE_PRESETS: dict[str, dict[str, float]] = {
    "none": {},
    "paper": {"rot_deg": 2.0, "trans_mm": 5.0, "theta": 0.02, "mask_px": 1, "depth_m": 0.002},
}


@dataclass(frozen=True)
class ViewSampling:
    """Where cameras go: like a robot's head looking down at a table.

    The camera sits ``distance`` metres from the object's centre at an ``elevation`` above its
    x-y plane and an ``azimuth`` about its z axis from its +x axis (each uniform in degrees; by
    default any azimuth), looks at the centre moved by a Gaussian offset (``target_jitter`` times
    the object's radius per axis), and rolls by a Gaussian angle.
    """

    distance: tuple[float, float] = (0.4, 1.0)
    elevation_deg: tuple[float, float] = (15.0, 75.0)
    azimuth_deg: tuple[float, float] = (0.0, 360.0)
    roll_deg: float = 4.0
    target_jitter: float = 0.15

    def sample(self, rng: np.random.Generator, centre: np.ndarray, radius: float) -> np.ndarray:
        """One camera pose ``T_cam_obj [4, 4]`` (float64) looking at ``centre [3]``."""
        distance = rng.uniform(*self.distance)
        elevation = math.radians(rng.uniform(*self.elevation_deg))
        low, high = self.azimuth_deg  # one draw over the turn, scaled: the whole turn draws as it always has
        azimuth = math.radians(low) + rng.uniform(0.0, 2 * math.pi) * (high - low) / 360.0
        ce, se = math.cos(elevation), math.sin(elevation)
        direction = np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), se])
        target = centre + rng.normal(scale=self.target_jitter * radius, size=3)
        roll = math.radians(rng.normal(scale=self.roll_deg))
        T_obj_cam = look_at(
            torch.from_numpy(target + distance * direction),
            torch.from_numpy(target),
            torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
        )
        c, s = math.cos(roll), math.sin(roll)
        R_roll = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        T_obj_cam[:3, :3] = T_obj_cam[:3, :3] @ R_roll  # roll about the optical axis
        return invert_pose(T_obj_cam).numpy()


@dataclass(frozen=True)
class NoiseOptions:
    """Hand-labelling error added to the *written* labels (the rendered RGB stays clean).

    ``rot_deg``/``trans_mm``: standard deviation per axis of a rotation (about the object origin,
    camera axes) and translation added to ``T_cam_obj``; ``theta``: standard deviation added to
    each joint value in its unit (radians or metres), clipped to the limits; ``mask_px``: the label
    silhouette is eroded or dilated by a radius drawn uniformly from ``-mask_px..mask_px``;
    ``depth_m``: Gaussian noise on depth returns.
    """

    rot_deg: float = 0.0
    trans_mm: float = 0.0
    theta: float = 0.0
    mask_px: int = 0
    depth_m: float = 0.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"noise {name} must be a finite number >= 0, got {value}")
        if int(self.mask_px) != self.mask_px:
            raise ValueError(f"noise mask_px must be a whole number of pixels, got {self.mask_px}")

    @classmethod
    def preset(cls, name: str) -> NoiseOptions:
        """A named setting: ``none``, or ``paper``: errors like those of LabelFusion-style hand
        labels of Primesense data (NARF22's data): 2 deg and 5 mm of pose error, 0.02 of joint
        error, 1 px of mask error and 2 mm of depth noise."""
        if name not in NOISE_PRESETS:
            raise ValueError(f"unknown noise preset '{name}'; expected one of {', '.join(NOISE_PRESETS)}")
        return cls(**NOISE_PRESETS[name])

    @property
    def active(self) -> bool:
        return any(v > 0 for v in asdict(self).values())


def perturb_pose(T: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_mm: float) -> np.ndarray:
    """``T_cam_obj [4, 4]`` rotated about the object origin by a Gaussian rotation vector (camera
    axes, ``rot_deg`` per axis) and moved by Gaussian ``trans_mm`` per axis."""
    omega = torch.from_numpy(np.radians(rng.normal(scale=rot_deg, size=3)))
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = so3_exp(omega).numpy() @ out[:3, :3]
    out[:3, 3] += rng.normal(scale=trans_mm / 1000.0, size=3)
    return out


def perturb_configuration(
    config: Configuration, joints: list[dict[str, Any]], rng: np.random.Generator, sigma: float
) -> Configuration:
    """Each joint value plus Gaussian ``sigma`` (its unit), clipped to the joint's limits."""
    limits = {j["name"]: (j["lower"], j["upper"]) for j in joints}
    return {
        name: float(np.clip(value + rng.normal(scale=sigma), *limits[name])) for name, value in config.items()
    }


def _disk_offsets(radius: int) -> list[tuple[int, int]]:
    r = abs(radius)
    return [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy * dy + dx * dx <= r * r]


def jitter_mask(labels: np.ndarray, radius: int) -> np.ndarray:
    """Labels ``[H, W]`` with the object's silhouette dilated (``radius > 0``) or eroded
    (``radius < 0``) by a disk of ``|radius|`` pixels. Dilation gives a background pixel the
    largest label within the disk; erosion clears object pixels with background within the disk.
    Part boundaries inside the silhouette are unchanged."""
    if radius == 0:
        return labels.copy()
    h, w = labels.shape
    r = abs(radius)
    padded = np.pad(labels, r, mode="edge")
    windows = [padded[r + dy : r + dy + h, r + dx : r + dx + w] for dy, dx in _disk_offsets(r)]
    if radius > 0:
        return np.where(labels == 0, np.max(windows, axis=0), labels).astype(np.uint8)
    return np.where(np.min(windows, axis=0) == 0, 0, labels).astype(np.uint8)


def add_depth_noise(depth: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """Gaussian noise on the returns of ``depth [H, W]`` (metres); no-return pixels stay 0 and
    returns stay >= 1 mm."""
    noisy = depth + rng.normal(scale=sigma, size=depth.shape).astype(depth.dtype)
    return np.where(depth > 0, np.maximum(noisy, 1e-3), 0).astype(np.float32)


@dataclass(frozen=True)
class _Shot:
    split: str
    configuration: Configuration


def _spread(split: str, configurations: list[Configuration], n: int) -> list[_Shot]:
    """``n`` views spread evenly (in contiguous blocks) over ``configurations``."""
    return [_Shot(split, configurations[k * len(configurations) // n]) for k in range(n)]


def default_configurations(
    joints: list[dict[str, Any]], rng: np.random.Generator
) -> tuple[list[Configuration], list[Configuration]]:
    """Train and novel configurations of an arbitrary URDF: train = mid-range plus two uniform
    random ones; novel = three uniform random ones (one empty configuration for a rigid object)."""
    if not joints:
        return [{}], [{}]

    def uniform() -> Configuration:
        return {j["name"]: float(rng.uniform(j["lower"], j["upper"])) for j in joints}

    mid = {j["name"]: 0.5 * (j["lower"] + j["upper"]) for j in joints}
    return [mid, uniform(), uniform()], [uniform(), uniform(), uniform()]


def resolve_tool(
    tool: str | Path, workdir: Path
) -> tuple[UrdfInfo, list[Configuration] | None, list[Configuration] | None]:
    """The object's URDF and, for a procedural tool, its train and novel configurations.

    ``tool`` is a name from :data:`narf_core.data.synth.tools.TOOLS` (built into ``workdir``) or a
    path to a ``.urdf`` file (then the configurations are ``None``: the caller picks them).
    """
    name = str(tool)
    if name in tools.TOOLS:
        spec = tools.tool_spec(name)
        urdf = read_urdf(tools.build_tool(name, workdir))
        return urdf, spec.train_configurations, spec.novel_configurations
    if name.lower().endswith(".urdf") or Path(name).is_file():
        return read_urdf(name), None, None
    known = ", ".join(tools.TOOLS)
    raise ValueError(f"unknown tool '{name}'; expected one of {known} or a path to a .urdf file")


def default_sampling(tool: str | Path) -> ViewSampling:
    """The views of ``tool``: the rig's, with the object's own ranges where it has them
    (:attr:`~narf_core.data.synth.tools.ToolSpec.views`)."""
    name = str(tool)
    return ViewSampling(**tools.tool_spec(name).views) if name in tools.TOOLS else ViewSampling()


def synthesize(
    tool: str | Path,
    out: str | Path,
    size: tuple[int, int] = (160, 120),
    views: int = DEFAULT_VIEWS,
    seed: int = 0,
    noise: NoiseOptions | None = None,
    background: bool = False,
    *,
    overwrite: bool = False,
    sampling: ViewSampling | None = None,
    supersample: int = 3,
    progress: bool = False,
) -> Path:
    """Render a dataset of ``tool`` into ``out`` and return ``out``.

    Args:
        tool: a procedural object's name (one of :data:`narf_core.data.synth.tools.TOOLS`: ``clamp``,
            ``lineman-a``, ``lineman-b``, ``longnose``, ``lamp``, ``gripper``, ``cabinet``) or a path to a URDF.
        out: the dataset folder (new or empty; with ``overwrite``, a previous dataset is replaced).
        size: image ``(width, height)``; the camera is a Primesense-like pinhole scaled to it.
        views: number of ``train`` images; ``test`` and ``novel`` get ``max(17, views // 4)`` each.
        seed: seeds configurations, views, noise and the table texture.
        noise: label noise (the clean ground truth is kept as ``clean/`` and
            ``generator.clean_frames``).
        background: render a textured table under the object (labelled background).
        supersample: colour samples per pixel along each axis (odd; labels and depth stay exact),
            like a camera's integration over its pixel area.
        sampling: where cameras go; by default :class:`ViewSampling`'s rig, with the object's own
            ranges where it has them (:attr:`~narf_core.data.synth.tools.ToolSpec.views`: a cabinet is
            seen from farther away than a pair of pliers, and from its front).
        progress: show a tqdm progress bar on stderr.
    """
    width, height = (int(v) for v in size)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if views <= 0:
        raise ValueError(f"views must be >= 1, got {views}")
    noise = noise or NoiseOptions()
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)]
    config_rng, noise_rng, texture_rng = streams[0], streams[4], streams[5]
    view_rngs = {"train": streams[1], "test": streams[2], "novel": streams[3]}
    camera = Pinhole.primesense(width, height)
    min_pixels = max(1, width * height // 1000)
    out = Path(out)

    with tempfile.TemporaryDirectory(prefix="narf-synth-") as workdir:
        urdf, train_configs, novel_configs = resolve_tool(tool, Path(workdir))
        if train_configs is None or novel_configs is None:
            train_configs, novel_configs = default_configurations(urdf.joints, config_rng)
        sampling = sampling or default_sampling(tool)
        train_configs = train_configs[:views]  # test must only hold configurations train has
        n_eval = max(MIN_EVAL_VIEWS, views // 4)
        shots = (
            _spread("train", train_configs, views)
            + _spread("test", train_configs, n_eval)
            + _spread("novel", novel_configs, n_eval)
        )
        generator = {
            "tool": str(tool),
            "seed": seed,
            "size": [width, height],
            "views": {"train": views, "test": n_eval, "novel": n_eval},
            "configurations": {"train": train_configs, "novel": novel_configs},
            "background": background,
            "supersample": supersample,
            "sampling": asdict(sampling),
            "noise": asdict(noise) if noise.active else None,
            "versions": _versions(),
        }
        texture_seed = int(texture_rng.integers(2**31))
        with (
            BulletScene(urdf, background=background, texture_seed=texture_seed) as scene,
            DatasetWriter(out, urdf, camera, generator, overwrite=overwrite) as writer,
        ):
            for shot in tqdm(shots, desc=f"synth {Path(str(tool)).stem}", unit="view", disable=not progress):
                if shot.configuration != scene.configuration:
                    scene.set_configuration(shot.configuration)
                T_cam_obj, images = _visible_view(
                    scene, camera, sampling, view_rngs[shot.split], min_pixels, supersample
                )
                if noise.active:
                    written = _add_noise(images, T_cam_obj, shot.configuration, urdf.joints, noise, noise_rng)
                    writer.add(shot.split, *written, clean=(images, T_cam_obj, shot.configuration))
                else:
                    writer.add(shot.split, images, T_cam_obj, shot.configuration)
    return out


def _visible_view(
    scene: BulletScene,
    camera: Pinhole,
    sampling: ViewSampling,
    rng: np.random.Generator,
    min_pixels: int,
    supersample: int,
) -> tuple[np.ndarray, FrameImages]:
    """Sample camera poses until the object covers at least ``min_pixels`` pixels."""
    bounds = scene.bounds()
    centre = bounds.mean(0)
    radius = 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
    for _ in range(_MAX_VIEW_TRIES):
        T_cam_obj = sampling.sample(rng, centre, radius)
        images = scene.render(camera, T_cam_obj, supersample)
        if np.count_nonzero(images.labels) >= min_pixels:
            return T_cam_obj, images
    raise ValueError(
        f"the object covered fewer than {min_pixels} pixels in {_MAX_VIEW_TRIES} sampled views "
        f"at {camera.width}x{camera.height}; is it too small (bounds {bounds.tolist()} m)?"
    )


def _add_noise(
    images: FrameImages,
    T_cam_obj: np.ndarray,
    config: Configuration,
    joints: list[dict[str, Any]],
    noise: NoiseOptions,
    rng: np.random.Generator,
) -> tuple[FrameImages, np.ndarray, Configuration]:
    """The written (noisy) images, pose and configuration of one frame."""
    radius = int(rng.integers(-noise.mask_px, noise.mask_px + 1)) if noise.mask_px else 0
    labels = jitter_mask(images.labels, radius)
    depth = images.depth
    if depth is not None and noise.depth_m > 0:
        depth = add_depth_noise(depth, rng, noise.depth_m)
    T = perturb_pose(T_cam_obj, rng, noise.rot_deg, noise.trans_mm)
    noisy_config = perturb_configuration(config, joints, rng, noise.theta)
    return FrameImages(images.rgb, depth, labels), T, noisy_config


def _versions() -> dict[str, str]:
    versions = {"narf": narf_core.__version__}
    for package in ("pybullet", "numpy", "yourdfpy"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "unknown"
    return versions
