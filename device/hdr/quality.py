"""How good a fused HDR image is, without ground truth.

- :func:`subset_consistency`: fuse two disjoint subsets of one static stack (even and odd
  exposures) and compare: a correct response and merge give the same radiance from any subset,
  so the median ``|d log L|`` after one global scale is the merge's own error (noise, response
  error, weighting), in log units (0.01 = 1%).
- :func:`log_correlation`: Pearson correlation of log luminance between two fusions (e.g. ours
  and OpenCV's) over pixels both find positive.
- :func:`dynamic_range`: the 99.9th over the 0.1th percentile of positive luminance.

Luminance is Rec. 709 (``lightprobe.core.sphere.luminance``); accumulation float64.
"""

from __future__ import annotations

import numpy as np

from lightprobe.core.sphere import luminance

__all__ = ["dynamic_range", "log_correlation", "subset_consistency"]


def _log_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    la = luminance(np.asarray(a, np.float64))
    lb = luminance(np.asarray(b, np.float64))
    ok = np.isfinite(la) & np.isfinite(lb) & (la > 0) & (lb > 0)
    return np.log(la[ok]), np.log(lb[ok])


def subset_consistency(a: np.ndarray, b: np.ndarray) -> float:
    """Median ``|log La - log Lb - median(log La - log Lb)|`` over pixels positive in both."""
    la, lb = _log_pair(a, b)
    if la.size == 0:
        return float("inf")
    d = la - lb
    return float(np.median(np.abs(d - np.median(d))))


def log_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Correlation of log luminance over pixels positive in both (nan if fewer than 2)."""
    la, lb = _log_pair(a, b)
    if la.size < 2 or np.std(la) == 0 or np.std(lb) == 0:
        return float("nan")
    return float(np.corrcoef(la, lb)[0, 1])


def dynamic_range(x: np.ndarray) -> float:
    """p99.9 / p0.1 of positive finite luminance (0 when there is none)."""
    lum = luminance(np.asarray(x, np.float64))
    lum = lum[np.isfinite(lum) & (lum > 0)]
    if lum.size == 0:
        return 0.0
    return float(np.percentile(lum, 99.9) / np.percentile(lum, 0.1))
