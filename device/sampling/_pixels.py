"""The one pixel-cleaning rule shared by the samplers' numba kernels.

NaN, +-Inf and negative values (a driver's bad pixel, a lossy EXR's ringing) count as zero
radiance and are counted: ``bad[0]`` non-finite, ``bad[1]`` negative (the same policy as
``device.sampling.base.sanitize_radiance``, inside the kernels so no cleaned copy is made).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["clean_pixel"]


@njit(cache=True, inline="always")
def clean_pixel(img, r, c, bad):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """(r, g, b) of ``img[r, c]`` as float64 with invalid values zeroed and counted in ``bad``."""
    vr = np.float64(img[r, c, 0])
    vg = np.float64(img[r, c, 1])
    vb = np.float64(img[r, c, 2])
    if not (vr >= 0.0 and vg >= 0.0 and vb >= 0.0 and vr + vg + vb < np.inf):
        for v in (vr, vg, vb):  # slow path: count and zero invalid values
            if not np.isfinite(v):
                bad[0] += 1
            elif v < 0.0:
                bad[1] += 1
        vr = vr if (vr >= 0.0 and vr < np.inf) else 0.0
        vg = vg if (vg >= 0.0 and vg < np.inf) else 0.0
        vb = vb if (vb >= 0.0 and vb < np.inf) else 0.0
    return vr, vg, vb
