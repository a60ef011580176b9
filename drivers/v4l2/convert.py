"""Pixel conversions from V4L2 buffer layouts to the frames of ``lightprobe.drivers.base``.

Pure functions, bytes in, arrays out. Processed formats (YUYV 4:2:2, MJPEG, GREY) become (H, W, 3)
uint8 RGB; Bayer formats become (H, W, 3) demosaiced RGB with the bit depth of the sensor: uint8
for 8-bit Bayer, uint16 for 10/12/16-bit (V4L2 stores those little-endian in 16-bit containers,
value in the low bits). Demosaicing is OpenCV's bilinear, which is linear in the input, so a raw
stream stays linear (the black level is still in: ``Frame.black_level``).

A corrupt MJPEG buffer (UVC cameras deliver truncated JPEGs when the bus drops packets) raises
:class:`CorruptFrame`; the camera drops it and counts it like a dropped frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from ._structs import (
    BAYER_FORMATS,
    V4L2_PIX_FMT_GREY,
    V4L2_PIX_FMT_MJPEG,
    V4L2_PIX_FMT_RGB24,
    V4L2_PIX_FMT_YUYV,
    fourcc_str,
)

__all__ = ["SUPPORTED_FORMATS", "CorruptFrame", "bayer_to_rgb", "buffer_to_rgb", "mosaic"]

# Bayer pattern (top-left 2x2 block read row-wise, the V4L2/libcamera naming) -> OpenCV code.
_BAYER_CV = {
    "RGGB": cv2.COLOR_BayerRGGB2RGB,
    "BGGR": cv2.COLOR_BayerBGGR2RGB,
    "GRBG": cv2.COLOR_BayerGRBG2RGB,
    "GBRG": cv2.COLOR_BayerGBRG2RGB,
}
SUPPORTED_FORMATS = frozenset(
    {V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_RGB24, *BAYER_FORMATS}
)


class CorruptFrame(ValueError):
    """A buffer that does not decode (truncated MJPEG, short buffer)."""


def _plane(buf: bytes | memoryview, width: int, height: int, bytesperline: int, bpp: int,
           dtype: type[np.generic] = np.uint8) -> np.ndarray:  # fmt: skip
    """View rows of ``bpp`` bytes per pixel, honouring the driver's line stride."""
    stride = bytesperline or width * bpp
    need = stride * (height - 1) + width * bpp
    if len(buf) < need:
        raise CorruptFrame(f"buffer has {len(buf)} bytes, {need} needed for {width}x{height}")
    raw = np.frombuffer(buf, np.uint8, count=stride * height if len(buf) >= stride * height else need)
    rows = np.lib.stride_tricks.as_strided(raw, (height, width * bpp), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width, -1)


def bayer_to_rgb(mosaic_img: np.ndarray, pattern: str) -> np.ndarray:
    """Demosaic a (H, W) uint8/uint16 Bayer image (pattern as V4L2 names it) to (H, W, 3) RGB."""
    if pattern not in _BAYER_CV:
        raise ValueError(f"unknown Bayer pattern {pattern!r}")
    return np.ascontiguousarray(cv2.cvtColor(mosaic_img, _BAYER_CV[pattern]))


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Sample an (H, W, 3) RGB image through a Bayer colour filter (the inverse, for tests/sims)."""
    out = np.empty(rgb.shape[:2], rgb.dtype)
    ch = {"R": 0, "G": 1, "B": 2}
    for dy in range(2):
        for dx in range(2):
            out[dy::2, dx::2] = rgb[dy::2, dx::2, ch[pattern[2 * dy + dx]]]
    return out


def buffer_to_rgb(buf: bytes | memoryview, pixelformat: int, width: int, height: int,
                  bytesperline: int = 0) -> np.ndarray:  # fmt: skip
    """Convert one dequeued buffer (``bytesused`` bytes) to an (H, W, 3) RGB array.

    Returns uint8 for YUYV, MJPEG, GREY, RGB24 and 8-bit Bayer; uint16 for 10/12/16-bit Bayer.
    Raises CorruptFrame for a buffer that is too short or does not decode, ValueError for a
    pixel format we do not convert.
    """
    if pixelformat == V4L2_PIX_FMT_YUYV:
        yuyv = _plane(buf, width, height, bytesperline, 2)
        return cv2.cvtColor(yuyv.reshape(height, width, 2), cv2.COLOR_YUV2RGB_YUYV)
    if pixelformat == V4L2_PIX_FMT_MJPEG:
        data = np.frombuffer(buf, np.uint8)
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size > 4 else None
        if bgr is None or bgr.shape[:2] != (height, width):
            raise CorruptFrame(f"MJPEG buffer of {data.size} bytes does not decode to {width}x{height}")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if pixelformat == V4L2_PIX_FMT_GREY:
        grey = _plane(buf, width, height, bytesperline, 1)[..., 0]
        return np.repeat(grey[..., None], 3, axis=2)
    if pixelformat == V4L2_PIX_FMT_RGB24:
        return _plane(buf, width, height, bytesperline, 3).copy()
    if pixelformat in BAYER_FORMATS:
        pattern, bits = BAYER_FORMATS[pixelformat]
        if bits == 8:
            return bayer_to_rgb(_plane(buf, width, height, bytesperline, 1)[..., 0], pattern)
        raw = _plane(buf, width, height, bytesperline, 2, np.dtype("<u2").type)[..., 0]
        return bayer_to_rgb(raw.astype(np.uint16), pattern)
    raise ValueError(f"pixel format {fourcc_str(pixelformat)!r} is not supported")
