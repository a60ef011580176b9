"""GGX-prefiltered cubemaps of the probe's map (split-sum specular, as glTF's
``EXT_lights_image_based``, ``KHR_lights_environment`` and ARCore's reflection cube carry it).

Faces and texels
- Faces ``+X, -X, +Y, -Y, +Z, -Z`` of the probe frame (+y up), each ``N x N``, row 0 at the top,
  in the OpenGL / KTX cube-map table: texel (row i, col j) has ``sc = 2 (j + 0.5) / N - 1``,
  ``tc = 2 (i + 0.5) / N - 1`` and direction
  ``+X: (1, -tc, -sc)``, ``-X: (-1, -tc, sc)``, ``+Y: (sc, 1, tc)``, ``-Y: (sc, -1, -tc)``,
  ``+Z: (sc, -tc, 1)``, ``-Z: (-sc, -tc, -1)`` (normalised).
- Mip ``m`` of ``M`` has size ``max(N >> m, 1)`` and perceptual roughness ``r_m = m / (M - 1)``
  (GGX ``alpha = r^2``); default ``N = 64`` down to 4, i.e. roughness 0, 0.25, 0.5, 0.75, 1.

The filter (Karis 2013's split-sum prefilter, ``n = v = r``): texel value
``P(n) = integral L(l) w(n . l) dl / integral w(n . l) dl`` with
``w(c) = D_GGX(h) max(c, 0)`` and ``(n . h)^2 = (1 + c) / 2``: a function of ``c = n . l``
alone, so the denominator is a per-mip constant (a 1-D integral, computed once). Mip 0 (roughness
0, a delta) is the map itself, sampled bilinearly at texel centres.

Evaluation: exact up to a controlled approximation, no Monte Carlo noise. The map becomes a
pyramid of points (128 x 256 at most, then 2 x 2 merges down to 4 x 8), each holding its power
(radiance x solid angle, float64), luminance power, and the luminance-weighted mean direction
``E[l]`` and second moment ``E[l l^T]`` of its pixels. Each output direction walks the pyramid
from the top (a Barnes-Hut descent): a cell is opened into its four children when it lies within
``NEAR`` lobe half-widths plus ``MARGIN`` cell radii, subtends more than half its distance, or
(rough lobes) straddles the direction's horizon; otherwise it counts as one point with
``E[w] ~ w(c) + w''(c) var(c) / 2`` (``c = n . E[l]``, ``var`` from the second moment), and
``g(c) E[max(c, 0)]`` under a normal ``c`` within three deviations of the clamp. The near field
is opened down to the coarsest level whose cells are at most ``FINE_FRACTION`` of the lobe
half-width (64 rows for roughness 0.25, 4 rows for roughness 1); only cells across the horizon
go deeper, where the clamp's kink needs them: to 64 rows when the lobe's weight at the horizon is
large (``w'(0) / w(1) = 4 alpha^4 >= 0.1``, roughness >= 0.75), to 32 rows when it is small but
not negligible (``>= 1e-3``). Black cells (the probe's lower hemisphere) are skipped. The tests
hold every mip within 1% of the brute-force integral over the map's own pixels (measured worst
0.92% over six maps, sphere and hemisphere, in mip 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from device.core.errors import InputError
from device.core.sphere import LUM_B, LUM_G, LUM_R, equirect_row_solid_angle

__all__ = ["FACES", "FACE_NAMES", "Cubemap", "CubemapFilter", "face_directions", "ggx_weight", "mip_roughness",
           "sample_equirect"]

FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
FACE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")  # the same faces in file and URL names
FINE_HEIGHT = 128
FINE_FRACTION = 0.7  # finest points at most this share of the lobe half-width
NEAR = 2.0  # cells within this many lobe half-widths of a direction are opened
MIN_FINE = 4  # the near field's finest level is never coarser than this
HORIZON = True  # open cells across a direction's horizon (rough lobes) ...
HORIZON_LEVELS = ((0.1, 64), (1e-3, 32))  # ... down to this height where 4 alpha^4 >= the bound
MARGIN = 1.0  # the near field reaches this many cell radii beyond NEAR half-widths


def face_directions(n: int) -> np.ndarray:
    """Unit directions (6, n, n, 3) of the texel centres, faces in :data:`FACES` order."""
    s = 2.0 * (np.arange(n) + 0.5) / n - 1.0
    tc, sc = np.meshgrid(s, s, indexing="ij")
    one = np.ones_like(sc)
    d = np.stack([
        np.stack([one, -tc, -sc], -1), np.stack([-one, -tc, sc], -1),
        np.stack([sc, one, tc], -1), np.stack([sc, -one, -tc], -1),
        np.stack([sc, -tc, one], -1), np.stack([-sc, -tc, -one], -1)])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def mip_roughness(levels: int) -> list[float]:
    return [m / (levels - 1) if levels > 1 else 0.0 for m in range(levels)]


def ggx_weight(c: np.ndarray, alpha: float) -> np.ndarray:
    """``D_GGX(h) max(n . l, 0)`` as a function of ``c = n . l`` (``n = v``)."""
    c = np.asarray(c, np.float64)
    a2 = alpha * alpha
    nh2 = 0.5 * (1.0 + c)
    den = nh2 * (a2 - 1.0) + 1.0
    return np.where(c > 0, a2 / (math.pi * den * den) * np.maximum(c, 0.0), 0.0)


def ggx_normaliser(alpha: float) -> float:
    """``integral over the sphere of w(n . l) dl = 2 pi integral_0^1 w(c) dc`` (Gauss-Legendre in
    a variable that resolves the peak at c = 1 for small alpha)."""
    # substitute c = 1 - s^2 ... the peak's width in (1 - c) is ~ alpha^2: integrate in u = log(1 - c)
    x, wq = np.polynomial.legendre.leggauss(400)
    lo, hi = math.log(1e-12), 0.0
    u = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
    one_minus_c = np.exp(u)
    c = 1.0 - one_minus_c
    f = ggx_weight(c, alpha) * one_minus_c  # dc = -(1 - c) du
    return float(2.0 * math.pi * 0.5 * (hi - lo) * np.dot(wq, f))


def _bilinear_taps(h: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices (n, 4) and weights (n, 4) of a bilinear lookup at directions (n, 3)."""
    from device.core.sphere import angles_from_directions

    w = 2 * h
    theta, phi = angles_from_directions(d)
    y = theta / math.pi * h - 0.5
    x = phi / (2 * math.pi) * w - 0.5
    y0 = np.floor(y).astype(np.int64)
    x0 = np.floor(x).astype(np.int64)
    fy, fx = y - y0, x - x0
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    xa, xb = x0 % w, (x0 + 1) % w
    idx = np.stack([ya * w + xa, ya * w + xb, yb * w + xa, yb * w + xb], -1)
    wts = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
    return idx, wts.astype(np.float32)


def sample_equirect(equirect: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, 2H, 3) map at unit directions (..., 3) (wraps in phi, clamps
    at the poles)."""
    from device.core.sphere import angles_from_directions

    h, w = equirect.shape[:2]
    theta, phi = angles_from_directions(d)
    y = theta / math.pi * h - 0.5
    x = phi / (2 * math.pi) * w - 0.5
    y0 = np.floor(y).astype(np.int64)
    x0 = np.floor(x).astype(np.int64)
    fy, fx = (y - y0)[..., None], (x - x0)[..., None]
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    xa, xb = x0 % w, (x0 + 1) % w
    m = equirect.astype(np.float64, copy=False)
    return ((1 - fy) * ((1 - fx) * m[ya, xa] + fx * m[ya, xb]) + fy * ((1 - fx) * m[yb, xa] + fx * m[yb, xb]))


@numba.njit(cache=True, nogil=True, parallel=True)
def _pixel_points(equirect: np.ndarray, omega_row: np.ndarray, f: int, pw: np.ndarray,
                  cen: np.ndarray, mom: np.ndarray, lum: np.ndarray) -> None:  # pragma: no cover
    """Finest points: f x f blocks of the map -> power, luminance power, and luminance-weighted
    sums of directions and of their outer products (xx, yy, zz, xy, xz, yz), each (h/f, 2h/f, .)
    (non-finite and negative values count as 0). Block rows in parallel; the columns' sines and
    cosines from one table."""
    h, w = equirect.shape[0], equirect.shape[1]
    sp = np.empty(w)
    cp = np.empty(w)
    for c in range(w):
        p = 2.0 * math.pi * (c + 0.5) / w
        sp[c] = math.sin(p)
        cp[c] = math.cos(p)
    for i in numba.prange(h // f):
        for j in range(w // f):
            pw[i, j, :] = 0.0
            cen[i, j, :] = 0.0
            mom[i, j, :] = 0.0
            lum[i, j] = 0.0
        for r in range(i * f, (i + 1) * f):
            t = math.pi * (r + 0.5) / h
            st, ct = math.sin(t), math.cos(t)
            om = omega_row[r]
            for c in range(w):
                red, grn, blu = equirect[r, c, 0], equirect[r, c, 1], equirect[r, c, 2]
                red = red if red > 0.0 and red < math.inf else 0.0
                grn = grn if grn > 0.0 and grn < math.inf else 0.0
                blu = blu if blu > 0.0 and blu < math.inf else 0.0
                y = LUM_R * red + LUM_G * grn + LUM_B * blu
                if y <= 0.0:
                    continue
                j = c // f
                pw[i, j, 0] += red * om
                pw[i, j, 1] += grn * om
                pw[i, j, 2] += blu * om
                yo = y * om
                dx, dy, dz = st * sp[c], ct, -st * cp[c]
                lum[i, j] += yo
                cen[i, j, 0] += yo * dx
                cen[i, j, 1] += yo * dy
                cen[i, j, 2] += yo * dz
                mom[i, j, 0] += yo * dx * dx
                mom[i, j, 1] += yo * dy * dy
                mom[i, j, 2] += yo * dz * dz
                mom[i, j, 3] += yo * dx * dy
                mom[i, j, 4] += yo * dx * dz
                mom[i, j, 5] += yo * dy * dz


@numba.njit(cache=True, nogil=True, inline="always")
def _expected_weight(nx: float, ny: float, nz: float, m: np.ndarray, s: np.ndarray,
                     k0: float, q: float) -> float:  # pragma: no cover - compiled
    """E[w(n . l)] over a point's pixels, ``w(c) = g(c) max(c, 0)``, ``g(c) = k0 / (1 + q (1 + c))^2``,
    from the point's moments: ``c = n . E[l]``, ``var(c) = n^T E[l l^T] n - c^2``.
    Away from the clamp, to second order: ``w(c) + w''(c) var / 2``. Within three standard
    deviations of it, the clamp is taken in expectation with ``c`` normal:
    ``g(c) E[max(c, 0)] = g(c) (c Phi(c / sd) + sd phi(c / sd))``."""
    c = nx * m[0] + ny * m[1] + nz * m[2]
    var = (nx * nx * s[0] + ny * ny * s[1] + nz * nz * s[2]
           + 2.0 * (nx * ny * s[3] + nx * nz * s[4] + ny * nz * s[5])) - c * c
    sd = math.sqrt(var) if var > 0.0 else 0.0
    if c < 3.0 * sd:
        if c < -3.0 * sd or sd <= 0.0:
            return 0.0
        den = 1.0 + q * (1.0 + c)
        z = c / sd
        clamp = c * 0.5 * math.erfc(-z * 0.7071067811865476) + sd * 0.3989422804014327 * math.exp(-0.5 * z * z)
        return k0 / (den * den) * clamp
    den = 1.0 + q * (1.0 + c)
    inv = 1.0 / den
    w = k0 * c * inv * inv
    if var > 0.0:
        w2 = k0 * inv * inv * inv * (-4.0 * q + 6.0 * c * q * q * inv)
        w += 0.5 * w2 * var
        if w < 0.0:
            w = 0.0
    return w


@numba.njit(cache=True, nogil=True, parallel=True)
def _prefilter_kernel(out_dirs: np.ndarray, alpha: float, inv_norm: float, open_cos: np.ndarray,
                      horizon_sin: np.ndarray, heights: np.ndarray, offsets: np.ndarray, mean: np.ndarray,
                      mom: np.ndarray, pw: np.ndarray, lum: np.ndarray,
                      out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Each output direction walks the point pyramid from its coarsest level (a Barnes-Hut
    descent): a cell of level k is taken as one point (its moments) unless ``n . E[l] >
    open_cos[k]`` (it lies within the near field or subtends too much of its distance, see
    :meth:`CubemapFilter._opening`) or ``|n . E[l]| < horizon_sin[k]`` (it straddles the
    direction's horizon); then its four children are visited. Cells of the finest level are always
    points. Levels are stored flat, coarsest first: level k has ``heights[k] x 2 heights[k]``
    cells from ``offsets[k]``."""
    a2 = alpha * alpha
    k0 = a2 / math.pi
    q = 0.5 * (a2 - 1.0)
    nlev = heights.shape[0]
    for i in numba.prange(out_dirs.shape[0]):
        nx, ny, nz = out_dirs[i, 0], out_dirs[i, 1], out_dirs[i, 2]
        r = 0.0
        g = 0.0
        b = 0.0
        stack_l = np.empty(256, np.int64)
        stack_k = np.empty(256, np.int64)
        top = 0
        h0 = heights[0]
        for kk in range(2 * h0 * h0):
            stack_l[top], stack_k[top] = 0, kk
            top += 1
        while top > 0:
            top -= 1
            lv, kk = stack_l[top], stack_k[top]
            k = offsets[lv] + kk
            if lum[k] <= 0.0:
                continue
            m = mean[k]
            c = nx * m[0] + ny * m[1] + nz * m[2]
            if lv + 1 < nlev and (c > open_cos[lv] or abs(c) < horizon_sin[lv]):
                h = heights[lv]
                rr, cc = kk // (2 * h), kk % (2 * h)
                w2 = 4 * h
                base = 2 * rr * w2 + 2 * cc
                stack_l[top], stack_k[top] = lv + 1, base
                stack_l[top + 1], stack_k[top + 1] = lv + 1, base + 1
                stack_l[top + 2], stack_k[top + 2] = lv + 1, base + w2
                stack_l[top + 3], stack_k[top + 3] = lv + 1, base + w2 + 1
                top += 4
                continue
            wt = _expected_weight(nx, ny, nz, m, mom[k], k0, q)
            if wt > 0.0:
                r += wt * pw[k, 0]
                g += wt * pw[k, 1]
                b += wt * pw[k, 2]
        out[i, 0] = r * inv_norm
        out[i, 1] = g * inv_norm
        out[i, 2] = b * inv_norm


@dataclass
class Cubemap:
    """``mips[m]``: (6, n_m, n_m, 3) float32, faces in :data:`FACES` order; ``roughness[m]``."""

    mips: list[np.ndarray]
    roughness: list[float]

    @property
    def size(self) -> int:
        return int(self.mips[0].shape[1])


@dataclass
class _Level:
    """Points of one pyramid level: power (h, 2h, 3), luminance power (h, 2h), and the
    luminance-weighted means of the direction (h, 2h, 3) and of its outer product (h, 2h, 6)."""

    pw: np.ndarray
    lum: np.ndarray
    mean: np.ndarray
    mom: np.ndarray

    @property
    def height(self) -> int:
        return int(self.lum.shape[0])


def _mean(total: np.ndarray, lum: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(total / np.where(lum > 0, lum, 1.0)[..., None])


def _pyramid(equirect: np.ndarray, top: int = FINE_HEIGHT) -> dict[int, _Level]:
    """Points of the map at heights top, top/2, ... 2 (keyed by height)."""
    h, w = equirect.shape[:2]
    hf = min(top, h)
    while h % hf:
        hf //= 2
    f = h // hf
    pw = np.empty((hf, 2 * hf, 3))
    cen = np.empty((hf, 2 * hf, 3))
    mom = np.empty((hf, 2 * hf, 6))
    lum = np.empty((hf, 2 * hf))
    _pixel_points(np.ascontiguousarray(equirect, np.float32), equirect_row_solid_angle(h, w), f,
                  pw, cen, mom, lum)
    out = {hf: _Level(pw, lum, _mean(cen, lum), _mean(mom, lum))}
    while pw.shape[0] >= 4:  # the sums merge 2 x 2; the means follow from them
        pw, lum, cen, mom = (_down(a) for a in (pw, lum, cen, mom))
        out[pw.shape[0]] = _Level(pw, lum, _mean(cen, lum), _mean(mom, lum))
    return out


def _down(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        return _down_sum(a[..., None])[..., 0]
    return _down_sum(a)


@numba.njit(cache=True, nogil=True)
def _down_sum(a: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """2 x 2 block sums of an (h, w, k) array (numpy's strided reductions cost 5 x this)."""
    h, w, k = a.shape
    out = np.zeros((h // 2, w // 2, k))
    for i in range(h // 2):
        for j in range(w // 2):
            for q in range(k):
                out[i, j, q] = (a[2 * i, 2 * j, q] + a[2 * i, 2 * j + 1, q]
                                + a[2 * i + 1, 2 * j, q] + a[2 * i + 1, 2 * j + 1, q])
    return out


def _flat_pyramid(pyr: dict[int, _Level]) -> tuple[np.ndarray, ...]:
    """Levels of height >= 4, coarsest first, as flat arrays for the kernel: (heights,
    offsets, mean (n, 3), mom (n, 6), pw (n, 3), lum (n,))."""
    hs = sorted(h for h in pyr if h >= 4) or [max(pyr)]
    offs = np.cumsum([0] + [2 * h * h for h in hs[:-1]]).astype(np.int64)
    cat = [np.ascontiguousarray(np.concatenate([getattr(pyr[h], name).reshape(2 * h * h, -1) for h in hs]))
           for name in ("mean", "mom", "pw", "lum")]
    return (np.array(hs, np.int64), offs, cat[0], cat[1], cat[2], cat[3].reshape(-1))


class CubemapFilter:
    """Prefilters maps into :class:`Cubemap` s of one size and mip count (directions, normalisers
    and near radii computed once)."""

    def __init__(self, size: int = 64, levels: int | None = None, min_size: int = 4) -> None:
        if size < 1 or size & (size - 1) or size > 1024:
            raise InputError(f"cubemap size must be a power of two in [1, 1024], got {size}", param="size")
        if levels is None:
            levels = int(math.log2(size // max(min_size, 1))) + 1 if size >= min_size else 1
        if not 1 <= levels <= int(math.log2(size)) + 1:
            raise InputError(f"cubemap levels must be in [1, {int(math.log2(size)) + 1}], got {levels}",
                             param="levels")
        self.size, self.levels = size, levels
        self.roughness = mip_roughness(levels)
        self._dirs = [face_directions(max(size >> m, 1)) for m in range(levels)]
        self._alpha = [max(r * r, 1e-4) for r in self.roughness]
        self._norm = [ggx_normaliser(a) for a in self._alpha]
        self._bilinear: tuple[tuple[int, int], tuple[np.ndarray, np.ndarray]] | None = None

    def _plan(self, m: int) -> tuple[int, float, int]:
        """For mip ``m``: the near field's finest pyramid height (cells at most ``FINE_FRACTION``
        of the lobe's half-width, GGX half-width in l ~ 2 atan(0.64 alpha)), the near angle
        (``NEAR`` half-widths), and the height down to which cells across the horizon are opened
        (0: none), from the lobe's weight at the horizon ``w'(0) / w(1) = 4 alpha^4``."""
        half = 2.0 * math.atan(0.64 * self._alpha[m])
        fine = FINE_HEIGHT
        while fine > MIN_FINE and math.pi / (fine // 2) <= FINE_FRACTION * half:
            fine //= 2
        edge = 4.0 * self._alpha[m] ** 4
        horizon = next((h for bound, h in HORIZON_LEVELS if edge >= bound), 0) if HORIZON else 0
        return fine, NEAR * half, horizon

    @staticmethod
    def _opening(heights: np.ndarray, fine: int, near: float, horizon: int) -> tuple[np.ndarray, np.ndarray]:
        """Per level, the opening tests without an arccos per cell: a cell of angular radius
        ``rho`` (bound ``sqrt(2) pi / h``) at angle ``acos(n . E[l])`` is opened when that angle
        is below ``max(near + MARGIN rho, 2 rho)`` (within the near field, or subtending more
        than half its distance), i.e. ``n . E[l] > cos(that)``, on levels coarser than ``fine``;
        and when it straddles the horizon, ``|n . E[l]| < sin(rho)``, on levels coarser than
        ``horizon``."""
        rho = math.sqrt(2.0) * math.pi / heights.astype(np.float64)
        limit = np.maximum(near + MARGIN * rho, 2.0 * rho)
        open_cos = np.where(limit >= math.pi, -2.0, np.cos(np.minimum(limit, math.pi)))
        open_cos = np.where(heights >= fine, 2.0, open_cos)
        horizon_sin = np.where(heights < horizon, np.sin(np.minimum(rho, math.pi / 2)), -1.0)
        return open_cos, horizon_sin

    def filter(self, equirect: np.ndarray) -> Cubemap:
        a = np.asarray(equirect)
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
            raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {a.shape}", param="equirect")
        mips = [self._mip0(a)]
        if self.levels > 1:
            flat = _flat_pyramid(_pyramid(a))
            heights, offsets = flat[0], flat[1]
            for m in range(1, self.levels):
                dirs = self._dirs[m].reshape(-1, 3)
                out = np.zeros((len(dirs), 3))
                fine_h, near, horizon = self._plan(m)
                n = int(np.searchsorted(heights, min(max(fine_h, horizon), int(heights[-1])))) + 1
                mean, mom, pw, lum = flat[2:]
                open_cos, horizon_sin = self._opening(heights[:n], fine_h, near, horizon)
                _prefilter_kernel(dirs, self._alpha[m], 1.0 / self._norm[m], open_cos, horizon_sin,
                                  heights[:n], offsets[:n], mean, mom, pw, lum, out)
                mips.append(out.reshape(self._dirs[m].shape).astype(np.float32))
        return Cubemap(mips, list(self.roughness))

    def _mip0(self, a: np.ndarray) -> np.ndarray:
        """Roughness 0: the map at texel centres, bilinear (indices and weights cached per map size)."""
        h = a.shape[0]
        key = (h, self.size)
        if self._bilinear is None or self._bilinear[0] != key:
            self._bilinear = (key, _bilinear_taps(h, self._dirs[0].reshape(-1, 3)))
        idx, wts = self._bilinear[1]
        flat = a.reshape(-1, 3)
        px = flat[idx]  # (n, 4, 3)
        px = np.where(np.isfinite(px) & (px > 0), px, np.float32(0))
        return np.einsum("nk,nkc->nc", wts, px).reshape(6, self.size, self.size, 3).astype(np.float32)

    def brute_force(self, equirect: np.ndarray, mip: int, dirs: np.ndarray) -> np.ndarray:
        """The reference: the filter integral over every pixel of the map at ``dirs`` (k, 3)."""
        from device.core.sphere import equirect_directions

        a = np.where(np.isfinite(equirect) & (equirect > 0), equirect, 0).astype(np.float64)
        h = a.shape[0]
        d = equirect_directions(h).reshape(-1, 3)
        pw = a.reshape(-1, 3) * np.repeat(equirect_row_solid_angle(h), 2 * h)[:, None]
        if mip == 0:
            return sample_equirect(a, dirs)
        wts = ggx_weight(np.asarray(dirs) @ d.T, self._alpha[mip])
        return wts @ pw / self._norm[mip]
