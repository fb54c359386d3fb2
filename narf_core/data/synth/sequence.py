"""Video-like synthetic sequences for tracking (``narf synth --sequence FRAMES``).

A sequence is a dataset in the usual format (docs/design.md §3) whose frames are in time order, every
frame in the ``test`` split with a ``"time"`` in seconds (``1 / fps`` apart). The camera moves
like a hand-held camera or a robot's head around the object (which stays at the world origin):

  - it orbits at a drifting, oscillating azimuth, with elevation, distance and roll swaying
    slowly and the look-at point wandering over the object (an object with camera distances of its
    own, too large for the rig's, is seen from as much farther, and one seen only from its front
    is orbited there: :func:`framed_path`);
  - the joints open and close (a sine between the tool's smallest and largest trained values);
  - with ``events`` (the default), the camera once glances away so that the object leaves the
    view for a few frames, and a grey bar (a stand-in for an arm or a cable) sweeps across the
    object once, occluding part of it; its pixels are background in the labels and carry the
    bar's depth (:mod:`narf_core.data.synth.bar`).

The path is smooth (sums of sines and raised-cosine ramps) and slowed down uniformly, if needed,
so that the camera never moves faster than ``max_speed_m_s`` nor turns faster than
``max_turn_deg_s``. Per-frame ground truth is the frame's ``T_cam_obj`` and ``joints``; the
generator block ``sequence`` records the fps, the limits, the measured peak speeds and, per
frame, whether the object is in view, how much of it the bar hides and where the bar is (``occluder``: its centre
as a fraction of the width and its depth, or null; ``narf restyle`` draws it from there).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from narf_core.data.dataset import DatasetWriter
from narf_core.data.synth.bar import bar_depth, occlude
from narf_core.geometry import Pinhole, invert_pose, look_at, so3_log

DEFAULT_FPS = 30.0


@dataclass(frozen=True)
class SequencePath:
    """The camera's path around the object and the joints' motion, as functions of time.

    Distances in metres, angles in degrees, rates per second. ``glance_*``: the look-at point
    moves ``glance_offset`` object radii sideways (a glance away) around ``glance_at`` (fraction
    of the sequence) for ``glance_s`` seconds of path time (only in sequences at least twice as
    long); ``occlusion_*``: the bar crosses the image around
    ``occlusion_at`` in ``occlusion_s`` seconds.
    """

    distance: float = 0.55
    distance_sway: float = 0.08
    elevation_deg: float = 45.0
    elevation_sway_deg: float = 15.0
    azimuth_rate_deg: float = 20.0
    azimuth_sway_deg: float = 12.0
    roll_sway_deg: float = 4.0
    target_wander: float = 0.2  # object radii
    joint_period_s: float = 4.0
    max_speed_m_s: float = 0.30
    max_turn_deg_s: float = 60.0
    # An object seen only from some azimuths (a cabinet against a wall: ViewSampling.azimuth_deg): the orbit
    # turns back at these ends, a triangle wave of the free orbit's azimuth (None: the whole turn).
    azimuth_range_deg: tuple[float, float] | None = None
    glance_at: float = 0.45
    glance_s: float = 2.4
    glance_offset: float = 4.0
    occlusion_at: float = 0.75
    occlusion_s: float = 1.5

    def camera(self, t: float, centre: np.ndarray, radius: float, phase: np.ndarray, glance: float) -> np.ndarray:
        """``T_cam_obj [4, 4]`` at time ``t`` (s); ``glance`` in [0, 1] is how far the camera looks away."""
        p = phase
        azimuth = math.radians(folded(p[0] * 360 + self.azimuth_rate_deg * t
                                      + self.azimuth_sway_deg * math.sin(2 * math.pi * 0.15 * t + p[1]),
                                      self.azimuth_range_deg))
        elevation = math.radians(self.elevation_deg + self.elevation_sway_deg * math.sin(2 * math.pi * 0.11 * t + p[2]))
        distance = self.distance + self.distance_sway * math.sin(2 * math.pi * 0.13 * t + p[3])
        wander = self.target_wander * radius * np.array(
            [math.sin(2 * math.pi * 0.17 * t + p[4]), math.sin(2 * math.pi * 0.19 * t + p[5]),
             math.sin(2 * math.pi * 0.23 * t + p[6])]
        )
        ce, se = math.cos(elevation), math.sin(elevation)
        direction = np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), se])
        side = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
        target = centre + wander + glance * self.glance_offset * radius * side
        eye = centre + wander + distance * direction
        T_obj_cam = look_at(torch.from_numpy(eye), torch.from_numpy(target), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        roll = math.radians(self.roll_sway_deg * math.sin(2 * math.pi * 0.21 * t + p[7]))
        c, s = math.cos(roll), math.sin(roll)
        T_obj_cam[:3, :3] = T_obj_cam[:3, :3] @ torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        return invert_pose(T_obj_cam).numpy()


def folded(angle_deg: float, span: tuple[float, float] | None) -> float:
    """``angle_deg`` (degrees, unbounded) folded into ``span = (low, high)`` as a triangle wave, so that a
    path that moves on turns back at either end; unchanged where ``span`` is None."""
    if span is None:
        return angle_deg
    low, high = span
    m = (angle_deg - low) % (2 * (high - low))
    return low + (m if m <= high - low else 2 * (high - low) - m)


def framed_path(tool: str | Path, path: SequencePath) -> SequencePath:
    """``path`` fitted to ``tool``'s own views (:func:`~narf_core.data.synth.generate.default_sampling`):
    its distances scaled as the object's camera distances are the rig's (by the nearest), so that an object
    too large for the rig's stays in view as the tools do; and, for an object seen from some azimuths only,
    its orbit kept to them and its elevation swaying inside the object's range."""
    from narf_core.data.synth.generate import ViewSampling, default_sampling

    own, rig = default_sampling(tool), ViewSampling()
    k = own.distance[0] / rig.distance[0]
    if k != 1:
        path = replace(path, distance=path.distance * k, distance_sway=path.distance_sway * k)
    if own.azimuth_deg != rig.azimuth_deg:
        path = replace(path, azimuth_range_deg=tuple(own.azimuth_deg))
    if own.elevation_deg != rig.elevation_deg:
        low, high = own.elevation_deg
        sway = min(path.elevation_sway_deg, (high - low) / 2)
        path = replace(path, elevation_deg=(low + high) / 2, elevation_sway_deg=sway)
    return path


def raised_cosine(x: float) -> float:
    """A smooth bump on ``x`` in [-1, 1]: 0 outside, 1 at 0, with zero slope at both ends and the top."""
    if abs(x) >= 1:
        return 0.0
    return 0.5 * (1 + math.cos(math.pi * x))


def camera_speeds(poses: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speed (m/s) of the camera's centre and turn rate (deg/s) between consecutive ``T_cam_obj [N,4,4]``."""
    T_obj_cam = np.linalg.inv(poses)
    dt = np.diff(times)
    speed = np.linalg.norm(np.diff(T_obj_cam[:, :3, 3], axis=0), axis=1) / dt
    R = T_obj_cam[:, :3, :3]
    relative = torch.from_numpy(np.einsum("nji,njk->nik", R[:-1], R[1:]))
    turn = np.degrees(so3_log(relative).norm(dim=-1).numpy()) / dt
    return speed, turn


@dataclass
class _Plan:
    times: np.ndarray  # [N] s
    poses: np.ndarray  # [N, 4, 4]
    joints: list[dict[str, float]]
    occluder: list[float | None]  # the bar's centre as a fraction of the image width, or None
    time_scale: float  # path time per real second (< 1 when slowed down to the limits)


def plan_sequence(
    frames: int,
    fps: float,
    centre: np.ndarray,
    radius: float,
    joint_ranges: dict[str, tuple[float, float]],
    rng: np.random.Generator,
    path: SequencePath = SequencePath(),
    events: bool = True,
) -> _Plan:
    """Poses, joints and occluder positions of ``frames`` frames at ``fps``, within the speed limits."""
    phase = rng.uniform(0, 2 * math.pi, size=8)
    phase[0] = rng.uniform()
    joint_phase = {name: rng.uniform(0, 2 * math.pi) for name in joint_ranges}
    duration = frames / fps
    real_times = np.arange(frames) / fps
    glances = events and duration >= 2 * path.glance_s

    def glance(tau: float, scale: float) -> float:  # in path time, so that slowing down slows the glance too
        if not glances:
            return 0.0
        return raised_cosine((tau - scale * path.glance_at * duration) / (0.5 * path.glance_s))

    def poses_at(scale: float) -> np.ndarray:
        return np.stack([path.camera(scale * t, centre, radius, phase, glance(scale * t, scale)) for t in real_times])

    scale = 1.0
    poses = poses_at(scale)
    if frames > 1:  # slow the path down (uniformly) until it keeps to the limits
        for _ in range(8):
            speed, turn = camera_speeds(poses, real_times)
            excess = max(float(speed.max()) / path.max_speed_m_s, float(turn.max()) / path.max_turn_deg_s)
            if excess <= 1.0:
                break
            scale /= excess * 1.02
            poses = poses_at(scale)
    joints = []
    for t in real_times:
        joints.append({
            name: lo + (hi - lo) * 0.5 * (1 - math.cos(2 * math.pi * t / path.joint_period_s + joint_phase[name]))
            for name, (lo, hi) in joint_ranges.items()
        })
    occluder: list[float | None] = []
    for t in real_times:
        x = (t - path.occlusion_at * duration) / (0.5 * path.occlusion_s)
        occluder.append(0.5 + 0.8 * x if events and abs(x) < 1 else None)
    return _Plan(real_times, poses, joints, occluder, scale)


def _joint_ranges(urdf, train, novel) -> dict[str, tuple[float, float]]:
    """Per joint, the range the motion covers: the tool's trained and novel values, else 10-90% of the limits."""
    if train is not None and novel is not None:
        values = {}
        for config in [*train, *novel]:
            for name, v in config.items():
                values.setdefault(name, []).append(v)
        return {name: (min(v), max(v)) for name, v in values.items()}
    return {j["name"]: (j["lower"] + 0.1 * (j["upper"] - j["lower"]), j["upper"] - 0.1 * (j["upper"] - j["lower"]))
            for j in urdf.joints}


def synthesize_sequence(
    tool: str | Path,
    out: str | Path,
    frames: int,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
    *,
    fps: float = DEFAULT_FPS,
    events: bool = True,
    background: bool = False,
    supersample: int = 3,
    path: SequencePath = SequencePath(),
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Render a ``frames``-long sequence of ``tool`` into ``out`` and return ``out`` (see the module docstring).

    ``events`` adds the glance away (the object leaves the view) and the occluding bar;
    ``size`` is ``(width, height)`` with a Primesense-like camera scaled to it.
    """
    width, height = (int(v) for v in size)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if frames < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {frames}")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    # the generator's packages (pybullet, shapely) only where a sequence is drawn: reading one needs none
    from narf_core.data.synth.generate import _versions, resolve_tool
    from narf_core.data.synth.render import BulletScene

    camera = Pinhole.primesense(width, height)
    rng = np.random.default_rng(seed)
    out = Path(out)
    path = framed_path(tool, path)
    with tempfile.TemporaryDirectory(prefix="narf-seq-") as workdir:
        urdf, train, novel = resolve_tool(tool, Path(workdir))
        ranges = _joint_ranges(urdf, train, novel)
        texture_seed = int(rng.integers(2**31))
        with BulletScene(urdf, background=background, texture_seed=texture_seed) as scene:
            scene.set_configuration({name: 0.5 * (lo + hi) for name, (lo, hi) in ranges.items()})
            bounds = scene.bounds()
            centre, radius = bounds.mean(0), 0.5 * float(np.linalg.norm(bounds[1] - bounds[0]))
            plan = plan_sequence(frames, fps, centre, radius, ranges, rng, path, events)
            speed, turn = camera_speeds(plan.poses, plan.times)
            per_frame: list[dict] = []
            generator = {
                "tool": str(tool), "seed": seed, "size": [width, height], "views": {"test": frames},
                "background": background, "supersample": supersample, "noise": None, "versions": _versions(),
                "sequence": {
                    "fps": fps, "frames": frames, "events": events, "path": asdict(path),
                    "time_scale": plan.time_scale, "peak_speed_m_s": float(speed.max()),
                    "peak_turn_deg_s": float(turn.max()), "joint_ranges": {k: list(v) for k, v in ranges.items()},
                    "per_frame": per_frame,
                },
            }
            with DatasetWriter(out, urdf, camera, generator, overwrite=overwrite) as writer:
                for i in tqdm(range(frames), desc=f"sequence {Path(str(tool)).stem}", unit="frame", disable=not progress):
                    scene.set_configuration(plan.joints[i])
                    images = scene.render(camera, plan.poses[i], supersample)
                    pixels = int(np.count_nonzero(images.labels))
                    hidden, bar = 0.0, None
                    if plan.occluder[i] is not None:
                        bar = {"x": float(plan.occluder[i]), "z": bar_depth(plan.poses[i], radius)}
                        images, hidden = occlude(images, bar["x"], bar["z"])
                    # (the bar is recorded so that narf restyle draws it into its frames of the sequence)
                    per_frame.append({"in_view": pixels > 0, "object_pixels": pixels, "occluded": round(hidden, 4),
                                      "occluder": bar})
                    writer.add("test", images, plan.poses[i], plan.joints[i], time=float(plan.times[i]))
    return out


def sequence_once(tool: str | Path, out: str | Path, frames: int, size: tuple[int, int] = (160, 120), seed: int = 0,
                  *, events: bool = True) -> Path:
    """``out``, the sequence :func:`synthesize_sequence` draws, drawn on first use: into a folder of this
    process's own, renamed into place when whole, so that processes started side by side on one folder (or
    one stopped halfway) never read or overwrite a sequence another is writing."""
    out = Path(out)
    if _current(out):  # the generator (pybullet) only where the sequence is missing or stale
        return out
    mine = out.with_name(f"{out.name}.part-{os.getpid()}")
    synthesize_sequence(tool, mine, frames, size=size, seed=seed, events=events, overwrite=True)
    if _current(out):  # another process finished it first: the same sequence
        shutil.rmtree(mine)
        return out
    shutil.rmtree(out, ignore_errors=True)  # an older run's unfinished folder (no scene.json) or a stale sequence
    try:
        mine.rename(out)
    except OSError:  # another process renamed its own into place in between
        if not (out / "scene.json").is_file():
            raise
        shutil.rmtree(mine)
    return out


def _current(out: Path) -> bool:
    """Whether ``out`` holds a whole sequence as this version draws it: one with events records its occluding
    bar per frame (``narf restyle`` draws it from there; an older narf's does not)."""
    try:
        sequence = json.loads((out / "scene.json").read_text())["generator"].get("sequence") or {}
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return not sequence.get("events") or all("occluder" in p for p in sequence.get("per_frame") or [])
