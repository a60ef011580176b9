"""Per-frame kernels: the projection's repair of rows fed by bad pixels (numba); the CSR x RGB
product itself is :func:`lightprobe.device.projection.sparse.spmv_rgb`.

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
def spmv_rgb_fix(indptr, indices, data, inv_gain, geo_sum, col_ptr, col_rows, x, valid, bad,
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
