"""The rolling HDR estimate: every frame, one exposure, updates the lighting in the output domain.

A live probe does not wait for a whole burst. Each frame (one exposure ``t``, gain ``g``) is
fused and projected *at once* into the output map the samplers and the API use (the equirect
map's upper hemisphere), by one compiled pass over the projection table's rows
(:func:`frame_to_map`): for output pixel ``j`` and channel ``c``, over its fisheye pixels ``i``
with geometric weight ``n_ji`` and gain ``g_i`` (scale / vignetting),

    m_j = sum_i n_ji g_i X_i / sum_i n_ji,   X_i = E(z_i) / (t g)                   (Debevec-Malik eq. 6)
    var(m_j) = sum_i n_ji^2 g_i^2 var(X_i) / (sum_i n_ji)^2

over the unsaturated samples (variances from the response's measured scatter or the sensor
model, :func:`lightprobe.device.hdr.fusion.packed_lut`). Inside one frame the samples of a pixel share the
exposure and are averaged by geometry alone: weighting them by their own noise would favour the
ones that came out low and bias the map down. Samples too dark to weigh stay in the mean (with
a variance as wide as their code range); a footprint with any saturated sample is *censored*:
this frame gives only a lower bound there (its mean with the saturated samples at the
threshold). Both rules keep a sun smaller than an output pixel at its energy: dropping the dark
samples would make the footprint as bright as the sun, dropping the saturated ones as dark as
the sky around it.

:class:`RollingMerge` keeps the latest map of every exposure in use (a *slot* per exposure and
gain) and fuses them per pixel by inverse variance (running sums, so a frame costs O(1) per
pixel beyond its own pass); with ``by_response`` (a measured JPEG/YUV response) the fused value
weighs the slots instead by the response's own weights, the footprint's mean of its samples'
``h(z) / sigma_core(z)^2``, as the offline fusion weighs exposures (a real tripod bracket: 0.37%
per pixel from its offline fusion, 0.87% by the precisions), while the change test keeps the
precisions, whose black floor it needs. A slot that measures the same value again (within 3 sigma of its
own last one) averages with its past (``decay``); a lamp whose edge pixels move beyond their
noise has its energy averaged by the tracker instead (:mod:`lightprobe.device.hdr.tracking`). When a new frame disagrees with the other slots beyond
their noise (``k sigma`` plus ``rel_tol``, or its saturation's lower bound lies above them: a
lamp switched on or off, a flashlight moved), the other slots are dropped at that pixel, so the
change is in the fused map from this very frame on, never averaged with what was there before.
A pixel no slot measures (saturated everywhere) holds the highest lower bound seen, until a
measurement below it (beyond noise) contradicts it.

A long exposure cannot measure a moving lamp, only where it is saturated now: left to the
merge, the pixels the lamp left would drop to the background while the ones it reached hold only
the saturation's lower bound, and the published lamp would lose a quarter of its energy in every
long frame. So what a pixel next to a region the frame sees saturated lost this frame is kept
back, the share the exposure could not have measured (:func:`_hold_moving`), and given to the
saturated pixels nearby that no exposure measures, where the lamp went (:func:`_place_held`),
or, if there are none, left where it was: the lamp keeps its energy, and the next short
exposure (the schedule puts one every other frame) measures it where it is. A lamp switched off
leaves nothing saturated nearby and is gone in the frame that shows it. That is the fallback: a
lamp measured on two frames is carried at its velocity by :mod:`lightprobe.device.hdr.tracking` (drawn where
it is on the frames that see it only saturated), which takes back what the hold placed near it.

Cost per frame: one pass over the table's non-zeros of the upper hemisphere (~470k at VGA ->
256 x 512) and one over the output pixels; no full-resolution image is written. The pass has no
branch per sample (:func:`sum_lut`: every sample adds to every sum, with factors 0 or 1): which
samples are saturated, too dark or measured changes from pixel to pixel, and a branch on it cost
2.4 times the branch-free pass (3.8 ms per VGA frame on the 2-core AMD VM with the merge, from 7.6).

Dtype policy: codes uint8/uint16 in, LUT float32, accumulation float64, maps float32.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from lightprobe.core.sphere import LUM_B, LUM_G, LUM_R
from lightprobe.device.hdr.tracking import LampTracker

# Floating-point contraction (FMA), reciprocal division and signless zeros for the per-frame
# passes (10% of their time); never the flags that assume no inf or NaN, which they test for.
_FAST = {"contract", "arcp", "nsz"}

__all__ = ["FrameMap", "RollingMerge", "frame_to_map", "lut_bounds", "sum_lut", "weight_lut", "weighted_luminance"]


def lut_bounds(lut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A packed LUT's (:func:`lightprobe.device.hdr.fusion.packed_lut`) bounds per channel: the value of
    the highest code below the merge's black threshold (what a too-dark sample may be at most)
    and of the first code at its saturation threshold (what a saturated one is at least)."""
    w, sat = lut[:-1, :, 1], lut[:-1, :, 3]
    dark, top = np.zeros(3), np.zeros(3)
    for c in range(3):
        first = int(np.argmax(w[:, c] > 0)) if (w[:, c] > 0).any() else 0
        dark[c] = float(lut[max(first - 1, 0), c, 0])
        k = int(np.argmax(sat[:, c] > 0)) if (sat[:, c] > 0).any() else w.shape[0] - 1
        top[c] = float(lut[k, c, 0])
    return dark, top


@dataclass
class FrameMap:
    """One frame in the output domain: per pixel and channel the estimate ``m``, its variance
    ``var`` (inf where unmeasured), the saturated and too-dark shares of the footprint, and the
    bounds they imply."""

    m: np.ndarray  # (N, 3) float32
    var: np.ndarray  # (N, 3) float32
    sat: np.ndarray  # (N, 3) float32 in [0, 1]
    dark: np.ndarray  # (N, 3) float32 in [0, 1]
    lower: np.ndarray  # (N, 3) float32: the saturated samples' lower bound (0 if none)
    upper: np.ndarray  # (N, 3) float32: the dark samples' upper bound (0 if none)


def sum_lut(lut: np.ndarray, dark_val: np.ndarray) -> np.ndarray:
    """A packed LUT (:func:`lightprobe.device.hdr.fusion.packed_lut`) as the per-code factors of the sums
    :func:`_terms` takes, so that every sample adds to every sum and none branches: (L + 1, 3, 4)
    float64 [value if unsaturated else 0, variance if unsaturated else 0 (too dark: at least the
    variance of the dark range, ``dark_val^2 / 3``), 1 if saturated, 1 if too dark].

    Which of a pixel's samples are saturated, too dark or measured changes from pixel to pixel
    (a short exposure reads most of a room as too dark and its lamps as measured): a branch per
    sample is mispredicted as often as not, and the pass took 2.4 times as long with them."""
    v, w, var, s = (lut[..., i].astype(np.float64) for i in range(4))
    sat = s > 0
    dark = ~sat & ~(w > 0)
    dark_var = np.asarray(dark_val, np.float64) ** 2 / 3.0
    out = np.zeros((*lut.shape[:2], 4), np.float64)
    out[..., 0] = np.where(sat, 0.0, v)
    out[..., 1] = np.where(sat, 0.0, np.where(dark, np.maximum(var, dark_var[None, :]), var))
    out[..., 2] = sat
    out[..., 3] = dark
    return out


def weight_lut(lut: np.ndarray) -> np.ndarray:
    """The LUT's weights of the unsaturated codes, (L + 1, 3) float64 (saturated: 0): what
    :class:`RollingMerge` with ``by_response`` fuses its slots by."""
    return np.where(lut[..., 3] > 0, 0.0, lut[..., 1].astype(np.float64))


@numba.njit(cache=True, nogil=True, inline="always")
def _terms(indptr, indices, data, geo_n, z, sl, j, wl):  # type: ignore[no-untyped-def]
    """Output pixel j's sums over its fisheye pixels, per channel: (sum a v, sum n, sum a^2 var
    over the unsaturated samples; sum n, sum a over the saturated ones; sum n over the too dark
    ones, which the first sums include), sum n over all and sum n w (the samples' weights ``wl``,
    :func:`weight_lut`; None: no such sums, compiled out); a = n g, ``sl`` the frame's
    :func:`sum_lut`. Within one frame the samples of a pixel are averaged by geometry alone:
    weighting them by their own noise would favour the ones that came out low (their variance
    is smaller) and bias the map down, and dropping the too-dark ones would leave a sun's
    footprint as bright as the sun. A sample is saturated or not, so the unsaturated ones' sum
    of n is the total's less the saturated ones' (exactly so where none is saturated, the only
    case that divides by it)."""
    num0 = num1 = num2 = q0 = q1 = q2 = 0.0
    s0 = s1 = s2 = lb0 = lb1 = lb2 = d0 = d1 = d2 = 0.0
    w0 = w1 = w2 = 0.0
    geo = 0.0
    for e in range(indptr[j], indptr[j + 1]):
        i = indices[e]
        a = np.float64(data[e])  # n_ji g_i
        n = np.float64(geo_n[e])  # n_ji
        aa = a * a
        geo += n
        k = z[i, 0]
        num0 += a * sl[k, 0, 0]
        q0 += aa * sl[k, 0, 1]
        s0 += n * sl[k, 0, 2]
        lb0 += a * sl[k, 0, 2]
        d0 += n * sl[k, 0, 3]
        if wl is not None:
            w0 += n * wl[k, 0]
        k = z[i, 1]
        num1 += a * sl[k, 1, 0]
        q1 += aa * sl[k, 1, 1]
        s1 += n * sl[k, 1, 2]
        lb1 += a * sl[k, 1, 2]
        d1 += n * sl[k, 1, 3]
        if wl is not None:
            w1 += n * wl[k, 1]
        k = z[i, 2]
        num2 += a * sl[k, 2, 0]
        q2 += aa * sl[k, 2, 1]
        s2 += n * sl[k, 2, 2]
        lb2 += a * sl[k, 2, 2]
        d2 += n * sl[k, 2, 3]
        if wl is not None:
            w2 += n * wl[k, 2]
    return (num0, num1, num2, geo - s0, geo - s1, geo - s2, q0, q1, q2, s0, s1, s2, lb0, lb1, lb2,
            d0, d1, d2, geo, w0, w1, w2)


@numba.njit(cache=True, nogil=True, inline="always")
def _estimate(num, den, q, s, lb, d, geo, inv_geo, dark_val, sat_val, g):  # type: ignore[no-untyped-def]
    """One channel's (m, precision, sat share, dark share, lower bound, upper bound) from its
    sums; precision 0: this frame measures nothing there (``inv_geo`` = 1 / ``geo``, shared by
    the three channels).

    A footprint with any saturated sample is *censored*: the mean of its other samples would
    drop the brightest part (a sun smaller than the output pixel, a lamp's edge) and bias the
    map low, so such a frame measures nothing there and gives a lower bound, the footprint's
    mean with the saturated samples at the saturation threshold. The upper bound of the
    too-dark samples is the highest weightless code's value x the pixel's mean gain; a footprint
    of nothing but too-dark samples is a weak measurement, the middle of [0, upper] with a
    variance (upper^2 / 3) wider than the uniform's, so that a short exposure reading black
    where a long one measured a dim wall is no change, and a lamp switched off is.

    The mean ``num / den`` and the precision ``den^2 / q`` share one division: 65,536 output
    pixels x 3 channels a frame, and the divisions were most of the merge's per-pixel cost."""
    if geo <= 0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    upper = dark_val * g if d > 0 else 0.0
    if s > 0:  # censored: the footprint's mean is at least this, and this frame measures no more
        lower = (num + sat_val * lb) * inv_geo
        return lower, 0.0, s * inv_geo, d * inv_geo, lower, upper
    if den <= d:  # nothing but too-dark samples: somewhere in [0, upper], a weak measurement
        if upper > 0:
            return 0.5 * upper, 3.0 / (upper * upper), 0.0, d * inv_geo, 0.0, upper
        return 0.0, 0.0, 0.0, d * inv_geo, 0.0, upper
    if not q > 0:  # no spread to weigh by: a mean, but no measurement
        return num / den, 0.0, 0.0, d * inv_geo, 0.0, upper
    r = 1.0 / (den * q)
    p = den * den * den * r
    return num * q * r, (p if p < np.inf else 0.0), 0.0, d * inv_geo, 0.0, upper


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=_FAST)
def _frame_kernel(indptr, indices, data, geo_n, mean_gain, z, sl, dark_val, sat_val, rows,  # type: ignore[no-untyped-def]
                  m, var, sat, dark, lower, upper):
    for j in numba.prange(rows):
        t = _terms(indptr, indices, data, geo_n, z, sl, j, None)
        inv_geo = 1.0 / t[18] if t[18] > 0 else 0.0
        for c in range(3):
            mc, pc, sat[j, c], dark[j, c], lower[j, c], upper[j, c] = _estimate(
                t[c], t[3 + c], t[6 + c], t[9 + c], t[12 + c], t[15 + c], t[18], inv_geo, dark_val[c], sat_val[c],
                mean_gain[j])
            m[j, c] = mc
            var[j, c] = 1.0 / pc if pc > 0 else np.inf


def frame_to_map(table: object, geo_n: np.ndarray, mean_gain: np.ndarray, codes: np.ndarray,
                 lut: np.ndarray, bounds: tuple[np.ndarray, np.ndarray], rows: int) -> FrameMap:
    """One frame's :class:`FrameMap` over the first ``rows`` output pixels of ``table`` (a
    projection table: CSR ``indptr``, ``indices``, ``data`` = geometric weight x gain).

    ``codes`` (H*W, 3) pixel values, ``lut`` (L + 1, 3, 5) float32 [value, weight, variance,
    saturated, merged value] of the frame's exposure (``packed_lut``; only the first four are
    read), ``bounds``: (3,) the value of the
    highest weightless dark code and (3,) of the saturation threshold, ``geo_n`` each table entry's
    geometric weight (``data`` / pixel gain), ``mean_gain`` (rows,) each output pixel's mean
    pixel gain. :meth:`RollingMerge.update` does the same and merges in one pass."""
    m = np.empty((rows, 3), np.float32)
    var = np.empty((rows, 3), np.float32)
    sat = np.empty((rows, 3), np.float32)
    dark = np.empty((rows, 3), np.float32)
    lower = np.empty((rows, 3), np.float32)
    upper = np.empty((rows, 3), np.float32)
    _frame_kernel(table.indptr, table.indices, table.data, geo_n, mean_gain, codes,  # type: ignore[attr-defined]
                  sum_lut(lut, bounds[0]), np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64),
                  rows,
                  m, var, sat, dark, lower, upper)
    return FrameMap(m, var, sat, dark, lower, upper)


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=_FAST)
def _merge_kernel(indptr, indices, data, geo_n, mean_gain, z, sl, dark_val, sat_val,  # type: ignore[no-untyped-def]
                  m_s, p_s, w_s, wl, numw, denw, nslots, slot, num, den, bound, k2, rel, dark_share, decay,
                  out, changed, bounded, satnow):
    """Fuse and project the frame (:func:`_terms`), update slot ``slot`` and fuse every pixel, in
    one pass (see the module docstring).

    ``m_s``, ``p_s``: (slots, pixels, 3) estimates and precisions, the first ``nslots`` in use;
    ``num``, ``den``: (pixels, 3) float64 running sums of p m and p over all slots, so a frame
    costs O(1) per pixel after its own sums; a changed pixel's other slots are cleared and its
    sums rebuilt. ``wl``: None, or the frame's :func:`weight_lut` (``RollingMerge.by_response``):
    then ``w_s`` (slots, pixels, 3) holds each slot's weight, the footprint's mean of its samples'
    weights in its last frame, ``numw``, ``denw`` (pixels, 3) the running sums of w m and w over
    the slots that measure, and the fused value is theirs (the precisions' where they weigh
    nothing); the change test keeps the precisions."""
    npx = m_s.shape[1]
    for j in numba.prange(npx):
        t = _terms(indptr, indices, data, geo_n, z, sl, j, wl)
        g = mean_gain[j]
        ig = 1.0 / t[18] if t[18] > 0 else 0.0
        e0 = _estimate(t[0], t[3], t[6], t[9], t[12], t[15], t[18], ig, dark_val[0], sat_val[0], g)
        e1 = _estimate(t[1], t[4], t[7], t[10], t[13], t[16], t[18], ig, dark_val[1], sat_val[1], g)
        e2 = _estimate(t[2], t[5], t[8], t[11], t[14], t[17], t[18], ig, dark_val[2], sat_val[2], g)
        ch = False
        for c in range(3):  # the others' estimate: the sums without this slot's old entry
            fm, fp, fs, _fd, fl, _fu = e0 if c == 0 else (e1 if c == 1 else e2)
            po = p_s[slot, j, c]
            dn = den[j, c] - po
            if dn <= 1e-6 * den[j, c] or dn <= 0:
                continue
            f = num[j, c] - po * m_s[slot, j, c]  # the others' estimate x dn (no division)
            if fs > 0:  # saturated (censored): brightened beyond the others?
                if fl * dn > f * (1.0 + rel) and f + np.sqrt(k2 * dn) < fl * dn:
                    ch = True
            elif fp > 0:  # measured (too dark included): disagrees beyond noise?
                fmd = fm * dn
                d = abs(fmd - f) - rel * max(f, fmd)  # x dn
                if d > 0 and d * d * fp > k2 * (dn + fp) * dn:  # d^2 > k2 (var dn + 1) dn, no division
                    ch = True
        changed[j] = ch
        satnow[j] = (e0[2] > 0) | (e1[2] > 0) | (e2[2] > 0)
        any_bound = False
        for c in range(3):
            fm, fp, fs, fd, fl, _fu = e0 if c == 0 else (e1 if c == 1 else e2)
            new_m = fm if fp > 0 else 0.0
            new_p = fp
            if ch:  # the other slots are stale here: this frame alone stands
                for k in range(nslots):
                    if k != slot:
                        p_s[k, j, c] = 0.0
                m_s[slot, j, c] = new_m
                p_s[slot, j, c] = new_p
                num[j, c] = np.float64(p_s[slot, j, c]) * m_s[slot, j, c]
                den[j, c] = p_s[slot, j, c]
                bound[j, c] = 0.0
                if wl is not None:
                    w_s[slot, j, c] = t[19 + c] * ig if new_p > 0 else 0.0
                    numw[j, c] = np.float64(w_s[slot, j, c]) * m_s[slot, j, c]
                    denw[j, c] = w_s[slot, j, c]
            else:
                old_p = np.float64(p_s[slot, j, c])
                old_m = np.float64(m_s[slot, j, c])
                old_pm = old_p * old_m
                # unchanged, and within noise of this exposure's own last value: average with it
                if (new_p > 0 and old_p > 0 and decay > 0
                        and (new_m - old_m) ** 2 * (new_p * old_p) < 9.0 * (new_p + old_p)):
                    kp = decay * old_p
                    new_m = (kp * old_m + new_p * new_m) / (kp + new_p)
                    new_p = kp + new_p
                m_s[slot, j, c] = new_m
                p_s[slot, j, c] = new_p  # stored as float32: the sums take the stored values
                sp = np.float64(p_s[slot, j, c])
                num[j, c] += sp * m_s[slot, j, c] - old_pm
                den[j, c] += sp - old_p
                if sp + old_p > 0 and den[j, c] <= 1e-6 * (sp + old_p):  # cancellation: sum afresh
                    a = 0.0
                    b = 0.0
                    for k in range(nslots):
                        pk = np.float64(p_s[k, j, c])
                        a += pk * m_s[k, j, c]
                        b += pk
                    num[j, c] = a
                    den[j, c] = b
                if wl is not None:
                    old_w = np.float64(w_s[slot, j, c]) if old_p > 0 else 0.0
                    w_s[slot, j, c] = t[19 + c] * ig if sp > 0 else 0.0
                    sw = np.float64(w_s[slot, j, c])
                    numw[j, c] += sw * m_s[slot, j, c] - old_w * old_m
                    denw[j, c] += sw - old_w
                    if sw + old_w > 0 and denw[j, c] <= 1e-6 * (sw + old_w):  # cancellation: sum afresh
                        a = 0.0
                        b = 0.0
                        for k in range(nslots):
                            if p_s[k, j, c] > 0:
                                wk = np.float64(w_s[k, j, c])
                                a += wk * m_s[k, j, c]
                                b += wk
                        numw[j, c] = a
                        denw[j, c] = b
            # A lower bound (saturated in every exposure that saw it) holds until a measurement
            # below it contradicts it, or a dark frame does
            if fs > 0:
                if fl > bound[j, c]:
                    bound[j, c] = fl
            elif new_p > 0:
                if bound[j, c] > 0 and (fm + np.sqrt(k2 / new_p)) < bound[j, c] * (1.0 - rel):
                    bound[j, c] = 0.0
            elif fd >= dark_share:
                bound[j, c] = 0.0
            if den[j, c] > 0:
                val = num[j, c] / den[j, c]
                if wl is not None and denw[j, c] > 0:
                    val = numw[j, c] / denw[j, c]
            else:  # no slot measures it (saturated in every exposure that saw it): the bound
                val = bound[j, c]
                any_bound = any_bound or val > 0
            out[j, c] = val
        bounded[j] = any_bound


@numba.njit(cache=True, nogil=True, parallel=True)
def _hold_moving(rel, sat_val, mean_gain, satnow, prev, out, held, amount, width, reach):  # type: ignore[no-untyped-def]
    """A pixel that darkened this frame next to a region the frame sees saturated keeps part of
    its previous value for this frame (if it was not held in the last one): the share
    ``1 - S / P`` of what it lost, ``P`` its previous value and ``S`` what this exposure reads
    at saturation there. A lamp moving on is saturated where it now is, which the merge can
    only credit with about ``S``; the rest of its energy stays where the last short exposure,
    one frame earlier, measured it, until the next short exposure measures it where it is now.
    A long exposure (``S`` far below the lamp) holds all, a nearly unsaturated one none. A lamp
    switched off leaves nothing saturated nearby and is gone at once."""
    npx = out.shape[0]
    rows = npx // width
    for j in numba.prange(npx):
        was = held[j]
        held[j] = False
        amount[j, 0] = amount[j, 1] = amount[j, 2] = 0.0
        if was or (out[j, 0] + out[j, 1] + out[j, 2]) >= (1.0 - rel) * (prev[j, 0] + prev[j, 1] + prev[j, 2]):
            continue
        r, c = j // width, j % width
        near = False
        for dr in range(-reach, reach + 1):
            rr = r + dr
            if rr < 0 or rr >= rows:
                continue
            for dc in range(-reach, reach + 1):
                if satnow[rr * width + (c + dc) % width]:
                    near = True
                    break
            if near:
                break
        if not near:
            continue
        for ch in range(3):
            p = prev[j, ch]
            if p > out[j, ch]:
                h = 1.0 - sat_val[ch] * mean_gain[j] / p
                if h > 0:
                    amount[j, ch] = h * (p - out[j, ch])
                    held[j] = True


@numba.njit(cache=True, nogil=True)
def _place_held(held, amount, bounded, satnow, out, width, reach):  # type: ignore[no-untyped-def]
    """Put what :func:`_hold_moving` kept back into the map: shared among the pixels nearby that
    the frame sees saturated and no exposure measures (where the lamp went), else in place.
    Returns where it went: the pixels and the amounts added (a lamp the tracker draws takes its
    held energy back, :mod:`lightprobe.device.hdr.tracking`)."""
    npx = out.shape[0]
    rows = npx // width
    src = np.flatnonzero(held)
    counts = np.zeros(len(src), np.int64)
    for q in range(len(src)):
        j = src[q]
        r, c = j // width, j % width
        n = 0
        if reach > 0:
            for dr in range(-reach, reach + 1):
                rr = r + dr
                if rr < 0 or rr >= rows:
                    continue
                for dc in range(-reach, reach + 1):
                    k = rr * width + (c + dc) % width
                    if bounded[k] and satnow[k]:
                        n += 1
        counts[q] = n
    total = 0
    for q in range(len(src)):
        total += max(counts[q], 1)
    dest = np.empty(total, np.int64)
    added = np.empty((total, 3), np.float32)
    e = 0
    for q in range(len(src)):
        j = src[q]
        n = counts[q]
        if n == 0:
            for ch in range(3):
                out[j, ch] += amount[j, ch]
                added[e, ch] = amount[j, ch]
            dest[e] = j
            e += 1
            continue
        r, c = j // width, j % width
        for dr in range(-reach, reach + 1):
            rr = r + dr
            if rr < 0 or rr >= rows:
                continue
            for dc in range(-reach, reach + 1):
                k = rr * width + (c + dc) % width
                if bounded[k] and satnow[k]:
                    for ch in range(3):
                        v = amount[j, ch] / n
                        out[k, ch] += v
                        added[e, ch] = v
                    dest[e] = k
                    e += 1
    return dest, added


@numba.njit(cache=True, nogil=True, parallel=True)
def _resum(m_s, p_s, nslots, num, den, w_s=None, numw=None, denw=None):  # type: ignore[no-untyped-def]
    """Rebuild the running sums from the slots (no drift over long runs); with ``w_s``, the
    weights' sums too (:func:`_merge_kernel`)."""
    for j in numba.prange(m_s.shape[1]):
        for c in range(3):
            a = 0.0
            b = 0.0
            aw = 0.0
            bw = 0.0
            for k in range(nslots):
                pk = np.float64(p_s[k, j, c])
                a += pk * m_s[k, j, c]
                b += pk
                if w_s is not None and pk > 0:
                    aw += np.float64(w_s[k, j, c]) * m_s[k, j, c]
                    bw += w_s[k, j, c]
            num[j, c] = a
            den[j, c] = b
            if numw is not None and denw is not None:
                numw[j, c] = aw
                denw[j, c] = bw


@numba.njit(cache=True, nogil=True)
def _weighted_luminance(rgb, weights, out):  # type: ignore[no-untyped-def]
    for j in range(rgb.shape[0]):
        out[j] = (LUM_R * np.float64(rgb[j, 0]) + LUM_G * np.float64(rgb[j, 1])
                  + LUM_B * np.float64(rgb[j, 2])) * weights[j]


def weighted_luminance(rgb: np.ndarray, weights: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Rec. 709 luminance of (N, 3) linear RGB x ``weights`` (N,), float64, in one pass (the
    change tests' per-pixel energy: luminance x solid angle, every frame), into ``out`` if given."""
    if out is None:
        out = np.empty(rgb.shape[0], np.float64)
    _weighted_luminance(rgb, np.asarray(weights, np.float64), out)
    return out


@dataclass
class RollingMerge:
    """Slots of per-exposure maps over ``pixels`` output pixels, fused per frame.

    ``k_sigma`` and ``rel_tol`` set the change test; ``dark_share`` is the share of an output
    pixel's footprint that must be too dark for its upper bound to count; at most
    ``max_slots`` exposures are kept (the one updated longest ago goes first)."""

    pixels: int
    width: int = 0  # pixels per row of the output map (0: no hold next to saturated regions)
    max_slots: int = 10
    k_sigma: float = 5.0
    rel_tol: float = 0.05
    dark_share: float = 0.5
    decay: float = 0.75  # an unchanged pixel's slot keeps this share of its past precision per update
    keys: list[tuple[float, float]] = field(default_factory=list)  # slot -> (exposure, gain)
    frames: list[int] = field(default_factory=list)  # slot -> frame number of its last update
    resum_every: int = 256
    hold_reach: int = 3  # output pixels around a saturated one where a darkening is held a frame
    # output pixels around a held one where its energy may go (0: held in place): a lamp's disc
    # plus a frame's motion, so that what the trailing edge lost reaches the whole leading edge
    # (flashlight, 3 deg disc at 40 deg/s, 256-row map: glossy p90 7.5% with 6, 3.8% with 12)
    move_reach: int = 12
    track: bool = True  # carry measured lamps at their velocity through censored frames (tracking.py)
    # Fuse the slots by the response's own weights (the footprint's mean of its samples' LUT
    # weights, h(z) / sigma_core(z)^2 for a measured response) instead of their precisions; the
    # change test keeps the precisions. For a measured (JPEG) response: the precisions hold the
    # black floor and the scatter's tails, which the change test needs and a combination should
    # not weigh by (a real tripod bracket: per-pixel 0.87% from its offline fusion, 0.4% with)
    by_response: bool = False

    def __post_init__(self) -> None:
        # slots are allocated as exposures arrive (a bracket often uses fewer than max_slots)
        self.m = np.zeros((0, self.pixels, 3), np.float32)
        self.p = np.zeros((0, self.pixels, 3), np.float32)
        # by_response: the slots' weights and the running sums by them (else not allocated)
        self.w = np.zeros((0, self.pixels if self.by_response else 0, 3), np.float32)
        self.numw = np.zeros((self.pixels if self.by_response else 0, 3), np.float64)
        self.denw = np.zeros_like(self.numw)
        self.num = np.zeros((self.pixels, 3), np.float64)
        self.den = np.zeros((self.pixels, 3), np.float64)
        self.bound = np.zeros((self.pixels, 3), np.float32)
        self.fused = np.zeros((self.pixels, 3), np.float32)
        self.changed = np.zeros(self.pixels, np.bool_)
        self.bounded = np.zeros(self.pixels, np.bool_)
        self.satnow = np.zeros(self.pixels, np.bool_)
        self.prev = np.zeros((self.pixels, 3), np.float32)
        self.held = np.zeros(self.pixels, np.bool_)
        self.amount = np.zeros((self.pixels, 3), np.float32)
        self._updates = 0
        self.tracker = LampTracker(self.width) if self.track and self.width > 0 else None
        self._sum_luts: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = {}

    def _sum_lut(self, lut: np.ndarray, dark_val: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """:func:`sum_lut` and, with ``by_response``, :func:`weight_lut`, memoised per LUT object
        while it is in use (a live probe repeats a few exposures, and a raw sensor's LUT has
        4,096-65,536 codes)."""
        hit = self._sum_luts.get(id(lut))
        if hit is not None and hit[0] is lut and np.array_equal(hit[1], dark_val):
            return hit[2], hit[3]
        if len(self._sum_luts) >= 2 * self.max_slots:
            self._sum_luts.clear()
        sl = sum_lut(lut, dark_val)
        wl = weight_lut(lut) if self.by_response else None
        self._sum_luts[id(lut)] = (lut, np.array(dark_val, np.float64), sl, wl)
        return sl, wl

    def _slot(self, key: tuple[float, float], frame: int) -> int:
        if key in self.keys:
            return self.keys.index(key)
        if len(self.keys) < self.max_slots:
            self.keys.append(key)
            self.frames.append(frame)
            if len(self.m) < len(self.keys):
                grow = np.zeros((len(self.keys) - len(self.m), self.pixels, 3), np.float32)
                self.m, self.p = np.concatenate([self.m, grow]), np.concatenate([self.p, grow])
                if self.by_response:
                    self.w = np.concatenate([self.w, grow])
            return len(self.keys) - 1
        s = int(np.argmin(self.frames))  # the slot updated longest ago
        self._clear(s)
        self.keys[s] = key
        return s

    def _clear(self, s: int) -> None:
        self.num -= self.p[s].astype(np.float64) * self.m[s]
        self.den -= self.p[s]
        np.maximum(self.den, 0.0, out=self.den)
        if self.by_response:
            w = np.where(self.p[s] > 0, self.w[s], 0.0)
            self.numw -= w * self.m[s]
            self.denw -= w
            np.maximum(self.denw, 0.0, out=self.denw)
            self.w[s] = 0.0
        self.m[s] = 0.0
        self.p[s] = 0.0

    def forget(self, keep: set[tuple[float, float]], older_than: int) -> None:
        """Drop slots not in ``keep`` last updated before frame ``older_than`` (an exposure the
        schedule no longer uses, once the ones that replace it have reported)."""
        for s, key in enumerate(self.keys):
            if key not in keep and self.frames[s] < older_than and self.p[s].any():
                self._clear(s)

    def update(self, key: tuple[float, float], frame: int, table: object, geo_n: np.ndarray,
               mean_gain: np.ndarray, codes: np.ndarray, lut: np.ndarray,
               bounds: tuple[np.ndarray, np.ndarray], sharing: np.ndarray | None = None,
               when: float | None = None) -> np.ndarray:
        """Fuse, project and merge one frame (arguments as :func:`frame_to_map`; ``sharing``: the
        table's :func:`lightprobe.device.projection.sample_sharing`, for the lamp tracker; ``when``:
        the middle of the frame's exposure on the sensor's clock, where the tracker draws the
        lamps it carries) into its slot;
        returns the fused map (pixels, 3) float32 (a buffer of the merge's that a later update
        overwrites: copy what must outlive the frame)."""
        s = self._slot(key, frame)
        self.frames[s] = frame
        self._updates += 1
        if self._updates % self.resum_every == 0:
            if self.by_response:
                _resum(self.m, self.p, len(self.keys), self.num, self.den, self.w, self.numw, self.denw)
            else:
                _resum(self.m, self.p, len(self.keys), self.num, self.den)
        sl, wl = self._sum_lut(lut, bounds[0])
        _merge_kernel(table.indptr, table.indices, table.data, geo_n, mean_gain, codes,  # type: ignore[attr-defined]
                      sl, np.asarray(bounds[0], np.float64),
                      np.asarray(bounds[1], np.float64), self.m, self.p, self.w, wl, self.numw, self.denw,
                      len(self.keys), s, self.num,
                      self.den, self.bound, float(self.k_sigma) ** 2, float(self.rel_tol),
                      float(self.dark_share), float(self.decay), self.fused, self.changed, self.bounded,
                      self.satnow)
        if self.width > 0 and self.hold_reach > 0:
            _hold_moving(float(self.rel_tol), np.asarray(bounds[1], np.float64), mean_gain, self.satnow,
                         self.prev, self.fused, self.held, self.amount, self.width, self.hold_reach)
            placed = _place_held(self.held, self.amount, self.bounded, self.satnow, self.fused, self.width,
                                 self.move_reach)
        else:
            placed = (np.zeros(0, np.int64), np.zeros((0, 3), np.float32))
        if self.tracker is not None:
            self.tracker.update(frame, self.fused, self.satnow, placed, self.move_reach, self.den, sharing, when)
        # this frame's map is the next one's ``prev``; the kernel writes every pixel of ``out``,
        # so the two buffers swap instead of copying 0.8 MB a frame
        self.prev, self.fused = self.fused, self.prev
        return self.prev

    def reset(self) -> None:
        self.keys.clear()
        self.frames.clear()
        for a in (self.m, self.p, self.w, self.num, self.den, self.numw, self.denw, self.bound, self.fused):
            a[:] = 0.0
        self.held[:] = False
        if self.tracker is not None:
            self.tracker.reset()
