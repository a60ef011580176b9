"""The 2^15 sample directions and their complete binary tree (depth 15).

Each hemisphere (+y, -y; probe frame, ``core/sphere.py``) is an equal-area square of
128 x 128 cells: Shirley-Chiu concentric map square -> disc, then Lambert's equal-area map disc ->
hemisphere. Cells are ordered by hemisphere, then Morton (Z) order of their (i, j) cell index, so
leaf ``l = hemisphere << 14 | morton(i, j)`` and every node of the complete binary tree covers a
contiguous range of leaves (quad-tree levels interleaved with binary splits). Every leaf has the
same solid angle ``4 pi / 2^15``.

Tree indexing: a node of *height* ``h`` (edges down to a leaf, 0..15) and position ``k`` covers
leaves ``[k 2^h, (k+1) 2^h)``; its heap index is ``2^(15-h) + k`` (root = 1, leaves 2^15..2^16-1),
so an index needs 16 bits and a height 4 bits (Iwasaki et al., Sec. V-A-2).

References
----------
P. Shirley, K. Chiu, "A low distortion map between disk and square", JGT 2(3), 1997.
K. Iwasaki et al., "Interactive relighting of captured illumination with visibility cuts", Sec. V.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = [
    "DEPTH",
    "LEAF_SOLID_ANGLE",
    "NDIR",
    "SIDE",
    "cluster_compactness",
    "direction_to_leaf",
    "heap_index",
    "leaf_directions",
    "morton_encode",
    "node_directions",
    "node_moments",
]

DEPTH = 15
NDIR = 1 << DEPTH
SIDE = 128
LEAF_SOLID_ANGLE = 4.0 * np.pi / NDIR


def _part1by1(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.int64) & 0x7F
    x = (x | (x << 4)) & 0x0F0F
    x = (x | (x << 2)) & 0x3333
    return (x | (x << 1)) & 0x5555


def morton_encode(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Interleave the 7-bit cell indices ``i`` (odd bits) and ``j`` (even bits)."""
    return (_part1by1(i) << 1) | _part1by1(j)


def heap_index(height: np.ndarray, start_leaf: np.ndarray) -> np.ndarray:
    """Heap index ``2^(15-h) + start >> h`` of the node of height ``h`` starting at a leaf."""
    h = np.asarray(height, np.int64)
    return (np.int64(1) << (DEPTH - h)) + (np.asarray(start_leaf, np.int64) >> h)


def _square_to_hemisphere(a: np.ndarray, b: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """(a, b) in [-1, 1]^2 -> unit vector, +y hemisphere if sign > 0 (equal-area)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    use_a = np.abs(a) > np.abs(b)
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    r = np.where(use_a, a, b)
    phi = np.where(use_a, (np.pi / 4) * (b / safe_a), np.pi / 2 - (np.pi / 4) * (a / safe_b))
    phi = np.where((a == 0) & (b == 0), 0.0, phi)
    r2 = r * r
    s = np.abs(r) * np.sqrt(np.maximum(2.0 - r2, 0.0))
    sgn = np.sign(r)
    x = sgn * s * np.cos(phi)
    z = sgn * s * np.sin(phi)
    y = np.asarray(sign, np.float64) * (1.0 - r2)
    return np.stack([x, y, z], axis=-1)


def _hemisphere_to_square(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`_square_to_hemisphere`: -> (a, b, hemisphere 0 for +y / 1 for -y)."""
    d = np.asarray(d, np.float64)
    hemi = (d[..., 1] < 0).astype(np.int64)
    r = np.sqrt(np.clip(1.0 - np.abs(d[..., 1]), 0.0, 1.0))
    psi = np.arctan2(d[..., 2], d[..., 0])                      # in (-pi, pi]
    psi = np.where(psi < -np.pi / 4, psi + 2 * np.pi, psi)      # in [-pi/4, 7pi/4)
    q = np.floor((psi + np.pi / 4) / (np.pi / 2)).astype(np.int64).clip(0, 3)
    t = 4.0 / np.pi
    a = np.select([q == 0, q == 1, q == 2, q == 3],
                  [r, (np.pi / 2 - psi) * t * r, -r, -(1.5 * np.pi - psi) * t * r])
    b = np.select([q == 0, q == 1, q == 2, q == 3],
                  [psi * t * r, r, -(psi - np.pi) * t * r, -r])
    return np.clip(a, -1, 1), np.clip(b, -1, 1), hemi


@lru_cache(maxsize=1)
def leaf_directions() -> np.ndarray:
    """(2^15, 3) float64 cell-centre directions in leaf (tree) order; read-only."""
    i, j = np.meshgrid(np.arange(SIDE), np.arange(SIDE), indexing="ij")
    m = morton_encode(i.ravel(), j.ravel())
    a = (i.ravel() + 0.5) / SIDE * 2 - 1
    b = (j.ravel() + 0.5) / SIDE * 2 - 1
    out = np.empty((NDIR, 3))
    for hemi, sign in ((0, 1.0), (1, -1.0)):
        out[(hemi << 14) | m] = _square_to_hemisphere(a, b, np.full(a.shape, sign))
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out.setflags(write=False)
    return out


def direction_to_leaf(d: np.ndarray) -> np.ndarray:
    """Leaf index (int64) of the cell containing each direction (..., 3)."""
    a, b, hemi = _hemisphere_to_square(d)
    i = np.clip(((a + 1) * 0.5 * SIDE).astype(np.int64), 0, SIDE - 1)
    j = np.clip(((b + 1) * 0.5 * SIDE).astype(np.int64), 0, SIDE - 1)
    return (hemi << 14) | morton_encode(i, j)


@lru_cache(maxsize=1)
def node_directions() -> np.ndarray:
    """(2^16, 3) float32 unit mean direction of every node, by heap index (entry 0 unused)."""
    out = np.zeros((2 * NDIR, 3))
    out[NDIR:] = leaf_directions()
    for lvl in range(DEPTH - 1, -1, -1):
        lo = 1 << lvl
        out[lo:2 * lo] = out[2 * lo:4 * lo:2] + out[2 * lo + 1:4 * lo:2]
    n = np.linalg.norm(out, axis=1, keepdims=True)
    out = np.where(n > 1e-12, out / np.where(n > 0, n, 1), np.array([0.0, 1.0, 0.0]))
    res = out.astype(np.float32)
    res.setflags(write=False)
    return res


def cluster_compactness() -> dict[int, float]:
    """Worst cluster radius per tree level (degrees): max angle between a node's mean direction
    and its leaves' cell centres, plus half a cell diagonal (~0.9 deg)."""
    leaves = leaf_directions()
    nodes = node_directions().astype(np.float64)
    half_cell = float(np.degrees(np.sqrt(2 * LEAF_SOLID_ANGLE) / 2))
    worst: dict[int, float] = {}
    for level in range(DEPTH + 1):
        h = DEPTH - level
        k = np.arange(NDIR) >> h
        c = nodes[(1 << level) + k]
        cosang = np.clip(np.einsum("ij,ij->i", c, leaves), -1, 1)
        worst[level] = float(np.degrees(np.arccos(cosang)).max()) + half_cell
    return worst


@lru_cache(maxsize=1)
def node_moments() -> tuple[np.ndarray, np.ndarray]:
    """Per node (heap index): the unnormalised mean ``M`` of its leaf directions (2^16, 3) and
    ``thr = |M| sin(radius)`` (radius = largest angle from the node's mean direction to a leaf
    centre; ``thr = |M|`` when radius >= 90 deg), so ``n . M > thr`` iff every leaf centre of
    the node lies strictly above the horizon of normal n."""
    leaves = leaf_directions()
    mean = np.zeros((2 * NDIR, 3))
    mean[NDIR:] = leaves
    for lvl in range(DEPTH - 1, -1, -1):
        lo = 1 << lvl
        mean[lo:2 * lo] = (mean[2 * lo:4 * lo:2] + mean[2 * lo + 1:4 * lo:2]) / 2
    norm = np.linalg.norm(mean, axis=1)
    unit = node_directions().astype(np.float64)
    radius = np.zeros(2 * NDIR)
    for level in range(DEPTH + 1):
        h = DEPTH - level
        k = (1 << level) + (np.arange(NDIR) >> h)
        ang = np.arccos(np.clip(np.einsum("ij,ij->i", unit[k], leaves), -1, 1))
        np.maximum.at(radius, k, ang)
    thr = np.where(radius < np.pi / 2, norm * np.sin(radius), norm)
    thr[0] = np.inf
    mean.setflags(write=False)
    thr.setflags(write=False)
    return mean, thr
