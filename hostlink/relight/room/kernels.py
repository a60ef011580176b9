"""Compiled helpers of :mod:`lightprobe.hostlink.relight.room.room` (numba; imported only when a room renders
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


@njit(cache=True, parallel=True)
def sphere_light_rays(P: np.ndarray, N: np.ndarray, S: np.ndarray, U: np.ndarray, c: np.ndarray,
                      radius: float, eps: float, cols: np.ndarray, o: np.ndarray, d: np.ndarray,
                      t: np.ndarray, cos: np.ndarray, state: np.ndarray) -> None:
    """The shadow rays from receivers ``P`` (normals ``N``) to the sample points ``S[cols]`` of a
    spherical light (centre ``c``, unit offsets ``U``): ``state[i, k]`` 0 where the sample is on
    the far side of the sphere from the receiver or the sphere wholly below its horizon (not
    counted), 1 a ray to trace (origin ``o``, unit direction ``d``, length ``t``, cosine ``cos``),
    2 a sample below the receiver's horizon (counted, dark)."""
    for i in prange(P.shape[0]):
        tx, ty, tz = c[0] - P[i, 0], c[1] - P[i, 1], c[2] - P[i, 2]
        dc = max(np.sqrt(tx * tx + ty * ty + tz * tz), 1e-12)
        cos_c = (N[i, 0] * tx + N[i, 1] * ty + N[i, 2] * tz) / dc
        for k in range(cols.shape[0]):
            j = cols[k]
            st = 0
            if -(tx * U[j, 0] + ty * U[j, 1] + tz * U[j, 2]) / dc > 0 and cos_c > -radius / dc:
                wx, wy, wz = S[j, 0] - P[i, 0], S[j, 1] - P[i, 1], S[j, 2] - P[i, 2]
                dj = np.sqrt(wx * wx + wy * wy + wz * wz)
                wx, wy, wz = wx / dj, wy / dj, wz / dj
                cj = N[i, 0] * wx + N[i, 1] * wy + N[i, 2] * wz
                st = 2
                if cj > 0:
                    st = 1
                    o[i, k, 0] = P[i, 0] + eps * N[i, 0]
                    o[i, k, 1] = P[i, 1] + eps * N[i, 1]
                    o[i, k, 2] = P[i, 2] + eps * N[i, 2]
                    d[i, k, 0], d[i, k, 1], d[i, k, 2] = wx, wy, wz
                    t[i, k] = max(dj - 2 * eps, 0.0)
                    cos[i, k] = cj
            state[i, k] = st
