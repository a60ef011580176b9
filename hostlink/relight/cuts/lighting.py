"""Source lighting per direction cluster: L_k = integral of radiance over cluster k (unit x sr).

The map is integrated over the 2^15 leaf cells once (each equirect pixel split into 2 x 2
sub-pixels, each sub-pixel's exact solid-angle share assigned to the leaf containing its centre),
then cumulative sums in tree order make any node's integral ``P[end] - P[start]`` (O(1)).
Energy is conserved: ``sum_leaves L = equirect_integral(map)``.
Dtype policy: float32 maps in, float64 leaf integrals and prefix sums out.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import directions_from_angles
from lightprobe.hostlink.relight.cuts.directions import NDIR, direction_to_leaf

__all__ = [
    "LightTables",
    "leaf_light_from_equirect",
    "leaf_light_from_lightset",
    "leaf_moments",
    "light_tables",
    "moment_prefix_sums",
    "node_table",
    "prefix_sums",
    "rotated_light_tables",
]

_SUB = 2


@lru_cache(maxsize=4)
def _equirect_matrix(height: int, width: int) -> sp.csr_matrix:
    """Sparse (2^15, H*W) matrix: pixel radiance -> leaf integral."""
    r = (np.arange(height * _SUB) + 0.5) / (height * _SUB)
    c = (np.arange(width * _SUB) + 0.5) / (width * _SUB)
    theta = np.pi * r
    phi = 2 * np.pi * c
    cos_edges = np.cos(np.pi * np.arange(height * _SUB + 1) / (height * _SUB))
    sub_dw = (2 * np.pi / (width * _SUB)) * (cos_edges[:-1] - cos_edges[1:])   # exact per sub-row
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    leaf = direction_to_leaf(directions_from_angles(tt, pp)).ravel()
    pix = ((np.arange(height * _SUB) // _SUB)[:, None] * width + (np.arange(width * _SUB) // _SUB)[None, :]).ravel()
    w = np.broadcast_to(sub_dw[:, None], tt.shape).ravel()
    m = sp.csr_matrix((w, (leaf, pix)), shape=(NDIR, height * width))
    m.sum_duplicates()
    return m


def leaf_light_from_equirect(img: np.ndarray) -> np.ndarray:
    """(2^15, 3) float64 radiance x solid angle per leaf cell of an equirect (H, 2H, 3) map.

    NaN / inf / negative pixels (e.g. lossy EXR) are treated as 0.
    """
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] < 3 or img.shape[1] != 2 * img.shape[0]:
        raise ValueError(f"expected an equirect map (H, 2H, 3), got {img.shape}")
    h, w = img.shape[:2]
    if img.dtype not in (np.float32, np.float64):
        img = img.astype(np.float32)                     # e.g. half-float EXR, integer maps
    m = _equirect_matrix(h, w)
    out = np.zeros((NDIR, 3))
    _csr_rgb(m.indptr, m.indices, m.data, img.reshape(h * w, img.shape[2]), out)
    return out


@njit(cache=True, parallel=True)
def _csr_rgb(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, pix: np.ndarray,
             out: np.ndarray) -> None:
    """out[leaf] = sum of weight x pixel rgb over the leaf's CSR row (float64 sums), with
    NaN / inf / negative pixel values taken as 0."""
    for r in prange(out.shape[0]):
        a0 = a1 = a2 = 0.0
        for q in range(indptr[r], indptr[r + 1]):
            p = indices[q]
            wq = data[q]
            x0, x1, x2 = float(pix[p, 0]), float(pix[p, 1]), float(pix[p, 2])
            if x0 > 0 and x0 < np.inf:
                a0 += wq * x0
            if x1 > 0 and x1 < np.inf:
                a1 += wq * x1
            if x2 > 0 and x2 < np.inf:
                a2 += wq * x2
        out[r, 0] = a0
        out[r, 1] = a1
        out[r, 2] = a2


def leaf_light_from_lightset(ls: LightSet) -> np.ndarray:
    """Bin each light's rgb (radiance x solid angle) into the leaf holding its direction."""
    out = np.zeros((NDIR, 3))
    if len(ls) == 0:
        return out
    leaf = direction_to_leaf(np.asarray(ls.directions, np.float64))
    rgb = np.nan_to_num(np.asarray(ls.rgb, np.float64))
    for ch in range(3):
        out[:, ch] = np.bincount(leaf, weights=rgb[:, ch], minlength=NDIR)
    return out


def prefix_sums(leaf_light: np.ndarray) -> np.ndarray:
    """(2^15 + 1, 3) float64 cumulative sums in tree order: node integral = P[end] - P[start]."""
    p = np.zeros((NDIR + 1, 3))
    np.cumsum(np.asarray(leaf_light, np.float64), axis=0, out=p[1:])
    return p


def leaf_moments(leaf_light: np.ndarray, dirs: np.ndarray | None = None) -> np.ndarray:
    """(2^15, 9) float64 first light moments L_c w_a per leaf (column 3 c + a; channel c,
    direction component a), with ``dirs`` the leaf directions (default: the leaf centres)."""
    from lightprobe.hostlink.relight.cuts.directions import leaf_directions

    d = leaf_directions() if dirs is None else np.asarray(dirs, np.float64)
    prod = np.asarray(leaf_light, np.float64)[:, :, None] * d[:, None, :]
    return prod.reshape(NDIR, 9)


def moment_prefix_sums(leaf_light: np.ndarray, moments: np.ndarray | None = None) -> np.ndarray:
    """(2^15 + 1, 9) float64 cumulative sums of L_c w_a (column 3 c + a; channel c, direction
    component a): a node's first light moment in O(1), for the cosine-moment correction."""
    q = np.zeros((NDIR + 1, 9))
    mom = leaf_moments(leaf_light) if moments is None else moments
    np.cumsum(mom, axis=0, out=q[1:])
    return q


@lru_cache(maxsize=1)
def _inorder_of_heap() -> np.ndarray:
    """In-order position ``2 start + 2^h - 1`` of every heap index 1 .. 2^16 - 1."""
    heap = np.arange(1, 2 * NDIR)
    lvl = np.floor(np.log2(heap)).astype(np.int64)
    h = 15 - lvl
    start = (heap - (1 << lvl)) << h
    return 2 * start + (1 << h) - 1


@njit(cache=True)
def _node_table(leaf: np.ndarray, mom: np.ndarray, ndir_inorder: np.ndarray, out: np.ndarray) -> None:
    """Bottom-up tree sums straight into in-order rows (float64 sums, float32 rows)."""
    acc = np.zeros((2 * NDIR, 12))
    for j in range(NDIR):                                  # leaves: h = 0, row 2 j
        for c in range(3):
            acc[2 * j, c] = leaf[j, c]
        for c in range(9):
            acc[2 * j, 3 + c] = mom[j, c]
    for h in range(1, 16):                                 # node (h, s) = (h-1, s) + (h-1, s + 2^(h-1))
        half = 1 << (h - 1)
        for s in range(0, NDIR, 1 << h):
            row = 2 * s + (1 << h) - 1
            a = 2 * s + half - 1
            b = 2 * (s + half) + half - 1
            for c in range(12):
                acc[row, c] = acc[a, c] + acc[b, c]
    for row in range(2 * NDIR - 1):
        for c in range(12):
            out[row, c] = acc[row, c]
        cx = acc[row, 3] + acc[row, 6] + acc[row, 9]       # sum over channels of L_c w
        cy = acc[row, 4] + acc[row, 7] + acc[row, 10]
        cz = acc[row, 5] + acc[row, 8] + acc[row, 11]
        n = np.sqrt(cx * cx + cy * cy + cz * cz)
        if n > 1e-300:
            out[row, 12], out[row, 13], out[row, 14] = cx / n, cy / n, cz / n
        else:
            out[row, 12], out[row, 13], out[row, 14] = ndir_inorder[row, 0], ndir_inorder[row, 1], ndir_inorder[row, 2]


@lru_cache(maxsize=1)
def _node_directions_inorder() -> np.ndarray:
    from lightprobe.hostlink.relight.cuts.directions import node_directions

    out = np.zeros((2 * NDIR, 3), np.float32)
    out[_inorder_of_heap()] = node_directions()[1:]
    return out


def node_table(leaf_light: np.ndarray, moments: np.ndarray | None = None) -> np.ndarray:
    """(2^16, 16) float32 per-node light integrals in **in-order** layout: the node of height h
    starting at leaf s is row ``2 s + 2^h - 1``, so the nodes of a cut, read leftmost-first,
    are rows in increasing order (streaming, prefetch-friendly access). Columns 0-2: the
    integral L_k (unit x sr); 3-11: the first moments (as :func:`moment_prefix_sums`); 12-14:
    the unit light centroid direction (the node's mean direction when the node is dark).

    Computed once per lighting change (tree sums in float64, stored as float32: one 64-byte row
    per node) and shared by every vertex, so shading a cut node is one row load.
    """
    mom = leaf_moments(leaf_light) if moments is None else moments
    out = np.zeros((2 * NDIR, 16), np.float32)
    _node_table(np.ascontiguousarray(leaf_light, np.float64), np.ascontiguousarray(mom, np.float64),
                _node_directions_inorder(), out)
    return out


@dataclass
class LightTables:
    """Everything the kernels read about one lighting (in one frame): prefix sums in leaf order
    for arbitrary leaf ranges (``P`` (2^15+1, 3), ``Q`` (2^15+1, 9), float64), the same packed
    one row per leaf boundary with the leaf-direction prefix sums (``PQ`` (2^15+1, 16): columns
    0-2 P, 3-11 Q, 12-14 directions; two cache lines per lookup), and the per-node table ``T``
    (:func:`node_table`)."""
    P: np.ndarray
    Q: np.ndarray
    T: np.ndarray
    PQ: np.ndarray


def light_tables(leaf_light: np.ndarray, moments: np.ndarray | None = None) -> LightTables:
    from lightprobe.hostlink.relight.cuts.directions import leaf_directions

    mom = leaf_moments(leaf_light) if moments is None else moments
    P, Q = prefix_sums(leaf_light), moment_prefix_sums(leaf_light, mom)
    pq = np.zeros((NDIR + 1, 16))
    pq[:, :3] = P
    pq[:, 3:12] = Q
    np.cumsum(leaf_directions(), axis=0, out=pq[1:, 12:15])
    return LightTables(P, Q, node_table(leaf_light, mom), pq)


def rotated_light_tables(leaf_light: np.ndarray, rot: np.ndarray) -> tuple[LightTables, LightTables]:
    """Lighting re-expressed over the direction tree of an object rotated by ``rot`` (object ->
    world): each world leaf j is binned into the object-frame leaf containing ``rot^T w_j``
    (energy conserving; directions move by at most one cell, ~1.3 deg).

    Returns (own, seen): ``own`` has moments in object coordinates (to shade the rotated
    object's own vertices with their precompute-pose normals), ``seen`` has moments in world
    coordinates (to weight occlusion the rotated object casts on world-frame receivers).
    """
    from lightprobe.hostlink.relight.cuts.directions import leaf_directions

    d = leaf_directions()
    dobj = d @ np.asarray(rot, np.float64)                # rows: rot^T w_j
    leaf = direction_to_leaf(dobj)
    L = np.asarray(leaf_light, np.float64)

    def binned(x: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(leaf, weights=x[:, c], minlength=NDIR) for c in range(x.shape[1])], 1)

    lo = binned(L)
    return (light_tables(lo, binned(leaf_moments(L, dobj))),
            light_tables(lo, binned(leaf_moments(L, d))))
