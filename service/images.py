"""Image codecs at the HTTP edge: PNG/JPEG in, PNG out, depth as 16-bit millimetres (docs/design.md §2).

Every decoder checks the pixel count from the file header *before* decoding, so a small file
that claims to be a huge image (a decompression bomb, a ``.npy`` header declaring any shape) is
refused without allocating it, and whatever a decoder raises on hostile bytes is a 422 naming the
part. A JPEG's EXIF orientation is applied, so the array is the image as it is meant to be seen.
"""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
from PIL import Image, ImageOps

from narf_core.depth import mm_to_depth
from narf_service.errors import ApiError, invalid

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
NPY_MAGIC = b"\x93NUMPY"


def _open(data: bytes, field: str, max_pixels: int, formats: tuple[str, ...]) -> Image.Image:
    if not data:
        raise invalid(field, "empty file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data), formats=list(formats))
    except (Image.DecompressionBombWarning, Image.DecompressionBombError):
        raise ApiError(413, f"{field}: image exceeds the limit of {max_pixels} pixels", field=field) from None
    except Exception:  # whatever a decoder raises on hostile bytes (OSError, SyntaxError, struct.error, ...)
        raise invalid(field, f"not a readable {' or '.join(formats)} image") from None
    w, h = image.size
    if w * h > max_pixels:
        raise ApiError(413, f"{field}: {w}x{h} = {w * h} pixels exceeds the limit of {max_pixels}", field=field)
    if w == 0 or h == 0:
        raise invalid(field, f"image has no pixels ({w}x{h})")
    try:
        image.load()
    except Exception:
        raise invalid(field, f"truncated or corrupt {image.format} data") from None
    return image


def decode_rgb(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """PNG or JPEG bytes -> ``uint8 [H, W, 3]``; RGB, RGBA (alpha dropped) or palette images."""
    image = _open(data, field, max_pixels, ("PNG", "JPEG"))
    if image.mode not in ("RGB", "RGBA", "P"):
        raise invalid(field, f"expected an RGB image, got mode {image.mode!r}")
    try:
        image = ImageOps.exif_transpose(image)  # a phone's JPEG is stored sideways, with an orientation tag
    except Exception:
        raise invalid(field, "corrupt EXIF data") from None
    return np.array(image.convert("RGB"), dtype=np.uint8)  # a writable copy: torch.from_numpy needs one


def decode_mask(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """Single-channel PNG bytes -> ``bool [H, W]`` (non-zero = object)."""
    image = _open(data, field, max_pixels, ("PNG",))
    if image.mode not in ("1", "L", "P", "I;16", "I"):
        raise invalid(field, f"expected a single-channel PNG mask, got mode {image.mode!r}")
    return np.asarray(image) != 0


def decode_depth(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """16-bit PNG millimetres or ``.npy`` float metres -> float32 metres ``[H, W]``, 0 = no return.

    NaN and +-inf (ROS 32FC1's "no return" markers) become 0; negative depths are an error.
    """
    if data.startswith(NPY_MAGIC):
        array = _read_npy(data, field, max_pixels)
        depth = np.where(np.isfinite(array), array, 0).astype(np.float32)
    elif data.startswith(PNG_MAGIC):
        image = _open(data, field, max_pixels, ("PNG",))
        if image.mode not in ("I;16", "I", "I;16B"):
            raise invalid(field, f"expected a 16-bit PNG in millimetres, got mode {image.mode!r}")
        depth = mm_to_depth(np.asarray(image))
    else:
        raise invalid(field, "expected a 16-bit PNG (millimetres) or a .npy float32 array (metres)")
    if (depth < 0).any():
        raise invalid(field, f"negative depth ({float(depth.min()):.3g} m)")
    return depth


def _read_npy(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """A ``.npy`` float array ``[H, W]``, its header checked (shape, dtype, pixel count, byte count)
    before any allocation: the header alone can ask for any size."""
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read_header:
            raise ValueError(f"unsupported .npy version {version}")
        shape, fortran_order, dtype = read_header[version](stream)
    except (ValueError, OSError, EOFError, SyntaxError, TypeError, MemoryError):
        raise invalid(field, "not a readable .npy array") from None
    if len(shape) != 2 or dtype.kind != "f" or dtype.hasobject:
        raise invalid(field, f"expected a 2-D float array in metres, got {dtype} {list(shape)}")
    pixels = math.prod(shape)
    if pixels > max_pixels:
        raise ApiError(413, f"{field}: {pixels} pixels exceeds the limit of {max_pixels}", field=field)
    if pixels == 0:
        raise invalid(field, f"array has no pixels ({list(shape)})")
    if len(data) - stream.tell() != pixels * dtype.itemsize:
        needed = pixels * dtype.itemsize
        raise invalid(field, f"truncated or padded .npy data: {list(shape)} {dtype} needs {needed} bytes")
    array = np.frombuffer(data, dtype=dtype, count=pixels, offset=stream.tell())
    return array.reshape(shape, order="F" if fortran_order else "C")


def encode_png(array: np.ndarray) -> bytes:
    """``uint8 [H, W, 3]``, ``uint8 [H, W]`` or ``uint16 [H, W]`` -> PNG bytes (fast compression)."""
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def rgb_to_uint8(rgb: np.ndarray) -> np.ndarray:
    """float ``[H, W, 3]`` in [0, 1] -> sRGB ``uint8``; non-finite values become 0."""
    rgb = np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0)
    return np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)


def opacity_to_uint8(opacity: np.ndarray) -> np.ndarray:
    """float ``[H, W]`` in [0, 1] -> ``uint8`` (255 = opaque)."""
    return rgb_to_uint8(opacity)


