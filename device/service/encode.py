"""Image encoders of the API (JPEG previews, Radiance HDR maps), run in worker threads."""

from __future__ import annotations

import numpy as np

__all__ = ["encode_hdr", "encode_jpeg"]


def encode_jpeg(rgb: np.ndarray, quality: int = 85) -> bytes:
    """(H, W, 3) uint8 sRGB -> JPEG bytes."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf.tobytes())


def encode_hdr(img: np.ndarray) -> bytes:
    """(H, W, 3) linear float -> Radiance .hdr bytes."""
    import cv2

    ok, buf = cv2.imencode(".hdr", np.ascontiguousarray(np.asarray(img, np.float32)[..., ::-1]))
    if not ok:
        raise RuntimeError("Radiance HDR encoding failed")
    return bytes(buf.tobytes())
