"""Compiled helpers of :mod:`hostlink.room.room` (numba; imported only when a room renders
virtual objects, so ``import hostlink`` stays light)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["near_pairs", "near_to_point"]


@njit(cache=True, inline="always")
def _seg_dist2(px: float, py: float, pz: float, qx: float, qy: float, qz: float,
               cx: float, cy: float, cz: float) -> float:
    dx, dy, dz = qx - px, qy - py, qz - pz
    L2 = dx * dx + dy * dy + dz * dz
    t = 0.0
    if L2 > 1e-300:
        t = min(1.0, max(0.0, ((cx - px) * dx + (cy - py) * dy + (cz - pz) * dz) / L2))
    ex, ey, ez = px + t * dx - cx, py + t * dy - cy, pz + t * dz - cz
    return ex * ex + ey * ey + ez * ez


@njit(cache=True, parallel=True)
def near_to_point(P: np.ndarray, q: np.ndarray, c: np.ndarray, r: float, out: np.ndarray) -> None:
    """``out[i]``: the segment ``P[i] -> q`` passes within ``r`` of ``c``."""
    r2 = r * r
    for i in prange(P.shape[0]):
        out[i] = _seg_dist2(P[i, 0], P[i, 1], P[i, 2], q[0], q[1], q[2], c[0], c[1], c[2]) <= r2


@njit(cache=True, parallel=True)
def near_pairs(X: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, r: float, out: np.ndarray) -> None:
    """``out[k]``: the segment ``X[a[k]] -> X[b[k]]`` passes within ``r`` of ``c``."""
    r2 = r * r
    for k in prange(a.shape[0]):
        i, j = a[k], b[k]
        out[k] = _seg_dist2(X[i, 0], X[i, 1], X[i, 2], X[j, 0], X[j, 1], X[j, 2], c[0], c[1], c[2]) <= r2


@njit(cache=True, parallel=True, fastmath=True)
def polygon_ff_vectors(x: np.ndarray, tri: np.ndarray, out: np.ndarray) -> None:
    """``out[r, p]``: Lambert's vector of triangle ``tri[p]`` (P, 3, 3) seen from point ``x[r]``
    (``1 / 2 pi sum_edges angle_i (R_i x R_i+1) / |R_i x R_i+1|``, R the unit directions to the
    corners), oriented towards the triangle: the form factor to a receiver of normal n is g . n
    while the triangle lies above its horizon."""
    for r in prange(x.shape[0]):
        for p in range(tri.shape[0]):
            R = np.empty((3, 3))
            for k in range(3):
                dx = tri[p, k, 0] - x[r, 0]
                dy = tri[p, k, 1] - x[r, 1]
                dz = tri[p, k, 2] - x[r, 2]
                ln = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-300)
                R[k, 0], R[k, 1], R[k, 2] = dx / ln, dy / ln, dz / ln
            gx = gy = gz = 0.0
            for k in range(3):
                a0, a1, a2 = R[k, 0], R[k, 1], R[k, 2]
                k1 = (k + 1) % 3
                b0, b1, b2 = R[k1, 0], R[k1, 1], R[k1, 2]
                cx, cy, cz = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
                ln = max(np.sqrt(cx * cx + cy * cy + cz * cz), 1e-300)
                ang = np.arccos(min(1.0, max(-1.0, a0 * b0 + a1 * b1 + a2 * b2)))
                gx += ang * cx / ln
                gy += ang * cy / ln
                gz += ang * cz / ln
            s = 1.0 / (2 * np.pi)
            if gx * (R[0, 0] + R[1, 0] + R[2, 0]) + gy * (R[0, 1] + R[1, 1] + R[2, 1]) \
                    + gz * (R[0, 2] + R[1, 2] + R[2, 2]) < 0:
                s = -s
            out[r, p, 0], out[r, p, 1], out[r, p, 2] = gx * s, gy * s, gz * s


@njit(cache=True, parallel=True, fastmath=True)
def gather_room_light(n: np.ndarray, lab: np.ndarray, G: np.ndarray, vis: np.ndarray, B: np.ndarray,
                      out: np.ndarray) -> None:
    """``out[i] = sum_p max(G[lab[i], p] . n[i], 0) vis[lab[i], p] B[p]``: the room's light
    (radiosity B (P, 3)) arriving at point i with normal n[i], seen through cluster lab[i]."""
    for i in prange(n.shape[0]):
        q = lab[i]
        s0 = s1 = s2 = 0.0
        for p in range(G.shape[1]):
            if vis[q, p]:
                f = G[q, p, 0] * n[i, 0] + G[q, p, 1] * n[i, 1] + G[q, p, 2] * n[i, 2]
                if f > 0:
                    s0 += f * B[p, 0]
                    s1 += f * B[p, 1]
                    s2 += f * B[p, 2]
        out[i, 0], out[i, 1], out[i, 2] = s0, s1, s2
