"""The one display tone mapper: linear HDR radiance -> sRGB uint8 (dashboard previews).

Both previews (the fisheye view in ``FrameResult.preview`` and ``GET /preview.jpg?view=equirect``)
use :func:`tone_map`: Reinhard et al.'s global photographic operator on *luminance*, with the
colour carried along (hue-preserving: every channel is scaled by ``L_d / L``, so a saturated
sky stays blue instead of washing out per channel), keyed on a robust log-average luminance:

    L_avg = exp(mean(log L))    over the valid lit pixels, darkest and brightest 1% left out   (1)
    L_s   = a L / L_avg         a = 0.18 (middle grey)                                           (2)
    L_d   = L_s / (1 + L_s)                                                                      (3)
    rgb_d = rgb a / L_avg / (1 + L_s)   (= rgb L_d / L), clipped to [0, 1], then the sRGB OETF

Trimming the log-average keeps a sun or a hot pixel (and the black housing ring) from moving the
exposure of the whole view. Degenerate inputs: NaN, inf and negative values (lossy EXR) count
as 0; an image with no lit pixel stays black. Dtype policy: float32 image, float64 key.

References
----------
Reinhard, Stark, Shirley, Ferwerda 2002, "Photographic tone reproduction for digital images",
SIGGRAPH, eqs. 1-3. IEC 61966-2-1 (sRGB transfer curve).
"""

from __future__ import annotations

import numpy as np

from lightprobe.core.sphere import LUMINANCE_WEIGHTS

__all__ = ["LUMINANCE", "log_average_key", "tone_map"]

LUMINANCE = LUMINANCE_WEIGHTS.astype(np.float32)  # Rec. 709 / sRGB luminance weights
MIDDLE_GREY = 0.18
TRIM = 0.01


def log_average_key(lum: np.ndarray, trim: float = TRIM) -> float:
    """Eq. (1): the geometric mean of the positive luminances, the ``trim`` fraction at each end
    left out (float64). 1.0 when nothing is lit."""
    sel = np.asarray(lum, np.float64).ravel()
    sel = sel[np.isfinite(sel) & (sel > 0)]
    if sel.size == 0:
        return 1.0
    logs = np.log(sel)
    if sel.size >= 20 and trim > 0:
        lo, hi = np.quantile(logs, [trim, 1.0 - trim])
        kept = logs[(logs >= lo) & (logs <= hi)]
        logs = kept if kept.size else logs
    return float(np.exp(logs.mean()))


def tone_map(radiance: np.ndarray, valid: np.ndarray | None = None, width: int | None = None) -> np.ndarray:
    """sRGB uint8 (h, w, 3) display image of linear radiance (H, W, 3), eqs. (1)-(3).

    ``valid``: the pixels that count for the key (e.g. the fisheye image circle); the others are
    drawn black. ``width``: downsize (area average) to at most this width first.
    """
    img: np.ndarray = np.nan_to_num(np.asarray(radiance, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(img, 0.0, out=img)
    h, w = img.shape[:2]
    if width is not None and w > width:
        import cv2

        size = (width, max(1, round(h * width / w)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        if valid is not None:
            valid = cv2.resize(valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    lum = img @ LUMINANCE
    key = log_average_key(lum[valid] if valid is not None else lum)
    scale = np.float32(MIDDLE_GREY / max(key, 1e-30))
    ls = lum * scale  # (2)
    y = img * (scale / (1.0 + ls))[..., None]  # (3), every channel scaled by L_d / L
    np.clip(y, 0.0, 1.0, out=y)
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    out = (srgb * 255.0 + 0.5).astype(np.uint8)
    if valid is not None:
        out[~valid] = 0
    return out
