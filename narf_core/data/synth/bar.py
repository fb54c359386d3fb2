"""The grey bar that sweeps across the object in a sequence with events (:mod:`narf_core.data.synth.sequence`):
a stand-in for an arm or a cable between the camera and the object, a fifth of the image's width, full height.
pybullet's frames get it when they are drawn (:func:`occlude`); ``narf restyle``'s path-traced frames of the same
sequence get it from the sequence's record (:func:`occlude_linear`), so that both hide the same pixels."""

from __future__ import annotations

import numpy as np

from narf_core.data.dataset import FrameImages

GREY = 90  # the bar's colour in pybullet's frames (sRGB, uint8)
# ... and its reflectance in a path-traced frame, where its brightness follows the image's (the same light falls on it)
_ALBEDO = 0.35


def bar_columns(width: int, centre_x: float) -> slice:
    """The image columns of the bar (a fifth of the ``width``) centred at ``centre_x`` (a fraction of the width):
    those inside the image, none where the bar lies beside it (it sweeps in from beyond one edge)."""
    half = max(1, width // 10)
    cx = int(round(centre_x * width))
    start = min(max(0, cx - half), width)
    return slice(start, max(start, min(width, cx + half)))


def bar_depth(T_cam_obj: np.ndarray, radius: float) -> float:
    """The bar's distance from the camera (m): two object radii in front of the object's origin."""
    return max(0.05, float(np.linalg.norm(T_cam_obj[:3, 3])) - 2 * radius)


def occlude(images: FrameImages, centre_x: float, bar_z: float) -> tuple[FrameImages, float]:
    """``images`` (sRGB uint8) with the bar at ``centre_x`` and ``bar_z`` metres from the camera, and the fraction of
    the object's pixels it hides (its pixels are background in the labels and carry its depth)."""
    cols = bar_columns(images.labels.shape[1], centre_x)
    visible_before = int(np.count_nonzero(images.labels))
    rgb, labels = images.rgb.copy(), images.labels.copy()
    depth = None if images.depth is None else images.depth.copy()
    rgb[:, cols] = GREY
    labels[:, cols] = 0
    if depth is not None:
        depth[:, cols] = bar_z
    hidden = visible_before - int(np.count_nonzero(labels))
    return FrameImages(rgb, depth, labels), hidden / visible_before if visible_before else 0.0


def occlude_linear(linear: np.ndarray, depth: np.ndarray, labels: np.ndarray, centre_x: float,
                   bar_z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A path-traced frame (linear RGB ``[H, W, 3]``, z-depth ``[H, W]``, labels ``[H, W]``) with the bar drawn as
    :func:`occlude` draws it, a matte grey lit like the rest of the image."""
    from narf_core.data.synth.faults import light_level  # (the realism extra's: scipy; pybullet's frames need none)

    cols = bar_columns(labels.shape[1], centre_x)
    linear, depth, labels = linear.copy(), depth.copy(), labels.copy()
    linear[:, cols] = _ALBEDO * light_level(linear)
    depth[:, cols] = bar_z
    labels[:, cols] = 0
    return linear, depth, labels
