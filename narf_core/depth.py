"""The depth codec: metric depth <-> 16-bit millimetres (ROS 16UC1), 0 = no return (docs/design.md §2).

One rule for every writer (dataset PNGs, ``narf render --depth``, the service's PNGs): encoding
*saturates*, it never refuses. A depth beyond 65.535 m is written as 65535; a positive depth
rounds to the nearest millimetre but to at least 1 (it never reads back as "no return"); 0,
negative and non-finite values are "no return". A writer that must not lose such values checks
its input before encoding (the dataset writer refuses non-finite and negative depth).
"""

from __future__ import annotations

import numpy as np

DEPTH_MM_MAX = int(np.iinfo(np.uint16).max)
"""The largest 16-bit value: 65.535 m."""


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """Metres ``[H, W]`` (any float or integer dtype) -> ``uint16`` millimetres, saturating (see above)."""
    depth = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.clip(np.rint(depth * 1000.0), 1, DEPTH_MM_MAX)
    return np.where(depth > 0, mm, 0).astype(np.uint16)


def mm_to_depth(mm: np.ndarray) -> np.ndarray:
    """16-bit millimetres ``[H, W]`` -> float32 metres (0 stays "no return")."""
    return (np.asarray(mm).astype(np.float64) / 1000.0).astype(np.float32)
