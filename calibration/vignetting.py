"""Vignetting (flat field): recover the radial fall-off V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6.

Two guided routines feed the same linear least-squares fit (the model of
``lightprobe.core.calibration.Vignetting``; measured = V x true [1, sec. 2]):

* flat field: a uniform light field (an integrating sphere, an opal diffuser over the lens);
  every valid pixel sees the same radiance c, so ``I(r) = c V(r)``;
* patch at positions: the same scene patch of unknown radiance c seen at several places in the
  image circle (the probe rotated between captures); ``I_i = c V(r_i)``.

Writing ``I = b0 + b1 r^2 + b2 r^4 + b3 r^6`` with ``b0 = c`` and ``b_k = c a_k`` makes the fit
linear; ``a_k = b_k / b0``. Dtype policy: inputs any float or integer dtype, the fit in float64.

References
----------
.. [1] D. B. Goldman, "Vignette and exposure calibration and compensation", IEEE TPAMI 32(12),
   2010 (polynomial radial fall-off in even powers of r).
"""

from __future__ import annotations

import numpy as np

from lightprobe.core.calibration import Vignetting
from lightprobe.core.sphere import LUMINANCE_WEIGHTS

__all__ = ["fit_radial", "max_relative_error", "vignetting_from_flat_field", "vignetting_from_patches"]


def fit_radial(r: np.ndarray, values: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, tuple[float, float, float]]:
    """Least-squares ``values ~ c (1 + a1 r^2 + a2 r^4 + a3 r^6)``; returns (c, (a1, a2, a3)).

    Non-finite samples are dropped; fewer than 4 usable samples or c <= 0 raise ValueError.
    """
    r = np.asarray(r, np.float64).ravel()
    y = np.asarray(values, np.float64).ravel()
    w = np.ones_like(y) if weights is None else np.asarray(weights, np.float64).ravel()
    ok = np.isfinite(r) & np.isfinite(y) & np.isfinite(w) & (w > 0)
    if np.count_nonzero(ok) < 4:
        raise ValueError("vignetting fit needs at least 4 valid samples")
    r2 = r[ok] ** 2
    A = np.stack([np.ones_like(r2), r2, r2**2, r2**3], axis=1)  # I = b0 + b1 r^2 + b2 r^4 + b3 r^6
    sw = np.sqrt(w[ok])
    b, *_ = np.linalg.lstsq(A * sw[:, None], y[ok] * sw, rcond=None)
    if not b[0] > 0:
        raise ValueError("vignetting fit gives a non-positive centre value: is the flat field lit?")
    return float(b[0]), (float(b[1] / b[0]), float(b[2] / b[0]), float(b[3] / b[0]))


def vignetting_from_flat_field(image: np.ndarray, center: tuple[float, float], radius_px: float, *,
                               saturation: float | None = None, bins: int = 200,
                               max_r: float = 1.0) -> Vignetting:
    """Fit V from a linear flat-field image (H, W[, 3]) inside the image circle.

    Pixels are averaged in ``bins`` rings of equal width (which also averages the noise) before
    the fit; saturated (>= ``saturation``), non-finite and outside-circle pixels are ignored, and
    so are pixels beyond ``max_r`` (e.g. 0.97 to keep the housing ring out of the fit).
    An all-black image raises ValueError.
    """
    img = np.asarray(image, np.float64)
    y = img @ LUMINANCE_WEIGHTS if img.ndim == 3 else img
    h, w = y.shape
    vv, uu = np.mgrid[0:h, 0:w]
    r = np.hypot(uu - center[0], vv - center[1]) / radius_px
    ok = np.isfinite(y) & (r <= min(max_r, 1.0))
    if saturation is not None:
        ok &= y < saturation
    idx = np.minimum((r[ok] * bins).astype(np.int64), bins - 1)
    counts = np.bincount(idx, minlength=bins)
    sums = np.bincount(idx, weights=y[ok], minlength=bins)
    rsum = np.bincount(idx, weights=r[ok], minlength=bins)
    have = counts > 0
    _, coeffs = fit_radial(rsum[have] / counts[have], sums[have] / counts[have], counts[have])
    return Vignetting((float(center[0]), float(center[1])), float(radius_px), coeffs)


def vignetting_from_patches(positions: np.ndarray, values: np.ndarray, center: tuple[float, float],
                            radius_px: float) -> Vignetting:
    """Fit V from one patch's mean value ``values[i]`` seen at pixel ``positions[i]`` (N, 2)."""
    p = np.asarray(positions, np.float64).reshape(-1, 2)
    r = np.hypot(p[:, 0] - center[0], p[:, 1] - center[1]) / radius_px
    _, coeffs = fit_radial(r, values)
    return Vignetting((float(center[0]), float(center[1])), float(radius_px), coeffs)


def max_relative_error(estimate: Vignetting, truth: Vignetting, n: int = 200) -> float:
    """max over r in [0, 1] of |V_est / V_true - 1| along a radius of the true circle."""
    r = np.linspace(0.0, 1.0, n) * truth.radius_px
    u = truth.center[0] + r
    v = np.full_like(u, truth.center[1])
    return float(np.max(np.abs(estimate.factor(u, v) / truth.factor(u, v) - 1.0)))
