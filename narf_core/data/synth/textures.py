"""Procedural surface colours for the synthetic tools: steel, plastic, rubber grips, printed marks.

A :class:`Surface` colours 3-D points of a link (metres, link frame). A texture atlas is painted by
mapping each texel back to the point of the mesh it lands on, so patterns run on continuously from
a face to the next and keep their physical size whatever the atlas resolution. Noise is seeded
lattice value noise: the same seed gives the same texture on every machine.

Colours are sRGB floats in ``[0, 1]`` (docs/design.md §2); :func:`to_uint8` quantises them for the PNG.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

Rgb = tuple[float, float, float]
Vec3 = tuple[float, float, float]
FloatArray = NDArray[np.float64]


class ValueNoise:
    """Seeded 3-D lattice value noise in ``[0, 1]``, smooth (trilinear with a smoothstep fade)."""

    def __init__(self, seed: int | Sequence[int], table_size: int = 256) -> None:
        rng = np.random.default_rng(seed)
        self._size = table_size
        self._perm = rng.permutation(table_size)
        self._values = rng.random(table_size)

    def _lattice(self, i: NDArray[np.int64], j: NDArray[np.int64], k: NDArray[np.int64]) -> FloatArray:
        n, perm = self._size, self._perm
        return self._values[perm[(perm[(perm[i % n] + j) % n] + k) % n]]

    def __call__(self, points: FloatArray, cell: Vec3) -> FloatArray:
        """Noise ``[n]`` at ``points [n, 3]``; ``cell`` is the lattice spacing along x, y, z in metres."""
        q = points / np.asarray(cell, dtype=np.float64)
        base = np.floor(q)
        f = q - base
        f = f * f * (3.0 - 2.0 * f)
        i, j, k = (base.astype(np.int64) % self._size).T
        fx, fy, fz = f.T
        out = np.zeros(len(points))
        for di in (0, 1):
            wx = fx if di else 1.0 - fx
            for dj in (0, 1):
                wy = fy if dj else 1.0 - fy
                for dk in (0, 1):
                    wz = fz if dk else 1.0 - fz
                    out += wx * wy * wz * self._lattice(i + di, j + dj, k + dk)
        return out

    def fbm(self, points: FloatArray, cell: Vec3, octaves: int = 3) -> FloatArray:
        """Fractal sum of ``octaves`` noise layers (each half the cell, half the weight), in ``[0, 1]``."""
        total, weight, norm = np.zeros(len(points)), 1.0, 0.0
        c = np.asarray(cell, dtype=np.float64)
        for octave in range(octaves):
            shifted = points + 0.37 * octave * c  # decorrelate the octaves' lattices
            total += weight * self(shifted, tuple(c))
            norm += weight
            weight, c = weight / 2, c / 2
        return total / norm


class Region(Protocol):
    """A part of the link frame that a :class:`Detail` is confined to."""

    def contains(self, points: FloatArray) -> NDArray[np.bool_]:
        """``[n, 3] -> [n]``: whether each point lies inside the region."""
        ...


@dataclass(frozen=True)
class Box:
    """An axis-aligned region of the link frame (metres); unbounded by default."""

    lo: Vec3 = (-np.inf, -np.inf, -np.inf)
    hi: Vec3 = (np.inf, np.inf, np.inf)

    def contains(self, points: FloatArray) -> NDArray[np.bool_]:
        return np.all((points >= np.asarray(self.lo)) & (points <= np.asarray(self.hi)), axis=-1)


@dataclass(frozen=True)
class Disk:
    """The points within ``radius`` of ``centre`` in xy (a vertical cylinder)."""

    centre: tuple[float, float]
    radius: float

    def contains(self, points: FloatArray) -> NDArray[np.bool_]:
        return np.hypot(points[:, 0] - self.centre[0], points[:, 1] - self.centre[1]) <= self.radius


class Detail(Protocol):
    """A pattern laid over a surface's base colour (ribs, dots, stripes, ...)."""

    def apply(self, rgb: FloatArray, points: FloatArray) -> FloatArray:
        """New colours ``[n, 3]`` for colours ``rgb [n, 3]`` at ``points [n, 3]``."""
        ...


def _smooth_pulse(phase: FloatArray, duty: float) -> FloatArray:
    """Periodic pulse of period 1: 1 at the centre of each ``duty``-wide slot, fading to 0 at its edges."""
    d = np.abs(phase - np.round(phase)) / (duty / 2)
    return np.clip(1.0 - d, 0.0, 1.0) ** 0.5


@dataclass(frozen=True)
class Ribs:
    """Parallel grooves ``pitch`` apart across ``axis``, darkening the surface by up to ``depth``."""

    pitch: float
    axis: Vec3 = (1.0, 0.0, 0.0)
    depth: float = 0.45
    duty: float = 0.4
    region: Region = field(default_factory=Box)

    def apply(self, rgb: FloatArray, points: FloatArray) -> FloatArray:
        inside = self.region.contains(points)
        phase = points @ np.asarray(self.axis) / self.pitch
        shade = 1.0 - self.depth * _smooth_pulse(phase, self.duty) * inside
        return rgb * shade[:, None]


@dataclass(frozen=True)
class Dots:
    """A hexagonal grid of round dots (``pitch`` apart, ``radius``) of ``colour``, laid out in xy."""

    pitch: float
    radius: float
    colour: Rgb
    region: Region = field(default_factory=Box)

    def apply(self, rgb: FloatArray, points: FloatArray) -> FloatArray:
        row_gap = self.pitch * np.sqrt(3) / 2
        row = np.round(points[:, 1] / row_gap)
        x = points[:, 0] / self.pitch - 0.5 * (row % 2)
        dist = np.hypot((x - np.round(x)) * self.pitch, points[:, 1] - row * row_gap)
        alpha = np.clip((self.radius - dist) / (0.3 * self.radius) + 0.5, 0.0, 1.0)
        alpha = alpha * self.region.contains(points)
        return rgb * (1 - alpha[:, None]) + np.asarray(self.colour) * alpha[:, None]


@dataclass(frozen=True)
class Paint:
    """A flat coat of ``colour`` over ``region`` (stripes, bands, caps)."""

    colour: Rgb
    region: Region

    def apply(self, rgb: FloatArray, points: FloatArray) -> FloatArray:
        inside = self.region.contains(points)[:, None]
        return np.where(inside, np.asarray(self.colour), rgb)


@dataclass(frozen=True)
class Ticks:
    """Ruler marks along x: a thin line every ``pitch``, longer every ``major`` ticks, inside ``region``.

    Lines run along y from ``region.lo[1]``; minor ticks cover 40 % of the region's width.
    """

    pitch: float
    colour: Rgb
    region: Box
    width: float = 0.0005
    major: int = 10

    def apply(self, rgb: FloatArray, points: FloatArray) -> FloatArray:
        k = np.round(points[:, 0] / self.pitch)
        on_line = np.abs(points[:, 0] - k * self.pitch) < self.width / 2
        span = self.region.hi[1] - self.region.lo[1]
        length = np.where(k % self.major == 0, span, np.where(k % (self.major // 2) == 0, 0.7 * span, 0.4 * span))
        on_tick = on_line & (points[:, 1] - self.region.lo[1] <= length) & self.region.contains(points)
        return np.where(on_tick[:, None], np.asarray(self.colour), rgb)


@dataclass(frozen=True)
class Surface:
    """A material: base ``colour`` with low-frequency ``mottle``, fine ``speckle``, brushed ``grain``.

    ``grain`` draws streaks along ``grain_axis`` (brushed or ground metal); ``details`` are applied
    in order on top.
    """

    colour: Rgb
    mottle: float = 0.06
    speckle: float = 0.04
    grain: float = 0.0
    grain_axis: Vec3 = (1.0, 0.0, 0.0)
    details: tuple[Detail, ...] = ()

    def paint(self, points: FloatArray, noise: ValueNoise) -> FloatArray:
        """Colours ``[n, 3]`` in ``[0, 1]`` at link-frame ``points [n, 3]``."""
        tone = 1.0 + self.mottle * (2 * noise.fbm(points, (0.02, 0.02, 0.02)) - 1)
        tone += self.speckle * (2 * noise(points + 11.0, (0.0006, 0.0006, 0.0006)) - 1)
        if self.grain:
            axis = np.asarray(self.grain_axis, dtype=np.float64)
            axis /= np.linalg.norm(axis)
            # Streak coordinates: long cells along the grain, hair-thin across it.
            across = points - np.outer(points @ axis, axis)
            streak_pts = np.column_stack([points @ axis, across @ _perpendicular(axis), points[:, 2]])
            tone += self.grain * (2 * noise.fbm(streak_pts + 5.0, (0.012, 0.00035, 0.00035), 2) - 1)
        rgb = np.asarray(self.colour)[None, :] * tone[:, None]
        for detail in self.details:
            rgb = detail.apply(rgb, points)
        return np.clip(rgb, 0.0, 1.0)


def _perpendicular(axis: FloatArray) -> FloatArray:
    """A unit vector perpendicular to unit ``axis [3]``, in the xy plane when possible."""
    p = np.array([-axis[1], axis[0], 0.0])
    if np.linalg.norm(p) < 1e-6:
        p = np.array([1.0, 0.0, 0.0])
    return p / np.linalg.norm(p)


@dataclass(frozen=True)
class Mark:
    """Printed text on a flat face: centred at ``centre`` (x, y), reading along ``angle`` (rad) in the
    xy plane, letters ``height`` metres tall, on the top (``face=+1``) or bottom (``-1``) face.
    Bottom marks are mirrored so that they read correctly when seen from below."""

    text: str
    centre: tuple[float, float]
    angle: float
    height: float
    colour: Rgb
    face: int = 1

    def __post_init__(self) -> None:
        if self.face not in (1, -1):
            raise ValueError(f"Mark.face must be +1 (top) or -1 (bottom), got {self.face}")


def text_mask(text: str, height_px: int) -> FloatArray:
    """Coverage ``[h, w]`` in ``[0, 1]`` of ``text`` set in Pillow's built-in font, cropped to the ink."""
    font = ImageFont.load_default(size=max(4, int(round(height_px / 0.72))))
    left, top, right, bottom = font.getbbox(text)
    image = Image.new("L", (right - left + 2, bottom - top + 2))
    ImageDraw.Draw(image).text((1 - left, 1 - top), text, font=font, fill=255)
    return np.asarray(image, dtype=np.float64) / 255.0


def rotated_mask(mask: FloatArray, angle: float, mirror: bool) -> FloatArray:
    """``mask [h, w]`` turned counter-clockwise by ``angle`` radians (as seen in the image), optionally
    mirrored left-right first; the result is enlarged to hold the whole turned mask."""
    image = Image.fromarray(np.round(mask * 255).astype(np.uint8))
    if mirror:
        image = image.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
    image = image.rotate(np.degrees(angle), resample=Image.Resampling.BILINEAR, expand=True)
    return np.asarray(image, dtype=np.float64) / 255.0


def to_uint8(rgb: FloatArray) -> NDArray[np.uint8]:
    """sRGB floats in ``[0, 1]`` (any shape) to ``uint8``."""
    return np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
