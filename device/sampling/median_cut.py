"""Median cut (Debevec 2005): the baseline sampler.

The equirect map is cut into rectangles of (nearly) equal energy: the region with the most
energy is split next, across its longer side (its width measured in radians scaled by the cosine
of the latitude at its centre, i.e. ``sin theta``), at the column/row that best halves its energy
(summed-area table of luminance x solid angle, binary search). Each final region gives one light
at its **energy centroid** (luminance x solid angle weighted mean direction, normalised) carrying
the region's summed radiance x solid angle (per channel, float64) and the region's solid angle.

Splitting everything ``k`` times gives Debevec's ``2^k`` regions; any other count is reached by
splitting the most energetic region first (which is the same order). Single-pixel regions cannot
be split, so a map may yield fewer lights than asked (at most ``H x W``); regions without energy
give no light (all channels are 0 there, so energy is still conserved exactly).

Degenerate maps: NaN/inf/negative -> 0 (counted in ``extra["sanitized"]``); all-black -> empty.
Stateless; ``ids`` are the split order (not temporally stable).

References
----------
Debevec, "A median cut algorithm for light probe sampling", SIGGRAPH 2005 poster / ACM SIGGRAPH
2006 courses; Crow 1984 (summed-area tables).
"""

from __future__ import annotations

import functools
import heapq

import numpy as np
from numba import njit

from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import LUM_B, LUM_G, LUM_R, equirect_row_solid_angle

from ._pixels import clean_invalid
from .pharr import empty_lightset

__all__ = ["MedianCutSampler", "median_cut_regions"]


@njit(cache=True)
def _region_energy(sat, r0, r1, c0, c1):  # type: ignore[no-untyped-def]  # pragma: no cover
    return sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]


@njit(cache=True)
def _best_split(sat, r0, r1, c0, c1, along_cols):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Index in (lo, hi) whose prefix energy is closest to half the region's (binary search)."""
    half = 0.5 * _region_energy(sat, r0, r1, c0, c1)
    lo, hi = (c0, c1) if along_cols else (r0, r1)
    a, b = lo + 1, hi - 1  # candidate split positions
    while a < b:  # first position whose prefix energy >= half
        m = (a + b) // 2
        e = _region_energy(sat, r0, r1, c0, m) if along_cols else _region_energy(sat, r0, m, c0, c1)
        if e < half:
            a = m + 1
        else:
            b = m
    best = a
    if a - 1 > lo:
        e1 = _region_energy(sat, r0, r1, c0, a) if along_cols else _region_energy(sat, r0, a, c0, c1)
        e0 = (_region_energy(sat, r0, r1, c0, a - 1) if along_cols
              else _region_energy(sat, r0, a - 1, c0, c1))
        if abs(e0 - half) < abs(e1 - half):
            best = a - 1
    return best


@njit(cache=True)
def _prepare_sat(img, omega):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """One pass over the map: summed-area table (H + 1, W + 1) of luminance x solid angle
    (Crow 1984), the per-channel integral and the invalid-value counts (read as 0, the rule of
    ``lightprobe.device.sampling._pixels``)."""
    h, w = img.shape[0], img.shape[1]
    sat = np.empty((h + 1, w + 1))
    sat[0, :] = 0.0
    total = np.zeros(3)
    bad = np.zeros(2, np.int64)
    for r in range(h):
        om = omega[r]
        sr = sg = sb = acc = 0.0
        sat[r + 1, 0] = 0.0
        for c in range(w):
            vr = np.float64(img[r, c, 0])
            vg = np.float64(img[r, c, 1])
            vb = np.float64(img[r, c, 2])
            if not (vr >= 0.0 and vg >= 0.0 and vb >= 0.0 and vr + vg + vb < np.inf):
                vr, vg, vb = clean_invalid(vr, vg, vb, bad)
            sr += vr
            sg += vg
            sb += vb
            acc += (LUM_R * vr + LUM_G * vg + LUM_B * vb) * om
            sat[r + 1, c + 1] = sat[r, c + 1] + acc
        total[0] += sr * om
        total[1] += sg * om
        total[2] += sb * om
    return sat, total, bad


@njit(cache=True)
def _energy_sat(energy):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    h, w = energy.shape
    sat = np.zeros((h + 1, w + 1))
    for r in range(h):  # Build the summed-area table
        acc = 0.0
        for c in range(w):
            acc += energy[r, c]
            sat[r + 1, c + 1] = sat[r, c + 1] + acc
    return sat


@njit(cache=True)
def _regions_from_sat(sat, sin_theta, count):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Median cut on a summed-area table (see :func:`median_cut_regions`)."""
    h, w = sat.shape[0] - 1, sat.shape[1] - 1
    rects = np.zeros((count, 4), np.int64)
    e = np.zeros(count)
    rects[0] = (0, h, 0, w)
    e[0] = sat[h, w]
    heap = [(-e[0], 0)]  # max-heap of splittable regions by energy
    k = 1
    while k < count and len(heap) > 0:
        _, best = heapq.heappop(heap)
        r0, r1, c0, c1 = rects[best]
        height = (r1 - r0) * np.pi / h
        width = (c1 - c0) * 2 * np.pi / w * sin_theta[(r0 + r1) // 2]
        along_cols = (width >= height and c1 - c0 > 1) or r1 - r0 == 1
        m = _best_split(sat, r0, r1, c0, c1, along_cols)
        if along_cols:
            rects[best] = (r0, r1, c0, m)
            rects[k] = (r0, r1, m, c1)
        else:
            rects[best] = (r0, m, c0, c1)
            rects[k] = (m, r1, c0, c1)
        for j in (best, k):
            e[j] = _region_energy(sat, rects[j, 0], rects[j, 1], rects[j, 2], rects[j, 3])
            if e[j] > 0 and (rects[j, 1] - rects[j, 0] > 1 or rects[j, 3] - rects[j, 2] > 1):
                heapq.heappush(heap, (-e[j], j))
        k += 1
    return rects[:k], e[:k]


def median_cut_regions(energy: np.ndarray, sin_theta: np.ndarray, count: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Rectangles (K, 4) int64 ``[r0, r1, c0, c1)`` and their energies from ``energy`` (H, W).

    ``sin_theta`` (H,) scales widths (cos latitude). Splits the most energetic splittable
    region until ``count`` regions exist or none can be split.
    """
    sat = _energy_sat(np.ascontiguousarray(energy, np.float64))
    rects, e = _regions_from_sat(sat, np.asarray(sin_theta, np.float64), int(count))
    return rects, e


@njit(cache=True, inline="always")
def _segment(x, xb, sin_p, cos_p):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """Raw sums over one row segment (``x`` flat rgb float32, ``xb`` its bits): r, g, b, Y,
    Y sin phi, Y cos phi, and whether a sign bit was set (a negative value)."""
    s0 = s1 = s2 = yy = ys = yc = 0.0
    sign = np.uint32(0)
    for i in range(len(sin_p)):
        sign |= xb[3 * i] | xb[3 * i + 1] | xb[3 * i + 2]
        vr = np.float64(x[3 * i])
        vg = np.float64(x[3 * i + 1])
        vb = np.float64(x[3 * i + 2])
        s0 += vr
        s1 += vg
        s2 += vb
        y = LUM_R * vr + LUM_G * vg + LUM_B * vb
        yy += y
        ys += y * sin_p[i]
        yc += y * cos_p[i]
    return s0, s1, s2, yy, ys, yc, sign >= np.uint32(0x80000000)


@njit(cache=True)
def _segment_clean(img, r, c0, c1, sin_p, cos_p):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Slow path of :func:`_segment` for a segment holding NaN/inf/negative values (read as 0);
    whole arrays and indices, so the hot loop passes no slices to a call."""
    s0 = s1 = s2 = yy = ys = yc = 0.0
    bad = np.zeros(2, np.int64)
    for c in range(c0, c1):
        vr, vg, vb = clean_invalid(np.float64(img[r, c, 0]), np.float64(img[r, c, 1]),
                                   np.float64(img[r, c, 2]), bad)
        s0 += vr
        s1 += vg
        s2 += vb
        y = LUM_R * vr + LUM_G * vg + LUM_B * vb
        yy += y
        ys += y * sin_p[c]
        yc += y * cos_p[c]
    return s0, s1, s2, yy, ys, yc


@njit(cache=True)
def _region_lights(img, rects, omega, sin_t, cos_t, sin_p, cos_p):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per region: summed rgb x solid angle, energy-weighted direction sum, solid angle.

    Row by row: the raw sums of a row segment (rgb, Y, Y sin phi, Y cos phi) are scaled once by
    the row's solid angle and sin/cos theta (d = (sin t sin p, cos t, -sin t cos p)). A segment
    with NaN/inf/negative values (caught by its sum and its sign bits) is summed again with
    those read as 0."""
    k = rects.shape[0]
    w = img.shape[1]
    flat = img.reshape(-1)
    bits = flat.view(np.uint32)
    rgb = np.zeros((k, 3))
    dsum = np.zeros((k, 3))
    solid = np.zeros(k)
    for i in range(k):
        r0, r1, c0, c1 = rects[i]
        a0 = a1 = a2 = d0 = d1 = d2 = om_sum = 0.0
        sp = sin_p[c0:c1]
        cp = cos_p[c0:c1]
        for r in range(r0, r1):
            lo, hi = 3 * (r * w + c0), 3 * (r * w + c1)
            s0, s1, s2, yy, ys, yc, neg = _segment(flat[lo:hi], bits[lo:hi], sp, cp)
            if neg or not s0 + s1 + s2 < np.inf:
                s0, s1, s2, yy, ys, yc = _segment_clean(img, r, c0, c1, sin_p, cos_p)
            om = omega[r]
            om_sum += om * (c1 - c0)
            a0 += s0 * om
            a1 += s1 * om
            a2 += s2 * om
            d0 += ys * (om * sin_t[r])
            d1 += yy * (om * cos_t[r])
            d2 -= yc * (om * sin_t[r])
        rgb[i, 0], rgb[i, 1], rgb[i, 2] = a0, a1, a2
        dsum[i, 0], dsum[i, 1], dsum[i, 2] = d0, d1, d2
        solid[i] = om_sum
        if d0 == 0.0 and d1 == 0.0 and d2 == 0.0:
            rm, cm = (r0 + r1) // 2, (c0 + c1) // 2  # no energy: geometric centre
            dsum[i, 0] = sin_t[rm] * sin_p[cm]
            dsum[i, 1] = cos_t[rm]
            dsum[i, 2] = -sin_t[rm] * cos_p[cm]
    return rgb, dsum, solid


class MedianCutSampler:
    """Debevec's median cut on the equirect map; stateless."""

    name = "median-cut"

    def reset(self) -> None:
        """Stateless: nothing to forget."""

    def sample(self, equirect: np.ndarray, count: int) -> LightSet:
        """At most ``count`` lights (see the module docstring)."""
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        img = np.asarray(equirect)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) radiance map, got shape {img.shape}")
        img = np.ascontiguousarray(img, np.float32)
        h, w = img.shape[:2]
        omega = equirect_row_solid_angle(h, w)
        sat, total, bad = _prepare_sat(img, omega)
        flags = {"nonfinite": int(bad[0]), "negative": int(bad[1])}
        extra: dict[str, object] = {"sanitized": flags} if any(flags.values()) else {}
        if not np.any(total > 0):
            return empty_lightset(self.name, extra)
        sin_t, cos_t, sin_p, cos_p = _trig(h, w)
        rects, e = _regions_from_sat(sat, sin_t, int(count))
        rects = rects[e > 0]
        rgb, dsum, solid = _region_lights(img, rects, omega, sin_t, cos_t, sin_p, cos_p)
        dirs = dsum / np.linalg.norm(dsum, axis=1, keepdims=True)
        extra["regions"] = len(rects)
        return LightSet(dirs, rgb, solid, np.arange(len(rects), dtype=np.int64),
                        method=self.name, extra=extra)


@functools.lru_cache(maxsize=8)
def _trig(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """sin/cos of the pixel-centre polar angle (per row) and azimuth (per column)."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(w) + 0.5) / w
    return np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
