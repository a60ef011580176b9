"""CSR sparse matrices without SciPy: the container (:class:`Csr`) and its compiled loops
(numba, single-threaded, float64 sums).

The projection's tables (:mod:`lightprobe.device.projection.tables`,
:mod:`lightprobe.device.projection.kernels`) hold and apply them without SciPy (``import
scipy.sparse`` costs ~70 ms with the ``numpy.f2py`` and ``numpy.testing`` its array-API shim
pulls in). The simulator has its own (:mod:`lightprobe.sim._sparse`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["Csr", "spmv_rgb", "warm_kernels"]


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


@numba.njit(cache=True, nogil=True)
def _transpose(indptr, indices, data, n_cols, t_indptr, t_indices, t_data):  # type: ignore[no-untyped-def]
    """The transpose's CSR arrays (a counting sort by column; rows stay in order)."""
    for p in range(indices.shape[0]):
        t_indptr[indices[p] + 1] += 1
    for j in range(n_cols):
        t_indptr[j + 1] += t_indptr[j]
    nxt = t_indptr[:-1].copy()
    for i in range(indptr.shape[0] - 1):
        for p in range(indptr[i], indptr[i + 1]):
            q = nxt[indices[p]]
            t_indices[q] = i
            t_data[q] = data[p]
            nxt[indices[p]] = q + 1


@numba.njit(cache=True, nogil=True)
def _rows_combination(indptr, indices, data, rows, weights, out):  # type: ignore[no-untyped-def]
    """out += sum_k weights[k] * row rows[k] (a dense vector over the columns)."""
    for k in range(rows.shape[0]):
        r = rows[k]
        w = np.float64(weights[k])
        for p in range(indptr[r], indptr[r + 1]):
            out[indices[p]] += w * data[p]


@dataclass(eq=False)
class Csr:
    """An (n, m) matrix in CSR form as SciPy stores one, each row's columns sorted: the projection
    table build's (float64 values while it balances them) and the simulator's render matrix
    (float32). Neither needs SciPy to hold or apply one (~20 MB and 70 ms of imports on a board)."""

    data: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def from_scipy(cls, m: object) -> Csr:
        """From a ``scipy.sparse`` matrix in CSR form (its arrays, not copied)."""
        return cls(m.data, m.indices, m.indptr, (int(m.shape[0]), int(m.shape[1])))  # type: ignore[attr-defined]

    @classmethod
    def checked(cls, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, shape: np.ndarray) -> Csr:
        """From stored arrays, with a ``ValueError`` if they do not form a (rows, cols) CSR matrix."""
        rows, cols = (int(v) for v in np.asarray(shape).reshape(2))
        if indptr.shape != (rows + 1,) or int(indptr[-1]) != indices.size or indices.size != data.size \
                or (indices.size and (int(indices.min()) < 0 or int(indices.max()) >= cols)):
            raise ValueError(f"CSR arrays do not form a {rows} x {cols} matrix")
        return cls(data, indices, indptr, (rows, cols))

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])

    def matmul_rgb(self, x: np.ndarray) -> np.ndarray:
        """``self @ x`` for ``x`` of shape (columns, 3): (rows, 3) float32."""
        if x.ndim != 2 or x.shape != (self.shape[1], 3):
            raise ValueError(f"matmul_rgb: x has shape {x.shape}, expected ({self.shape[1]}, 3)")
        out = np.empty((self.shape[0], 3), np.float32)
        spmv_rgb(self.indptr, self.indices, self.data, np.ascontiguousarray(x, dtype=np.float32), out)
        return out

    def transpose(self) -> Csr:
        """The transpose, in CSR form (the columns of ``self`` as rows: SciPy's ``tocsc``)."""
        n_rows, n_cols = self.shape
        t_indptr = np.zeros(n_cols + 1, np.int64)
        t_indices = np.empty(self.nnz, np.int32 if n_rows < 2**31 else np.int64)
        t_data = np.empty(self.nnz, self.data.dtype)
        _transpose(self.indptr, self.indices, self.data, n_cols, t_indptr, t_indices, t_data)
        return Csr(t_data, t_indices, t_indptr, (n_cols, n_rows))

    def rows_combination(self, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """``sum_k weights[k] * self[rows[k], :]`` as a dense float64 vector over the columns."""
        out = np.zeros(self.shape[1], np.float64)
        _rows_combination(self.indptr, self.indices, self.data, np.ascontiguousarray(rows, np.int64),
                          np.ascontiguousarray(weights, np.float64), out)
        return out


def warm_kernels() -> None:
    """Load the three loops' compiled code (numba's cache) for the arrays the simulator's render matrix has
    (float32 values, int32 indices and row pointers; the transpose's row pointers int64), so
    the first frame does not pay for it."""
    m = Csr(np.ones(1, np.float32), np.zeros(1, np.int32), np.array([0, 1], np.int32), (1, 1))
    m.matmul_rgb(np.ones((1, 3), np.float32))
    m.transpose().rows_combination(np.zeros(1, np.int64), np.ones(1))
