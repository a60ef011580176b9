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

Evaluation: exact at grid points up to a truncation in azimuthal frequency, no Monte Carlo
noise. The weight depends on ``n . l`` alone, so between an output row at polar angle
``theta_i`` and a source row ``theta_j`` of equirect grids it depends only on the difference of
their longitudes: the filter is a circular convolution along each row pair, i.e. one real
(rows x source rows) matrix per azimuthal frequency ``m`` (:func:`_kernel_spectra`, made once per
mip and source size and kept by the filter) applied to the source rows' spectra (one ``rfft``
of the map per frame, shared by every mip):
``Y[m, i] = sum_j K[m, i, j] X[j, m]``; an inverse ``rfft`` of ``Y`` gives the mip on an
equirect grid of output directions, from which each texel is read with Catmull-Rom weights
(across a pole, the row beyond it half a turn away). Per mip, from the lobe's half-width ``hw``
(GGX, in l, ``2 atan(0.64 alpha)``): grid rows ``>= GRID_PER_LOBE pi / hw`` (a power of two,
16 .. 256: 128 for roughness 0.25, 16 for 0.75 and 1), frequencies ``FREQ_PER_LOBE / hw``
but at least ``MIN_FREQS`` (82 for roughness 0.25, 48 above).

What the grid cannot carry is taken apart: the ``BRIGHT`` pixels of most power (a sun, a
lamp) leave the map before its ``rfft`` and are summed exactly at every texel from their own
directions (:func:`_add_points`). Through the grid, a sun would put the clamp ``max(n . l, 0)``
- a kink along the great circle 90 degrees from it - and the narrow lobe of roughness 0.25
between grid points, where interpolation cannot follow them (7-160% in the rough mips, 1.4-2.6%
in mip 1, measured); what remains of the map is spread enough that its kinks are smoothed over.
Maps of more than ``MAX_SOURCE`` rows are averaged 2 x 2 first (that moves a pixel's power up
to a quarter of a source pixel); black rows (a probe's lower hemisphere) are left out of the
transform and the products. The tests hold every mip within 1% of the brute-force integral over
the map's own pixels (measured worst 0.91%, dikhololo's probe hemisphere in mip 3; 0.03-0.09% in
mip 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import LUM_B, LUM_G, LUM_R, equirect_row_solid_angle

__all__ = ["FACES", "FACE_NAMES", "Cubemap", "CubemapFilter", "face_directions", "ggx_weight", "mip_roughness",
           "sample_equirect"]

FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
FACE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")  # the same faces in file and URL names
MAX_SOURCE = 512  # source rows at most (larger maps are averaged 2 x 2 down to this)
BRIGHT = 512  # the brightest pixels, summed exactly at each texel
GRID_PER_LOBE = 3.2  # output grid cells per lobe half-width (at least)
FREQ_PER_LOBE = 6.4  # azimuthal frequencies kept: this / the half-width in radians ...
MIN_FREQS = 48  # ... and never fewer (the clamp max(n . l, 0) is a kink in the rough lobes)


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


def _cells(rows: int, cols: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where unit directions (n, 3) fall in a (rows, cols) equirect grid of cell centres: the
    cell at or before each (row ``y0``, column ``x0``, unwrapped) and the fractions ``fy``, ``fx``
    beyond it."""
    from lightprobe.core.sphere import angles_from_directions

    theta, phi = angles_from_directions(d)
    y = theta / math.pi * rows - 0.5
    x = phi / (2 * math.pi) * cols - 0.5
    y0 = np.floor(y).astype(np.int64)
    x0 = np.floor(x).astype(np.int64)
    return y0, x0, y - y0, x - x0


def _bilinear(h: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices (n, 4) and float64 weights (n, 4) of a bilinear lookup in an (h, 2h)
    map at directions (n, 3) (wraps in phi, clamps at the poles)."""
    w = 2 * h
    y0, x0, fy, fx = _cells(h, w, d)
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    xa, xb = x0 % w, (x0 + 1) % w
    idx = np.stack([ya * w + xa, ya * w + xb, yb * w + xa, yb * w + xb], -1)
    return idx, np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)


def sample_equirect(equirect: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (H, 2H, 3) map at unit directions (..., 3) (wraps in phi, clamps
    at the poles), float64."""
    d = np.asarray(d)
    idx, wts = _bilinear(equirect.shape[0], d.reshape(-1, 3))
    m = equirect.astype(np.float64, copy=False).reshape(-1, 3)
    return np.einsum("nk,nkc->nc", wts, m[idx]).reshape(d.shape)


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _add_points(dirs: np.ndarray, pts: np.ndarray, power: np.ndarray, alpha: float, inv_norm: float,
                out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[i] += sum_k w(dirs[i] . pts[:, k]) power[:, k] / norm``: the brightest pixels,
    each at its own direction (``w`` of :func:`ggx_weight`; ``pts`` (3, k) and ``power`` (3, k),
    component-major so the inner loop vectorises). Texels in parallel."""
    a2 = alpha * alpha
    k0 = a2 / math.pi * inv_norm
    q = 0.5 * (a2 - 1.0)
    px, py, pz = pts[0], pts[1], pts[2]
    pr, pg, pb = power[0], power[1], power[2]
    for i in numba.prange(dirs.shape[0]):
        nx, ny, nz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        r = 0.0
        g = 0.0
        b = 0.0
        for k in range(px.shape[0]):
            c = max(nx * px[k] + ny * py[k] + nz * pz[k], 0.0)
            den = 1.0 + q * (1.0 + c)
            wt = k0 * c / (den * den)
            r += wt * pr[k]
            g += wt * pg[k]
            b += wt * pb[k]
        out[i, 0] += r
        out[i, 1] += g
        out[i, 2] += b


@numba.njit(cache=True, nogil=True, parallel=True)
def _gather(flat: np.ndarray, idx: np.ndarray, wts: np.ndarray, clean: bool,
            out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[i] = sum_k wts[i, k] flat[idx[i, k]]`` (rows of 3); with ``clean``, non-finite and
    negative values read as 0. Texels in parallel."""
    for i in numba.prange(idx.shape[0]):
        r = 0.0
        g = 0.0
        b = 0.0
        for k in range(idx.shape[1]):
            j = idx[i, k]
            wt = wts[i, k]
            x, y, z = flat[j, 0], flat[j, 1], flat[j, 2]
            if clean:
                x = x if x > 0.0 and x < math.inf else 0.0
                y = y if y > 0.0 and y < math.inf else 0.0
                z = z if z > 0.0 and z < math.inf else 0.0
            r += wt * x
            g += wt * y
            b += wt * z
        out[i, 0] = r
        out[i, 1] = g
        out[i, 2] = b


@numba.njit(cache=True, nogil=True, parallel=True)
def _clean_power(a: np.ndarray, omega_row: np.ndarray, src: np.ndarray,
                 power: np.ndarray) -> None:  # pragma: no cover - compiled
    """``src``: ``a`` with non-finite and negative values 0; ``power``: its luminance x the
    row's solid angle per pixel. Rows in parallel."""
    for i in numba.prange(a.shape[0]):
        om = omega_row[i]
        for j in range(a.shape[1]):
            red, grn, blu = a[i, j, 0], a[i, j, 1], a[i, j, 2]
            red = red if red > 0.0 and red < math.inf else 0.0
            grn = grn if grn > 0.0 and grn < math.inf else 0.0
            blu = blu if blu > 0.0 and blu < math.inf else 0.0
            src[i, j, 0] = red
            src[i, j, 1] = grn
            src[i, j, 2] = blu
            power[i, j] = (LUM_R * red + LUM_G * grn + LUM_B * blu) * om


def _kernel_spectra(alpha: float, norm: float, height: int, rows: int, freqs: int, j0: int,
                    j1: int) -> np.ndarray:
    """``K[m, i, j]`` (float32, ``(freqs + 1, rows, j1 - j0)``): the real DFT, over the column
    offset ``q`` of a ``(height, 2 height)`` source grid, of ``w(n_i . l_jq) omega_j / norm``,
    ``n_i`` at the centre of output row ``i`` of ``rows`` (column 0), ``l_jq`` at the centre of
    source row ``j0 + j``, ``q`` columns away. Real: the weight is even in the offset."""
    w = 2 * height
    ts = math.pi * (np.arange(j0, j1) + 0.5) / height
    cos_dphi = np.cos(2.0 * math.pi * np.arange(w) / w)
    scale = (equirect_row_solid_angle(height, w)[j0:j1] / norm)[:, None]
    out = np.empty((freqs + 1, rows, j1 - j0), np.float32)
    for i in range(rows):
        t = math.pi * (i + 0.5) / rows
        c = (math.cos(t) * np.cos(ts))[:, None] + (math.sin(t) * np.sin(ts))[:, None] * cos_dphi[None, :]
        out[:, i, :] = np.fft.rfft(ggx_weight(c, alpha) * scale, axis=1)[:, : freqs + 1].real.T
    return out


def _cubic_taps(rows: int, cols: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (n, 16) and weights (n, 16) of a Catmull-Rom lookup at directions (n, 3) in a
    (rows, cols) equirect grid of cell centres; beyond a pole, row ``-1 - r`` half a turn away."""
    y0, x0, fy, fx = _cells(rows, cols, d)

    def weights(f: np.ndarray) -> np.ndarray:
        f2, f3 = f * f, f * f * f
        return np.stack([-0.5 * f3 + f2 - 0.5 * f, 1.5 * f3 - 2.5 * f2 + 1.0, -1.5 * f3 + 2.0 * f2 + 0.5 * f,
                         0.5 * f3 - 0.5 * f2], -1)

    wy, wx = weights(fy), weights(fx)
    r = y0[:, None] + np.arange(-1, 3)[None, :]  # (n, 4)
    c = x0[:, None] + np.arange(-1, 3)[None, :]
    over = (r < 0) | (r >= rows)
    rr = np.where(r < 0, -1 - r, np.where(r >= rows, 2 * rows - 1 - r, r))
    idx = rr[:, :, None] * cols + (c[:, None, :] + np.where(over, cols // 2, 0)[:, :, None]) % cols
    return idx.reshape(-1, 16), (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16).astype(np.float32)


def _source(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map as the filter's source, float32, non-finite and negative values 0, averaged 2 x 2
    down to at most ``MAX_SOURCE`` rows; its power per pixel (luminance x solid angle); its rows'
    solid angles."""
    a = np.ascontiguousarray(a, np.float32)
    while a.shape[0] > MAX_SOURCE:
        h, w = a.shape[0] // 2, a.shape[1] // 2
        a = np.where(np.isfinite(a) & (a > 0), a, 0)[: 2 * h, : 2 * w].reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
    h, w = a.shape[:2]
    src = np.empty((h, w, 3), np.float32)
    power = np.empty((h, w), np.float32)
    omega = equirect_row_solid_angle(h, w)
    _clean_power(a, omega, src, power)
    return src, power, omega


def _take_brightest(src: np.ndarray, power: np.ndarray, omega: np.ndarray, count: int, j0: int,
                    j1: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` pixels of most power (among rows ``j0 .. j1``, the rest is black): their
    directions and powers (3, k) float64, taken out of ``src`` (set to 0 there)."""
    from lightprobe.core.sphere import directions_from_angles

    h, w = src.shape[:2]
    flat = power[j0:j1].reshape(-1)
    idx = np.argpartition(flat, -count)[-count:] if count < flat.size else np.arange(flat.size)
    idx = idx[flat[idx] > 0]
    r, c = j0 + idx // w, idx % w
    pts = directions_from_angles(math.pi * (r + 0.5) / h, 2.0 * math.pi * (c + 0.5) / w)
    pw = src[r, c].astype(np.float64) * omega[r][:, None]
    src[r, c] = 0.0
    return np.ascontiguousarray(pts.T, np.float64), np.ascontiguousarray(pw.T)


@dataclass
class Cubemap:
    """``mips[m]``: (6, n_m, n_m, 3) float32, faces in :data:`FACES` order; ``roughness[m]``."""

    mips: list[np.ndarray]
    roughness: list[float]

    @property
    def size(self) -> int:
        return int(self.mips[0].shape[1])

    def ktx2(self, unit: str) -> bytes:
        """The cube map as the probe serves it and ``lightprobe export`` writes it: RGBA16F KTX2
        (:mod:`lightprobe.core.ktx2`) with each mip's roughness, the unit and the face table."""
        from lightprobe.core.ktx2 import ktx2_cubemap_bytes

        return ktx2_cubemap_bytes(self.mips, {"lightprobe.roughness": ",".join(f"{x:g}" for x in self.roughness),
                                              "lightprobe.unit": str(unit),
                                              "lightprobe.faces": "+X,-X,+Y,-Y,+Z,-Z probe frame, +y up"})


class CubemapFilter:
    """Prefilters maps into :class:`Cubemap` s of one size and mip count (texel directions and
    normalisers made once; per source size, each mip's kernel spectra and grid taps, kept)."""

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
        # (mip, source height) -> (first row, end row, _kernel_spectra of those source rows)
        self._tables: dict[tuple[int, int], tuple[int, int, np.ndarray]] = {}
        self._grid_taps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _plan(self, m: int, width: int) -> tuple[int, int, int]:
        """Mip ``m``'s output grid and frequencies for a source ``width`` columns wide: rows
        (a power of two, cells at most 1 / ``GRID_PER_LOBE`` of the lobe's half-width, GGX
        half-width in l ~ 2 atan(0.64 alpha); 16 .. 256), the azimuthal frequencies kept
        (``FREQ_PER_LOBE`` / half-width, at least ``MIN_FREQS``, below the source's Nyquist) and
        the grid's columns (>= 2 rows, holding every kept frequency)."""
        half = 2.0 * math.atan(0.64 * self._alpha[m])
        rows = min(max(1 << max(0, math.ceil(math.log2(math.pi * GRID_PER_LOBE / half))), 16), 256)
        freqs = min(max(math.ceil(FREQ_PER_LOBE / half), MIN_FREQS), width // 2 - 1)
        return rows, freqs, max(2 * rows, 2 * (freqs + 1))

    def _spectra(self, m: int, height: int, j0: int, j1: int) -> np.ndarray:
        """Mip ``m``'s :func:`_kernel_spectra` for source rows ``j0 .. j1`` (a probe's maps are
        black below the horizon: half the table), kept for the last rows asked."""
        key = (m, height)
        hit = self._tables.get(key)
        if hit is None or hit[0] > j0 or hit[1] < j1:
            rows, freqs, _ = self._plan(m, 2 * height)
            hit = (j0, j1, _kernel_spectra(self._alpha[m], self._norm[m], height, rows, freqs, j0, j1))
            self._tables[key] = hit
        return hit[2][:, :, j0 - hit[0]: j1 - hit[0]]

    def _taps(self, m: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        key = (m, height)
        if key not in self._grid_taps:
            rows, _, cols = self._plan(m, 2 * height)
            self._grid_taps[key] = _cubic_taps(rows, cols, self._dirs[m].reshape(-1, 3))
        return self._grid_taps[key]

    @staticmethod
    def _shift(freqs: int, cols: int, width: int) -> np.ndarray:
        return np.exp(1j * math.pi * np.arange(freqs + 1) * (1.0 / cols - 1.0 / width)).astype(np.complex64)

    def filter(self, equirect: np.ndarray) -> Cubemap:
        a = np.asarray(equirect)
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
            raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {a.shape}", param="equirect")
        mips = [self._mip0(a)]
        if self.levels == 1:
            return Cubemap(mips, list(self.roughness))
        src, power, omega = _source(a)
        h, w = src.shape[:2]
        nonzero = np.flatnonzero(power.any(axis=1))
        j0, j1 = (int(nonzero[0]), int(nonzero[-1]) + 1) if len(nonzero) else (0, 0)
        pts, pw = _take_brightest(src, power, omega, BRIGHT, j0, j1)
        most = max(self._plan(m, w)[1] for m in range(1, self.levels))
        spec = np.fft.rfft(np.ascontiguousarray(src[j0:j1].transpose(2, 0, 1)), axis=2)[:, :, : most + 1]
        x = np.ascontiguousarray(np.concatenate([spec.real, spec.imag]).transpose(2, 1, 0), np.float32)
        for m in range(1, self.levels):
            _, freqs, cols = self._plan(m, w)
            dirs = self._dirs[m].reshape(-1, 3)
            if j1 > j0:
                y = np.matmul(self._spectra(m, h, j0, j1), x[: freqs + 1])  # (freqs + 1, rows, 6)
                yc = np.ascontiguousarray((y[..., :3] + 1j * y[..., 3:]).transpose(1, 2, 0))  # (rows, 3, freqs + 1)
                # grid columns at 2 pi (p + 1/2) / cols, the source's at 2 pi (q + 1/2) / w
                yc *= self._shift(freqs, cols, w)
                grid = np.fft.irfft(yc, n=cols, axis=2).transpose(0, 2, 1)  # (rows, cols, 3)
                grid = np.ascontiguousarray(grid.reshape(-1, 3), np.float32)
                idx, wts = self._taps(m, h)
                out = np.empty((len(dirs), 3))
                _gather(grid, idx, wts, False, out)
                out *= cols / w
            else:
                out = np.zeros((len(dirs), 3))
            _add_points(dirs, pts, pw, self._alpha[m], 1.0 / self._norm[m], out)
            mips.append(np.maximum(out, 0.0).reshape(self._dirs[m].shape).astype(np.float32))
        return Cubemap(mips, list(self.roughness))

    def _mip0(self, a: np.ndarray) -> np.ndarray:
        """Roughness 0: the map at texel centres, bilinear (indices and weights cached per map size)."""
        h = a.shape[0]
        key = (h, self.size)
        if self._bilinear is None or self._bilinear[0] != key:
            idx, wts = _bilinear(h, self._dirs[0].reshape(-1, 3))
            self._bilinear = (key, (idx, wts.astype(np.float32)))
        idx, wts = self._bilinear[1]
        out = np.empty((len(idx), 3))
        _gather(np.ascontiguousarray(a, np.float32).reshape(-1, 3), idx, wts, True, out)
        return out.reshape(6, self.size, self.size, 3).astype(np.float32)
