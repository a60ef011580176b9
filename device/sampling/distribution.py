"""2D sampling distributions over the unit square, pbrt-style Sample / PDF / Invert triplets.

``Distribution2D(func, interpolate=False)`` is pbrt-v3's ``Distribution2D``: ``func`` (nv, nu) is
piecewise constant over the cells of the unit square, the marginal is taken over rows (v) and the
conditional within a row (u).

``Distribution2D(func, interpolate=True)`` is its bicontinuous variant (what Hemigon needs, cf.
Mitsuba 3's continuous ``Marginal2D``): the function is linearly interpolated in v between row
centres (still piecewise constant in u), so the conditional CDF at v is the interpolation of the
two neighbouring rows' (unnormalised) CDFs and the marginal is piecewise linear in v. A small
change of ``func`` or of the input point then moves the sample a little, which is what keeps
lights from jumping between rows from frame to frame. Its density is exactly the interpolated
function, normalised: ``pdf(u, v) = f_interp(u, v) / integral``.

Conventions: points are (N, 2) ``(u, v)`` with u along columns (index ``k = floor(u nu)``) and v
along rows (``j = floor(v nv)``), as in pbrt (``u[1]`` picks the row, ``u[0]`` the column). All
arrays are float64. Degenerate path: an all-zero (or non-finite-sum) ``func`` gives the uniform
distribution, like pbrt's fallback; a zero row in the piecewise-constant mode gets a uniform
conditional (never chosen by the marginal).

References
----------
Pharr, Jakob, Humphreys, "Physically Based Rendering", 3rd ed., sec. 13.6.7 (Distribution2D) and
4th ed., sec. A.4 (SampleLinear / InvertLinearSample, eq. A.6).
Jakob et al., Mitsuba 3 ``Marginal2D`` (continuous interpolation of conditional CDFs).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["Distribution2D", "halton", "invert_linear_sample", "radical_inverse", "sample_linear",
           "sample_one"]

ONE_MINUS_EPSILON = float(np.nextafter(1.0, 0.0))


def radical_inverse(index: np.ndarray, base: int) -> np.ndarray:
    """Van der Corput radical inverse of non-negative integers in ``base`` (float64)."""
    n = np.asarray(index, dtype=np.int64).copy()
    out = np.zeros(n.shape, np.float64)
    f = 1.0 / base
    while np.any(n > 0):
        out += (n % base) * f
        n //= base
        f /= base
    return out


def halton(n: int, start: int = 1) -> np.ndarray:
    """The Halton (2, 3) points of indices ``start .. start + n - 1``: (n, 2) float64.

    Index 0 is the degenerate point (0, 0), so samplers start at 1; the point of light ``i`` is
    always index ``start + i`` whatever ``n`` is, which gives lights a stable identity.
    """
    idx = np.arange(start, start + n, dtype=np.int64)
    return np.stack([radical_inverse(idx, 2), radical_inverse(idx, 3)], axis=1)


def sample_linear(u: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sample x in [0, 1) with density proportional to ``lerp(x, a, b)`` (pbrt-v4 eq. A.6)."""
    u, a, b = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(a, np.float64),
                                  np.asarray(b, np.float64))
    den = a + np.sqrt((1 - u) * a * a + u * b * b)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = np.where(den > 0, u * (a + b) / np.where(den > 0, den, 1.0), u)
    return np.minimum(x, ONE_MINUS_EPSILON)


def invert_linear_sample(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Inverse of :func:`sample_linear`: the CDF of the linear density at ``x``."""
    x, a, b = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(a, np.float64),
                                  np.asarray(b, np.float64))
    s = a + b
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(s > 0, x * (a * (2 - x) + b * x) / np.where(s > 0, s, 1.0), x)


def _find_interval(cdf: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Largest i with cdf[i] <= u, clamped to [0, len(cdf) - 2] (pbrt FindInterval)."""
    return np.clip(np.searchsorted(cdf, u, side="right") - 1, 0, len(cdf) - 2)


@njit(cache=True)
def sample_one(u0, u1, mcdf, seg_start, seg_width, seg_a, seg_b, row_cdf, row_int, func,
               interpolate):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """Compiled :meth:`Distribution2D.sample` of one point: ``(u, v, f(u, v))`` (unnormalised
    density; the numpy methods ``pdf``/``invert`` check it in the tests)."""
    nv, nu = func.shape
    # Sample the marginal (u1) to get v
    s, hi = 0, mcdf.shape[0] - 1  # largest s with mcdf[s] <= u1 (FindInterval)
    while hi - s > 1:
        mid = (s + hi) // 2
        if mcdf[mid] <= u1:
            s = mid
        else:
            hi = mid
    c0, c1 = mcdf[s], mcdf[s + 1]
    du = (u1 - c0) / (c1 - c0) if c1 > c0 else 0.0
    a, b = seg_a[s], seg_b[s]
    den = a + np.sqrt((1 - du) * a * a + du * b * b)
    x = du * (a + b) / den if den > 0 else du  # SampleLinear (pbrt-v4 eq. A.6)
    v = min(seg_start[s] + min(x, ONE_MINUS_EPSILON) * seg_width[s], ONE_MINUS_EPSILON)
    # Rows and blend weight at v
    if interpolate:
        y = v * nv - 0.5
        j0 = min(max(int(np.floor(y)), 0), nv - 1)
        j1 = min(j0 + 1, nv - 1)
        t = min(max(y - j0, 0.0), 1.0)
    else:
        j0 = min(int(v * nv), nv - 1)
        j1 = j0
        t = 0.0
    if (1 - t) * row_int[j0] + t * row_int[j1] <= 0.0:
        # v on the zero end of a linear segment (u1 exactly at a CDF step): use the segment's
        # lit row, so no sample lands where the density is 0
        j0 = j1 if row_int[j1] > 0.0 else j0
        j1 = j0
        t = 0.0
    # Sample the (interpolated) conditional: largest k with G(k) <= target
    target = u0 * ((1 - t) * row_int[j0] + t * row_int[j1])
    lo, hi = 0, nu
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if (1 - t) * row_cdf[j0, mid] + t * row_cdf[j1, mid] <= target:
            lo = mid
        else:
            hi = mid
    g0 = (1 - t) * row_cdf[j0, lo] + t * row_cdf[j1, lo]
    fk = (1 - t) * func[j0, lo] + t * func[j1, lo]
    d = (target - g0) * nu / fk if fk > 0 else 0.5
    return min((lo + min(max(d, 0.0), 1.0)) / nu, ONE_MINUS_EPSILON), v, fk


@njit(cache=True)
def _sample_kernel(u, mcdf, seg_start, seg_width, seg_a, seg_b, row_cdf, row_int, func,
                   interpolate):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    n = u.shape[0]
    pts = np.empty((n, 2))
    pdf = np.empty(n)
    for i in range(n):
        pts[i, 0], pts[i, 1], pdf[i] = sample_one(u[i, 0], u[i, 1], mcdf, seg_start, seg_width,
                                                  seg_a, seg_b, row_cdf, row_int, func,
                                                  interpolate)
    return pts, pdf


class Distribution2D:
    """Sampling distribution proportional to a non-negative ``func`` (nv, nu) on the unit square.

    Parameters
    ----------
    func : (nv, nu) array_like
        Non-negative values per cell (row j covers ``v in [j/nv, (j+1)/nv)``). Copied as float64;
        NaN/negative values are the caller's job (see ``sanitize_radiance``). Not copied when
        already float64: the caller must not modify it while the distribution is in use.
    interpolate : bool
        False: piecewise constant (pbrt-v3). True: linear in v between row centres, conditional
        CDFs interpolated between rows (bicontinuous).
    row_cdf : (nv, nu + 1) array, optional
        Precomputed ``[0, cumsum(func, axis=1)] / nu`` (saves a pass over a large ``func``).
    """

    def __init__(self, func: np.ndarray, interpolate: bool = False,
                 row_cdf: np.ndarray | None = None) -> None:
        f = np.asarray(func, dtype=np.float64)  # not modified (replaced in the uniform case)
        if f.ndim != 2 or f.size == 0:
            raise ValueError(f"func must be a non-empty 2D array, got shape {f.shape}")
        self.nv, self.nu = f.shape
        self.interpolate = bool(interpolate)
        # Compute unnormalised row CDFs F[j, k] = int_0^{k/nu} f(u, row j) du
        if row_cdf is not None and row_cdf.shape == (self.nv, self.nu + 1):
            cum = row_cdf  # precomputed by the caller (e.g. in one pass with ``func``)
        else:
            cum = np.empty((self.nv, self.nu + 1))
            cum[:, 0] = 0.0
            np.cumsum(f, axis=1, out=cum[:, 1:])
            cum *= 1.0 / self.nu
        self.row_integral = cum[:, -1].copy()
        self.integral = float(self.row_integral.mean())
        self.uniform = not (np.isfinite(self.integral) and self.integral > 0)
        if self.uniform:  # degenerate: sample uniformly (pbrt's all-zero fallback)
            f = np.ones_like(f)
            cum = np.tile(np.arange(self.nu + 1) / self.nu, (self.nv, 1))
            self.row_integral = np.ones(self.nv)
            self.integral = 1.0
        self.func = f
        self.row_cdf = cum  # unnormalised
        self._build_marginal()

    # -- construction --------------------------------------------------------------------------
    def _build_marginal(self) -> None:
        s = self.row_integral
        nv = self.nv
        if not self.interpolate:
            self.seg_start = np.arange(nv) / nv
            self.seg_width = np.full(nv, 1.0 / nv)
            self.seg_a = s.copy()
            self.seg_b = s.copy()
        else:
            # Segments: [0, v_0] constant S_0, [v_{j-1}, v_j] linear S_{j-1} -> S_j, [v_last, 1]
            knots = (np.arange(nv) + 0.5) / nv
            self.seg_start = np.concatenate([[0.0], knots])
            self.seg_width = np.concatenate([[0.5 / nv], np.full(nv - 1, 1.0 / nv), [0.5 / nv]])
            self.seg_a = np.concatenate([[s[0]], s])
            self.seg_b = np.concatenate([s, [s[-1]]])
        mass = 0.5 * (self.seg_a + self.seg_b) * self.seg_width
        cdf = np.zeros(len(mass) + 1)
        np.cumsum(mass, out=cdf[1:])
        self.marginal_cdf = cdf / cdf[-1]

    def _rows_at(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows (j0, j1) and blend weight t of ``v``: f(., v) = (1 - t) f[j0] + t f[j1]."""
        if not self.interpolate:
            j = np.clip((v * self.nv).astype(np.int64), 0, self.nv - 1)
            return j, j, np.zeros(v.shape)
        y = v * self.nv - 0.5
        j0 = np.clip(np.floor(y).astype(np.int64), 0, self.nv - 1)
        j1 = np.minimum(j0 + 1, self.nv - 1)
        t = np.clip(y - j0, 0.0, 1.0)
        return j0, j1, t

    # -- Sample / PDF / Invert -----------------------------------------------------------------
    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map uniform points ``u`` (N, 2) in [0,1)^2 to ``(points (N, 2), pdf (N,))``."""
        u = np.ascontiguousarray(u, np.float64).reshape(-1, 2)
        pts, fk = _sample_kernel(u, *self.kernel_args())
        return pts, fk / self.integral

    def kernel_args(self) -> tuple[object, ...]:
        """The arrays :func:`sample_one` takes after the point (for compiled callers)."""
        return (self.marginal_cdf, self.seg_start, self.seg_width, self.seg_a, self.seg_b,
                self.row_cdf, self.row_integral, np.ascontiguousarray(self.func),
                self.interpolate)

    def pdf(self, pts: np.ndarray) -> np.ndarray:
        """Density (w.r.t. area on the unit square) of points (N, 2)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        k = np.clip((pts[:, 0] * self.nu).astype(np.int64), 0, self.nu - 1)
        j0, j1, t = self._rows_at(pts[:, 1])
        return ((1 - t) * self.func[j0, k] + t * self.func[j1, k]) / self.integral

    def invert(self, pts: np.ndarray) -> np.ndarray:
        """The uniform point that :meth:`sample` maps to ``pts`` (N, 2)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        uu, v = pts[:, 0], pts[:, 1]
        # Invert the marginal
        s = np.clip(np.searchsorted(self.seg_start, v, side="right") - 1, 0, len(self.seg_start) - 1)
        x = (v - self.seg_start[s]) / self.seg_width[s]
        c0, c1 = self.marginal_cdf[s], self.marginal_cdf[s + 1]
        xi1 = c0 + (c1 - c0) * invert_linear_sample(x, self.seg_a[s], self.seg_b[s])
        # Invert the conditional
        j0, j1, t = self._rows_at(v)
        k = np.clip((uu * self.nu).astype(np.int64), 0, self.nu - 1)
        g0 = (1 - t) * self.row_cdf[j0, k] + t * self.row_cdf[j1, k]
        fk = (1 - t) * self.func[j0, k] + t * self.func[j1, k]
        total = (1 - t) * self.row_integral[j0] + t * self.row_integral[j1]
        with np.errstate(invalid="ignore", divide="ignore"):
            xi0 = np.where(total > 0, (g0 + (uu * self.nu - k) * fk / self.nu)
                           / np.where(total > 0, total, 1.0), uu)
        return np.stack([xi0, xi1], axis=1)
