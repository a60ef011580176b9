"""The simulated lens's render matrix at run time: CSR arrays and three compiled loops.

A frame of the simulator applies one sparse matrix (sensor pixels x equirect pixels) to an RGB
map and, for each dynamic light, a handful of its columns to the light's disc. SciPy builds the
matrix (:meth:`sim.lens.SimLens.render_matrix`, once per lens and map height, then cached on
disk); applying it needs only its three arrays. Keeping ``scipy.sparse`` out of the frame path
keeps its import (70 ms on the 2-core VM, measured 2026-12-06, with ``numpy.f2py`` and
``numpy.testing`` that SciPy's array-API shim pulls in) out of the service's start, as a
camera driver imports no SciPy either.

Sums run in float64 and are stored as float32 (the map and the matrix are float32).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from device.core.sparse import spmv_rgb  # the projection's own CSR x RGB

__all__ = ["Csr", "warm_kernels"]


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


@dataclass(frozen=True, eq=False)
class Csr:
    """A CSR matrix (float32 values, int32 or int64 indices) as SciPy stores one."""

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
    """Load the three loops' compiled code (numba's cache) for the arrays a render matrix has
    (float32 values, int32 indices and row pointers; the transpose's row pointers int64), so
    the first frame does not pay for it."""
    m = Csr(np.ones(1, np.float32), np.zeros(1, np.int32), np.array([0, 1], np.int32), (1, 1))
    m.matmul_rgb(np.ones((1, 3), np.float32))
    m.transpose().rows_combination(np.zeros(1, np.int64), np.ones(1))
