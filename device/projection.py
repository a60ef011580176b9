"""Fisheye radiance image -> hemisphere polar map, full equirect map and NESTED HEALPix map.

Tables are built once from a :class:`calibration.model.Calibration`; a frame is then one sparse
matrix-vector product per map (float32, three channels, numba CSR kernel).

Conservative (area-correct) remapping
-------------------------------------
Every valid fisheye pixel ``i`` is split into ``s x s`` subpixels. The subpixel corners are
unprojected through the KB4 model (``FisheyeModel``) and rotated to the probe frame with
``device.sphere.CAMERA_TO_PROBE``; a subpixel's solid angle is that of its spherical quadrilateral
(two triangles, Van Oosterom & Strackee 1983, eq. (VOS)) and it is binned by its centre direction
into output pixel ``j``::

    W[j, i] = sum of the solid angles of the subpixels of i that fall into j      (O)

so the columns of ``W`` sum to the fisheye pixel solid angles ``Omega_i`` exactly. Output pixels
that receive no subpixel (tiny polar-cap pixels near the zenith) get a *gather* row: bilinear
weights at the pixel centre times ``Omega_j`` (hole-free fallback). Then ``W`` is balanced by
iterative proportional fitting (Sinkhorn / RAS) so that, to 1e-7,

* every *interior* output pixel (fully inside the lens's valid region) has row sum ``Omega_j``
  (its exact solid angle): a constant image gives a constant map, and
* every column keeps its subpixel total: the energy of each fisheye pixel
  (radiance x solid angle) is handed out exactly, also through the gather rows.

Rows on the rim of the valid region are free; their row sum ``A_j`` is the covered solid angle and
``coverage_j = A_j / Omega_j``. The per-frame operator is ``L_j = sum_i W[j, i] g_i L_i / A_j``
(eq. (P)) with the gain ``g_i = scale / V_i`` folding in 1/vignetting and the photometric scale; a
partly covered pixel holds the mean radiance of its covered part. Hence, for every map,
``sum_j Omega_j coverage_j L_j = sum_i Omega_i g_i L_i`` (energy conservation, eq. (E)).

Invalid pixels (``valid`` mask False, NaN or Inf) are dropped per frame and each output pixel is
renormalised over its valid contributions (a second kernel that runs only when needed); an output
pixel with no valid contribution is 0. Outputs are never NaN.

Lower hemisphere of the equirect map (``lower=``): the lens sees a thin band below the horizon
(fov ~185 deg); partly covered pixels are blended ``c L_seen + (1 - c) L_fill`` with

* ``"zero"`` (default): ``L_fill = 0`` (the map's integral is exactly the energy seen);
* ``"mirror"``: ``L_fill(theta, phi) = ground_albedo x L(pi - theta, phi)`` (upper hemisphere
  reflected by a grey ground);
* ``"mean-horizon"``: ``L_fill`` = mean radiance of the lowest fully covered band
  (``horizon_band_deg`` high), the same for every azimuth.

The calibration's pose is not applied: all maps are in the probe frame.

Dtype policy: geometry and table construction in float64; tables, images and maps float32;
per-pixel accumulation in the kernels is float64.

References
----------
Van Oosterom, A. & Strackee, J. 1983, "The solid angle of a plane triangle", IEEE Trans. Biomed.
Eng. 30(2), eq. (VOS): tan(Omega/2) = |a.(b x c)| / (1 + a.b + b.c + c.a).
Jones, P. 1999, "First- and second-order conservative remapping schemes for grids in spherical
coordinates", Mon. Wea. Rev. 127 (first-order conservative remapping, eq. (O)).
Bishop, Fienberg & Holland 1975, "Discrete Multivariate Analysis" (iterative proportional fitting).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from calibration.model import Calibration, FisheyeModel
from device.errors import InputError
from device.healpix import face_xy_to_directions, nest_to_xyf, npix, vec2pix_nest
from device.sphere import CAMERA_TO_PROBE, angles_from_directions, equirect_row_solid_angle

__all__ = [
    "LOWER_POLICIES",
    "ProbeMaps",
    "Projector",
    "fisheye_pixel_directions",
    "fisheye_pixel_solid_angles",
    "fisheye_valid_mask",
    "spherical_triangle_solid_angle",
]

LowerPolicy = Literal["zero", "mirror", "mean-horizon"]
LOWER_POLICIES: tuple[str, ...] = ("zero", "mirror", "mean-horizon")


# ------------------------------------------------------------------------------------------------
# Pure geometry helpers
# ------------------------------------------------------------------------------------------------
def spherical_triangle_solid_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Solid angle (sr) of spherical triangles with unit vertices ``a, b, c`` (..., 3), float64.

    Van Oosterom & Strackee 1983, eq. (VOS); orientation-free (absolute triple product).
    """
    num = np.abs(np.einsum("...k,...k->...", a, np.cross(b, c)))
    den = 1.0 + np.einsum("...k,...k->...", a, b) + np.einsum("...k,...k->...", b, c) \
        + np.einsum("...k,...k->...", c, a)
    return 2.0 * np.arctan2(num, den)  # (VOS)


def _theta_table(fisheye: FisheyeModel) -> tuple[np.ndarray, np.ndarray]:
    """Monotone table (theta_d, theta) over the range where KB4 is increasing (float64)."""
    theta = np.linspace(0.0, np.pi, 100001)
    theta_d = fisheye.distort_theta(theta)
    bad = np.flatnonzero(np.diff(theta_d) <= 0)
    if bad.size:
        theta, theta_d = theta[: bad[0] + 1], theta_d[: bad[0] + 1]
    if theta.size < 2:
        raise InputError("fisheye.D gives a non-increasing distortion", param="fisheye.D")
    return theta_d, theta


def _unproject(fisheye: FisheyeModel, table: tuple[np.ndarray, np.ndarray],
               u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Probe-frame unit directions (..., 3) and camera polar angle of pixel coordinates.

    KB4 inverted by interpolation in a monotone table (OpenCV pixel centres at integers).
    """
    K = fisheye.K
    my = (v - K[1, 2]) / K[1, 1]
    mx = (u - K[0, 2] - K[0, 1] * my) / K[0, 0]
    rd = np.hypot(mx, my)
    theta = np.interp(rd, table[0], table[1])
    s = np.where(rd > 1e-15, np.sin(theta) / np.where(rd > 1e-15, rd, 1.0), 1.0)
    cam = np.stack(np.broadcast_arrays(mx * s, my * s, np.cos(theta)), axis=-1)
    return cam @ CAMERA_TO_PROBE.T, theta


def fisheye_pixel_directions(fisheye: FisheyeModel) -> np.ndarray:
    """Probe-frame directions (h, w, 3) of the fisheye pixel centres (float64)."""
    w, h = fisheye.image_size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    return _unproject(fisheye, _theta_table(fisheye), uu, vv)[0]


def fisheye_valid_mask(fisheye: FisheyeModel, ring_margin_deg: float = 0.5) -> np.ndarray:
    """Pixels (h, w) bool whose centre lies within ``fov_deg / 2 - ring_margin_deg`` of the axis."""
    w, h = fisheye.image_size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    _, theta = _unproject(fisheye, _theta_table(fisheye), uu, vv)
    limit = np.deg2rad(fisheye.fov_deg / 2.0 - ring_margin_deg)
    return np.asarray(theta <= min(limit, float(_theta_table(fisheye)[1][-1]) - 1e-9))


@dataclass(frozen=True)
class _Chunk:
    """Subpixels of a band of fisheye rows: the valid ones, with their corner lattice."""

    pix: np.ndarray  # (n,) flat fisheye pixel index of each subpixel
    omega: np.ndarray  # (n,) solid angle (sr)
    centre: np.ndarray  # (n, 3) probe-frame centre direction
    lattice: np.ndarray  # (k, 3) probe-frame corner directions
    corners: np.ndarray  # (n, 4) indices into lattice


def _subpixel_chunks(fisheye: FisheyeModel, valid: np.ndarray, s: int,
                     rows: int = 24) -> Iterator[_Chunk]:
    """Yield the s x s subpixels of the valid pixels, a band of fisheye rows at a time.

    Subpixel solid angles come from their corner directions, two triangles each (VOS), so the
    subpixels of a pixel sum to its solid angle.
    """
    w, h = fisheye.image_size
    table = _theta_table(fisheye)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        cols = np.flatnonzero(valid[r0:r1].any(axis=0))
        if cols.size == 0:
            continue
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        nu, nv = (c1 - c0) * s, (r1 - r0) * s
        uu = c0 - 0.5 + np.arange(nu + 1) / s
        vv = r0 - 0.5 + np.arange(nv + 1) / s
        p, _ = _unproject(fisheye, table, uu[None, :], vv[:, None])
        a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, 1:], p[1:, :-1]
        omega = spherical_triangle_solid_angle(a, b, c) + spherical_triangle_solid_angle(a, c, d)
        centre = a + b + c + d
        centre /= np.linalg.norm(centre, axis=-1, keepdims=True)
        sr = r0 + np.arange(nv) // s
        sc = c0 + np.arange(nu) // s
        keep = valid[sr][:, sc]
        pix = (sr[:, None] * w + sc[None, :])[keep]
        ia = (np.arange(nv)[:, None] * (nu + 1) + np.arange(nu)[None, :])[keep]
        corners = np.stack([ia, ia + 1, ia + nu + 2, ia + nu + 1], axis=1)
        yield _Chunk(pix, omega[keep], centre[keep], p.reshape(-1, 3), corners)


def fisheye_pixel_solid_angles(fisheye: FisheyeModel, subdiv: int = 4,
                               valid: np.ndarray | None = None) -> np.ndarray:
    """Solid angle (sr) of each fisheye pixel's footprint, (h, w) float64 (0 where not valid).

    Sum over ``subdiv x subdiv`` subpixel quadrilaterals of their spherical solid angle (VOS).
    ``valid`` defaults to every pixel whose footprint is inside the monotone range of the lens.
    """
    w, h = fisheye.image_size
    if valid is None:
        valid = fisheye_valid_mask(fisheye.__class__(fisheye.image_size, fisheye.K, fisheye.D,
                                                     fov_deg=360.0), 0.0)
    out = np.zeros(h * w)
    for ch in _subpixel_chunks(fisheye, valid, subdiv):
        out += np.bincount(ch.pix, weights=ch.omega, minlength=h * w)
    return out.reshape(h, w)


# ------------------------------------------------------------------------------------------------
# Output grids
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _LatLong:
    """Equirect-style grid: ``rows`` rows of ``pi / full_rows`` rad from the zenith, ``cols`` cols."""

    rows: int
    cols: int
    full_rows: int  # rows of the whole sphere at this spacing (polar map: 2 x rows)

    @property
    def size(self) -> int:
        return self.rows * self.cols

    def solid_angle(self) -> np.ndarray:
        row = equirect_row_solid_angle(self.full_rows, self.cols)[: self.rows]
        return np.repeat(row, self.cols)

    def bin(self, d: np.ndarray) -> np.ndarray:
        theta, phi = angles_from_directions(d)
        r = np.minimum((theta * (self.full_rows / np.pi)).astype(np.int64), self.full_rows - 1)
        c = (phi * (self.cols / (2 * np.pi))).astype(np.int64) % self.cols
        return np.where(r < self.rows, r * self.cols + c, -1)

    def points(self, fr: np.ndarray) -> np.ndarray:
        """Directions (size, len(fr)**2, 3) at fractional positions ``fr`` inside every pixel."""
        r = np.arange(self.rows)[:, None, None, None] + fr[None, None, :, None]
        c = np.arange(self.cols)[None, :, None, None] + fr[None, None, None, :]
        theta = r * (np.pi / self.full_rows)
        phi = c * (2 * np.pi / self.cols)
        st = np.sin(theta)
        d = np.stack(np.broadcast_arrays(st * np.sin(phi), np.cos(theta), -st * np.cos(phi)), -1)
        return d.reshape(self.size, fr.size**2, 3)


@dataclass(frozen=True)
class _Healpix:
    nside: int

    @property
    def size(self) -> int:
        return npix(self.nside)

    def solid_angle(self) -> np.ndarray:
        return np.full(self.size, 4 * np.pi / self.size)

    def bin(self, d: np.ndarray) -> np.ndarray:
        return vec2pix_nest(self.nside, d)

    def points(self, fr: np.ndarray) -> np.ndarray:
        ix, iy, face = nest_to_xyf(self.nside, np.arange(self.size))
        x = (ix[:, None, None] + fr[None, :, None]) / self.nside
        y = (iy[:, None, None] + fr[None, None, :]) / self.nside
        f = np.broadcast_to(face[:, None, None], (*x.shape[:1], fr.size, fr.size))
        return face_xy_to_directions(f, np.broadcast_to(x, f.shape), np.broadcast_to(y, f.shape)
                                     ).reshape(self.size, fr.size**2, 3)


_Grid = _LatLong | _Healpix


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


class _Geometry:
    """What the table builder needs to know about the lens and the valid region."""

    def __init__(self, fisheye: FisheyeModel, valid: np.ndarray) -> None:
        self.fisheye = fisheye
        self.valid = valid
        self.w, self.h = fisheye.image_size
        self.eroded = ndimage.binary_erosion(valid, border_value=0)
        self.theta_valid = min(np.deg2rad(fisheye.fov_deg / 2), float(_theta_table(fisheye)[1][-1]))

    def covered(self, d: np.ndarray, margin: bool = True) -> np.ndarray:
        """True where the probe direction lands on a valid pixel (with ``margin``: on a valid
        pixel whose 4 neighbours are valid too, i.e. at least one pixel inside)."""
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


def _balance(W: sp.csr_matrix, row_target: np.ndarray, interior: np.ndarray,
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
    _ipf(W.indptr.astype(np.int64), W.indices.astype(np.int64), data,
                 np.asarray(row_target, np.float64), np.asarray(interior, np.bool_),
                 np.asarray(col_target, np.float64), sweeps, tol, omega)
    W.data = data
    rs = np.bincount(np.repeat(np.arange(W.shape[0]), np.diff(W.indptr)), weights=data,
                     minlength=W.shape[0])
    ok = interior & (rs > 0)
    return float(np.max(np.abs(rs[ok] / row_target[ok] - 1.0), initial=0.0))


def _chunk_entries(grid: _Grid, ch: _Chunk, m: int) -> sp.coo_matrix:
    """Entries of eq. (O) for one chunk, a 5-point rule per subpixel (1/2 centre, 1/8 corners).

    The corners make sure that thin overlaps (a sliver of a fisheye pixel inside an output
    pixel) get an entry, so balancing can reach the exact row sums.
    """
    jl = grid.bin(ch.lattice)
    j = np.concatenate([grid.bin(ch.centre), jl[ch.corners].ravel()])
    i = np.concatenate([ch.pix, np.repeat(ch.pix, 4)])
    w = np.concatenate([0.5 * ch.omega, np.repeat(0.125 * ch.omega, 4)])
    ok = j >= 0
    W = sp.csr_matrix((w[ok], (j[ok], i[ok])), shape=(grid.size, m))
    W.sum_duplicates()
    return W.tocoo()


def _build_table(grid: _Grid, geo: _Geometry, parts: list[sp.coo_matrix],
                 gain: np.ndarray) -> _Table:
    """Assemble eq. (O), fill holes by gather, balance (IPF) and normalise to eq. (P)."""
    n, m = grid.size, geo.w * geo.h
    row = np.concatenate([p.row for p in parts] or [np.zeros(0, np.int64)])
    col = np.concatenate([p.col for p in parts] or [np.zeros(0, np.int64)])
    wt = np.concatenate([p.data for p in parts] or [np.zeros(0)])
    W = sp.csr_matrix((wt, (row, col)), shape=(n, m), dtype=np.float64)
    W.sum_duplicates()
    omega = grid.solid_angle()
    col_target = np.bincount(W.indices, weights=W.data, minlength=m)

    # Interior pixels: a 3 x 3 grid of points (edges included) all well inside the valid region
    fr = np.linspace(0.0, 1.0, 3)
    interior = geo.covered(grid.points(fr).reshape(-1, 3)).reshape(n, -1).all(axis=1)

    # Hole-free fallback: pixels with no subpixel but a covered centre gather bilinearly
    empty = np.diff(W.indptr) == 0
    centre = grid.points(np.array([0.5]))[:, 0, :]
    holes = np.flatnonzero(empty & geo.covered(centre, margin=False))
    if holes.size:
        k, p, g = geo.gather(centre[holes])
        extra = sp.csr_matrix((g * omega[holes[k]], (holes[k], p)), shape=(n, m))
        W = (W + extra).tocsr()
        W.sum_duplicates()
    W.sort_indices()

    # With no free row the two marginals must have the same total
    if not np.any(~interior & (np.diff(W.indptr) > 0)):
        col_target *= omega[interior].sum() / col_target.sum()
    resid = _balance(W, omega, interior, col_target)

    rowsum = np.bincount(np.repeat(np.arange(n), np.diff(W.indptr)), weights=W.data, minlength=n)
    coverage = np.where(interior, 1.0, np.clip(rowsum / omega, 0.0, 1.0))
    coverage[rowsum <= 0] = 0.0
    row_of = np.repeat(np.arange(n), np.diff(W.indptr))
    norm = W.data / rowsum[row_of]  # (P): geometric weights, rows sum to 1
    data = (norm * gain[W.indices]).astype(np.float32)
    geo_sum = np.bincount(row_of, weights=norm, minlength=n)
    return _Table(W.indptr.astype(np.int64), W.indices.astype(np.int32), data, geo_sum,
                  coverage.astype(np.float32), omega, resid)


# ------------------------------------------------------------------------------------------------
# Per-frame kernels
# ------------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _spmv_rgb(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out[j] = sum_k data[k] x[indices[k]] for CSR rows j (3 channels, float64 sums), eq. (P)."""
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


@numba.njit(cache=True, nogil=True)
def _spmv_rgb_valid(indptr, indices, data, inv_gain, geo_sum, x, valid, out):  # pragma: no cover
    """Eq. (P) over valid, finite inputs only, renormalised by the valid geometric weight."""
    big = 3.0e38
    for j in range(indptr.size - 1):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        wv = 0.0
        for k in range(indptr[j], indptr[j + 1]):
            i = indices[k]
            x0 = x[i, 0]
            x1 = x[i, 1]
            x2 = x[i, 2]
            if valid[i] and np.isfinite(x0) and np.isfinite(x1) and np.isfinite(x2):
                w = data[k]
                a0 += w * x0
                a1 += w * x1
                a2 += w * x2
                wv += w * inv_gain[i]
        s = geo_sum[j] / wv if wv > 0.0 else 0.0
        out[j, 0] = min(max(a0 * s, -big), big)
        out[j, 1] = min(max(a1 * s, -big), big)
        out[j, 2] = min(max(a2 * s, -big), big)


# ------------------------------------------------------------------------------------------------
# Public API
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProbeMaps:
    """One frame's radiance on the sphere, probe frame, in the calibration's photometric unit.

    ``coverage_*`` are static per projector (fraction of each pixel the lens sees; 0 = no data)
    and shared read-only between frames.
    """

    polar: np.ndarray  # (Hp, 4 Hp, 3) float32, Hp = 90 by default
    equirect: np.ndarray  # (He, 2 He, 3) float32
    healpix: np.ndarray  # (12 nside^2, 3) float32, NESTED
    nside: int
    coverage_polar: np.ndarray  # (Hp, 4 Hp) float32 in [0, 1]
    coverage_equirect: np.ndarray | None = None  # (He, 2 He) float32 (before the lower fill)
    coverage_healpix: np.ndarray | None = None  # (12 nside^2,) float32
    unit: str = "relative"


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


class Projector:
    """Remap tables from one calibration; :meth:`project` maps a fused fisheye radiance image.

    Parameters
    ----------
    calibration : needs ``fisheye``; ``vignetting``, ``photometric`` and ``mask`` (the clean image
        circle) are used when present; ``pose`` is not applied (maps are in the probe frame).
    polar_height : rows of the hemisphere polar map (width 4 x; 90 = one pixel per degree).
    equirect_height : rows of the full equirect map (width 2 x).
    nside : HEALPix resolution (power of two), NESTED.
    lower : lower-hemisphere policy of the equirect map, one of ``LOWER_POLICIES``.
    ground_albedo : reflectance used by ``lower="mirror"``.
    horizon_band_deg : height of the band averaged by ``lower="mean-horizon"``.
    ring_margin_deg : fisheye pixels beyond ``fov_deg / 2 - ring_margin_deg`` are not used
        (keeps the housing ring's shadow out of the maps).
    subdiv : subpixels per fisheye pixel side for the conservative remap.
    """

    def __init__(self, calibration: Calibration, *, polar_height: int = 90,
                 equirect_height: int = 256, nside: int = 64, lower: str = "zero",
                 ground_albedo: float = 0.2, horizon_band_deg: float = 5.0,
                 ring_margin_deg: float = 0.5, subdiv: int = 4) -> None:
        if calibration.fisheye is None:
            raise InputError("calibration has no fisheye section", param="fisheye")
        if lower not in LOWER_POLICIES:
            raise InputError(f"lower={lower!r} is not one of {LOWER_POLICIES}", param="lower")
        for name, val in (("polar_height", polar_height), ("equirect_height", equirect_height),
                          ("subdiv", subdiv)):
            if int(val) < 1:
                raise InputError(f"{name} must be a positive integer, got {val}", param=name)
        if nside < 1 or nside & (nside - 1):
            raise InputError(f"nside must be a power of two, got {nside}", param="nside")
        self.calibration = calibration
        self.polar_height, self.equirect_height, self.nside = polar_height, equirect_height, nside
        self.lower, self.ground_albedo = lower, float(ground_albedo)
        self.horizon_band_deg, self.ring_margin_deg = float(horizon_band_deg), float(ring_margin_deg)
        self.subdiv = int(subdiv)
        self._build()

    # -- construction ---------------------------------------------------------------------------
    def _build(self) -> None:
        fe = self.calibration.fisheye
        assert fe is not None
        w, h = fe.image_size
        m = w * h
        valid0 = fisheye_valid_mask(fe, self.ring_margin_deg)
        lens_mask = getattr(self.calibration, "mask", None)
        if lens_mask is not None:  # the calibrated clean image circle, when present
            vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
            cx, cy = lens_mask.center
            valid0 &= np.hypot(uu - cx, vv - cy) <= lens_mask.radius_px
        gain, valid = _pixel_gain(self.calibration, valid0)
        self.lens_mask = valid
        self.pixel_gain = gain
        self._inv_gain = np.where(gain > 0, 1.0 / np.where(gain > 0, gain, 1.0), 0.0)
        Hp, He = self.polar_height, self.equirect_height
        grids: dict[str, _Grid] = {"polar": _LatLong(Hp, 4 * Hp, 2 * Hp),
                                   "equirect": _LatLong(He, 2 * He, He),
                                   "healpix": _Healpix(self.nside)}
        parts: dict[str, list[sp.coo_matrix]] = {k: [] for k in grids}
        omega_pix = np.zeros(m)
        for ch in _subpixel_chunks(fe, valid, self.subdiv):
            omega_pix += np.bincount(ch.pix, weights=ch.omega, minlength=m)
            for name, grid in grids.items():
                parts[name].append(_chunk_entries(grid, ch, m))
        self.pixel_solid_angle = omega_pix.reshape(h, w)
        geo = _Geometry(fe, valid)
        self._tables = {k: _build_table(g, geo, parts[k], gain) for k, g in grids.items()}
        self._setup_lower()

    def _setup_lower(self) -> None:
        """Rows of the equirect map that need the lower-hemisphere fill, and the horizon band."""
        He = self.equirect_height
        cov = self._tables["equirect"].coverage.reshape(He, 2 * He)
        full = np.flatnonzero(cov.min(axis=1) >= 1.0)
        last_full = int(full.max()) if full.size else -1
        # Fill rows: below the last fully covered row (only those in the lower hemisphere matter)
        self._fill_rows = np.arange(last_full + 1, He)
        n_band = max(1, round(self.horizon_band_deg / (180.0 / He)))
        first = max(0, last_full + 1 - n_band)
        self._horizon_rows = np.arange(first, last_full + 1)

    # -- per frame ------------------------------------------------------------------------------
    def _prepare(self, image: np.ndarray, valid: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        fe = self.calibration.fisheye
        assert fe is not None
        w, h = fe.image_size
        image = np.asarray(image)
        if image.shape != (h, w, 3):
            raise InputError(f"fisheye image has shape {image.shape}, calibration expects "
                             f"({h}, {w}, 3)", param="image")
        x = np.ascontiguousarray(image, dtype=np.float32).reshape(-1, 3)
        if valid is None:
            return x, None
        valid = np.asarray(valid)
        if valid.shape != (h, w):
            raise InputError(f"valid mask has shape {valid.shape}, expected ({h}, {w})",
                             param="valid")
        valid = valid.astype(bool, copy=False)
        if not np.any(self.lens_mask & ~valid):
            return x, None
        return x, np.ascontiguousarray(valid.ravel(), dtype=np.uint8)

    def _apply(self, name: str, x: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
        """Eq. (P) for one map: fast kernel; masked kernel when pixels are invalid or non-finite."""
        t = self._tables[name]
        out = np.empty((t.indptr.size - 1, 3), np.float32)
        if valid is None:
            _spmv_rgb(t.indptr, t.indices, t.data, x, out)
            if np.isfinite(out).all():
                return out
            valid = np.ones(x.shape[0], np.uint8)
        _spmv_rgb_valid(t.indptr, t.indices, t.data, self._inv_gain, t.geo_sum, x, valid, out)
        return out

    def _fill_lower(self, eq: np.ndarray) -> np.ndarray:
        """Blend partly covered and uncovered rows with the lower-hemisphere policy."""
        rows = self._fill_rows
        if rows.size == 0:
            return eq
        He = self.equirect_height
        c = self.coverage_equirect[rows][..., None]
        if self.lower == "zero":
            fill = np.zeros((1, 1, 3), np.float32)
        elif self.lower == "mirror":
            mirror = np.clip(He - 1 - rows, 0, He - 1)
            fill = self.ground_albedo * eq[mirror]
        else:  # mean-horizon: rows of one band have equal solid angles, so a plain mean is exact
            fill = eq[self._horizon_rows].reshape(-1, 3).mean(axis=0, dtype=np.float64)[None, None]
        eq[rows] = (c * eq[rows] + (1.0 - c) * fill).astype(np.float32)
        return eq

    def project_polar(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Hemisphere polar map (Hp, 4 Hp, 3) float32."""
        x, v = self._prepare(image, valid)
        return self._apply("polar", x, v).reshape(self.polar_height, 4 * self.polar_height, 3)

    def project_equirect(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Full equirect map (He, 2 He, 3) float32 with the lower-hemisphere policy applied."""
        x, v = self._prepare(image, valid)
        return self._equirect(x, v)

    def _equirect(self, x: np.ndarray, v: np.ndarray | None) -> np.ndarray:
        He = self.equirect_height
        return self._fill_lower(self._apply("equirect", x, v).reshape(He, 2 * He, 3))

    def project_healpix(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """NESTED HEALPix map (12 nside^2, 3) float32."""
        x, v = self._prepare(image, valid)
        return self._apply("healpix", x, v)

    def project(self, fisheye_radiance: np.ndarray, valid: np.ndarray | None = None) -> ProbeMaps:
        """All three maps of one fused fisheye radiance image (h, w, 3); ``valid`` (h, w) bool."""
        x, v = self._prepare(fisheye_radiance, valid)
        Hp = self.polar_height
        unit = "relative" if self.calibration.photometric is None else self.calibration.photometric.unit
        return ProbeMaps(
            polar=self._apply("polar", x, v).reshape(Hp, 4 * Hp, 3),
            equirect=self._equirect(x, v),
            healpix=self._apply("healpix", x, v),
            nside=self.nside,
            coverage_polar=self.coverage_polar,
            coverage_equirect=self.coverage_equirect,
            coverage_healpix=self.coverage_healpix,
            unit=unit,
        )

    # -- static facts ---------------------------------------------------------------------------
    def _static(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        a = self._tables[name].coverage.reshape(shape)
        a.flags.writeable = False
        return a

    @property
    def coverage_polar(self) -> np.ndarray:
        return self._static("polar", (self.polar_height, 4 * self.polar_height))

    @property
    def coverage_equirect(self) -> np.ndarray:
        return self._static("equirect", (self.equirect_height, 2 * self.equirect_height))

    @property
    def coverage_healpix(self) -> np.ndarray:
        return self._static("healpix", (npix(self.nside),))

    def solid_angle(self, name: str) -> np.ndarray:
        """Exact solid angle (sr) of each pixel of map ``name`` ("polar", "equirect", "healpix")."""
        return self._tables[name].solid_angle

    def nnz(self, name: str) -> int:
        """Non-zeros of a map's table (the per-frame work is proportional to it)."""
        return int(self._tables[name].indices.size)

    def balance_residual(self, name: str) -> float:
        """Max relative row-sum error of the interior rows after balancing (IPF), ~1e-7."""
        return self._tables[name].ipf_residual
