"""Cuts of the 2^15-direction binary tree: selection, height/index coding, products, interpolation.

A *cut* is a set of nodes with exactly one node on every root-to-leaf path. Stored leftmost-first,
a node's position follows from the heights of the nodes before it, so a cut is fully described by
``heights`` (uint8, 0..15: 4 bits) and ``values`` (Iwasaki et al., Sec. V-A-2, Fig. 5). The
index-coded form (previous methods) stores a 16-bit heap index per node instead.

Dtype policy: leaf values float64 in, cut values float32 (SVC) or uint8 0/1 (VCF); sums float64.
Stored SVC values: 8-bit codes with a float16 scale per cut (``u8``), or float16 (``f16``).

References
----------
K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita, "Interactive relighting of captured
illumination with visibility cuts", Sec. V-A (cut selection, height-based representation,
Steps 1-4 and Fig. 6 for operations on several cuts).
E. Cheslack-Postava et al., "Fast, realistic lighting and material design using nonlinear cut
approximation", TOG 27(5), 2008 (index-coded cuts).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from lightprobe.hostlink.relight.cuts.directions import DEPTH, NDIR, heap_index

__all__ = [
    "binary_cut",
    "cut_interpolate",
    "cut_product",
    "decode_height",
    "decode_index",
    "dense",
    "encode_height",
    "encode_index",
    "height_coded_nbytes",
    "index_coded_nbytes",
    "is_cut",
    "merge_cuts",
    "quantize_cuts_u8",
    "quantize_u8",
    "select_cut",
]


# ---- cut selection ------------------------------------------------------------------------------
@njit(cache=True)
def _select_cut(leaf: np.ndarray, tau: float, dw: float, out_h: np.ndarray, out_v: np.ndarray) -> int:
    """SSE-thresholded cut of one leaf vector: emit node iff err <= tau and parent err > tau."""
    s1 = np.zeros(2 * NDIR)
    s2 = np.zeros(2 * NDIR)
    for i in range(NDIR):
        x = leaf[i]
        s1[NDIR + i] = x
        s2[NDIR + i] = x * x
    for k in range(NDIR - 1, 0, -1):
        s1[k] = s1[2 * k] + s1[2 * k + 1]
        s2[k] = s2[2 * k] + s2[2 * k + 1]
    stack = np.empty(64, np.int64)
    sp = 0
    stack[0] = 1
    sp = 1
    n = 0
    while sp > 0:
        sp -= 1
        k = stack[sp]
        lvl = 0
        t = k
        while t > 1:
            t >>= 1
            lvl += 1
        cnt = float(1 << (DEPTH - lvl))
        mean = s1[k] / cnt
        err = max(s2[k] - s1[k] * mean, 0.0) * dw      # integrated SSE (sr), monotone
        if err <= tau or k >= NDIR:
            out_h[n] = DEPTH - lvl
            out_v[n] = mean
            n += 1
        else:
            stack[sp] = 2 * k + 1                     # right pushed first: left pops first
            stack[sp + 1] = 2 * k
            sp += 2
    return n


def select_cut(leaf: np.ndarray, tau: float, dw: float = 4 * np.pi / NDIR) -> tuple[np.ndarray, np.ndarray]:
    """Cut of a leaf vector at integrated-SSE threshold ``tau`` (sr units with ``dw`` per leaf).

    The error of a node is ``dw * sum_leaves (v - mean)^2``; it never grows from parent to child,
    so the selected nodes (``err <= tau`` with ``parent err > tau``) form a cut with no holes.
    """
    leaf = np.ascontiguousarray(leaf, np.float64)
    if leaf.shape != (NDIR,):
        raise ValueError(f"leaf vector must have {NDIR} entries")
    leaf = np.nan_to_num(leaf, nan=0.0, posinf=0.0, neginf=0.0)   # degenerate: NaN -> 0
    h = np.empty(NDIR, np.uint8)
    v = np.empty(NDIR, np.float32)
    n = _select_cut(leaf, float(tau), float(dw), h, v)
    return h[:n].copy(), v[:n].copy()


@njit(cache=True)
def _binary_cut(bits: np.ndarray, out_h: np.ndarray, out_v: np.ndarray) -> int:
    """Lossless cut of binary leaves: two children merge only if both are uniform and equal."""
    u = np.empty(2 * NDIR, np.uint8)                 # 0 / 1 uniform, 2 mixed
    for i in range(NDIR):
        u[NDIR + i] = 1 if bits[i] else 0
    for k in range(NDIR - 1, 0, -1):
        a = u[2 * k]
        u[k] = a if a == u[2 * k + 1] and a != 2 else 2
    stack = np.empty(64, np.int64)
    stack[0] = 1
    sp = 1
    n = 0
    while sp > 0:
        sp -= 1
        k = stack[sp]
        if u[k] != 2:
            lvl = 0
            t = k
            while t > 1:
                t >>= 1
                lvl += 1
            out_h[n] = DEPTH - lvl
            out_v[n] = u[k]
            n += 1
        else:
            stack[sp] = 2 * k + 1
            stack[sp + 1] = 2 * k
            sp += 2
    return n


def binary_cut(bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lossless height-coded cut (heights uint8, values uint8 0/1) of a binary leaf vector."""
    bits = np.ascontiguousarray(bits, np.uint8)
    h = np.empty(NDIR, np.uint8)
    v = np.empty(NDIR, np.uint8)
    n = _binary_cut(bits, h, v)
    return h[:n].copy(), v[:n].copy()


# ---- dense reference and checks ------------------------------------------------------------------
def dense(heights: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Expand a cut to its 2^15 leaf values (each node's value on all its leaves)."""
    return np.repeat(np.asarray(values), np.left_shift(1, np.asarray(heights, np.int64)))


def is_cut(heights: np.ndarray) -> bool:
    """True iff the leftmost-first heights describe a cut: every node aligned, leaves covered once
    (equivalently, exactly one node on every root-to-leaf path)."""
    h = np.asarray(heights, np.int64)
    if h.size == 0 or h.min() < 0 or h.max() > DEPTH:
        return False
    size = np.left_shift(1, h)
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    return bool(size.sum() == NDIR and np.all(start % size == 0))


# ---- counter-based traversal of several cuts (Steps 1-4, Fig. 6) --------------------------------
@njit(cache=True)
def min_height(heights: np.ndarray, p: np.ndarray, m: int) -> int:
    """Smallest height among the m nodes the pointers p point at (Step 2's h_min)."""
    hmin = 99
    for j in range(m):
        hj = heights[p[j]]
        if hj < hmin:
            hmin = hj
    return hmin


@njit(cache=True)
def advance_counters(heights: np.ndarray, p: np.ndarray, c: np.ndarray, m: int, hmin: int) -> None:
    """Step 3: (a) a cut whose node has height h_min moves on, its counter reset; (b) any other
    adds 2^h_min to its counter and moves on once the counter reaches 2^h_j."""
    step = 1 << hmin
    for j in range(m):
        hj = heights[p[j]]
        if hj == hmin:
            p[j] += 1
            c[j] = 0
        else:
            c[j] += step
            if c[j] >= (1 << hj):
                p[j] += 1
                c[j] = 0


@njit(cache=True)
def merge_cuts(heights: np.ndarray, values: np.ndarray, starts: np.ndarray, ends: np.ndarray,
               weights: np.ndarray, mode: int, out_h: np.ndarray, out_v: np.ndarray) -> int:
    """Combine m height-coded cuts node by node; mode 0 = product, 1 = sum of ``weights * v``.

    Cut j occupies ``heights[starts[j]:ends[j]]``. Step 1: pointers p_j at the first node, counters
    c_j = 0. Step 2: operate on the pointed nodes, store at the minimum height h_min. Step 3(a):
    if h_j == h_min advance p_j, c_j = 0; (b) else c_j += 2^h_min and advance when c_j = 2^h_j.
    Step 4: repeat until every pointer passed its last node.
    """
    m = starts.shape[0]
    p = starts.copy()                                          # Step 1
    c = np.zeros(m, np.int64)
    n = 0
    while p[0] < ends[0]:
        hmin = min_height(heights, p, m)
        if mode == 0:                                          # Step 2
            acc = 1.0
            for j in range(m):
                acc *= values[p[j]]
        else:
            acc = 0.0
            for j in range(m):
                acc += weights[j] * values[p[j]]
        out_h[n] = hmin
        out_v[n] = acc
        n += 1
        advance_counters(heights, p, c, m, hmin)               # Step 3
    return n


def _stack(cuts: list[tuple[np.ndarray, np.ndarray]]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    hs = np.concatenate([np.asarray(h, np.int64) for h, _ in cuts])
    vs = np.concatenate([np.asarray(v, np.float64) for _, v in cuts])
    lens = np.array([len(h) for h, _ in cuts], np.int64)
    ends = np.cumsum(lens)
    return hs, vs, ends - lens, ends, int(lens.sum())


def cut_product(cuts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Product of several cuts, itself a cut (Iwasaki et al. Eq. 4 on cuts)."""
    hs, vs, st, en, tot = _stack(cuts)
    oh = np.empty(tot, np.int64)
    ov = np.empty(tot, np.float64)
    n = merge_cuts(hs, vs, st, en, np.ones(len(cuts)), 0, oh, ov)
    return oh[:n], ov[:n]


def cut_interpolate(cuts: list[tuple[np.ndarray, np.ndarray]], weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted sum (e.g. trilinear weights of the 8 neighbouring VCF points) of cuts."""
    hs, vs, st, en, tot = _stack(cuts)
    oh = np.empty(tot, np.int64)
    ov = np.empty(tot, np.float64)
    n = merge_cuts(hs, vs, st, en, np.asarray(weights, np.float64), 1, oh, ov)
    return oh[:n], ov[:n]


# ---- storage: height-coded vs index-coded ---------------------------------------------------------
# Value encodings (the same for both position codings, so the comparison is fair):
#   "binary": 1 bit per node (VCF);
#   "f16":    IEEE half float per node;
#   "u8":     8-bit linear code per node, v = code / 255 * scale, with one float16 scale per cut
#             (the cut's largest value; SVC values are >= 0). Step <= 0.2% of the cut's maximum.
_SCALE_BYTES = 2


def quantize_u8(values: np.ndarray) -> tuple[float, np.ndarray]:
    """(float16-representable scale, uint8 codes) of one cut's non-negative values."""
    v = np.maximum(np.nan_to_num(np.asarray(values, np.float64)), 0.0)
    scale = float(np.float16(v.max())) if v.size else 0.0
    if scale > 0 and v.size and v.max() > scale:                   # rounding down would clip
        scale = float(np.nextafter(np.float16(scale), np.float16(np.inf)))
    codes = np.rint(v / scale * 255).clip(0, 255).astype(np.uint8) if scale > 0 else np.zeros(v.size, np.uint8)
    return scale, codes


def quantize_cuts_u8(offsets: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Values of many cuts (cut k at ``values[offsets[k]:offsets[k+1]]``) as the u8 encoding
    stores them (float32): what a renderer reading the u8 stream sees."""
    v = np.maximum(np.nan_to_num(np.asarray(values, np.float64)), 0.0)
    lens = np.diff(offsets)
    out = np.zeros(len(v), np.float32)
    if not len(v):
        return out
    nz = lens > 0
    mx = np.zeros(len(lens))
    mx[nz] = np.maximum.reduceat(v, offsets[:-1][nz])
    scale = mx.astype(np.float16).astype(np.float64)
    up = scale < mx                                                  # keep scale >= max
    scale[up] = np.nextafter(mx[up].astype(np.float16), np.float16(np.inf)).astype(np.float64)
    s = np.repeat(scale, lens)
    codes = np.where(s > 0, np.rint(v / np.where(s > 0, s, 1) * 255), 0).clip(0, 255)
    out[:] = codes / 255.0 * s
    return out


def _value_bytes(values: np.ndarray, kind: str) -> bytes:
    if kind == "binary":
        return np.packbits(np.asarray(values, np.uint8) & 1).tobytes()
    if kind == "f16":
        return np.asarray(values, np.float16).tobytes()
    if kind == "u8":
        scale, codes = quantize_u8(values)
        return np.float16(scale).tobytes() + codes.tobytes()
    raise ValueError(f"unknown value kind {kind!r} (binary, f16 or u8)")


def _values_from(buf: bytes, n: int, kind: str) -> np.ndarray:
    if kind == "binary":
        return np.unpackbits(np.frombuffer(buf, np.uint8))[:n].astype(np.uint8)
    if kind == "u8":
        scale = float(np.frombuffer(buf, np.float16, count=1)[0])
        codes = np.frombuffer(buf, np.uint8, count=n, offset=_SCALE_BYTES)
        return (codes / 255.0 * scale).astype(np.float32)
    return np.frombuffer(buf, np.float16, count=n).astype(np.float32)


def _values_nbytes(n: int, kind: str) -> int:
    if kind == "binary":
        return (n + 7) // 8
    if kind == "u8":
        return _SCALE_BYTES + n
    return 2 * n


def height_coded_nbytes(n: int, kind: str) -> int:
    """Bytes of a height-coded cut: 4-bit heights (two per byte) + values."""
    return (n + 1) // 2 + _values_nbytes(n, kind)


def index_coded_nbytes(n: int, kind: str) -> int:
    """Bytes of an index-coded cut: 16-bit heap indices + values (the same value encoding)."""
    return 2 * n + _values_nbytes(n, kind)


def encode_height(heights: np.ndarray, values: np.ndarray, kind: str = "binary") -> bytes:
    """Pack heights as nibbles (low nibble first), then the values. Self-delimiting: a decoder
    reads nibbles until they cover the 2^15 leaves."""
    h = np.asarray(heights, np.uint8)
    if h.size and int(h.max()) > DEPTH:
        raise ValueError("height above 15")
    if h.size % 2:
        h = np.concatenate([h, np.zeros(1, np.uint8)])
    nib = (h[0::2] | (h[1::2] << 4)).astype(np.uint8)
    return nib.tobytes() + _value_bytes(values, kind)


def decode_height(data: bytes, kind: str = "binary") -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_height`."""
    raw = np.frombuffer(data, np.uint8)
    nib = np.empty(2 * raw.size, np.uint8)
    nib[0::2] = raw & 15
    nib[1::2] = raw >> 4
    covered = np.cumsum(np.left_shift(1, nib.astype(np.int64)))
    n = int(np.searchsorted(covered, NDIR) + 1)
    if n > nib.size or covered[n - 1] != NDIR:
        raise ValueError("height code does not close a cut")
    off = (n + 1) // 2
    return nib[:n].copy(), _values_from(data[off:], n, kind)


def encode_index(heights: np.ndarray, values: np.ndarray, kind: str = "binary") -> bytes:
    """Index-coded cut: uint16 heap indices (little-endian), then the values."""
    h = np.asarray(heights, np.int64)
    start = np.concatenate([[0], np.cumsum(np.left_shift(1, h))[:-1]])
    idx = heap_index(h, start).astype("<u2")
    return len(h).to_bytes(4, "little") + idx.tobytes() + _value_bytes(values, kind)


def decode_index(data: bytes, kind: str = "binary") -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_index` (heights from the heap index: h = 15 - floor(log2 idx))."""
    n = int.from_bytes(data[:4], "little")
    idx = np.frombuffer(data, "<u2", count=n, offset=4).astype(np.int64)
    h = (DEPTH - (np.floor(np.log2(idx)).astype(np.int64))).astype(np.uint8)
    return h, _values_from(data[4 + 2 * n:], n, kind)
