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

import heapq

import numpy as np
from numba import njit

from device.sphere import equirect_row_solid_angle

from .base import LightSet
from .pharr import empty_lightset, prepare_density

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
def median_cut_regions(energy, sin_theta, count):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Rectangles (K, 4) int64 ``[r0, r1, c0, c1)`` and their energies from ``energy`` (H, W).

    ``sin_theta`` (H,) scales widths (cos latitude). Splits the most energetic splittable
    region until ``count`` regions exist or none can be split.
    """
    h, w = energy.shape
    sat = np.zeros((h + 1, w + 1))
    for r in range(h):  # Build the summed-area table
        acc = 0.0
        for c in range(w):
            acc += energy[r, c]
            sat[r + 1, c + 1] = sat[r, c + 1] + acc
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


@njit(cache=True)
def _region_lights(img, energy, rects, omega, sin_t, cos_t, sin_p, cos_p):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per region: summed rgb x solid angle, energy-weighted direction sum, solid angle."""
    k = rects.shape[0]
    rgb = np.zeros((k, 3))
    dsum = np.zeros((k, 3))
    solid = np.zeros(k)
    for i in range(k):
        r0, r1, c0, c1 = rects[i]
        for r in range(r0, r1):
            om = omega[r]
            solid[i] += om * (c1 - c0)
            for c in range(c0, c1):
                for ch in range(3):
                    v = np.float64(img[r, c, ch])
                    if np.isfinite(v) and v > 0.0:  # NaN/inf/negative read as 0
                        rgb[i, ch] += v * om
                en = energy[r, c]
                dsum[i, 0] += en * sin_t[r] * sin_p[c]
                dsum[i, 1] += en * cos_t[r]
                dsum[i, 2] -= en * sin_t[r] * cos_p[c]
        if dsum[i, 0] == 0.0 and dsum[i, 1] == 0.0 and dsum[i, 2] == 0.0:
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
        energy, _, total, flags = prepare_density(equirect)
        extra: dict[str, object] = {"sanitized": flags} if any(flags.values()) else {}
        h, w = energy.shape
        omega = equirect_row_solid_angle(h, w)
        if not np.any(total > 0):
            return empty_lightset(self.name, extra)
        theta = np.pi * (np.arange(h) + 0.5) / h
        phi = 2 * np.pi * (np.arange(w) + 0.5) / w
        rects, e = median_cut_regions(energy, np.sin(theta), int(count))
        rects = rects[e > 0]
        rgb, dsum, solid = _region_lights(np.ascontiguousarray(equirect, np.float32), energy, rects, omega, np.sin(theta),
                                          np.cos(theta), np.sin(phi), np.cos(phi))
        dirs = dsum / np.linalg.norm(dsum, axis=1, keepdims=True)
        extra["regions"] = len(rects)
        return LightSet(dirs, rgb, solid, np.arange(len(rects), dtype=np.int64),
                        method=self.name, extra=extra)
