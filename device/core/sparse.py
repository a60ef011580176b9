"""CSR sparse matrix x RGB image: float32 in and out, float64 sums (numba), single-threaded.

The one product of the projection's tables (:mod:`device.projection.kernels`) and of the
simulator's render matrix (:mod:`sim._sparse`): it lives in the base layer so both may call it.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["spmv_rgb"]


@numba.njit(cache=True, nogil=True)
def spmv_rgb(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out[j] = sum_k data[k] x[indices[k]] for CSR rows j (3 channels, float64 sums), eq. (P).

    Returns False if an output is not finite (a NaN/Inf input or float32 overflow)."""
    ok = True
    for j in range(indptr.size - 1):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for k in range(indptr[j], indptr[j + 1]):
            i = indices[k]
            w = data[k]
            a0 += w * x[i, 0]
            a1 += w * x[i, 1]
            a2 += w * x[i, 2]
        out[j, 0] = a0
        out[j, 1] = a1
        out[j, 2] = a2
        if not (np.isfinite(out[j, 0]) and np.isfinite(out[j, 1]) and np.isfinite(out[j, 2])):
            ok = False
    return ok
