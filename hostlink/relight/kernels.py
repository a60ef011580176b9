"""numba kernels: BRDFs, per-vertex cut shading (Iwasaki et al. Eq. 3) and the brute-force sum.

Material rows (float64): ``[type, kd_r, kd_g, kd_b, ks_r, ks_g, ks_b, p]`` with type 0 Lambert,
1 Phong (p = exponent), 2 Blinn-Phong (p = exponent), 3 isotropic Ward (p = alpha). The SVC value
already holds the cosine, so the kernels multiply ``L_k V_k f_r(w_k, w_o)`` only.

References
----------
K. Iwasaki et al., Eq. (3) B(x, w_o) = sum_k L_k V_k f_r(w_k, w_o); Steps 1-4 (Fig. 6).
E. Lafortune, Y. Willems, "Using the modified Phong reflectance model", 1994 (normalised Phong).
G. Ward, "Measuring and modeling anisotropic reflection", SIGGRAPH 1992, Eq. 5 (isotropic).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["brdf_spec", "shade_dense", "shade_dynamic", "shade_static"]

_INV_PI = 1.0 / np.pi
_MAXC = 1 + 8 * 8


@njit(cache=True, fastmath=True, inline="always")
def brdf_spec(typ: int, p: float, n: np.ndarray, wx: float, wy: float, wz: float,
              ox: float, oy: float, oz: float) -> float:
    """Specular lobe (multiplies ks) of the material; 0 for Lambert."""
    if typ == 0:
        return 0.0
    ci = n[0] * wx + n[1] * wy + n[2] * wz
    if typ == 1:                                           # Phong: (p+2)/(2pi) (r.wo)^p
        rx = 2 * ci * n[0] - wx
        ry = 2 * ci * n[1] - wy
        rz = 2 * ci * n[2] - wz
        c = rx * ox + ry * oy + rz * oz
        return (p + 2) * 0.5 * _INV_PI * c ** p if c > 0 else 0.0
    hx = wx + ox
    hy = wy + oy
    hz = wz + oz
    hl = np.sqrt(hx * hx + hy * hy + hz * hz)
    if hl < 1e-12:
        return 0.0
    ch = (n[0] * hx + n[1] * hy + n[2] * hz) / hl
    if ch <= 0:
        return 0.0
    if typ == 2:                                           # Blinn-Phong: (p+8)/(8pi) (n.h)^p
        return (p + 8) * 0.125 * _INV_PI * ch ** p
    co = n[0] * ox + n[1] * oy + n[2] * oz                 # Ward (isotropic), Eq. 5
    if co <= 0 or ci <= 0:
        return 0.0
    t2 = (1 - ch * ch) / (ch * ch)                        # tan^2 of the half-vector angle
    return np.exp(-t2 / (p * p)) / (4 * np.pi * p * p * np.sqrt(max(ci, 1e-2) * max(co, 1e-2)))


@njit(cache=True, fastmath=True)
def _accumulate(mats: np.ndarray, m: int, n: np.ndarray, wo: np.ndarray, wx: float, wy: float,
                wz: float, lr: float, lg: float, lb: float, v: float, acc: np.ndarray) -> None:
    typ = int(mats[m, 0])
    s = brdf_spec(typ, mats[m, 7], n, wx, wy, wz, wo[0], wo[1], wo[2])
    acc[0] += lr * v * (mats[m, 1] * _INV_PI + mats[m, 4] * s)
    acc[1] += lg * v * (mats[m, 2] * _INV_PI + mats[m, 5] * s)
    acc[2] += lb * v * (mats[m, 3] * _INV_PI + mats[m, 6] * s)


@njit(cache=True, fastmath=True)
def _node_light(P: np.ndarray, Q: np.ndarray, M: np.ndarray, thr: np.ndarray, ndir: np.ndarray,
                n: np.ndarray, leaf: int, h: int, moment: bool, lw: np.ndarray) -> None:
    """Light of node (h, leaf): lw = (L_r, L_g, L_b, w_x, w_y, w_z).

    With ``moment``, a node entirely above the vertex's horizon gets the cosine-moment
    correction: L_c <- n . (sum_j L_cj w_j) / (n . mean_j w_j), so that L_k V_k with
    V_k = mean(V cos) equals sum_j L_j V cos_j exactly when V is constant over the node; the BRDF
    is then evaluated at the light centroid direction instead of the node centre.
    """
    e = leaf + (1 << h)
    node = (1 << (15 - h)) + (leaf >> h)
    lw[0] = P[e, 0] - P[leaf, 0]
    lw[1] = P[e, 1] - P[leaf, 1]
    lw[2] = P[e, 2] - P[leaf, 2]
    lw[3] = ndir[node, 0]
    lw[4] = ndir[node, 1]
    lw[5] = ndir[node, 2]
    if not moment or h == 0:
        return
    nm = n[0] * M[node, 0] + n[1] * M[node, 1] + n[2] * M[node, 2]
    if nm <= thr[node]:
        return
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for c in range(3):
        qx = Q[e, c, 0] - Q[leaf, c, 0]
        qy = Q[e, c, 1] - Q[leaf, c, 1]
        qz = Q[e, c, 2] - Q[leaf, c, 2]
        lw[c] = (n[0] * qx + n[1] * qy + n[2] * qz) / nm
        sx += qx
        sy += qy
        sz += qz
    sl = np.sqrt(sx * sx + sy * sy + sz * sz)
    if sl > 0:
        lw[3] = sx / sl
        lw[4] = sy / sl
        lw[5] = sz / sl


@njit(cache=True, parallel=True, fastmath=True)
def shade_static(vidx: np.ndarray, normals: np.ndarray, wo: np.ndarray, matid: np.ndarray,
                 mats: np.ndarray, offs: np.ndarray, hs: np.ndarray, vs: np.ndarray,
                 ndir: np.ndarray, P: np.ndarray, Q: np.ndarray, M: np.ndarray, thr: np.ndarray,
                 moment: bool, out: np.ndarray) -> None:
    """B = sum over SVC nodes of L_k V_k f_r (static scene: one cut per vertex)."""
    for t in prange(vidx.shape[0]):
        i = vidx[t]
        m = matid[i]
        lambert = mats[m, 0] == 0
        acc = np.zeros(3)
        lw = np.empty(6)
        n = normals[i]
        leaf = 0
        for q in range(offs[i], offs[i + 1]):
            h = hs[q]
            v = vs[q]
            if v != 0:                                    # Eq. 3: L_k V_k f_r(w_k, w_o)
                _node_light(P, Q, M, thr, ndir, n, leaf, h, moment, lw)
                if lambert:                               # f_r constant: sum L_k V_k only
                    acc[0] += lw[0] * v
                    acc[1] += lw[1] * v
                    acc[2] += lw[2] * v
                else:
                    _accumulate(mats, m, n, wo[t], lw[3], lw[4], lw[5], lw[0], lw[1], lw[2], v, acc)
            leaf += 1 << h
        if lambert:
            for c in range(3):
                acc[c] *= mats[m, 1 + c] * _INV_PI
        out[t, 0] = acc[0]
        out[t, 1] = acc[1]
        out[t, 2] = acc[2]


@njit(cache=True, fastmath=True)
def _vcf_lookup(x: np.ndarray, center: np.ndarray, radii: np.ndarray, grid: int,
                pts: np.ndarray, wts: np.ndarray) -> None:
    """8 neighbouring VCF sample points of x and their trilinear weights (radius x face s, t)."""
    lx = x[0] - center[0]
    ly = x[1] - center[1]
    lz = x[2] - center[2]
    d = np.sqrt(lx * lx + ly * ly + lz * lz)
    u = np.array([lx, ly, lz]) / max(d, 1e-12)
    a = 0
    if abs(u[1]) > abs(u[a]):
        a = 1
    if abs(u[2]) > abs(u[a]):
        a = 2
    f = 2 * a + (1 if u[a] < 0 else 0)
    s = u[(a + 1) % 3] / abs(u[a])
    tt = u[(a + 2) % 3] / abs(u[a])
    K = radii.shape[0]
    fr = 0.0 if K == 1 else (d - radii[0]) / (radii[K - 1] - radii[0]) * (K - 1)
    fr = min(max(fr, 0.0), K - 1.0)
    fx = min(max((s + 1) * 0.5 * grid - 0.5, 0.0), grid - 1.0)
    fy = min(max((tt + 1) * 0.5 * grid - 0.5, 0.0), grid - 1.0)
    k0 = int(fr)
    x0 = int(fx)
    y0 = int(fy)
    wr = fr - k0
    wx = fx - x0
    wy = fy - y0
    q = 0
    for dk in range(2):
        k = min(k0 + dk, K - 1)
        for dy in range(2):
            yy = min(y0 + dy, grid - 1)
            for dx in range(2):
                xx = min(x0 + dx, grid - 1)
                pts[q] = ((k * 6 + f) * grid + yy) * grid + xx
                wts[q] = (wr if dk else 1 - wr) * (wy if dy else 1 - wy) * (wx if dx else 1 - wx)
                q += 1


@njit(cache=True, fastmath=True)
def _collect_vcf(x: np.ndarray, n: np.ndarray, own: int, centers: np.ndarray, obj_r: np.ndarray,
                 radii: np.ndarray, grid: np.ndarray, pbase: np.ndarray, voffs: np.ndarray,
                 p: np.ndarray, en: np.ndarray, w: np.ndarray) -> int:
    """Append the 8 VCF cuts (and trilinear weights) of every movable object that can shadow x:
    not x's own object, x inside the outermost sphere, bounding sphere not under x's horizon."""
    pts = np.empty(8, np.int64)
    wts = np.empty(8)
    nc = 1
    for mm in range(centers.shape[0]):
        if mm == own or nc + 8 > _MAXC:
            continue
        dx = centers[mm, 0] - x[0]
        dy = centers[mm, 1] - x[1]
        dz = centers[mm, 2] - x[2]
        d = np.sqrt(dx * dx + dy * dy + dz * dz)
        if d >= radii[mm, radii.shape[1] - 1]:                 # beyond the last sphere
            continue
        if dx * n[0] + dy * n[1] + dz * n[2] < -obj_r[mm]:     # under the horizon plane
            continue
        _vcf_lookup(x, centers[mm], radii[mm], grid[mm], pts, wts)
        for q in range(8):
            pt = pbase[mm] + pts[q]
            p[nc] = voffs[pt]
            en[nc] = voffs[pt + 1]
            w[nc] = wts[q]
            nc += 1
    return nc


@njit(cache=True, parallel=True, fastmath=True)
def shade_dynamic(vidx: np.ndarray, pos: np.ndarray, normals: np.ndarray, wo: np.ndarray,
                  matid: np.ndarray, mats: np.ndarray, offs: np.ndarray, hs: np.ndarray,
                  vs: np.ndarray, ndir: np.ndarray, P: np.ndarray, Q: np.ndarray, M: np.ndarray,
                  thr: np.ndarray, moment: bool, own: np.ndarray,
                  centers: np.ndarray, obj_r: np.ndarray, radii: np.ndarray, grid: np.ndarray,
                  pbase: np.ndarray, voffs: np.ndarray, vh: np.ndarray, vv: np.ndarray,
                  out: np.ndarray, nodes: np.ndarray) -> None:
    """B = sum_k L_k V_k f_r with V = SVC x prod_objects(trilinear mix of 8 VCF cuts).

    Objects are culled per vertex when the vertex lies beyond the outermost VCF sphere or the
    object's bounding sphere is under the vertex's horizon plane. The SVC and all VCF cuts are
    traversed together with per-cut pointers and counters (Steps 1-4); an SVC node of value 0 is
    skipped whole (its leaf range contributes nothing).
    """
    for t in prange(vidx.shape[0]):
        i = vidx[t]
        x = pos[i]
        n = normals[i]
        p = np.empty(_MAXC, np.int64)
        en = np.empty(_MAXC, np.int64)
        c = np.zeros(_MAXC, np.int64)
        w = np.empty(_MAXC)
        p[0] = offs[i]
        en[0] = offs[i + 1]
        nc = _collect_vcf(x, n, own[i], centers, obj_r, radii, grid, pbase, voffs, p, en, w)
        ng = (nc - 1) // 8
        m = matid[i]
        lambert = mats[m, 0] == 0
        acc = np.zeros(3)
        lw = np.empty(6)
        leaf = 0
        cnt = 0
        while p[0] < en[0]:
            h0 = hs[p[0]]
            v0 = vs[p[0]]
            if v0 == 0 and c[0] == 0:                        # skip a dark SVC node whole
                target = leaf + (1 << h0)
                for j in range(1, nc):
                    start = leaf - c[j]
                    while p[j] < en[j] and start + (1 << vh[p[j]]) <= target:
                        start += 1 << vh[p[j]]
                        p[j] += 1
                    c[j] = target - start
                p[0] += 1
                leaf = target
                continue
            hmin = h0                                        # Step 2: operate at h_min
            for j in range(1, nc):
                if vh[p[j]] < hmin:
                    hmin = vh[p[j]]
            val = float(v0)
            for g in range(ng):
                s = 0.0
                for q in range(8):
                    j = 1 + 8 * g + q
                    s += w[j] * vv[p[j]]
                val *= s
            size = 1 << hmin
            if val > 0:
                cnt += 1
                _node_light(P, Q, M, thr, ndir, n, leaf, hmin, moment, lw)
                if lambert:
                    acc[0] += lw[0] * val
                    acc[1] += lw[1] * val
                    acc[2] += lw[2] * val
                else:
                    _accumulate(mats, m, n, wo[t], lw[3], lw[4], lw[5], lw[0], lw[1], lw[2], val, acc)
            for j in range(nc):                              # Step 3 (a) / (b)
                hj = hs[p[0]] if j == 0 else vh[p[j]]
                if hj == hmin:
                    p[j] += 1
                    c[j] = 0
                else:
                    c[j] += size
                    if c[j] >= (1 << hj):
                        p[j] += 1
                        c[j] = 0
            leaf += size
        if lambert:
            for ch in range(3):
                acc[ch] *= mats[m, 1 + ch] * _INV_PI
        out[t, 0] = acc[0]
        out[t, 1] = acc[1]
        out[t, 2] = acc[2]
        nodes[t] = cnt


@njit(cache=True, parallel=True, fastmath=True)
def shade_dense(vis_cos: np.ndarray, rows: np.ndarray, normals: np.ndarray, wo: np.ndarray,
                matid: np.ndarray, mats: np.ndarray, ldirs: np.ndarray, leafL: np.ndarray,
                out: np.ndarray) -> None:
    """Brute force: B = sum_j L_j V_j cos_j f_r(w_j, w_o) over all 2^15 directions.

    ``vis_cos`` (n, 2^15) holds V cos for the vertices ``rows``; ``leafL`` is (maps, 2^15, 3);
    ``out`` is (maps, n, 3).
    """
    for t in prange(vis_cos.shape[0]):
        i = rows[t]
        m = matid[i]
        n = normals[i]
        for mp in range(leafL.shape[0]):
            acc = np.zeros(3)
            for j in range(vis_cos.shape[1]):
                v = vis_cos[t, j]
                if v > 0:
                    _accumulate(mats, m, n, wo[t], ldirs[j, 0], ldirs[j, 1], ldirs[j, 2],
                                leafL[mp, j, 0], leafL[mp, j, 1], leafL[mp, j, 2], v, acc)
            out[mp, t, 0] = acc[0]
            out[mp, t, 1] = acc[1]
            out[mp, t, 2] = acc[2]
