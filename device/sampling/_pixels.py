"""The one pixel-cleaning rule shared by the samplers' numba kernels.

NaN, +-Inf and negative values (a driver's bad pixel, a lossy EXR's ringing) count as zero
radiance and are counted: ``bad[0]`` non-finite, ``bad[1]`` negative (the same policy as
``lightprobe.device.sampling.base.sanitize_radiance``, inside the kernels so no cleaned copy is made).
Kernels keep the cheap test ``vr >= 0 and vg >= 0 and vb >= 0 and vr + vg + vb < inf`` in their
own loop (a helper returning a tuple there halved Pharr's speed) and call
:func:`clean_invalid` only for the rare pixel that fails it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["clean_invalid"]


@njit(cache=True)
def clean_invalid(vr, vg, vb, bad):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """Slow path: count the invalid channels in ``bad`` and return them zeroed."""
    for v in (vr, vg, vb):
        if not np.isfinite(v):
            bad[0] += 1
        elif v < 0.0:
            bad[1] += 1
    return (vr if (vr >= 0.0 and vr < np.inf) else 0.0,
            vg if (vg >= 0.0 and vg < np.inf) else 0.0,
            vb if (vb >= 0.0 and vb < np.inf) else 0.0)
