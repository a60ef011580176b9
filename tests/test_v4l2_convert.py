"""Pixel conversions (lightprobe.drivers.v4l2.convert): YUYV, MJPEG, GREY, RGB24, Bayer 8/10/12/16-bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lightprobe.drivers.v4l2 import _structs as S
from lightprobe.drivers.v4l2.convert import CorruptFrame, bayer_to_rgb, buffer_to_rgb, mosaic
from lightprobe.sim.v4l2_fake import rgb_to_yuyv

RNG = np.random.default_rng(1234)


def _smooth(h: int, w: int) -> np.ndarray:
    """A smooth RGB image (chroma constant over pixel pairs, so 4:2:2 loses nothing)."""
    small = RNG.integers(20, 236, (h // 8, w // 8, 3), dtype=np.uint8)
    return np.repeat(np.repeat(small, 8, axis=0), 8, axis=1)


def test_yuyv_with_line_stride() -> None:
    rgb = _smooth(48, 64)
    yuyv = rgb_to_yuyv(rgb)  # (48, 64, 2)
    stride = 64 * 2 + 32
    buf = np.zeros((48, stride), np.uint8)
    buf[:, : 64 * 2] = yuyv.reshape(48, -1)
    out = buffer_to_rgb(buf.tobytes(), S.V4L2_PIX_FMT_YUYV, 64, 48, stride)
    assert out.shape == (48, 64, 3)
    assert out.dtype == np.uint8
    assert np.abs(out.astype(int) - rgb).max() <= 2


def test_mjpeg_and_corrupt_mjpeg() -> None:
    rgb = _smooth(48, 64)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 98])
    assert ok
    out = buffer_to_rgb(jpg.tobytes(), S.V4L2_PIX_FMT_MJPEG, 64, 48)
    assert np.median(np.abs(out.astype(int) - rgb)) <= 2  # 4:2:0 chroma blurs only block edges
    with pytest.raises(CorruptFrame):
        buffer_to_rgb(jpg.tobytes()[:40], S.V4L2_PIX_FMT_MJPEG, 64, 48)
    with pytest.raises(CorruptFrame):  # decodes, but to the wrong size
        buffer_to_rgb(jpg.tobytes(), S.V4L2_PIX_FMT_MJPEG, 32, 48)


def test_grey_rgb24_and_short_buffers() -> None:
    grey = RNG.integers(0, 256, (10, 12), dtype=np.uint8)
    out = buffer_to_rgb(grey.tobytes(), S.V4L2_PIX_FMT_GREY, 12, 10)
    assert (out == grey[..., None]).all()
    rgb = RNG.integers(0, 256, (10, 12, 3), dtype=np.uint8)
    assert (buffer_to_rgb(rgb.tobytes(), S.V4L2_PIX_FMT_RGB24, 12, 10) == rgb).all()
    with pytest.raises(CorruptFrame):
        buffer_to_rgb(grey.tobytes()[:-1], S.V4L2_PIX_FMT_GREY, 12, 10)
    with pytest.raises(ValueError, match="not supported"):
        buffer_to_rgb(b"\0" * 240, S.fourcc("NV12"), 12, 10)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("bits", [8, 10, 12, 16])
def test_bayer_patterns_recover_flat_colour(pattern: str, bits: int) -> None:
    """A flat colour through each CFA and back: exact in the interior, for every pattern/depth."""
    white = (1 << bits) - 1
    colour = np.array([0.8, 0.5, 0.2]) * white
    dtype = np.uint8 if bits == 8 else np.uint16
    rgb = np.broadcast_to(colour.astype(dtype), (16, 20, 3)).copy()
    raw = mosaic(rgb, pattern)
    code = next(k for k, (p, b) in S.BAYER_FORMATS.items() if p == pattern and b == bits)
    out = buffer_to_rgb(raw.astype("<u2" if bits > 8 else np.uint8).tobytes(), code, 20, 16)
    assert out.dtype == dtype
    assert out.shape == (16, 20, 3)
    inner = out[2:-2, 2:-2].reshape(-1, 3).astype(float)
    assert np.abs(inner - colour.astype(dtype)).max() <= 1


def test_bayer_demosaic_is_linear() -> None:
    """Raw stays linear: demosaic(a*x) == a*demosaic(x) (up to rounding)."""
    x = RNG.integers(0, 1000, (32, 32), dtype=np.uint16)
    a = bayer_to_rgb(x, "RGGB").astype(float)
    b = bayer_to_rgb(x * 4, "RGGB").astype(float)
    assert np.abs(b - 4 * a).max() <= 4
    with pytest.raises(ValueError, match="unknown Bayer"):
        bayer_to_rgb(x, "RGBG")
