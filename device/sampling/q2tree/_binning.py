"""Per-frame node sums of the Q2-Tree: a coarse pyramid each frame, finer nodes on demand, and
the incremental update of both between frames.

Binning a 1024 x 512 map into every quad down to nside 256 (786k quads, more than the map has
pixels) cost 10 ms a frame, while a tree of 1000 lights reads about 1300 nodes. So the map is
binned only down to a *coarse level* ``Lc`` (:func:`coarse_level`: about as many quads as
lights, at least 16 pixels a quad), in one pass that sums each pixel whole into the quad
holding its centre (exact float64 energy, true pixel directions), and levels above it are sums
of 4 NESTED children. A node finer than ``Lc`` is summed from its own pixels the first time the
tree needs it (:func:`fill_children`): in NESTED order its pixels are one contiguous range of
the input sorted by finest-level index (``first[i << 2 (K - k)] .. first[(i + 1) << 2 (K -
k)]``), so this costs its pixel count.

The pass works on *runs*: consecutive pixels of one equirect row (or of the NESTED map) in one
coarse quad. A run is summed raw and scaled once by its row's solid angle and direction
factors; a quad is the sum of its runs in image order.

Incremental input. The previous frame's raw bits are kept (a full pass copies them; an
update copies only the changed spans, so the kept copy is the comparison base with no copy of
the whole frame per update). Each row is compared whole (vectorised, as uint64 pairs); in a
row that changed, the span from its first to its last differing value (found chunk by chunk)
marks the runs to sum again, and only their quads and those quads' ancestors are recombined
(:func:`update_coarse`), with the same kernels in the same order, so the pyramid equals a fresh
pass bit for bit (NaN compares equal to NaN: bits, not floats). Fine nodes remember the frame
they were summed in (``stamp``) and each coarse quad the frame it last changed (``qver``): a
fine node is current iff ``stamp >= qver`` of its quad. When most runs change (camera noise, a
gain change) comparing only adds to a full pass, so the next ``RETRY - 1`` frames skip it.

Where an update's time goes (local change at N = 256, minima, load ~1.3): 1k map 256 us
comparing (reading the new frame, 6 MB from memory, and the kept one: the floor of an exact
update), 18 us re-summing 313 changed runs, 3 us for 15 coarse quads and their ancestors;
512 x 256: 55 + 7 + 2 us; nside-64 HEALPix: 16 + 2 + 1.5 us.

Pixels. NaN/inf and negative values read as 0, per channel (``sanitize_radiance``'s rule,
without copying the map).

Dtype policy: sums, moments, directions float64; input float32 (equirect) or float32/float64
(HEALPix); indices int32 in tables, int64 node ids; frame counters int64.

References
----------
Wan, Wong, Leung 2005, "Spherical Q2-tree for sampling dynamic environment sequences", EGSR
(node importance from per-quad sums, incremental update between frames).
Gorski et al. 2005, "HEALPix", ApJ 622 (NESTED scheme: a quad's descendants are contiguous).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from lightprobe.core.healpix import pix2vec_nest, vec2pix_nest
from lightprobe.core.sphere import LUMINANCE_WEIGHTS, equirect_directions, equirect_row_solid_angle

__all__ = [
    "PIXELS_PER_COARSE_QUAD",
    "FrameState",
    "children_stale",
    "coarse_level",
    "fill_children",
    "update_coarse",
]

PIXELS_PER_COARSE_QUAD = 16.0
BUSY_FRACTION = 0.5  # a frame changing more of the runs than this ...
RETRY = 4  # ... is followed by RETRY - 1 full passes before the next comparison


def coarse_level(max_level: int, pixels: int, count: int) -> int:
    """The level binned every frame: the coarsest with at least ``count`` quads (a tree of
    ``count`` leaves then mostly ends above it; finer nodes are summed on demand), but not so
    fine that its quads hold fewer than ``PIXELS_PER_COARSE_QUAD`` input pixels on average,
    and at most ``max_level``. Measured on 1k maps (load ~2): N = 1000 total 2.3 ms at nside
    16 against 2.9 at 32; N = 10000 6.4 ms at 32 against 10.8 at 16."""
    level = 0
    while level < max_level and 12 * 4**level < count:
        level += 1
    while level > 0 and pixels / (12.0 * 4.0**level) < PIXELS_PER_COARSE_QUAD:
        level -= 1
    return level


# -- kernels -------------------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _clean(v: float) -> float:
    return v if (v >= 0.0 and v < np.inf) else 0.0


@njit(cache=True)
def range_sums(flat: np.ndarray, order: np.ndarray, lo: int, hi: int, pomega: np.ndarray,
               pdirs: np.ndarray, weights: np.ndarray, moments: bool, out: np.ndarray,
               identity: bool = False) -> None:
    """Sums over the sorted pixels ``lo .. hi`` (``flat[order[i]]``, or ``flat[i]`` if
    ``identity``): out = (r, g, b, Y, Yx, Yy, Yz) of radiance x solid angle ``pomega[i]``,
    first moments at ``pdirs[i]``."""
    a0 = a1 = a2 = m0 = m1 = m2 = 0.0
    w0, w1, w2 = weights[0], weights[1], weights[2]
    for i in range(lo, hi):
        p = i if identity else order[i]
        v0 = float(flat[p, 0])
        v1 = float(flat[p, 1])
        v2 = float(flat[p, 2])
        if not (v0 >= 0.0 and v1 >= 0.0 and v2 >= 0.0 and v0 + v1 + v2 < np.inf):
            v0, v1, v2 = _clean(v0), _clean(v1), _clean(v2)
        om = pomega[i]
        v0 *= om
        v1 *= om
        v2 *= om
        a0 += v0
        a1 += v1
        a2 += v2
        if moments:
            y = w0 * v0 + w1 * v1 + w2 * v2
            m0 += y * pdirs[i, 0]
            m1 += y * pdirs[i, 1]
            m2 += y * pdirs[i, 2]
    out[0], out[1], out[2] = a0, a1, a2
    out[3] = w0 * a0 + w1 * a1 + w2 * a2
    out[4], out[5], out[6] = m0, m1, m2


@njit(cache=True, inline="always")
def _store(u: int, s: np.ndarray, moments: bool, rgb: np.ndarray, lum: np.ndarray,
           moment: np.ndarray) -> None:
    rgb[u, 0], rgb[u, 1], rgb[u, 2] = s[0], s[1], s[2]
    lum[u] = s[3]
    if moments:
        moment[u, 0], moment[u, 1], moment[u, 2] = s[4], s[5], s[6]


@njit(cache=True, inline="always")
def _row_run(x: np.ndarray, xb: np.ndarray, sp: np.ndarray, cp: np.ndarray,
             weights: np.ndarray, moments: bool
             ) -> tuple[float, float, float, float, float, float, bool]:
    """Raw sums over a run of pixels ``x`` (flat rgb float32, ``xb`` its uint32 bits) of one
    equirect row: (r, g, b, Y, Y sin phi, Y cos phi) and whether a sign bit was set (a negative
    value: the run is then summed again by :func:`_row_run_clean`)."""
    w0, w1, w2 = weights[0], weights[1], weights[2]
    s0 = s1 = s2 = yy = ys = yc = 0.0
    sign = np.uint32(0)
    for i in range(len(sp)):
        sign |= xb[3 * i] | xb[3 * i + 1] | xb[3 * i + 2]
        v0 = np.float64(x[3 * i])
        v1 = np.float64(x[3 * i + 1])
        v2 = np.float64(x[3 * i + 2])
        s0 += v0
        s1 += v1
        s2 += v2
        if moments:
            y = w0 * v0 + w1 * v1 + w2 * v2
            yy += y
            ys += y * sp[i]
            yc += y * cp[i]
    return s0, s1, s2, yy, ys, yc, bool(sign >= np.uint32(0x80000000))


@njit(cache=True)
def _row_run_clean(flat: np.ndarray, lo: int, hi: int, sp: np.ndarray, cp: np.ndarray,
                   c0: int, weights: np.ndarray, moments: bool
                   ) -> tuple[float, float, float, float, float, float]:
    """Slow path of :func:`_row_run` for pixels ``lo .. hi`` (from column ``c0``) holding
    NaN/inf/negative values, read as 0. Takes whole arrays and indices: passing slices to a
    non-inlined call would cost the hot loop a reference count per run."""
    w0, w1, w2 = weights[0], weights[1], weights[2]
    s0 = s1 = s2 = yy = ys = yc = 0.0
    for p in range(lo, hi):
        v0 = _clean(np.float64(flat[3 * p]))
        v1 = _clean(np.float64(flat[3 * p + 1]))
        v2 = _clean(np.float64(flat[3 * p + 2]))
        s0 += v0
        s1 += v1
        s2 += v2
        if moments:
            y = w0 * v0 + w1 * v1 + w2 * v2
            c = c0 + p - lo
            yy += y
            ys += y * sp[c]
            yc += y * cp[c]
    return s0, s1, s2, yy, ys, yc


@njit(cache=True)
def equirect_run_sums(flat: np.ndarray, bits: np.ndarray, runs: np.ndarray, run_p0: np.ndarray,
                      run_p1: np.ndarray, run_rc: np.ndarray, run_pos: np.ndarray,
                      omega: np.ndarray, st: np.ndarray, ct: np.ndarray, sp: np.ndarray,
                      cp: np.ndarray, weights: np.ndarray, moments: bool, out: np.ndarray
                      ) -> None:
    """Sums of the runs ``runs`` of an equirect map (``flat``: H*W*3 float32, ``bits`` the
    same as uint32): radiance x
    solid angle and first moments, ``out[run_pos[j]]`` = (r, g, b, Yx, Yy, Yz) (runs stored
    quad by quad). A run is part of one row,
    so its solid angle and sin/cos theta are factored out (d = (sin t sin p, cos t,
    -sin t cos p), CONVENTIONS.md). A run holding NaN/inf/negative values (caught by its sum
    and by its sign bits) is summed again with those read as 0."""
    for k in range(len(runs)):
        j = runs[k]
        lo, hi = run_p0[j], run_p1[j]
        r, c0 = run_rc[j, 0], run_rc[j, 1]
        x = flat[3 * lo:3 * hi]
        xb = bits[3 * lo:3 * hi]
        spj = sp[c0:c0 + hi - lo]
        cpj = cp[c0:c0 + hi - lo]
        s0, s1, s2, yy, ys, yc, neg = _row_run(x, xb, spj, cpj, weights, moments)
        if neg or not s0 + s1 + s2 < np.inf:
            s0, s1, s2, yy, ys, yc = _row_run_clean(flat, lo, hi, sp, cp, c0, weights, moments)
        om = omega[r]
        o = run_pos[j]
        out[o, 0] = s0 * om
        out[o, 1] = s1 * om
        out[o, 2] = s2 * om
        if moments:
            out[o, 3] = ys * (om * st[r])
            out[o, 4] = yy * (om * ct[r])
            out[o, 5] = -yc * (om * st[r])


@njit(cache=True)
def healpix_run_sums(flat: np.ndarray, runs: np.ndarray, run_p0: np.ndarray,
                     run_p1: np.ndarray, order: np.ndarray, pomega: np.ndarray,
                     pdirs: np.ndarray, weights: np.ndarray, moments: bool, out: np.ndarray
                     ) -> None:
    """Sums of the runs ``runs`` (contiguous NESTED pixel ranges, one per quad, so stored in
    run order) of a HEALPix map ``flat`` (P, 3): out[j] = (r, g, b, Yx, Yy, Yz) of radiance x
    solid angle."""
    s = np.empty(7)
    for k in range(len(runs)):
        j = runs[k]
        range_sums(flat, order, run_p0[j], run_p1[j], pomega, pdirs, weights, moments, s,
                   True)
        out[j, 0], out[j, 1], out[j, 2] = s[0], s[1], s[2]
        out[j, 3], out[j, 4], out[j, 5] = s[4], s[5], s[6]


@njit(cache=True)
def combine_quads(quads: np.ndarray, q_first: np.ndarray, run_sum: np.ndarray,
                  weights: np.ndarray, moments: bool, offset: int, rgb: np.ndarray,
                  lum: np.ndarray, moment: np.ndarray) -> None:
    """Coarse node ``offset + q`` = the sum of quad q's run sums (``run_sum[q_first[q] ..
    q_first[q + 1]]``, in image order)."""
    s = np.empty(7)
    for k in range(len(quads)):
        q = quads[k]
        a0 = a1 = a2 = m0 = m1 = m2 = 0.0
        for t in range(q_first[q], q_first[q + 1]):
            a0 += run_sum[t, 0]
            a1 += run_sum[t, 1]
            a2 += run_sum[t, 2]
            m0 += run_sum[t, 3]
            m1 += run_sum[t, 4]
            m2 += run_sum[t, 5]
        s[0], s[1], s[2] = a0, a1, a2
        s[3] = weights[0] * a0 + weights[1] * a1 + weights[2] * a2
        s[4], s[5], s[6] = m0, m1, m2
        _store(offset + q, s, moments, rgb, lum, moment)


@njit(cache=True, inline="always")
def _differ(a: np.ndarray, b: np.ndarray) -> bool:
    # Take slices: a loop over a slice vectorises, one over an index range of the whole
    # array does not (bounds arithmetic); measured 0.25 against 2.0 ms on a 1k map
    d = a.dtype.type(0)
    for t in range(len(a)):
        d |= a[t] ^ b[t]
    return d != 0


CHUNK = 64  # words compared at once when looking for the first / last difference in a row


@njit(cache=True, inline="always")
def _first_diff(bits: np.ndarray, prev: np.ndarray, lo: int, hi: int) -> int:
    """First index in ``lo .. hi`` where the words differ (there is one): whole chunks by the
    vectorised test, then word by word inside the chunk that differs."""
    while lo + CHUNK < hi and not _differ(bits[lo:lo + CHUNK], prev[lo:lo + CHUNK]):
        lo += CHUNK
    while bits[lo] == prev[lo]:
        lo += 1
    return lo


@njit(cache=True, inline="always")
def _last_diff(bits: np.ndarray, prev: np.ndarray, lo: int, hi: int) -> int:
    """Last index in ``lo .. hi`` where the words differ (there is one)."""
    while hi - CHUNK > lo and not _differ(bits[hi - CHUNK:hi], prev[hi - CHUNK:hi]):
        hi -= CHUNK
    hi -= 1
    while bits[hi] == prev[hi]:
        hi -= 1
    return hi


@njit(cache=True)
def compare_runs(bits: np.ndarray, prev: np.ndarray, words: int, row_run: np.ndarray,
                 run_p0: np.ndarray, run_p1: np.ndarray, run_quad: np.ndarray,
                 qver: np.ndarray, frame: int, runs_out: np.ndarray, quads_out: np.ndarray
                 ) -> tuple[int, int]:
    """Find the runs whose raw bits (``words`` uint32 per pixel) differ from the previous
    frame's. Rows of runs (``row_run[r] .. row_run[r + 1]``, contiguous in memory) are compared
    whole; in a row that changed, the first and last differing words bound the change and every
    run meeting that span counts as changed (one span per row: exact for a global change, a
    bounding interval for a local one). Copies the span into ``prev``, lists the runs in
    ``runs_out`` and their quads once each in ``quads_out`` (stamped ``qver = frame``).
    Each new word is read once (a changed row, 12 kB on a 1k map, again from cache); a row
    starting and ending on an even word is tested as uint64 pairs (0.20 against 0.25 ms over a
    1k map's 12 MB: the test is bound by reading the new frame). Returns (changed runs,
    changed quads)."""
    bits2 = bits.view(np.uint64)
    prev2 = prev.view(np.uint64)
    nr = nq = 0
    for r in range(len(row_run) - 1):
        j0, j1 = row_run[r], row_run[r + 1]
        row_lo, row_hi = run_p0[j0] * words, run_p1[j1 - 1] * words
        if row_lo % 2 == 0 and row_hi % 2 == 0:
            same = not _differ(bits2[row_lo // 2:row_hi // 2], prev2[row_lo // 2:row_hi // 2])
        else:
            same = not _differ(bits[row_lo:row_hi], prev[row_lo:row_hi])
        if same:
            continue
        lo = _first_diff(bits, prev, row_lo, row_hi)
        hi = _last_diff(bits, prev, lo, row_hi)
        prev[lo:hi + 1] = bits[lo:hi + 1]
        p_lo, p_hi = lo // words, hi // words  # first and last changed pixels
        for j in range(j0, j1):
            if run_p1[j] <= p_lo or run_p0[j] > p_hi:
                continue
            runs_out[nr] = j
            nr += 1
            q = run_quad[j]
            if qver[q] != frame:
                qver[q] = frame
                quads_out[nq] = q
                nq += 1
    return nr, nq


@njit(cache=True, inline="always")
def _sum_children(arr: np.ndarray, u: int) -> None:
    """Node u of a dense NUNIQ array (M, C) = the sum of its children 4u .. 4u+3."""
    for ch in range(arr.shape[1]):
        arr[u, ch] = (arr[4 * u, ch] + arr[4 * u + 1, ch]) + (arr[4 * u + 2, ch]
                                                              + arr[4 * u + 3, ch])


@njit(cache=True)
def update_coarse(quads: np.ndarray, q_first: np.ndarray, run_sum: np.ndarray,
                  weights: np.ndarray, moments: bool, coarse: int, rgb: np.ndarray,
                  lum: np.ndarray, moment: np.ndarray, mark: np.ndarray) -> None:
    """Coarse nodes of ``quads`` from their run sums (:func:`combine_quads`), then their
    ancestors, level by level, as the sums of 4 children (a full pass recombines every quad
    and so every node above the coarse level, in the same arithmetic). ``mark`` (one int64
    per node above the coarse level, zero on entry and on return) is scratch."""
    offset = 4 << (2 * coarse)
    combine_quads(quads, q_first, run_sum, weights, moments, offset, rgb, lum, moment)
    lum2 = lum.reshape(-1, 1)
    # the dirty nodes of a level, their parents deduplicated by a mark (one pass per level)
    n = len(quads)
    cur = np.empty(n, np.int64)
    for k in range(n):
        cur[k] = offset + quads[k]
    for _ in range(coarse):
        m = 0
        for k in range(n):
            u = cur[k] >> 2
            if mark[u] != -1 - u:
                mark[u] = -1 - u
                cur[m] = u
                m += 1
        for k in range(m):
            u = cur[k]
            mark[u] = 0
            _sum_children(rgb, u)
            _sum_children(lum2, u)
            if moments:
                _sum_children(moment, u)
        n = m


@njit(cache=True, inline="always")
def children_stale(lc: int, stamp: np.ndarray, qver: np.ndarray, u: int, level: int) -> bool:
    """Whether :func:`fill_children` has work for node ``u``: its children are finer than the
    coarse level ``lc`` and were not summed since their coarse quad last changed. Callers test
    this first: passing the ``src`` tuple to a call costs a reference count per array (82
    calls that did nothing took 6 us)."""
    if level + 1 <= lc:
        return False
    return stamp[4 * u] < qver[(u - (4 << (2 * level))) >> (2 * (level - lc))]


@njit(cache=True)
def fill_children(src: tuple, u: int, level: int) -> None:  # type: ignore[type-arg]
    """Make the sums of the four children of node ``u`` (at ``level``) current.

    ``src`` = (flat, order, first, pomega, pdirs, weights, moments, coarse level, max level,
    stamp, qver, frame, rgb, lum, moment, scratch (7,)). Children at or above the coarse level
    come from the per-frame pyramid; finer ones are summed from their pixel range unless
    already summed since their coarse quad last changed."""
    (flat, order, first, pomega, pdirs, weights, moments, lc, kmax, stamp, qver, frame,
     rgb, lum, moment, s) = src
    if level + 1 <= lc:
        return
    i = u - (4 << (2 * level))
    q = i >> (2 * (level - lc))
    if stamp[4 * u] >= qver[q]:
        return
    sh = 2 * (kmax - level - 1)
    for ch in range(4):
        j = 4 * i + ch
        range_sums(flat, order, first[j << sh], first[(j + 1) << sh], pomega, pdirs, weights,
                   moments, s)
        _store(4 * u + ch, s, moments, rgb, lum, moment)
        stamp[4 * u + ch] = frame


# -- tables --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Tables:
    """Input geometry at (max level K, coarse level Lc): pixels sorted by finest-level quad
    (``order``, ``first``, ``pomega``, ``pdirs``), the runs of consecutive pixels in one coarse
    quad (``run_p0 .. run_p1``; equirect: within one row), where each run's sum is stored so
    that a quad's runs are contiguous and in image order (``run_pos``, quad q from
    ``q_first[q]``) and rows of runs contiguous in memory (``row_run``)."""

    max_level: int
    coarse: int
    pixels: int
    order: np.ndarray
    first: np.ndarray
    pomega: np.ndarray
    pdirs: np.ndarray
    run_p0: np.ndarray
    run_p1: np.ndarray
    run_quad: np.ndarray
    q_first: np.ndarray
    run_pos: np.ndarray
    row_run: np.ndarray
    width: int = 0  # equirect width (0: HEALPix input)
    run_rc: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))  # (row, col)
    trig: tuple[np.ndarray, ...] = ()  # equirect (omega, sin t, cos t, sin p, cos p) per row/col


def _csr(keys: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(first, order): stable order of ``keys`` and the start of each key 0..n in it."""
    order = np.argsort(keys, kind="stable").astype(np.int32)
    first = np.searchsorted(keys[order], np.arange(n + 1)).astype(np.int32)
    return first, order


@functools.lru_cache(maxsize=4)
def equirect_tables(height: int, max_level: int, coarse: int) -> _Tables:
    """Tables of an (H, 2H) equirect map whose pixels go whole to the quad holding their centre."""
    width = 2 * height
    nside = 1 << max_level
    dirs = equirect_directions(height, width).reshape(-1, 3)
    fine = vec2pix_nest(nside, dirs)
    first, order = _csr(fine, 12 * nside * nside)
    omega = equirect_row_solid_angle(height, width)
    quad = fine >> (2 * (max_level - coarse))
    p = np.arange(height * width)
    start = (p % width == 0) | np.r_[True, quad[1:] != quad[:-1]]
    run_p0 = np.flatnonzero(start).astype(np.int32)
    run_p1 = np.r_[run_p0[1:], height * width].astype(np.int32)
    run_quad = quad[run_p0].astype(np.int32)
    q_first, q_runs = _csr(run_quad, 12 << (2 * coarse))
    run_pos = np.empty_like(q_runs)
    run_pos[q_runs] = np.arange(len(q_runs), dtype=np.int32)
    row_run = np.searchsorted(run_p0, np.arange(height + 1) * width).astype(np.int32)
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    trig = (omega, np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi))
    return _Tables(max_level, coarse, height * width, order, first, omega[order // width],
                   np.ascontiguousarray(dirs[order]), run_p0, run_p1, run_quad, q_first, run_pos,
                   row_run, width=width, trig=trig,
                   run_rc=np.stack([run_p0 // width, run_p0 % width], axis=1).astype(np.int32))


@functools.lru_cache(maxsize=4)
def healpix_tables(max_level: int, coarse: int) -> _Tables:
    """Tables of a NESTED map at nside 2^max_level (already sorted: ``order`` is the identity);
    each coarse quad is one run, rows are 1024 pixels."""
    npix = 12 << (2 * max_level)
    group = 1 << (2 * (max_level - coarse))
    nq = npix // group
    ident = np.arange(npix + 1, dtype=np.int32)
    run_p0 = np.arange(nq, dtype=np.int32) * group
    row_run = np.r_[np.arange(0, nq, max(1, 1024 // group)), nq].astype(np.int32)
    return _Tables(max_level, coarse, npix, ident[:-1], ident, np.full(npix, 4 * np.pi / npix),
                   pix2vec_nest(1 << max_level, np.arange(npix)), run_p0, run_p0 + group,
                   np.arange(nq, dtype=np.int32), ident[:nq + 1], ident[:nq], row_run)


class FrameState:
    """The pyramid of one input geometry and what it needs to be updated frame to frame.

    ``load(flat)`` bins a frame: a full pass the first time (or after ``valid = False``), then
    only the runs whose bits changed and their coarse quads (``incremental``). After it, levels
    ``0 .. coarse`` of ``rgb`` / ``lum`` / ``moment`` hold the frame's sums and :meth:`source`
    lets the tree kernels sum finer nodes.
    """

    def __init__(self, tables: _Tables, moments: bool) -> None:
        self.tables = tables
        self.moments = moments
        self.key: tuple[object, ...] = ()  # what the owner built it for
        m = 16 << (2 * tables.max_level)
        self.rgb = np.zeros((m, 3))
        self.lum = np.zeros(m)
        self.moment = np.zeros((m if moments else 1, 3))
        self.stamp = np.zeros(m, np.int64)
        self.mark = np.zeros(4 << (2 * tables.coarse), np.int64)  # update_coarse's scratch
        self.scratch = np.zeros(7)
        nq = 12 << (2 * tables.coarse)
        nr = len(tables.run_p0)
        self.qver = np.zeros(nq, np.int64)
        self.run_sum = np.zeros((nr, 6))
        self.all_quads = np.arange(nq, dtype=np.int32)
        self.all_runs = np.arange(nr, dtype=np.int32)
        self.dirty = np.empty(nq, np.int32)
        self.dirty_runs = np.empty(nr, np.int32)
        self.frame = 0
        self.prev: np.ndarray | None = None  # the previous frame's bits (buffer kept)
        self.valid = False  # False: the next load is a full pass
        self.busy = 0  # frames left before comparing again
        self.flat: np.ndarray = np.zeros((0, 3), np.float32)
        self.changed = nq

    def invalidate(self) -> None:
        """Forget the previous frame: the next load is a full pass."""
        self.valid = False
        self.busy = 0

    def _run_sums(self, flat: np.ndarray, bits: np.ndarray, runs: np.ndarray) -> None:
        t = self.tables
        if t.width:
            om, st, ct, sp, cp = t.trig
            equirect_run_sums(flat.reshape(-1), bits, runs, t.run_p0, t.run_p1, t.run_rc,
                              t.run_pos, om, st, ct, sp, cp, LUMINANCE_WEIGHTS, self.moments,
                              self.run_sum)
        else:
            healpix_run_sums(flat, runs, t.run_p0, t.run_p1, t.order, t.pomega, t.pdirs,
                             LUMINANCE_WEIGHTS, self.moments, self.run_sum)

    def load(self, flat: np.ndarray, incremental: bool = True) -> str:
        """Bin the (P, 3) frame ``flat`` (kept by reference until the next call); returns
        "full" or "incremental". Sets ``changed`` to the number of coarse quads re-summed."""
        self.frame += 1
        self.flat = flat
        bits = flat.reshape(-1).view(np.uint32)
        t = self.tables
        prev = self.prev
        compare = incremental and self.valid and prev is not None and prev.shape == bits.shape
        if compare and self.busy > 0:
            # most runs changed lately (a camera's noise, a gain change): comparing would
            # only add to a full pass; try again every RETRY frames
            self.busy -= 1
            compare = False
        if compare and prev is not None:
            n_runs, n = compare_runs(bits, prev, bits.size // t.pixels, t.row_run,
                                     t.run_p0, t.run_p1, t.run_quad, self.qver, self.frame,
                                     self.dirty_runs, self.dirty)
            self._run_sums(flat, bits, self.dirty_runs[:n_runs])
            quads = self.dirty[:n]
            mode = "incremental"
            if n_runs > BUSY_FRACTION * len(t.run_p0):
                self.busy = RETRY - 1
        else:
            if self.prev is None or self.prev.shape != bits.shape:
                self.prev = np.empty_like(bits)
            np.copyto(self.prev, bits)
            self.valid = True
            self.qver[:] = self.frame
            self._run_sums(flat, bits, self.all_runs)
            quads = self.all_quads
            mode = "full"
        self.changed = len(quads)
        if len(quads):
            update_coarse(quads, t.q_first, self.run_sum, LUMINANCE_WEIGHTS, self.moments,
                          t.coarse, self.rgb, self.lum, self.moment, self.mark)
        return mode

    def source(self) -> tuple:  # type: ignore[type-arg]
        """The ``src`` tuple of :func:`fill_children` for the current frame."""
        t = self.tables
        return (self.flat, t.order, t.first, t.pomega, t.pdirs, LUMINANCE_WEIGHTS,
                self.moments, t.coarse, t.max_level, self.stamp, self.qver, self.frame,
                self.rgb, self.lum, self.moment, self.scratch)
