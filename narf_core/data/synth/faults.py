"""What a real camera, depth sensor and segmenter do to a clean rendered view, as array functions.

Every function takes arrays and a ``numpy.random.Generator`` (when it draws anything) and returns
new arrays, so each effect can be tested on its own and any subset applied in order by
:func:`apply_faults`. Conventions: ``linear`` is scene-referred linear RGB float ``[H, W, 3]``
(before the camera's tone curve), ``rgb`` sRGB uint8 ``[H, W, 3]``, ``depth`` metric z-depth float32
``[H, W]`` with 0 = no return, ``mask`` bool ``[H, W]`` (the tool's visible pixels), ``labels``
uint8 ``[H, W]`` (0 = background, 1 + i = link i).

Named conditions (:data:`CONDITIONS`) are the sets the shift benchmark measures; each adds faults to
the physically-based render (``lighting``: the render itself, exposed and encoded, nothing more).
The random draws of each effect come from their own stream of the frame's seed, so a condition
that adds one effect leaves the draws of the others unchanged (``all`` has the same noise as
``noise``, the same occluder as ``occlusion-20``).
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from PIL import Image
from scipy import ndimage

# ------------------------------------------------------------------------------------------------
# camera: exposure, white balance, blur, noise, tone curve, JPEG


def auto_exposure(
    linear: np.ndarray, mean: float = 0.18, highlight: float = 0.95, percentile: float = 99.5
) -> np.ndarray:
    """Scale ``linear`` as a camera's auto-exposure does: the frame's mean luminance to ``mean``
    (middle grey), but no further than keeps its ``percentile`` luminance at ``highlight`` (highlight
    priority, so that the lighting alone rarely clips)."""
    luminance = linear @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    average, high = float(luminance.mean()), float(np.percentile(luminance, percentile))
    if average <= 0:
        return linear.astype(np.float32)
    return (linear * min(mean / average, highlight / high if high > 0 else np.inf)).astype(np.float32)


def exposure_white_balance(linear: np.ndarray, exposure_ev: float, gains: tuple[float, float, float]) -> np.ndarray:
    """An exposure off by ``exposure_ev`` stops and a white balance off by per-channel ``gains``."""
    return (linear * (2.0**exposure_ev) * np.asarray(gains, dtype=np.float32)).astype(np.float32)


def lens_blur(linear: np.ndarray, sigma_px: float) -> np.ndarray:
    """Defocus / small motion: a Gaussian of ``sigma_px`` pixels over each channel."""
    if sigma_px <= 0:
        return linear
    return ndimage.gaussian_filter(linear, sigma=(sigma_px, sigma_px, 0), mode="nearest").astype(np.float32)


def shot_read_noise(linear: np.ndarray, rng: np.random.Generator, full_well: float, read_std: float) -> np.ndarray:
    """Photon shot noise (Poisson, ``full_well`` electrons at linear 1.0) plus Gaussian read noise
    (``read_std`` in linear units): the variance grows as ``x / full_well + read_std^2``."""
    electrons = rng.poisson(np.clip(linear, 0, None) * full_well).astype(np.float32)
    return (electrons / full_well + rng.normal(0.0, read_std, linear.shape)).astype(np.float32)


def to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear RGB to sRGB uint8, clipping what the sensor saturates."""
    x = np.clip(linear, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB uint8 to linear float32 (inverse of :func:`to_srgb` before clipping and rounding)."""
    x = rgb.astype(np.float32) / 255
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    """``rgb`` through a JPEG encode and decode at ``quality`` (1-95)."""
    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="JPEG", quality=int(quality))
    buffer.seek(0)
    with Image.open(buffer) as im:
        return np.asarray(im.convert("RGB")).copy()


# ------------------------------------------------------------------------------------------------
# depth sensor: stereo-like noise, holes, quantisation


def stereo_depth_noise(
    depth: np.ndarray, rng: np.random.Generator, fx: float, baseline_m: float, disparity_std_px: float
) -> np.ndarray:
    """Depth from a noisy disparity ``d = fx * baseline / z + N(0, disparity_std_px)``: the error's
    std grows as ``z^2 * disparity_std_px / (fx * baseline)``. Pixels without a return stay 0."""
    valid = depth > 0
    disparity = np.where(valid, fx * baseline_m / np.where(valid, depth, 1.0), 0.0)
    disparity = disparity + rng.normal(0.0, disparity_std_px, depth.shape)
    ok = valid & (disparity > 0)
    return np.where(ok, fx * baseline_m / np.where(ok, disparity, 1.0), 0.0).astype(np.float32)


def depth_discontinuities(depth: np.ndarray, jump_m: float) -> np.ndarray:
    """Pixels ``[H, W]`` bool next to a depth jump larger than ``jump_m`` (or next to no return)."""
    padded = np.pad(depth, 1, mode="edge")
    edge = np.zeros(depth.shape, dtype=bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        neighbour = padded[dy : dy + depth.shape[0], dx : dx + depth.shape[1]]
        edge |= np.abs(neighbour - depth) > jump_m
    return edge & (depth > 0)


def thin_parts(mask: np.ndarray, width_px: int) -> np.ndarray:
    """Pixels of ``mask`` in structures narrower than about ``2 * width_px + 1`` pixels (what a
    morphological opening with a disc of radius ``width_px`` removes)."""
    if width_px <= 0:
        return np.zeros_like(mask, dtype=bool)
    opened = ndimage.binary_opening(mask, structure=_disc(width_px))
    return mask & ~opened


def depth_holes(
    depth: np.ndarray,
    mask: np.ndarray,
    rng: np.random.Generator,
    *,
    edge_px: int,
    edge_drop: float,
    thin_px: int,
    speckle: float,
    jump_m: float = 0.02,
) -> np.ndarray:
    """Missing returns where stereo matching fails: within ``edge_px`` of a depth discontinuity
    (each pixel dropped with probability ``edge_drop``), on the parts of ``mask`` thinner than
    about ``2 * thin_px + 1`` pixels (all dropped), and anywhere with probability ``speckle``."""
    edges = depth_discontinuities(depth, jump_m)
    if edge_px > 1:
        edges = ndimage.binary_dilation(edges, structure=_disc(edge_px - 1))
    drop = edges & (rng.random(depth.shape) < edge_drop)
    drop |= thin_parts(mask, thin_px)
    drop |= rng.random(depth.shape) < speckle
    return np.where(drop, 0.0, depth).astype(np.float32)


def quantise_depth(depth: np.ndarray, step_m: float = 1e-3) -> np.ndarray:
    """Depth rounded to multiples of ``step_m`` (a sensor's 1 mm output); 0 stays 0."""
    return (np.round(depth / step_m) * step_m).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# segmenter: mask errors


def _disc(radius: int) -> np.ndarray:
    y, x = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return x * x + y * y <= radius * radius


def grow_mask(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` dilated by a disc of ``px`` pixels (eroded for ``px < 0``)."""
    if px == 0:
        return mask.copy()
    op = ndimage.binary_dilation if px > 0 else ndimage.binary_erosion
    return op(mask, structure=_disc(abs(px)))


def mask_blob(mask: np.ndarray, rng: np.random.Generator, radius_px: float, extra: bool) -> np.ndarray:
    """A segmenter's blob error: a disc of ``radius_px`` removed around a random mask pixel (a
    missed jaw), or (``extra``) added just outside the mask (a neighbouring object taken for tool)."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return mask.copy()
    h, w = mask.shape
    yy, xx = np.mgrid[0:h, 0:w]
    if extra:
        ring = ndimage.binary_dilation(mask, structure=_disc(max(1, round(radius_px)))) & ~mask
        ys, xs = np.nonzero(ring)
    i = rng.integers(len(ys))
    disc = (yy - ys[i]) ** 2 + (xx - xs[i]) ** 2 <= radius_px**2
    return mask | disc if extra else mask & ~disc


def soft_edge_mask(mask: np.ndarray, rng: np.random.Generator, sigma_px: float, wobble: float) -> np.ndarray:
    """A segmenter's soft, uneven boundary: the mask blurred by ``sigma_px`` and thresholded at a
    level that varies smoothly over the image in ``0.5 ± wobble`` (so the edge bleeds out in some
    places and eats in at others)."""
    soft = ndimage.gaussian_filter(mask.astype(np.float32), sigma_px)
    field_ = ndimage.gaussian_filter(rng.normal(size=mask.shape).astype(np.float32), 4 * sigma_px + 4)
    field_ /= max(float(np.abs(field_).max()), 1e-12)
    return soft > 0.5 + wobble * field_


# ------------------------------------------------------------------------------------------------
# occluders


def occluder_region(mask: np.ndarray, rng: np.random.Generator, fraction: float,
                    direction: float | None = None) -> np.ndarray:
    """A lumpy blob ``[H, W]`` bool (a hand, another tool) that covers ``fraction`` of ``mask``'s pixels.

    The blob is star-shaped about a centre on the mask's edge with a random smooth radius profile;
    it is scaled so that exactly the asked share of mask pixels falls inside (the ``fraction``
    quantile of the mask pixels' normalised distances), so the hidden share matches up to pixel
    rounding. The centre is a random edge pixel, or with ``direction`` (radians, image axes) the edge
    pixel in that direction from the mask's centroid: the same draws and a direction that turns
    slowly give one occluder moving round the tool (a sequence's, :func:`apply_faults`).
    """
    if fraction <= 0 or not mask.any():
        return np.zeros_like(mask, dtype=bool)
    ys, xs = np.nonzero(mask)
    edge = mask & ~ndimage.binary_erosion(mask)
    eys, exs = np.nonzero(edge if edge.any() else mask)
    i = rng.integers(len(eys))  # drawn in either case: the shape's draws below stay the same
    if direction is not None:
        bearing = np.arctan2(eys - ys.mean(), exs - xs.mean())
        i = int(np.argmin(np.abs(np.angle(np.exp(1j * (bearing - direction))))))
    cy, cx = float(eys[i]), float(exs[i])
    h, w = mask.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    angle = np.arctan2(yy - cy, xx - cx)
    profile = np.ones_like(angle)
    for k in (1, 2, 3):
        profile += rng.uniform(0.0, 0.25 / k) * np.cos(k * angle + rng.uniform(0, 2 * np.pi))
    stretch = rng.uniform(0.5, 1.0)  # elongated, at a random orientation
    tilt = rng.uniform(0, np.pi)
    u = (xx - cx) * np.cos(tilt) + (yy - cy) * np.sin(tilt)
    v = -(xx - cx) * np.sin(tilt) + (yy - cy) * np.cos(tilt)
    distance = np.hypot(u, v / stretch) / profile
    scale = np.quantile(distance[ys, xs], min(fraction, 1.0))
    return distance <= scale


def light_level(linear: np.ndarray) -> float:
    """The brightness a matte surface of reflectance 1 takes in ``linear`` (RGB ``[H, W, 3]``) where it stands in
    front of the scene: the same light falls on it, so it follows the image's (its 75th percentile over 0.45)."""
    return float(np.percentile(linear.mean(-1), 75)) / 0.45


def composite_occluder(
    linear: np.ndarray, depth: np.ndarray, region: np.ndarray, rng: np.random.Generator, tool_depth: float
) -> tuple[np.ndarray, np.ndarray]:
    """Paint an occluder over ``region``: a matte, softly shaded surface of a random colour with
    fine texture in ``linear``, and in ``depth`` a tilted plane 5-15 cm in front of ``tool_depth``.
    Its brightness follows the image's (the same light falls on it)."""
    if not region.any():
        return linear, depth
    h, w = region.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    colour = rng.uniform(0.15, 0.7, 3).astype(np.float32)
    slope = rng.uniform(-1, 1, 2) * np.pi / max(h, w)
    gradient = 0.75 + 0.25 * np.cos(rng.uniform(0, 2 * np.pi) + xx * slope[0] + yy * slope[1])
    texture = 1.0 + 0.08 * ndimage.gaussian_filter(rng.normal(size=(h, w)).astype(np.float32), 1.5) / 0.2
    paint = colour[None, None] * (gradient * texture)[..., None] * light_level(linear)
    out = np.where(region[..., None], paint.astype(np.float32), linear)
    z0 = max(tool_depth - rng.uniform(0.05, 0.15), 0.05)
    plane = z0 + 0.05 * ((xx - w / 2) * rng.uniform(-1, 1) + (yy - h / 2) * rng.uniform(-1, 1)) / max(h, w)
    return out, np.where(region, plane, depth).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# conditions


@dataclass(frozen=True)
class FaultOptions:
    """Which faults to apply and how strong (the defaults are a mid-range consumer RGB-D camera
    with a learnt segmenter). Each group is off unless its flag is set. Sizes in pixels are the native
    camera's (``native_fx``, 640x480) and scale with a view's own ``fx`` (:func:`apply_faults`)."""

    sensor: bool = False  # exposure/white balance off, blur, shot + read noise, JPEG
    exposure_ev: tuple[float, float] = (-0.7, 0.7)  # drawn uniformly
    white_balance: float = 0.12  # per-channel gain in 1 ± this
    blur_px: tuple[float, float] = (0.3, 1.0)
    full_well: float = 2000.0  # electrons at linear 1.0
    read_std: float = 0.004
    jpeg_quality: tuple[int, int] = (70, 92)
    depth: bool = False  # stereo noise, holes, 1 mm quantisation
    baseline_m: float = 0.05
    disparity_std_px: float = 0.08  # at the camera's native 640x480 (scaled with fx)
    native_fx: float = 536.5  # fx of the sensor whose disparity noise is given
    edge_px: int = 2
    edge_drop: float = 0.6
    thin_px: int = 1
    speckle: float = 0.01
    depth_step_m: float = 1e-3
    mask: bool = False  # boundary erosion/dilation, a missing or extra blob, a soft edge
    mask_grow_px: tuple[int, int] = (-2, 2)
    blob_radius: float = 0.06  # of the mask's bounding-box diagonal
    soft_sigma_px: float = 1.5
    soft_wobble: float = 0.25
    occlusion: float = 0.0  # share of the tool's visible pixels hidden by an occluder

    def to_json(self) -> dict:
        return asdict(self)


CONDITIONS: dict[str, FaultOptions] = {
    "lighting": FaultOptions(),
    "noise": FaultOptions(sensor=True),
    "depth": FaultOptions(depth=True),
    "mask": FaultOptions(mask=True),
    "occlusion-20": FaultOptions(occlusion=0.2),
    "occlusion-40": FaultOptions(occlusion=0.4),
    "all": FaultOptions(sensor=True, depth=True, mask=True, occlusion=0.2),
}

# Bumped when a condition's faults change for the same seed, so that cached sets are remade
# (2: the occluder lies in front of every part it hides, not only of the tool's median depth;
# 3: pixel sizes scale with the camera's resolution: unchanged at the native 640x480;
# 4: a sequence's occluder is one object moving round the tool, not one drawn anew in every frame;
# 5: a sequence synthesised with events keeps its own occluding bar in its restyled frames).
VERSION = 5

# independent random streams per effect, so that conditions share the draws of the effects they share
_STREAMS = {"exposure": 1, "blur": 2, "noise": 3, "jpeg": 4, "depth": 5, "holes": 6, "mask": 7, "occluder": 8,
            "occluder_path": 9}

# A sequence's occluder turns round the tool's silhouette at a speed drawn from this range (degrees per
# second, either way): a hand or another object that moves, not one that jumps from frame to frame.
OCCLUDER_TURN_DEG_S = (10.0, 40.0)


@dataclass
class Faulted:
    """A faulty observation (what the refiner is given) and the clean one it came from."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    clean_depth: np.ndarray
    clean_labels: np.ndarray
    info: dict = field(default_factory=dict)


def apply_faults(
    linear: np.ndarray,
    depth: np.ndarray,
    labels: np.ndarray,
    options: FaultOptions,
    seed: tuple[int, ...],
    fx: float,
    sequence_seed: tuple[int, ...] | None = None,
    time: float = 0.0,
) -> Faulted:
    """The observation a camera (``fx`` pixels) and segmenter would give of a clean render.

    The options' sizes in pixels (blur, mask growth and soft edge, depth holes' widths, disparity noise)
    are those of the native camera (``options.native_fx``) and scale with ``fx``: a view drawn at a
    quarter of its resolution gets the faults of the native image seen at that resolution (a 2-pixel
    segmenter error at 640x480 is half a pixel at 160x120, not two pixels of a thin tool four times
    coarser).

    Each effect draws from its own stream of ``seed``. A frame of a sequence (``sequence_seed`` given, the
    frame at ``time`` seconds) draws what stays through the sequence from that seed instead: the camera's
    exposure and white-balance error, and the occluder (its shape, colour and place in depth), which
    turns round the tool at a speed of :data:`OCCLUDER_TURN_DEG_S`.

    Order: occluder (into the scene: it is lit, exposed and seen by the depth sensor), auto-exposure,
    exposure/white balance error, blur, shot + read noise, tone curve to sRGB, JPEG; depth noise,
    holes, quantisation; labels lose the occluded pixels, then mask errors (the wrong pixels take
    the nearest link's label). ``info`` records the drawn values.
    """
    def rng(name: str, base: tuple[int, ...] = seed) -> np.random.Generator:
        return np.random.default_rng([*base, _STREAMS[name]])

    o, info = options, {}
    px = fx / o.native_fx  # this camera's pixels per native pixel
    mask = labels > 0
    linear, z = linear.astype(np.float32), depth.astype(np.float32)
    if o.occlusion > 0:
        direction, occluder_seed = None, seed
        if sequence_seed is not None:
            path, occluder_seed = rng("occluder_path", sequence_seed), sequence_seed
            speed = np.radians(path.uniform(*OCCLUDER_TURN_DEG_S)) * path.choice((-1.0, 1.0))
            direction = float(path.uniform(0, 2 * np.pi) + speed * time)
            info["occluder_direction_deg"] = float(np.degrees(direction) % 360)
        region = occluder_region(mask, rng("occluder", occluder_seed), o.occlusion, direction)
        tool_z = float(np.median(depth[mask & (depth > 0)])) if (mask & (depth > 0)).any() else 1.0
        hidden = region & mask & (depth > 0)
        if hidden.any():  # in front of every part it hides, also of a tool seen obliquely (nearer than its median)
            tool_z = min(tool_z, float(depth[hidden].min()))
        linear, z = composite_occluder(linear, z, region, rng("occluder", occluder_seed), tool_z)
        info["occluded"] = float((region & mask).sum() / max(mask.sum(), 1))
        visible = mask & ~region
    else:
        visible = mask
    linear = auto_exposure(linear)
    if o.sensor:
        r = rng("exposure", seed if sequence_seed is None else sequence_seed)
        ev = float(r.uniform(*o.exposure_ev))
        gains = tuple(float(g) for g in 1 + r.uniform(-o.white_balance, o.white_balance, 3))
        linear = exposure_white_balance(linear, ev, gains)
        sigma = float(rng("blur").uniform(*o.blur_px)) * px
        linear = lens_blur(linear, sigma)
        linear = shot_read_noise(linear, rng("noise"), o.full_well, o.read_std)
        quality = int(rng("jpeg").integers(o.jpeg_quality[0], o.jpeg_quality[1] + 1))
        rgb = jpeg(to_srgb(linear), quality)
        info.update(exposure_ev=ev, white_balance=list(gains), blur_px=sigma, jpeg_quality=quality)
    else:
        rgb = to_srgb(linear)
    if o.depth:
        disparity_std = o.disparity_std_px * px
        z = stereo_depth_noise(z, rng("depth"), fx, o.baseline_m, disparity_std)
        z = depth_holes(z, visible, rng("holes"), edge_px=round(o.edge_px * px), edge_drop=o.edge_drop,
                        thin_px=round(o.thin_px * px),
                        speckle=o.speckle)
        z = quantise_depth(z, o.depth_step_m)
    out_mask = visible
    if o.mask:
        r = rng("mask")
        grow = round(int(r.integers(o.mask_grow_px[0], o.mask_grow_px[1] + 1)) * px)
        thickest = float(ndimage.distance_transform_edt(visible).max()) if visible.any() else 0.0
        grow = max(grow, -int(thickest // 3))  # erosion never wipes out a small (far, low-resolution) tool
        out_mask = grow_mask(out_mask, grow)
        ys, xs = np.nonzero(visible)
        diagonal = float(np.hypot(np.ptp(ys), np.ptp(xs))) if len(ys) else 0.0
        extra = bool(r.random() < 0.5)
        out_mask = mask_blob(out_mask, r, o.blob_radius * diagonal, extra)
        out_mask = soft_edge_mask(out_mask, r, o.soft_sigma_px * px, o.soft_wobble)
        info.update(mask_grow_px=grow, blob="extra" if extra else "missing")
    out_labels = _labels_for(np.where(visible, labels, 0).astype(np.uint8), out_mask)
    return Faulted(rgb, z, out_labels, depth.astype(np.float32), labels.copy(), info)


def _labels_for(labels: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Labels on ``mask``'s pixels: each pixel takes the label of the nearest labelled pixel."""
    if not labels.any():
        return np.zeros_like(labels)
    _, (iy, ix) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    return np.where(mask, labels[iy, ix], 0).astype(np.uint8)


def condition(name: str) -> FaultOptions:
    """The fault options of a named condition (:data:`CONDITIONS`)."""
    if name not in CONDITIONS:
        raise ValueError(f"unknown condition {name!r}; choose from {', '.join(CONDITIONS)}")
    return replace(CONDITIONS[name])
