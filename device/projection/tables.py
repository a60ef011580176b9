"""Remap tables: conservative remapping matrix, hole-free fallback, balancing, normalisation.

See the package docstring for the method (eqs. O, P, E). Dtype policy: construction in float64,
stored weights float32.

References
----------
Jones, P. 1999, "First- and second-order conservative remapping schemes for grids in spherical
coordinates", Mon. Wea. Rev. 127 (first-order conservative remapping, eq. (O)).
Bishop, Fienberg & Holland 1975, "Discrete Multivariate Analysis" (iterative proportional fitting).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from lightprobe.core.calibration import Calibration, FisheyeModel
from lightprobe.core.sphere import CAMERA_TO_PROBE
from lightprobe.device.projection.sparse import Csr

from .geometry import (
    _Chunk,
    _Grid,
    _Healpix,
    _LatLong,
    _subpixel_chunks,
    _theta_table,
    fisheye_valid_mask,
)


# ------------------------------------------------------------------------------------------------
# Table construction
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Table:
    """One output map's operator (eq. P) in CSR form plus what the per-frame kernels need."""

    indptr: np.ndarray  # (n+1,) int64
    indices: np.ndarray  # (nnz,) int32 flat fisheye pixel index
    data: np.ndarray  # (nnz,) float32 = W[j, i] g_i / A_j
    geo_sum: np.ndarray  # (n,) float64: sum_i data / g_i (1 where covered, 0 elsewhere)
    coverage: np.ndarray  # (n,) float32 in [0, 1]
    solid_angle: np.ndarray  # (n,) float64 exact output pixel solid angle
    ipf_residual: float  # max |row sum / Omega_j - 1| over interior rows after balancing
    col_ptr: np.ndarray  # (m+1,) int64: transpose (CSC) structure, to find the rows a pixel feeds
    col_rows: np.ndarray  # (nnz,) int32


_COVER_CHUNK = 1 << 16


@dataclass
class _Coo:
    """Sparse entries sorted by (row, column), no duplicates (what the build's chunks hand on)."""

    row: np.ndarray  # int32
    col: np.ndarray  # int32
    data: np.ndarray  # float64

    @property
    def nnz(self) -> int:
        return len(self.data)

    @classmethod
    def summed(cls, row: np.ndarray, col: np.ndarray, val: np.ndarray, m: int) -> _Coo:
        """Entries sorted, duplicates summed (in their order of arrival)."""
        key = row.astype(np.int64) * m + col
        order = np.argsort(key, kind="stable")
        key = key[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else np.zeros(0, np.int64)
        data = np.add.reduceat(np.asarray(val, np.float64)[order], starts) if len(key) else np.zeros(0)
        return cls((key[starts] // m).astype(np.int32), (key[starts] % m).astype(np.int32), data)


class _Geometry:
    """What the table builder needs to know about the lens and the valid region."""

    def __init__(self, fisheye: FisheyeModel, valid: np.ndarray) -> None:
        self.fisheye = fisheye
        self.valid = valid
        self.w, self.h = fisheye.image_size
        import cv2  # (the 4-neighbour erosion, as scipy.ndimage.binary_erosion with border 0)

        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        self.eroded = cv2.erode(valid.astype(np.uint8), cross, borderType=cv2.BORDER_CONSTANT,
                                borderValue=0).astype(bool)
        self.theta_valid = min(np.deg2rad(fisheye.fov_deg / 2), float(_theta_table(fisheye)[1][-1]))

    def covered(self, d: np.ndarray, margin: bool = True) -> np.ndarray:
        """True where the probe direction lands on a valid pixel (with ``margin``: on a valid
        pixel whose 4 neighbours are valid too, i.e. at least one pixel inside). In slices of
        ``_COVER_CHUNK`` directions: the projection's temporaries for a table's 1.2M test points
        would be ~100 MB at once."""
        flat = d.reshape(-1, 3)
        out = np.empty(len(flat), bool)
        for i in range(0, len(flat), _COVER_CHUNK):
            out[i:i + _COVER_CHUNK] = self._covered(flat[i:i + _COVER_CHUNK], margin)
        return out.reshape(d.shape[:-1])

    def _covered(self, d: np.ndarray, margin: bool) -> np.ndarray:
        dc = d @ CAMERA_TO_PROBE
        uv = self.fisheye.project(dc)
        iu = np.rint(uv[..., 0]).astype(np.int64)
        iv = np.rint(uv[..., 1]).astype(np.int64)
        inside = (iu >= 0) & (iu < self.w) & (iv >= 0) & (iv < self.h)
        mask = self.eroded if margin else self.valid
        ok = inside & mask[np.clip(iv, 0, self.h - 1), np.clip(iu, 0, self.w - 1)]
        # KB4 is not monotone far behind the lens: only directions inside the fov are seen
        return ok & (np.arctan2(np.hypot(dc[..., 0], dc[..., 1]), dc[..., 2]) <= self.theta_valid)

    def gather(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear weights at directions d (n, 3) over valid pixels: (row k, pixel, weight)."""
        uv = self.fisheye.project(d @ CAMERA_TO_PROBE)
        u0 = np.floor(uv[:, 0]).astype(np.int64)
        v0 = np.floor(uv[:, 1]).astype(np.int64)
        fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
        ks, ps, ws = [], [], []
        for du, dv, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)),
                           (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
            iu, iv = u0 + du, v0 + dv
            ok = (iu >= 0) & (iu < self.w) & (iv >= 0) & (iv < self.h)
            ok[ok] &= self.valid[iv[ok], iu[ok]]
            ok &= wt > 0
            ks.append(np.flatnonzero(ok))
            ps.append(iv[ok] * self.w + iu[ok])
            ws.append(wt[ok])
        k, p, wt = np.concatenate(ks), np.concatenate(ps), np.concatenate(ws)
        norm = np.bincount(k, weights=wt, minlength=len(d))
        return k, p, wt / norm[k]


@numba.njit(cache=True, nogil=True)
def _ipf(indptr, indices, data, row_target, interior, col_target, sweeps, tol, omega):  # pragma: no cover
    """Over-relaxed iterative proportional fitting in place on CSR ``data``.

    A factor ``r`` is applied as ``1 + omega (r - 1)`` (clamped to [0.5, 2]), the first-order
    form of ``r ** omega``. The last column sweep is exact (omega = 1).
    """
    n = indptr.size - 1
    m = col_target.size
    cs = np.zeros(m)
    cf = np.ones(m)
    for sweep in range(sweeps + 1):
        om = omega if sweep < sweeps else 1.0
        if sweep < sweeps:
            # Scale interior rows to their exact solid angle
            resid = 0.0
            for j in range(n):
                if interior[j]:
                    s = 0.0
                    for k in range(indptr[j], indptr[j + 1]):
                        s += data[k]
                    if s > 0.0:
                        r = row_target[j] / s
                        resid = max(resid, abs(r - 1.0))
                        f = min(max(1.0 + om * (r - 1.0), 0.5), 2.0)
                        for k in range(indptr[j], indptr[j + 1]):
                            data[k] *= f
            if resid < tol:
                om = 1.0
        # Scale columns back to the energy each fisheye pixel hands out
        cs[:] = 0.0
        for k in range(indices.size):
            cs[indices[k]] += data[k]
        for c in range(m):
            if col_target[c] > 0.0 and cs[c] > 0.0:
                r = col_target[c] / cs[c]
                cf[c] = r if om == 1.0 else min(max(1.0 + om * (r - 1.0), 0.5), 2.0)
            else:
                cf[c] = 1.0
        for k in range(indices.size):
            data[k] *= cf[indices[k]]
        if om == 1.0:
            break


_COARSE_SWEEPS = 30  # a coarse table's balancing sweeps (energy within ~0.1%: _build_table)


def _balance(W: Csr, row_target: np.ndarray, interior: np.ndarray,
             col_target: np.ndarray, sweeps: int = 150, tol: float = 1e-5,
             omega: float = 1.9) -> float:
    """Balance ``W`` in place: interior rows -> ``row_target``, columns -> ``col_target``.

    Iterative proportional fitting (RAS / Sinkhorn), rows not ``interior`` free. The quadrature
    errors of eq. (O) are a few percent per output pixel and must travel across the map, so this
    would take thousands of plain sweeps; over-relaxation (factors raised to ``omega`` = 1.9)
    reaches ~1e-4 in ~150 (numba, a few ms each). The last sweep scales the columns exactly.
    Returns the final max relative row residual over the interior rows.
    """
    data = np.ascontiguousarray(W.data, dtype=np.float64)
    # (no int64 copies of the structure: the build's peak memory)
    _ipf(W.indptr.astype(np.int64, copy=False), W.indices.astype(np.int32, copy=False), data,
         np.asarray(row_target, np.float64), np.asarray(interior, np.bool_),
         np.asarray(col_target, np.float64), sweeps, tol, omega)
    W.data = data
    rs = np.bincount(np.repeat(np.arange(W.shape[0], dtype=np.int32), np.diff(W.indptr)), weights=data,
                     minlength=W.shape[0])
    ok = interior & (rs > 0)
    return float(np.max(np.abs(rs[ok] / row_target[ok] - 1.0), initial=0.0))


def _chunk_entries(grid: _Grid, ch: _Chunk, m: int) -> _Coo:
    """Entries of eq. (O) for one chunk, a 5-point rule per subpixel (1/2 centre, 1/8 corners).

    The corners make sure that thin overlaps (a sliver of a fisheye pixel inside an output
    pixel) get an entry, so balancing can reach the exact row sums.
    """
    jc = grid.bin(ch.centre)
    jk = grid.bin(ch.lattice)[ch.corners]
    # Most subpixels lie inside one output pixel: one entry; the others get five
    one = (jk == jc[:, None]).all(axis=1)
    split = ~one
    j = np.concatenate([jc, jk[split].ravel()])
    i = np.concatenate([ch.pix, np.repeat(ch.pix[split], 4)])
    w = np.concatenate([np.where(one, ch.omega, 0.5 * ch.omega),
                        np.repeat(0.125 * ch.omega[split], 4)])
    ok = j >= 0
    return _Coo.summed(j[ok], i[ok], w[ok], m)


def _assemble_csr(parts: list[_Coo], n: int, m: int) -> Csr:
    """The (n, m) CSR matrix of the chunks' entries, written in place, part by part (emptying
    ``parts``), with no COO copy of the whole (the build's peak memory). Exact because each part
    is duplicate-free (``_Coo.summed``) and the parts hold disjoint, increasing column ranges
    (bands of fisheye rows), so each row's columns come out sorted."""
    counts = np.zeros(n, np.int64)
    for p in parts:
        counts += np.bincount(p.row, minlength=n)
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(int(indptr[-1]), np.int32)
    data = np.empty(int(indptr[-1]), np.float64)
    fill = indptr[:-1].copy()
    last = -1
    for p in parts:
        if p.nnz:
            assert int(p.col.min()) > last, "parts must hold increasing column ranges"
            last = int(p.col.max())
        r = p.row.astype(np.int64)  # (sorted by row, then column)
        first = np.searchsorted(r, r, side="left")  # each entry's rank within its row in this part
        pos = fill[r] + (np.arange(len(r)) - first)
        indices[pos] = p.col
        data[pos] = p.data
        fill += np.bincount(r, minlength=n)
    parts.clear()
    return Csr(data=data, indices=indices, indptr=indptr, shape=(n, m))


def _add_rows(W: Csr, extra: _Coo) -> Csr:
    """``W`` with the entries of ``extra`` (sorted, in rows that are empty in ``W``)."""
    n, _ = W.shape
    counts = np.diff(W.indptr) + np.bincount(extra.row, minlength=n)
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    old_rows = np.repeat(np.arange(n), np.diff(W.indptr))
    pos_old = indptr[old_rows] + (np.arange(len(old_rows)) - W.indptr[old_rows])
    r = extra.row.astype(np.int64)
    pos_new = indptr[r] + (np.arange(len(r)) - np.searchsorted(r, r, side="left"))
    indices = np.empty(int(indptr[-1]), np.int32)
    data = np.empty(int(indptr[-1]), np.float64)
    indices[pos_old], data[pos_old] = W.indices, W.data
    indices[pos_new], data[pos_new] = extra.col, extra.data
    return Csr(data=data, indices=indices, indptr=indptr, shape=W.shape)


def _interior(grid: _Grid, geo: _Geometry, balance: bool) -> np.ndarray:
    """Output pixels whose 3 x 3 grid of points (edges included) is all well inside the valid
    region (a coarse table tests the corners only: a quarter of the projections), by bands of
    pixels (all the points at once are 28 MB at 256 x 512)."""
    fr = np.linspace(0.0, 1.0, 3) if balance else np.array([0.0, 1.0])
    out = np.empty(grid.size, bool)
    step = max(1, _COVER_CHUNK // fr.size**2)
    for lo in range(0, grid.size, step):
        hi = min(grid.size, lo + step)
        out[lo:hi] = geo.covered(grid.points(fr, lo, hi)).all(axis=1)
    return out


def _build_table(grid: _Grid, geo: _Geometry, parts: list[_Coo],
                 gain: np.ndarray, balance: bool = True, interior: np.ndarray | None = None) -> _Table:
    """Assemble eq. (O), fill holes by gather, balance (IPF; ``balance=False``: a coarse table,
    ``_COARSE_SWEEPS`` sweeps only, rows not yet at their exact solid angle but the map's energy
    within ~0.1%) and normalise to eq. (P). Consumes ``parts`` (emptied once assembled: on a board the
    build's peak memory is the service's)."""
    n, m = grid.size, geo.w * geo.h
    if interior is None:
        interior = _interior(grid, geo, balance)
    W = _assemble_csr(parts, n, m)
    omega = grid.solid_angle()
    col_target = np.bincount(W.indices, weights=W.data, minlength=m)

    # Hole-free fallback: pixels with no subpixel but a covered centre gather bilinearly
    empty = np.diff(W.indptr) == 0
    centre = grid.points(np.array([0.5]))[:, 0, :]
    holes = np.flatnonzero(empty & geo.covered(centre, margin=False))
    if holes.size:
        k, p, g = geo.gather(centre[holes])
        W = _add_rows(W, _Coo.summed(holes[k], p, g * omega[holes[k]], m))

    # With no free row the two marginals must have the same total
    if not np.any(~interior & (np.diff(W.indptr) > 0)):
        col_target *= omega[interior].sum() / col_target.sum()
    # a coarse table is balanced too, briefly: its pixels stay a few percent off, but the map's
    # energy comes within ~0.1% of the balanced table's (unbalanced: 1.3% low on rooitou_park, a
    # step in the published lighting when the balanced table replaced it); +0.1 s of build
    resid = _balance(W, omega, interior, col_target, sweeps=150 if balance else _COARSE_SWEEPS)
    if not balance:
        resid = float("nan")

    # (arrays of nnz entries one at a time, in place where they can be: the build's peak memory)
    row_of = np.repeat(np.arange(n, dtype=np.int32), np.diff(W.indptr))
    rowsum = np.bincount(row_of, weights=W.data, minlength=n)
    coverage = np.where(interior, 1.0, np.clip(rowsum / omega, 0.0, 1.0))
    coverage[rowsum <= 0] = 0.0
    norm = W.data  # W's values are not needed after this
    norm /= rowsum[row_of]  # (P): geometric weights, rows sum to 1
    data = gain[W.indices]
    data *= norm
    data = data.astype(np.float32)
    geo_sum = np.bincount(row_of, weights=norm, minlength=n)
    del norm
    # the transpose's structure (what W.tocsc() gives: each column's rows ascending)
    col_ptr = np.zeros(m + 1, np.int64)
    np.cumsum(np.bincount(W.indices, minlength=m), out=col_ptr[1:])
    col_rows = row_of[np.argsort(W.indices, kind="stable")]
    return _Table(W.indptr.astype(np.int64), W.indices.astype(np.int32), data, geo_sum,
                  coverage.astype(np.float32), omega, resid, col_ptr, col_rows)


def _pixel_gain(cal: Calibration, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gain ``g_i = scale / V_i`` per fisheye pixel (flat float64) and the valid mask it leaves."""
    fe = cal.fisheye
    assert fe is not None
    w, h = fe.image_size
    scale = 1.0 if cal.photometric is None else float(cal.photometric.scale)
    if cal.vignetting is None:
        vig = np.ones((h, w))
    else:
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        vig = cal.vignetting.factor(uu, vv)
    ok = valid & np.isfinite(vig) & (vig > 1e-6)
    gain = np.where(ok, scale / np.where(ok, vig, 1.0), 0.0)
    return gain.ravel(), ok


@dataclass(frozen=True)
class _Built:
    """Everything a projector derives from its calibration (shared, read-only)."""

    lens_mask: np.ndarray  # (h, w) bool: fisheye pixels used
    pixel_gain: np.ndarray  # (h*w,) float64: scale / vignetting, 0 where unused
    inv_gain: np.ndarray  # (h*w,) float64
    pixel_solid_angle: np.ndarray  # (h, w) float64 sr, 0 where unused
    tables: dict[str, _Table]


# Tables built per (calibration id, geometry parameters); a pure memo so that a service restart or a
# second projector on the same calibration does not rebuild them. Weak: an entry lives while a
# projector uses it or while it is among the TABLE_CACHE_SIZE most recent (TABLE_KEEP), so the
# staged start's coarse table goes once the balanced one replaces it (~15 MB on the board).
TABLE_CACHE: weakref.WeakValueDictionary[tuple[object, ...], _Built] = weakref.WeakValueDictionary()
TABLE_KEEP: list[_Built] = []
TABLE_CACHE_SIZE = 1


def build_all(cal: Calibration, polar_height: int, equirect_height: int, nside: int,
               ring_margin_deg: float, subdiv: int,
               maps: tuple[str, ...] = ("polar", "equirect", "healpix"), balance: bool = True) -> _Built:
    """Build the tables of ``maps`` (eq. O, gather fallback, balancing, eq. P) from one
    calibration."""
    fe = cal.fisheye
    assert fe is not None
    w, h = fe.image_size
    m = w * h
    valid0 = fisheye_valid_mask(fe, ring_margin_deg)
    lens_mask = getattr(cal, "mask", None)
    if lens_mask is not None:  # the calibrated clean image circle, when present
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        cx, cy = lens_mask.center
        valid0 &= np.hypot(uu - cx, vv - cy) <= lens_mask.radius_px
    gain, valid = _pixel_gain(cal, valid0)
    every: dict[str, Any] = {"polar": lambda: _LatLong(polar_height, 4 * polar_height, 2 * polar_height),
                             "equirect": lambda: _LatLong(equirect_height, 2 * equirect_height, equirect_height),
                             "healpix": lambda: _Healpix(nside)}
    grids: dict[str, _Grid] = {k: every[k]() for k in maps}
    geo = _Geometry(fe, valid)
    interiors = {k: _interior(g, geo, balance) for k, g in grids.items()}  # before the parts: peak memory
    parts: dict[str, list[_Coo]] = {k: [] for k in grids}
    omega_pix = np.zeros(m)
    for ch in _subpixel_chunks(fe, valid, subdiv):
        omega_pix += np.bincount(ch.pix, weights=ch.omega, minlength=m)
        for name, grid in grids.items():
            parts[name].append(_chunk_entries(grid, ch, m))
    tables = {k: _build_table(g, geo, parts[k], gain, balance, interiors.pop(k)) for k, g in grids.items()}
    inv_gain = np.where(gain > 0, 1.0 / np.where(gain > 0, gain, 1.0), 0.0)
    arrays = [valid, gain, inv_gain, omega_pix]
    for t in tables.values():
        arrays += [t.indptr, t.indices, t.data, t.geo_sum, t.coverage, t.solid_angle, t.col_ptr,
                   t.col_rows]
    for a in arrays:
        a.flags.writeable = False
    return _Built(valid, gain, inv_gain, omega_pix.reshape(h, w), tables)


# ------------------------------------------------------------------------------------------------
# What a table's rows share
# ------------------------------------------------------------------------------------------------
def sample_sharing(indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray, rows: int,
                   row_of: np.ndarray | None = None, total: np.ndarray | None = None) -> np.ndarray:
    """Per output pixel ``j`` of a table's first ``rows`` rows, how much a sum over a region of
    output pixels varies more than the sum of their variances says, because neighbouring output
    pixels read the same fisheye pixels (``rows``,) float64, >= 1 where a row has entries.

    With ``a[j, i]`` the row-normalised weights (``L_j = sum_i a[j, i] x_i``) and independent
    fisheye pixels of equal variance, ``var L_j = s2 sum_i a[j, i]^2``, while a region that holds
    every output pixel reading fisheye pixel ``i`` takes ``c_i = sum_j a[j, i]`` of it, so the
    region's sum has variance ``s2 sum_i c_i^2``. Handing each ``c_i^2`` to the rows in proportion
    to ``a[j, i] / c_i``: ``var(region) = sum_j var L_j k_j`` with
    ``k_j = sum_i a[j, i] c_i / sum_i a[j, i]^2``. Near the horizon of a fisheye probe's
    equirect map ``k ~ 1.3``; towards the zenith, where a row of 512 output pixels reads a few
    dozen fisheye pixels, it grows to 4-6 (16 rows down) and past 100 (the first row).
    ``row_of`` (each entry's row) and ``total`` (each row's weight sum), when the caller has them."""
    ip = np.asarray(indptr[: rows + 1], np.int64)
    n = int(ip[-1])
    idx = np.asarray(indices[:n], np.int64)
    w = np.asarray(weights[:n], np.float64)
    if row_of is None:
        row_of = np.repeat(np.arange(rows), np.diff(ip))
    if total is None:
        total = np.bincount(row_of, w, rows)
    a = w / np.maximum(total[row_of], 1e-300)
    col = np.bincount(idx, a, int(idx.max()) + 1 if n else 0)
    num = np.bincount(row_of, a * col[idx], rows)
    den = np.bincount(row_of, a * a, rows)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)
