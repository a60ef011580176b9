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

from lightprobe.hostlink.relight.cuts.coding import advance_counters, min_height

__all__ = ["brdf_spec", "shade_dense", "shade_dynamic", "shade_static"]

_INV_PI = 1.0 / np.pi
_MAXC = 1 + 8 * 8


@njit(cache=True, fastmath=True, inline="always")
def _pow(c: float, p: float) -> float:
    """c^p for c > 0: repeated squaring when p is a small whole number (Phong / Blinn-Phong
    exponents usually are), else the library pow."""
    if p == np.floor(p) and 0 <= p < 4096:
        e = int(p)
        r = 1.0
        x = c
        while e > 0:
            if e & 1:
                r *= x
            x *= x
            e >>= 1
        return r
    return c ** p


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
        return (p + 2) * 0.5 * _INV_PI * _pow(c, p) if c > 0 else 0.0
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
        return (p + 8) * 0.125 * _INV_PI * _pow(ch, p)
    co = n[0] * ox + n[1] * oy + n[2] * oz                 # Ward (isotropic), Eq. 5
    if co <= 0 or ci <= 0:
        return 0.0
    t2 = (1 - ch * ch) / (ch * ch)                        # tan^2 of the half-vector angle
    return np.exp(-t2 / (p * p)) / (4 * np.pi * p * p * np.sqrt(max(ci, 1e-2) * max(co, 1e-2)))


@njit(cache=True, fastmath=True, inline="always")
def _brdf(mats: np.ndarray, m: int, n: np.ndarray, wo: np.ndarray, wx: float, wy: float,
          wz: float) -> tuple[float, float, float]:
    """f_r(w, w_o) per channel: kd / pi + ks * specular lobe."""
    s = brdf_spec(int(mats[m, 0]), mats[m, 7], n, wx, wy, wz, wo[0], wo[1], wo[2])
    return (mats[m, 1] * _INV_PI + mats[m, 4] * s, mats[m, 2] * _INV_PI + mats[m, 5] * s,
            mats[m, 3] * _INV_PI + mats[m, 6] * s)


@njit(cache=True, fastmath=True, inline="always")
def _finish(mats: np.ndarray, m: int, lambert: bool, ar: float, ag: float,
            ab: float) -> tuple[float, float, float]:
    """Lambert sums were accumulated without f_r: multiply by kd / pi once."""
    if lambert:
        return ar * mats[m, 1] * _INV_PI, ag * mats[m, 2] * _INV_PI, ab * mats[m, 3] * _INV_PI
    return ar, ag, ab


@njit(cache=True, fastmath=True, inline="always")
def _node_light(P: np.ndarray, Q: np.ndarray, M: np.ndarray, thr: np.ndarray, ndir: np.ndarray,
                nx: float, ny: float, nz: float, leaf: int, h: int, moment: bool,
                need_dir: bool) -> tuple[float, float, float, float, float, float]:
    """Light of node (h, leaf) -> (L_r, L_g, L_b, w_x, w_y, w_z).

    With ``moment``, a node entirely above the vertex's horizon gets the cosine-moment
    correction: L_c <- n . (sum_j L_cj w_j) / (n . mean_j w_j), so that L_k V_k with
    V_k = mean(V cos) equals sum_j L_j V cos_j exactly when V is constant over the node; the BRDF
    is then evaluated at the light centroid direction (``need_dir``) instead of the node centre.
    ``Q`` is (2^15 + 1, 9): prefix sums of L_c w_a at column 3 c + a.
    """
    e = leaf + (1 << h)
    node = (1 << (15 - h)) + (leaf >> h)
    lr = P[e, 0] - P[leaf, 0]
    lg = P[e, 1] - P[leaf, 1]
    lb = P[e, 2] - P[leaf, 2]
    wx = wy = wz = 0.0
    if need_dir:
        wx = ndir[node, 0]
        wy = ndir[node, 1]
        wz = ndir[node, 2]
    if not moment or h == 0:
        return lr, lg, lb, wx, wy, wz
    nm = nx * M[node, 0] + ny * M[node, 1] + nz * M[node, 2]
    if nm <= thr[node]:
        return lr, lg, lb, wx, wy, wz
    inv = 1.0 / nm
    q0 = Q[e, 0] - Q[leaf, 0]
    q1 = Q[e, 1] - Q[leaf, 1]
    q2 = Q[e, 2] - Q[leaf, 2]
    q3 = Q[e, 3] - Q[leaf, 3]
    q4 = Q[e, 4] - Q[leaf, 4]
    q5 = Q[e, 5] - Q[leaf, 5]
    q6 = Q[e, 6] - Q[leaf, 6]
    q7 = Q[e, 7] - Q[leaf, 7]
    q8 = Q[e, 8] - Q[leaf, 8]
    lr = (nx * q0 + ny * q1 + nz * q2) * inv
    lg = (nx * q3 + ny * q4 + nz * q5) * inv
    lb = (nx * q6 + ny * q7 + nz * q8) * inv
    if need_dir:
        d0 = q0 + q3 + q6
        d1 = q1 + q4 + q7
        d2 = q2 + q5 + q8
        sl = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if sl > 0:
            wx = d0 / sl
            wy = d1 / sl
            wz = d2 / sl
    return lr, lg, lb, wx, wy, wz


@njit(cache=True, parallel=True)
def svc_weights(normals: np.ndarray, offs: np.ndarray, hs: np.ndarray, vs: np.ndarray,
                M: np.ndarray, thr: np.ndarray, moment: bool, out: np.ndarray) -> None:
    """Light-independent per-node factors (float32) for :func:`shade_static`: ``v / (n . M_k)``
    (> 0) for nodes that take the cosine-moment correction (entirely above the horizon, height
    > 0), ``-v`` (<= 0) for the others; 0 for dark nodes. The cosine is folded in here once, so a
    Lambertian vertex needs no per-node BRDF or cosine evaluation at render time."""
    for i in prange(offs.shape[0] - 1):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        leaf = 0
        for q in range(offs[i], offs[i + 1]):
            h = hs[q]
            v = vs[q]
            node = (1 << (15 - h)) + (leaf >> h)
            nm = nx * M[node, 0] + ny * M[node, 1] + nz * M[node, 2]
            if v != 0 and moment and h > 0 and nm > thr[node]:
                out[q] = v / nm
            else:
                out[q] = -v
            leaf += 1 << h


@njit(cache=True, fastmath=True)
def _static_diffuse(o0: int, o1: int, hs: np.ndarray, sw: np.ndarray, T: np.ndarray, nx: float,
                    ny: float, nz: float) -> tuple[float, float, float]:
    """sum_k L_k V_k over one SVC (no BRDF): 3 FMAs per plain node, 9 per corrected node."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = 0.0
    pr = pg = pb = 0.0
    leaf = 0
    for q in range(o0, o1):
        h = hs[q]
        node = 2 * leaf + (1 << h) - 1                     # in-order row: increasing along the cut
        leaf += 1 << h
        w = sw[q]
        b = max(w, 0.0)                                    # cosine-moment corrected node: sw > 0
        a = max(-w, 0.0)                                   # plain node: sw < 0 (branch-free)
        s0 += b * T[node, 3]
        s1 += b * T[node, 4]
        s2 += b * T[node, 5]
        s3 += b * T[node, 6]
        s4 += b * T[node, 7]
        s5 += b * T[node, 8]
        s6 += b * T[node, 9]
        s7 += b * T[node, 10]
        s8 += b * T[node, 11]
        pr += a * T[node, 0]
        pg += a * T[node, 1]
        pb += a * T[node, 2]
    return (pr + nx * s0 + ny * s1 + nz * s2, pg + nx * s3 + ny * s4 + nz * s5,
            pb + nx * s6 + ny * s7 + nz * s8)


@njit(cache=True, fastmath=True)
def _static_specular(o0: int, o1: int, hs: np.ndarray, sw: np.ndarray, T: np.ndarray,
                     typ: int, p: float, n: np.ndarray, ox: float, oy: float,
                     oz: float) -> tuple[float, float, float]:
    """sum_k L_k V_k f_s(w_k, w_o): the specular lobe once per node, at its light centroid."""
    nx, ny, nz = n[0], n[1], n[2]
    sr = sg = sb = 0.0
    leaf = 0
    for q in range(o0, o1):
        h = hs[q]
        node = 2 * leaf + (1 << h) - 1
        leaf += 1 << h
        w = sw[q]
        if w == 0:
            continue
        if w > 0:
            lr = w * (nx * T[node, 3] + ny * T[node, 4] + nz * T[node, 5])
            lg = w * (nx * T[node, 6] + ny * T[node, 7] + nz * T[node, 8])
            lb = w * (nx * T[node, 9] + ny * T[node, 10] + nz * T[node, 11])
        else:
            lr, lg, lb = -w * T[node, 0], -w * T[node, 1], -w * T[node, 2]
        if lr == 0 and lg == 0 and lb == 0:
            continue
        f = brdf_spec(typ, p, n, T[node, 12], T[node, 13], T[node, 14], ox, oy, oz)
        sr += lr * f
        sg += lg * f
        sb += lb * f
    return sr, sg, sb


@njit(cache=True, parallel=True, fastmath=True)
def shade_static(vidx: np.ndarray, normals: np.ndarray, wo: np.ndarray, matid: np.ndarray,
                 mats: np.ndarray, offs: np.ndarray, hs: np.ndarray, sw: np.ndarray,
                 T: np.ndarray, out: np.ndarray) -> None:
    """B = sum over SVC nodes of L_k V_k f_r(w_k, w_o) (Iwasaki et al. Eq. 3, one cut per vertex).

    ``sw`` from :func:`svc_weights` (cosine folded in), ``T`` the per-node light table in
    in-order layout (:func:`lightprobe.hostlink.relight.cuts.lighting.node_table`). Diffuse part: plain nodes
    accumulate ``-sw L_k`` (3 sums), moment-corrected ones ``sw (L_c w)_k`` (9 sums, dotted with
    n once per vertex), times kd / pi once; the specular lobe (materials with ks != 0 only) is
    evaluated once per node, at the node's light centroid.
    """
    for t in prange(vidx.shape[0]):
        i = vidx[t]
        m = matid[i]
        typ = int(mats[m, 0])
        n = normals[i]
        dr, dg, db = _static_diffuse(offs[i], offs[i + 1], hs, sw, T, n[0], n[1], n[2])
        sr = sg = sb = 0.0
        if typ != 0 and (mats[m, 4] != 0 or mats[m, 5] != 0 or mats[m, 6] != 0):
            sr, sg, sb = _static_specular(offs[i], offs[i + 1], hs, sw, T, typ, mats[m, 7], n,
                                          wo[t, 0], wo[t, 1], wo[t, 2])
        out[t, 0] = mats[m, 1] * _INV_PI * dr + mats[m, 4] * sr
        out[t, 1] = mats[m, 2] * _INV_PI * dg + mats[m, 5] * sg
        out[t, 2] = mats[m, 3] * _INV_PI * db + mats[m, 6] * sb


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


@njit(cache=True, fastmath=True)
def _interp8(vh: np.ndarray, vv: np.ndarray, p0: np.ndarray, en: np.ndarray, w: np.ndarray,
             base: int, out_h: np.ndarray, out_v: np.ndarray, o: int) -> int:
    """Trilinear mix of the 8 VCF cuts p0[base:base+8] into one cut (Steps 1-4, interpolation),
    written at out[o:]; returns the new end."""
    p = p0[base:base + 8].copy()
    c = np.zeros(8, np.int64)
    while p[0] < en[base]:
        hmin = min_height(vh, p, 8)
        s = 0.0
        for j in range(8):
            s += w[base + j] * vv[p[j]]
        out_h[o] = hmin
        out_v[o] = s
        o += 1
        advance_counters(vh, p, c, 8, hmin)
    return o


@njit(cache=True, parallel=True, fastmath=True)
def shade_dynamic(vidx: np.ndarray, pos: np.ndarray, normals: np.ndarray, wo: np.ndarray,
                  matid: np.ndarray, mats: np.ndarray, offs: np.ndarray, hs: np.ndarray,
                  vs: np.ndarray, ndir: np.ndarray, P: np.ndarray, Q: np.ndarray, M: np.ndarray,
                  thr: np.ndarray, moment: bool, own: np.ndarray,
                  centers: np.ndarray, obj_r: np.ndarray, radii: np.ndarray, grid: np.ndarray,
                  pbase: np.ndarray, voffs: np.ndarray, vh: np.ndarray, vv: np.ndarray,
                  out: np.ndarray, nodes: np.ndarray) -> None:
    """B = sum_k L_k V_k f_r with V = SVC x prod_objects(trilinear mix of 8 VCF cuts).

    Per vertex: cull objects (beyond the outermost VCF sphere, or bounding sphere under the
    horizon plane); interpolate each remaining object's 8 neighbouring VCF cuts into one cut;
    then traverse the SVC and the interpolated cuts together with per-cut pointers and counters
    (Steps 1-4). An SVC node of value 0 is skipped whole (its leaf range contributes nothing).
    """
    for t in prange(vidx.shape[0]):
        i = vidx[t]
        x = pos[i]
        n = normals[i]
        p8 = np.empty(_MAXC, np.int64)
        en8 = np.empty(_MAXC, np.int64)
        w = np.empty(_MAXC)
        nc8 = _collect_vcf(x, n, own[i], centers, obj_r, radii, grid, pbase, voffs, p8, en8, w)
        ng = (nc8 - 1) // 8
        total = 0
        for j in range(1, nc8):
            total += en8[j] - p8[j]
        ih = np.empty(max(total, 1), np.uint8)
        iv = np.empty(max(total, 1))
        p = np.empty(ng + 1, np.int64)
        en = np.empty(ng + 1, np.int64)
        c = np.zeros(ng + 1, np.int64)
        o = 0
        for g in range(ng):                                  # interpolation of 8 cuts per object
            p[g + 1] = o
            o = _interp8(vh, vv, p8, en8, w, 1 + 8 * g, ih, iv, o)
            en[g + 1] = o
        p[0] = offs[i]
        en[0] = offs[i + 1]
        m = matid[i]
        lambert = mats[m, 0] == 0
        nx, ny, nz = n[0], n[1], n[2]
        ar = ag = ab = 0.0
        leaf = 0
        cnt = 0
        while p[0] < en[0]:
            h0 = hs[p[0]]
            v0 = vs[p[0]]
            if v0 == 0 and c[0] == 0:                        # skip a dark SVC node whole
                target = leaf + (1 << h0)
                for j in range(1, ng + 1):
                    start = leaf - c[j]
                    while p[j] < en[j] and start + (1 << ih[p[j]]) <= target:
                        start += 1 << ih[p[j]]
                        p[j] += 1
                    c[j] = target - start
                p[0] += 1
                leaf = target
                continue
            hmin = h0                                        # Step 2: product at h_min
            val = float(v0)
            for j in range(1, ng + 1):
                if ih[p[j]] < hmin:
                    hmin = ih[p[j]]
                val *= iv[p[j]]
            size = 1 << hmin
            if val > 0:
                cnt += 1
                lr, lg, lb, wx, wy, wz = _node_light(P, Q, M, thr, ndir, nx, ny, nz, leaf, hmin,
                                                     moment, not lambert)
                if lambert:
                    ar += lr * val
                    ag += lg * val
                    ab += lb * val
                else:
                    fr, fg, fb = _brdf(mats, m, n, wo[t], wx, wy, wz)
                    ar += lr * val * fr
                    ag += lg * val * fg
                    ab += lb * val * fb
            for j in range(ng + 1):                          # Step 3 (a) / (b)
                hj = hs[p[0]] if j == 0 else ih[p[j]]
                if hj == hmin:
                    p[j] += 1
                    c[j] = 0
                else:
                    c[j] += size
                    if c[j] >= (1 << hj):
                        p[j] += 1
                        c[j] = 0
            leaf += size
        acc = _finish(mats, m, lambert, ar, ag, ab)
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
                    fr, fg, fb = _brdf(mats, m, n, wo[t], ldirs[j, 0], ldirs[j, 1], ldirs[j, 2])
                    acc[0] += leafL[mp, j, 0] * v * fr
                    acc[1] += leafL[mp, j, 1] * v * fg
                    acc[2] += leafL[mp, j, 2] * v * fb
            out[mp, t, 0] = acc[0]
            out[mp, t, 1] = acc[1]
            out[mp, t, 2] = acc[2]
