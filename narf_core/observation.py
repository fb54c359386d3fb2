"""Sanity checks of an observation before the refiner trusts it.

A real view can be valid as arrays and still wrong in ways that bias an estimate without any
error: a blown-out exposure (the photometric loss then fits white), a mask cut by the image border
(the object continues outside it), depth in the wrong unit (millimetres read as metres, or metres
written into a millimetre PNG), or a depth image that does not line up with the mask. Each check
gives one warning, a string ``"<code>: <what and why>"``; :func:`usable_depth` drops the depth that
a warning says is unusable, so the refiner falls back to RGB instead of fitting a wrong distance.

Conventions as everywhere (docs/design.md §2): ``image`` sRGB uint8 ``[H, W, 3]``, ``mask`` ``[H, W]``
(nonzero = object), ``depth`` float metres ``[H, W]`` with 0 or NaN = no return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from narf_core.geometry import Pinhole

CLIPPED_SHARE = 0.10  # of the object's pixels at 255 (or at 0) in some channel
BORDER_PIXELS = 3  # object pixels on the image's outermost rows and columns
BORDER_CODE = "mask_border"  # the warning's code (a mask cut by the image's border)
DEPTH_OVERLAP_SHARE = 0.10  # least share of the object's pixels with a depth return
DEPTH_UNIT_FACTOR = 20.0  # observed vs expected distance: a wrong unit is a factor of 1000
DEPTH_RANGE_M = (0.02, 20.0)  # object distances a camera sees it at, without an expected distance

# warnings after which the depth is not used
DEPTH_UNUSABLE = ("depth_unit", "depth_overlap")

# What the depth says about a segmenter's mask (mask_evidence)
RING_PX = 4  # how far outside the mask an occluder is looked for
OCCLUDER_STEP_M = 0.015  # nearer than the object beside it by this much: something in front of it
SEAM_STEP_M = 0.005  # across the mask's edge the depth changes less than this: the surface goes on
OCCLUDED_SHARE = 0.01  # of the ring outside the mask in front of the object: an occluder touches the mask
SEAM_SHARE = 0.30  # of the pixels next to the mask on the object's surface: the edge is not the object's


def check_observation(
    image: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray | None,
    camera: Pinhole,
    *,
    expected_depth_m: float | None = None,
) -> list[str]:
    """Warnings about an observation (empty when it looks sound).

    ``expected_depth_m`` (e.g. the initial pose's z) sharpens the depth-unit check: the median
    depth over the mask must be within a factor of :data:`DEPTH_UNIT_FACTOR` of it; without it the
    median must lie in :data:`DEPTH_RANGE_M`. Arrays must already have matching shapes.
    """
    mask = np.asarray(mask) != 0
    warnings: list[str] = []
    n = int(mask.sum())
    if n == 0:
        return warnings
    pixels = np.asarray(image)[mask]
    high = float((pixels >= 255).any(-1).mean())
    low = float((pixels <= 0).all(-1).mean())
    if high > CLIPPED_SHARE:
        warnings.append(f"clipped: {100 * high:.0f}% of the object's pixels are saturated at 255 (overexposed): "
                        "their colour is lost, so the photometric fit is biased")
    if low > CLIPPED_SHARE:
        warnings.append(f"clipped: {100 * low:.0f}% of the object's pixels are black (underexposed)")
    border = int(mask[0].sum() + mask[-1].sum() + mask[1:-1, 0].sum() + mask[1:-1, -1].sum())
    if border >= BORDER_PIXELS:
        warnings.append(f"{BORDER_CODE}: the mask touches the image border on {border} pixels: the object may "
                        f"continue outside the {camera.width}x{camera.height} view, which biases the estimate")
    if depth is None:
        return warnings
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    on_object = valid & mask
    share = on_object.sum() / n
    if share < DEPTH_OVERLAP_SHARE:
        elsewhere = " (there is depth elsewhere: misaligned or from another frame?)" if valid.any() else ""
        warnings.append(f"depth_overlap: only {100 * share:.0f}% of the mask's pixels have a depth return"
                        f"{elsewhere}; the depth is not used")
        return warnings
    median = float(np.median(depth[on_object]))
    if expected_depth_m is not None and expected_depth_m > 0:
        ratio = median / expected_depth_m
        wrong = ratio > DEPTH_UNIT_FACTOR or ratio < 1 / DEPTH_UNIT_FACTOR
    else:
        ratio = None
        wrong = not DEPTH_RANGE_M[0] <= median <= DEPTH_RANGE_M[1]
    if wrong:
        guess = "millimetres read as metres" if median > (expected_depth_m or 1.0) else "metres written as millimetres"
        against = f" vs {expected_depth_m:.3g} m expected from the initial pose" if ratio is not None else ""
        warnings.append(f"depth_unit: the object's median depth is {median:.4g} m{against}; it looks like "
                        f"{guess} (depth must be metres, or a 16-bit PNG in millimetres); the depth is not used")
    return warnings


def usable_depth(depth: np.ndarray | None, warnings: list[str]) -> np.ndarray | None:
    """``depth``, or ``None`` when one of ``warnings`` says it cannot be trusted (:data:`DEPTH_UNUSABLE`)."""
    if depth is None or any(w.split(":", 1)[0] in DEPTH_UNUSABLE for w in warnings):
        return None
    return depth


@dataclass(frozen=True)
class MaskEvidence:
    """What a depth image says about a mask (:func:`mask_evidence`); shares in [0, 1].

    ``occluded``: of the pixels outside the mask within :data:`RING_PX` of it (with a return), the
    share lying :data:`OCCLUDER_STEP_M` in front of the nearest object pixel around them: an
    occluder touches the mask, so the mask is the object's visible part only. ``seam``: of the
    pixels just outside the mask (one pixel; those without a return count as no seam, since a
    stereo sensor loses many at a depth step), the share whose depth is within :data:`SEAM_STEP_M`
    of the object's beside them: the surface goes on across the mask's edge, which is therefore not
    the object's silhouette (an eroded or grown mask, a missed or an extra blob). An exact mask's
    edge is a depth step (the object in front of what lies behind it) except where the object
    touches a surface; a view without background depth (a render) gives 0 for both.
    """

    occluded: float
    seam: float

    @property
    def doubtful(self) -> bool:
        """Whether the mask should not be taken as the object's whole silhouette."""
        return self.occluded > OCCLUDED_SHARE or self.seam > SEAM_SHARE


def _min_filter(values: np.ndarray, radius: int) -> np.ndarray:
    """The minimum of ``values [h, w]`` over the ``(2 radius + 1)^2`` square about each pixel (inf outside)."""
    window = 2 * radius + 1
    padded = np.pad(values, radius, constant_values=np.inf)
    rows = np.lib.stride_tricks.sliding_window_view(padded, window, axis=0).min(-1)
    return np.lib.stride_tricks.sliding_window_view(rows, window, axis=1).min(-1)


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Boolean ``mask [..., H, W]`` dilated by a ``(2 radius + 1)^2`` square over the last two axes
    (an integral image: the cost does not grow with ``radius``)."""
    if radius <= 0:
        return mask.astype(bool, copy=True)
    h, w = mask.shape[-2:]
    pad = [(0, 0)] * (mask.ndim - 2) + [(radius + 1, radius), (radius + 1, radius)]
    s = np.pad(mask.astype(np.int32), pad).cumsum(-2).cumsum(-1)
    k = 2 * radius + 1
    return (s[..., k:, k:] - s[..., :h, k:] - s[..., k:, :w] + s[..., :h, :w]) > 0


def _around(mask: np.ndarray, radius: int) -> np.ndarray:
    """``[h, w]`` bool: the pixels outside ``mask`` within ``radius`` of it (chessboard distance)."""
    return ~mask & dilate(mask, radius)


def mask_evidence(mask: np.ndarray, depth: np.ndarray) -> MaskEvidence:
    """How far ``depth [H, W]`` (metres, 0 or NaN = no return) contradicts ``mask [H, W]`` (nonzero
    = object) as the object's whole silhouette (:class:`MaskEvidence`). Looks only at the mask's
    box grown by :data:`RING_PX`."""
    mask = np.asarray(mask) != 0
    if not mask.any():
        return MaskEvidence(0.0, 0.0)
    rows, cols = np.nonzero(mask.any(1))[0], np.nonzero(mask.any(0))[0]
    r0, c0 = max(0, rows[0] - RING_PX), max(0, cols[0] - RING_PX)
    box = (slice(r0, rows[-1] + RING_PX + 1), slice(c0, cols[-1] + RING_PX + 1))
    mask, depth = mask[box], np.asarray(depth, dtype=np.float64)[box]
    valid = np.isfinite(depth) & (depth > 0)
    object_depth = np.where(mask & valid, depth, np.inf)
    nearest = _min_filter(object_depth, RING_PX)
    ring = valid & _around(mask, RING_PX) & np.isfinite(nearest)
    occluded = ring & (depth < nearest - OCCLUDER_STEP_M)
    beside = _min_filter(object_depth, 1)
    edge = _around(mask, 1)
    seam = edge & valid & (np.abs(depth - beside) < SEAM_STEP_M)
    return MaskEvidence(float(occluded.sum() / max(ring.sum(), 1)), float(seam.sum() / max(edge.sum(), 1)))
