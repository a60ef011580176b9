"""Per-frame kernels: CSR sparse matrix x RGB image, float32 in and out, float64 sums (numba).

Single-threaded on purpose: on the shared 2-core box numba's ``parallel=True`` pool was 10x
slower than one thread under load (threads wait for a time slice); the three maps together are
~1.2 M non-zeros.
"""

from __future__ import annotations

import numba
import numpy as np


# ------------------------------------------------------------------------------------------------
# Per-frame kernels
# ------------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _spmv_rgb(indptr, indices, data, x, out):  # pragma: no cover - compiled
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


@numba.njit(cache=True, nogil=True)
def _spmv_rgb_fix(indptr, indices, data, inv_gain, geo_sum, col_ptr, col_rows, x, valid, bad,
                  out):  # pragma: no cover - compiled
    """Recompute eq. (P) for the rows fed by the ``bad`` pixels, over valid, finite inputs only.

    Each such row is renormalised by its valid geometric weight (``data / gain``); a row with no
    valid contribution is 0. ``col_ptr``/``col_rows`` is the transpose structure of the table.
    """
    big = 3.0e38
    mark = np.zeros(indptr.size - 1, np.uint8)
    for b in range(bad.size):
        p = bad[b]
        for k in range(col_ptr[p], col_ptr[p + 1]):
            mark[col_rows[k]] = 1
    for j in range(indptr.size - 1):
        if mark[j] == 0:
            continue
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        wv = 0.0
        for k in range(indptr[j], indptr[j + 1]):
            i = indices[k]
            if valid[i]:
                w = data[k]
                a0 += w * x[i, 0]
                a1 += w * x[i, 1]
                a2 += w * x[i, 2]
                wv += w * inv_gain[i]
        s = geo_sum[j] / wv if wv > 0.0 else 0.0
        out[j, 0] = min(max(a0 * s, -big), big)
        out[j, 1] = min(max(a1 * s, -big), big)
        out[j, 2] = min(max(a2 * s, -big), big)
