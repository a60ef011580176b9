"""Lens frame mask: find where the image circle ends (housing ring, frame reflections) and fill.

A circular fisheye image is bright inside the image circle and dark outside it, with the lens
housing's ring and reflections of the frame in a thin band at the edge. :func:`find_mask` takes
the radial profile of a capture (median luminance in one-pixel rings around ``center``), finds
the first radius where it falls below ``threshold`` x the interior level, and pulls the valid
radius in by ``margin_px`` to exclude the ring. :func:`fill_masked` inpaints the masked band
just outside the valid radius (Telea's fast marching method, ``cv2.INPAINT_TELEA`` [1]) so the
projection to the sphere does not smear the dark ring into the horizon before sampling.

Dtype policy: images float32 (linear) or uint8; profiles and radii float64.

References
----------
.. [1] A. Telea, "An image inpainting technique based on the fast marching method", Journal of
   Graphics Tools 9(1), 2004.
"""

from __future__ import annotations

import cv2
import numpy as np

from lightprobe.core.calibration import LensMask
from lightprobe.core.sphere import LUMINANCE_WEIGHTS

__all__ = ["fill_masked", "find_mask", "mask_image", "radial_profile"]


def radial_profile(image: np.ndarray, center: tuple[float, float]) -> np.ndarray:
    """Median luminance per one-pixel ring around ``center``; NaN where a ring has no pixels."""
    img = np.asarray(image, np.float64)
    y = img @ LUMINANCE_WEIGHTS if img.ndim == 3 else img
    h, w = y.shape
    vv, uu = np.mgrid[0:h, 0:w]
    r = np.hypot(uu - center[0], vv - center[1]).astype(np.int64).ravel()
    vals = np.where(np.isfinite(y), y, 0.0).ravel()
    order = np.argsort(r, kind="stable")
    r, vals = r[order], vals[order]
    n = int(r.max()) + 1
    starts = np.searchsorted(r, np.arange(n + 1))
    out = np.full(n, np.nan)
    for i in range(n):
        a, b = starts[i], starts[i + 1]
        if b > a:
            out[i] = np.median(vals[a:b])
    return out


def find_mask(image: np.ndarray, center: tuple[float, float], *, threshold: float = 0.25,
              margin_px: float = 3.0, max_radius: float | None = None) -> LensMask:
    """Valid image-circle radius from the radial profile of a capture.

    Interior level = median of the profile over the inner half of the radius range. The edge is
    the first radius past the inner half where the profile drops below ``threshold`` x that
    level; ``margin_px`` more is cut to drop the housing ring. An all-black image raises
    ValueError (no circle to find); a profile that never drops (a full-frame lens) keeps the
    largest radius fully inside the image.
    """
    prof = radial_profile(image, center)
    h, w = np.asarray(image).shape[:2]
    inside = min(center[0], center[1], w - 1 - center[0], h - 1 - center[1])
    limit = int(min(len(prof), max_radius if max_radius else len(prof)))
    inner = prof[: max(limit // 2, 1)]
    level = float(np.nanmedian(inner)) if np.any(np.isfinite(inner)) else 0.0
    if not level > 0:
        raise ValueError("capture is black inside the image circle: cannot find the lens edge")
    below = np.nonzero(np.nan_to_num(prof[limit // 2 : limit], nan=0.0) < threshold * level)[0]
    edge = float(limit // 2 + below[0]) if below.size else float(inside)
    return LensMask((float(center[0]), float(center[1])), max(edge - margin_px, 1.0))


def mask_image(mask: LensMask, shape: tuple[int, int]) -> np.ndarray:
    """Boolean (H, W): True where a pixel lies inside the valid image circle."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    return np.hypot(uu - mask.center[0], vv - mask.center[1]) <= mask.radius_px


def fill_masked(image: np.ndarray, mask: LensMask, *, band_px: float = 8.0, inpaint_radius: float = 3.0) -> np.ndarray:
    """Inpaint the band ``radius_px < r <= radius_px + band_px`` from the valid interior.

    Float images are inpainted per channel in float32 (OpenCV supports 1-channel float32);
    uint8 images directly. Pixels beyond the band are left as they are; non-finite pixels
    anywhere are filled too (a NaN from the sensor must not reach the sampler).
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w]
    r = np.hypot(uu - mask.center[0], vv - mask.center[1])
    band = (r > mask.radius_px) & (r <= mask.radius_px + band_px)
    # The whole exterior is marked unknown so the fill propagates inwards-out from the valid
    # interior only (never from the black frame); only the band is copied back.
    unknown = r > mask.radius_px
    if img.dtype.kind == "f":
        bad = ~np.isfinite(img).all(axis=-1) if img.ndim == 3 else ~np.isfinite(img)
        band |= bad
        unknown |= bad
    m8 = unknown.astype(np.uint8)
    if img.dtype == np.uint8:
        filled = cv2.inpaint(img, m8, inpaint_radius, cv2.INPAINT_TELEA)
    else:
        src = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if src.ndim == 2:
            filled = cv2.inpaint(src, m8, inpaint_radius, cv2.INPAINT_TELEA)
        else:
            filled = np.stack([cv2.inpaint(np.ascontiguousarray(src[..., c]), m8, inpaint_radius,
                                           cv2.INPAINT_TELEA) for c in range(src.shape[2])], axis=-1)
    out = np.array(img, copy=True) if img.dtype == np.uint8 else np.nan_to_num(img.astype(np.float32))
    out[band] = filled[band]
    return out
