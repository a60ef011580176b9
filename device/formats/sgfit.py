"""The probe's lighting as spherical Gaussians (Michiels, Put, Bekaert 2015, Section 5-6): SG lobes
fitted to the peaks, plus a multiscale residual transform on HEALPix for the rest.

The paper fixes the structure and leaves the numbers open (``../shared/NOTES.md``). The choices:

1. **Peaks** (paper Section 6: threshold + connected components). The bright regions of
   :mod:`lightprobe.device.formats.bright_regions` on a 64 x 128 energy-preserving reduction (threshold
   ``max(2% of the brightest, 20 x the mean)``), at most ``max_peaks`` by energy, each carrying at
   least ``min_peak_fraction`` of the light. At full resolution every pixel of the region, grown by
   one coarse pixel, gives up its *excess* over the local background (the per-channel median of a
   ring two coarse pixels wide around it): a lamp's light goes to its lobe, the wall behind it
   stays in the residual, continuous with its surroundings (the levels see no hole). A region becomes 1 SG, or 2-3 when it is
   elongated (the ratio of its principal spreads above 2 / 4: split along the major axis into
   equal-energy parts): the paper's "1-3 SGs per component".
2. **A peak lobe**: axis = the luminance-weighted mean direction ``m`` of its excess, normalised;
   sharpness from the mean resultant length ``|m|`` (``coth l - 1/l = |m|``: a lobe with the same
   spread); amplitude from its energy, ``mu = E / (2 pi (1 - exp(-2 l)) / l)`` per channel, so the
   lobe's integral is exactly the light it took.
3. **Residual levels** (after Ferrari 2004, as the paper cites): HEALPix ``nside`` 1, 2, 4, 8, 16 (by
   default), one lobe per pixel centre, sharpness ``ln 2 / (1 - cos theta_l)`` (half maximum at the
   pixel spacing ``theta_l``). Amplitudes by quasi-interpolation: each lobe carries its pixel's
   residual energy (``mu_k = E_k / integral G``), so a level's lobes hold exactly the residual's
   energy; the level's reconstruction is then scaled by the step ``s in [0, 1]`` that minimises the
   solid-angle-weighted L2 norm of what is left (so the residual never grows: ``s = 0`` leaves it
   unchanged) and subtracted; the next level fits what remains. Stop when the remaining
   ``|residual|`` holds less than ``residual_threshold`` of the light, or after the last level.
   Residual amplitudes may be negative (a correction of the coarser level); their sum with the
   coarser lobes is the radiance.
4. The residual lives on HEALPix ``nside`` 32 working cells (1.8 deg, 12,288 equal areas; fewer for
   maps under 128 rows): the map's power (peaks' excess removed) is summed into them exactly, every
   level's cells are unions of them (nested indexing: a lobe's energy is a contiguous sum), and a
   level's reconstruction is its lobes evaluated at the working cells' centres through a sparse
   float32 table truncated where a lobe falls below 1e-3 of its peak (built once per level set,
   14 MB). Equal areas make the step's weighted norms plain sums. Two compiled passes per level
   (reconstruction with the step's sums; subtraction with the remainder's norms), and one for a
   level's lobe energies (the contiguous sums). Each peak's growth, ring, background median and
   excess is one compiled pass over the region's box (:func:`_region_excess`; it was a dozen
   NumPy / ndimage calls of 0.1-0.3 ms each per peak). 36-64 ms per fit on a 128 x 256 equirect
   working map at first, 2.4-4.0 ms now on 256 x 512 (BENCHMARKS.md), at the same energy,
   diffuse and glossy errors.

Energy: the peaks' lobes plus the levels' hold the map's integral up to what the last level
leaves (asserted within 1% on the six shared maps).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numba
import numpy as np

from lightprobe.core.sg import SGLighting, level_sharpness, lobe_integral, sharpness_from_resultant
from lightprobe.core.sphere import (
    LUM_B,
    LUM_G,
    LUM_R,
    directions_from_angles,
    equirect_directions,
    equirect_row_solid_angle,
    lit_rows,
    luminance,
)

__all__ = ["DEFAULT_LEVELS", "fit_sg"]

DEFAULT_LEVELS = (1, 2, 4, 8, 16)
WORK_HEIGHT = 128
MAX_SHARPNESS = 1e6
PEAK_RELATIVE = 0.002  # a peak pixel exceeds 0.2% of the brightest ...
PEAK_CONTRAST = 20.0  # ... and 20 x the mean
_TRUNCATE = 1e-3


def _clean(a: np.ndarray) -> np.ndarray:
    """A float32 copy of an (H, W, 3) map with NaN, infinite and negative values as 0."""
    a = np.array(a, np.float32, order="C", copy=True)
    mn, mx = float(a.min(initial=0.0)), float(a.max(initial=0.0))
    if not (np.isfinite(mn) and np.isfinite(mx) and mn >= 0):
        a = np.where(np.isfinite(a) & (a > 0), a, np.float32(0))
    return a


WORK_NSIDE = 32  # the residual lives on HEALPix cells of this nside (equal areas, nested under every level)


def _work_nside(height: int, levels: tuple[int, ...]) -> int:
    """The working cells' nside: 32 (1.8 deg), coarser for maps under 128 rows (at least two of
    the map's pixels per cell), never coarser than the finest level."""
    n = WORK_NSIDE
    while n > 1 and n // 2 >= max(levels) and 12 * n * n > height * height:
        n //= 2
    return max(n, max(levels))


@lru_cache(maxsize=4)
def _work_cells(height: int, nside: int) -> np.ndarray:
    """The working cell (nested index) of every pixel centre of an (height, 2 height) map."""
    from lightprobe.core.healpix import vec2pix_nest

    return np.asarray(vec2pix_nest(nside, equirect_directions(height).reshape(-1, 3)), np.int32)


@lru_cache(maxsize=4)
def _level_tables(nside_w: int, levels: tuple[int, ...]) -> tuple[Any, ...]:
    """Per level: cell centres (n, 3), sharpness, and the unit-amplitude lobes at the working cell
    centres as a CSR matrix (indptr, indices int32, values float32), truncated where a lobe falls
    below ``_TRUNCATE`` of its peak."""
    from lightprobe.core.healpix import npix, pix2vec_nest

    d = pix2vec_nest(nside_w, np.arange(npix(nside_w)))
    out = []
    for nside in levels:
        centres = pix2vec_nest(nside, np.arange(npix(nside)))
        lam = level_sharpness(nside)
        cut = 1.0 + math.log(_TRUNCATE) / lam  # exp(lam (c - 1)) >= _TRUNCATE
        counts, cols, vals = [], [], []
        for s in range(0, len(d), 2048):
            c = d[s:s + 2048] @ centres.T
            i, j = np.nonzero(c >= cut)  # row-major: sorted by working cell
            counts.append(np.bincount(i, minlength=len(c)))
            cols.append(j.astype(np.int32))
            vals.append(np.exp(lam * (c[i, j] - 1.0)).astype(np.float32))
        indptr = np.concatenate([[0], np.cumsum(np.concatenate(counts))]).astype(np.int64)
        out.append((centres, lam, indptr, np.concatenate(cols), np.concatenate(vals)))
    return tuple(out)


@numba.njit(cache=True, nogil=True)
def _block_power(a, rows, f, omega_row):  # type: ignore[no-untyped-def]
    """Luminance x solid angle of the first ``rows`` rows of an (H, W, 3) map summed over f x f
    blocks: (H / f, W / f) float64."""
    w = a.shape[1]
    out = np.zeros((a.shape[0] // f, w // f))
    for r in range(rows):
        om = omega_row[r]
        br = r // f
        for c in range(w):
            out[br, c // f] += (LUM_R * a[r, c, 0] + LUM_G * a[r, c, 1] + LUM_B * a[r, c, 2]) * om
    return out


@numba.njit(cache=True, nogil=True)
def _cell_power(a, omega_row, cells, ncells):  # type: ignore[no-untyped-def]
    """Radiance x solid angle of an (H, W, 3) map summed per working cell (float64)."""
    h, w = a.shape[0], a.shape[1]
    out = np.zeros((ncells, 3))
    for r in range(h):
        om = omega_row[r]
        for c in range(w):
            k = cells[r * w + c]
            out[k, 0] += a[r, c, 0] * om
            out[k, 1] += a[r, c, 1] * om
            out[k, 2] += a[r, c, 2] * om
    return out


@numba.njit(cache=True, nogil=True)
def _group_sums(resid, n, scale):  # type: ignore[no-untyped-def]
    """``scale`` x the sums of ``n`` equal runs of consecutive rows of ``resid`` (cells, 3): a
    level's lobes from their nested working cells (numpy's strided ``reshape(n, -1, 3).sum(1)``
    took 0.1-0.2 ms a level)."""
    g = resid.shape[0] // n
    out = np.zeros((n, 3))
    for k in range(n):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for c in range(k * g, (k + 1) * g):
            s0 += resid[c, 0]
            s1 += resid[c, 1]
            s2 += resid[c, 2]
        out[k, 0] = s0 * scale
        out[k, 1] = s1 * scale
        out[k, 2] = s2 * scale
    return out


@numba.njit(cache=True, nogil=True)
def _subtract(resid, recon, step):  # type: ignore[no-untyped-def]
    """``resid -= step recon`` in place; returns what is left as the sum of its |luminance| and
    of its squares (``step = 0``: only the sums)."""
    lum = 0.0
    sq = 0.0
    for c in range(resid.shape[0]):  # 12k cells: a thread pool's wake-up costs more
        r0 = resid[c, 0] - step * recon[c, 0]
        r1 = resid[c, 1] - step * recon[c, 1]
        r2 = resid[c, 2] - step * recon[c, 2]
        resid[c, 0] = r0
        resid[c, 1] = r1
        resid[c, 2] = r2
        lum += abs(LUM_R * r0 + LUM_G * r1 + LUM_B * r2)
        sq += r0 * r0 + r1 * r1 + r2 * r2
    return lum, sq


@numba.njit(cache=True, nogil=True, parallel=True)
def _reconstruct(indptr, indices, vals, mu, resid, out):  # type: ignore[no-untyped-def]
    """A level's radiance at the working cells (``out``) from its lobes' amplitudes ``mu``, and
    the sums ``<resid, out>`` and ``<out, out>`` the step needs (equal cells: no weights).

    The product is the projection's CSR x RGB (:func:`lightprobe.device.projection.sparse.spmv_rgb`), but
    parallel and with the step's sums fused: 1.1-1.3 ms per fit against 2.1 ms for that serial
    kernel plus two dot products (measured 2026-12-06, five levels, AMD VM), a fifth of the fit."""
    num = 0.0
    den = 0.0
    for c in numba.prange(out.shape[0]):
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        for q in range(indptr[c], indptr[c + 1]):
            k = indices[q]
            v = np.float64(vals[q])
            r0 += v * mu[k, 0]
            r1 += v * mu[k, 1]
            r2 += v * mu[k, 2]
        out[c, 0] = r0
        out[c, 1] = r1
        out[c, 2] = r2
        num += resid[c, 0] * r0 + resid[c, 1] * r1 + resid[c, 2] * r2
        den += r0 * r0 + r1 * r1 + r2 * r2
    return num, den


@numba.njit(cache=True, nogil=True)
def _region_excess(full, labels, lab, r0, r1, c0, c1, f, rows):  # type: ignore[no-untyped-def]
    """One peak's excess, taken out of ``full`` (H, W, 3) in place: the region ``lab`` of the
    coarse ``labels`` grown by one coarse pixel (4-neighbours), within its box ``[r0, r1) x
    [c0, c1)``, gives up at full resolution (f x f blocks, rows below ``rows``) its radiance above
    the per-channel median of a ring two coarse pixels wide around it (unlabelled pixels only).
    Returns the rows, columns and excess (float64) of the pixels with a positive luminance excess,
    in row-major block order."""
    bh, bw = r1 - r0, c1 - c0
    grown = np.zeros((bh, bw), np.bool_)
    for i in range(bh):
        for j in range(bw):
            if labels[r0 + i, c0 + j] == lab:
                grown[i, j] = True
                if i > 0:
                    grown[i - 1, j] = True
                if i + 1 < bh:
                    grown[i + 1, j] = True
                if j > 0:
                    grown[i, j - 1] = True
                if j + 1 < bw:
                    grown[i, j + 1] = True
    # the ring: two more 4-neighbour dilations (a diamond of radius 2), minus the grown region
    dist = np.full((bh, bw), 3, np.int64)
    for i in range(bh):
        for j in range(bw):
            if grown[i, j]:
                for di in range(-2, 3):
                    for dj in range(abs(di) - 2, 3 - abs(di)):
                        ii, jj = i + di, j + dj
                        if 0 <= ii < bh and 0 <= jj < bw:
                            dist[ii, jj] = min(dist[ii, jj], abs(di) + abs(dj))
    n_ring = 0
    n_grown = 0
    for i in range(bh):
        for j in range(bw):
            rows_here = min(f, max(rows - (r0 + i) * f, 0))
            if grown[i, j]:
                n_grown += rows_here * f
            elif dist[i, j] <= 2 and labels[r0 + i, c0 + j] == 0:
                n_ring += rows_here * f
    bg = np.zeros(3)
    if n_ring > 0:
        vals = np.empty((3, n_ring), np.float32)
        k = 0
        for i in range(bh):
            for j in range(bw):
                if grown[i, j] or dist[i, j] > 2 or labels[r0 + i, c0 + j] != 0:
                    continue
                for a in range((r0 + i) * f, min((r0 + i + 1) * f, rows)):
                    for b in range((c0 + j) * f, (c0 + j + 1) * f):
                        for ch in range(3):
                            vals[ch, k] = full[a, b, ch]
                        k += 1
        for ch in range(3):
            bg[ch] = np.median(vals[ch])
    r_out = np.empty(n_grown, np.int64)
    c_out = np.empty(n_grown, np.int64)
    ex_out = np.empty((n_grown, 3))
    k = 0
    for i in range(bh):
        for j in range(bw):
            if not grown[i, j]:
                continue
            for a in range((r0 + i) * f, min((r0 + i + 1) * f, rows)):
                for b in range((c0 + j) * f, (c0 + j + 1) * f):
                    e0 = max(np.float64(full[a, b, 0]) - bg[0], 0.0)
                    e1 = max(np.float64(full[a, b, 1]) - bg[1], 0.0)
                    e2 = max(np.float64(full[a, b, 2]) - bg[2], 0.0)
                    if LUM_R * e0 + LUM_G * e1 + LUM_B * e2 <= 0:
                        continue
                    full[a, b, 0] = max(full[a, b, 0] - np.float32(e0), np.float32(0))
                    full[a, b, 1] = max(full[a, b, 1] - np.float32(e1), np.float32(0))
                    full[a, b, 2] = max(full[a, b, 2] - np.float32(e2), np.float32(0))
                    r_out[k] = a
                    c_out[k] = b
                    ex_out[k, 0] = e0
                    ex_out[k, 1] = e1
                    ex_out[k, 2] = e2
                    k += 1
    return r_out[:k], c_out[:k], ex_out[:k]


def _peaks(full: np.ndarray, rows: int, max_peaks: int, min_fraction: float, relative: float, contrast: float
           ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], float]:
    """The peaks' excess pixels: a list of (directions (k, 3), power (k, 3), luminance power (k,))
    per peak (brightest first), after taking the excess out of ``full`` in place; and the map's
    luminance integral."""
    from scipy import ndimage

    from lightprobe.device.formats.bright_regions import peak_threshold, sphere_labels

    h, w = full.shape[:2]
    ch = WORK_HEIGHT if h > WORK_HEIGHT and h % WORK_HEIGHT == 0 else h
    f = h // ch
    omega = equirect_row_solid_angle(h, w)
    c_pow = _block_power(full, rows, f, omega)
    c_omega = equirect_row_solid_angle(ch)
    total = float(c_pow.sum())
    if not total > 0:
        return [], 0.0
    c_lum = c_pow / c_omega[:, None]
    t = peak_threshold(c_lum, c_omega, relative, contrast, -(-rows // f))
    labels, n = sphere_labels(c_lum > t)
    if n == 0:
        return [], total
    power = np.bincount(labels.ravel(), c_pow.ravel(), n + 1)[1:]
    found = []
    boxes = ndimage.find_objects(labels)
    for lab in np.argsort(-power)[:max_peaks] + 1:
        if power[lab - 1] < min_fraction * total:
            break
        # the region's box, 3 coarse pixels wider (the growth and the ring; no wrap, as before)
        rs, cs = boxes[lab - 1]
        r0, r1 = max(rs.start - 3, 0), min(rs.stop + 3, ch)
        c0, c1 = (cs.start - 3, cs.stop + 3) if cs.start >= 3 and cs.stop + 3 <= 2 * ch else (0, 2 * ch)
        r_idx, c_idx, excess = _region_excess(full, labels, int(lab), r0, r1, c0, c1, f, rows)
        if len(r_idx) == 0:
            continue
        dirs = directions_from_angles(np.pi * (r_idx + 0.5) / h, 2 * np.pi * (c_idx + 0.5) / w)
        pw = excess * omega[r_idx][:, None]
        found.append((dirs, pw, luminance(pw)))
    return found, total


def _split(dirs: np.ndarray, pw: np.ndarray, lp: np.ndarray, max_lobes: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """1-3 parts of a peak, each fitted by one lobe. A peak whose light is concentrated far more
    than one Gaussian of its spread (a sun in its halo: the inner half of the energy within a
    radius under a third of the outer half's) splits radially into a core and one or two halo
    shells of equal energy; an elongated one (principal spreads above 2 : 1, above 4 : 1 for
    three parts) splits along its major axis into parts of equal energy; otherwise one part."""
    if max_lobes <= 1 or len(dirs) < 8:
        return [(dirs, pw, lp)]
    wsum = lp.sum()
    mean = lp @ dirs / wsum
    centre = mean / np.linalg.norm(mean)
    radius = np.arccos(np.clip(dirs @ centre, -1.0, 1.0))
    order = np.argsort(radius)
    cum = np.cumsum(lp[order]) / wsum
    inner = order[cum <= 0.5]
    outer = order[cum > 0.5]
    if len(inner) and len(outer):
        r_in = float(lp[inner] @ radius[inner] / lp[inner].sum())
        r_out = float(lp[outer] @ radius[outer] / lp[outer].sum())
        if r_in < r_out / 3.0:
            parts = min(max_lobes, 3)
            bins = np.minimum((cum * parts).astype(np.int64), parts - 1)
            return [(dirs[order[bins == b]], pw[order[bins == b]], lp[order[bins == b]])
                    for b in range(parts) if np.any(bins == b)]
    x = dirs - mean
    cov = (x * lp[:, None]).T @ x / wsum
    ev, evec = np.linalg.eigh(cov)
    spread = np.sqrt(np.maximum(ev[::-1], 0.0))  # descending: major, minor, (normal)
    ratio = spread[0] / max(spread[1], 1e-12)
    parts = 3 if (ratio > 4.0 and max_lobes >= 3) else 2 if ratio > 2.0 else 1
    if parts == 1:
        return [(dirs, pw, lp)]
    proj = x @ evec[:, -1]
    order = np.argsort(proj)
    cum = np.cumsum(lp[order]) / wsum
    bins = np.minimum((cum * parts).astype(np.int64), parts - 1)
    out = []
    for b in range(parts):
        idx = order[bins == b]
        if len(idx):
            out.append((dirs[idx], pw[idx], lp[idx]))
    return out


def _lobe(dirs: np.ndarray, pw: np.ndarray, lp: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Axis, sharpness and amplitude of one peak part (energy kept exactly)."""
    m = lp @ dirs / lp.sum()
    r = float(np.linalg.norm(m))
    lam = min(float(sharpness_from_resultant(np.array(r))), MAX_SHARPNESS)
    energy = pw.sum(axis=0)
    return m / r, lam, energy / float(lobe_integral(np.array(lam)))


def fit_sg(equirect: np.ndarray, *, levels: tuple[int, ...] = DEFAULT_LEVELS, residual_threshold: float = 0.01,
           max_peaks: int = 8, min_peak_fraction: float = 1e-3, max_peak_lobes: int = 3,
           peak_relative: float = PEAK_RELATIVE, peak_contrast: float = PEAK_CONTRAST,
           rows: int | None = None, **meta: Any) -> SGLighting:
    """SG lobes of an (H, 2H, 3) map (see the module notes). ``rows``: only the first rows hold
    light (default: the upper half if the lower half is black). ``meta``: probe, frame, timestamp,
    unit for the result."""
    from lightprobe.core.errors import InputError

    a = np.asarray(equirect)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0] or (a.shape[0] % WORK_HEIGHT and a.shape[0] > WORK_HEIGHT):
        raise InputError(f"expected an (H, 2H, 3) equirect map with H a multiple of {WORK_HEIGHT}, got shape {a.shape}",
                         param="equirect")
    h = a.shape[0]
    full = _clean(a)
    if rows is None:
        rows = lit_rows(full)
    axes: list[np.ndarray] = []  # per peak lobe, then per level: (n, 3) axes, (n,) sharpness, (n, 3) amplitudes
    lams: list[np.ndarray] = []
    amps: list[np.ndarray] = []
    kinds: list[str] = []
    peaks, total = _peaks(full, rows, max_peaks, min_peak_fraction, peak_relative, peak_contrast)
    for dirs, pw, lp in peaks:
        for part in _split(dirs, pw, lp, max_peak_lobes):
            ax, lam, mu = _lobe(*part)
            axes.append(ax[None])
            lams.append(np.array([lam]))
            amps.append(mu[None])
            kinds.append("peak")
    levels = tuple(int(n) for n in levels)
    nside_w = _work_nside(h, levels)
    ncells = 12 * nside_w * nside_w
    cell_omega = 4.0 * math.pi / ncells
    # the map without the peaks' excess, as mean radiance per working cell (energy kept exactly)
    resid = _cell_power(full, equirect_row_solid_angle(h), _work_cells(h, nside_w), ncells) / cell_omega
    rem_lum, sq = _subtract(resid, resid, 0.0)  # |luminance| and squares of what is left
    total_lum = max(total, float(luminance(resid).sum()) * cell_omega, 1e-300)
    l2_ref = math.sqrt(max(sq, 1e-300))
    info = []
    recon = np.empty_like(resid)
    for nside, (centres, lam, indptr, indices, vals) in zip(levels, _level_tables(nside_w, levels), strict=True):
        rem = rem_lum * cell_omega / total_lum
        if rem < residual_threshold:
            break
        # each lobe carries its cell's residual energy (nested cells: contiguous working cells)
        mu = _group_sums(resid, len(centres), cell_omega / float(lobe_integral(np.array(lam))))
        num, den = _reconstruct(indptr, indices, vals, mu, resid, recon)
        step = min(1.0, max(0.0, num / den)) if den > 0 else 0.0
        if step <= 0:
            info.append({"nside": int(nside), "lobes": 0, "sharpness": lam, "step": 0.0, "residual": rem,
                         "residual_l2": math.sqrt(sq) / l2_ref})
            continue
        rem_lum, sq = _subtract(resid, recon, step)
        keep = np.flatnonzero(mu.any(axis=1))
        axes.append(centres[keep])
        lams.append(np.full(len(keep), lam))
        amps.append(step * mu[keep])
        kinds.extend(["residual"] * len(keep))
        info.append({"nside": int(nside), "lobes": len(keep), "sharpness": lam, "step": step,
                     "residual": rem_lum * cell_omega / total_lum, "residual_l2": math.sqrt(sq) / l2_ref})
    if not axes:
        return SGLighting(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), kinds, info, **meta)
    return SGLighting(np.concatenate(axes), np.concatenate(lams), np.concatenate(amps), kinds, info, **meta)
