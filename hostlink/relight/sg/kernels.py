"""numba kernels of the SG relighting (:mod:`lightprobe.hostlink.relight.sg.relighter`): direction-table lookups,
per-point shading from SG tables and peaks, voxelisation and voxel cone tracing.

Conventions. Direction tables are (6, N, N, 3) cube maps: face ``f`` on axis ``f // 2`` (+ for even
``f``), texel ``[i, j]`` at ``(u_j, v_i) = (-1 + (2 j + 1) / N, ...)`` on the next two axes
(``(a + 1) % 3``, ``(a + 2) % 3``), looked up bilinearly within the face (clamped at its edges): no trigonometry per lookup. Zonal tables are (K,) samples of a function of ``t = a . p`` on
``t_k = -1 + 2 k / (K - 1)``, looked up linearly.

A voxel pyramid is one flat float32 array: level ``l`` holds ``(R >> l)^3`` occupancies (x
fastest, z slowest: index ``(z * r + y) * r + x``) from ``offsets[l]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["cone_frame", "interpolate", "rect_clear", "residual_visibility", "scatter_pixels", "shade_points", "trace_cones", "voxelize"]


@njit(cache=True, fastmath=True, inline="always")
def _dir_lookup3(tab: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Bilinear lookup of the three channels of a (6, N, N, 3) cube-map table at unit
    ``(x, y, z)`` (no trigonometry: the major axis picks the face)."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        f = 0 if x > 0 else 1
        m, pu, pv = ax, y, z
    elif ay >= az:
        f = 2 if y > 0 else 3
        m, pu, pv = ay, z, x
    else:
        f = 4 if z > 0 else 5
        m, pu, pv = az, x, y
    N = tab.shape[1]
    fj = min(max((pu / m + 1) * 0.5 * N - 0.5, 0.0), N - 1.0)
    fi = min(max((pv / m + 1) * 0.5 * N - 0.5, 0.0), N - 1.0)
    j0 = min(int(fj), N - 2)
    i0 = min(int(fi), N - 2)
    wj = fj - j0
    wi = fi - i0
    a = (1 - wi) * (1 - wj)
    b = (1 - wi) * wj
    c = wi * (1 - wj)
    d = wi * wj
    return (a * tab[f, i0, j0, 0] + b * tab[f, i0, j0 + 1, 0] + c * tab[f, i0 + 1, j0, 0] + d * tab[f, i0 + 1, j0 + 1, 0],
            a * tab[f, i0, j0, 1] + b * tab[f, i0, j0 + 1, 1] + c * tab[f, i0 + 1, j0, 1] + d * tab[f, i0 + 1, j0 + 1, 1],
            a * tab[f, i0, j0, 2] + b * tab[f, i0, j0 + 1, 2] + c * tab[f, i0 + 1, j0, 2] + d * tab[f, i0 + 1, j0 + 1, 2])


@njit(cache=True, fastmath=True, inline="always")
def _zonal(tab: np.ndarray, t: float) -> float:
    K = tab.shape[0]
    f = (min(1.0, max(-1.0, t)) + 1.0) * 0.5 * (K - 1)
    k = min(int(f), K - 2)
    w = f - k
    return (1 - w) * tab[k] + w * tab[k + 1]


@njit(cache=True, fastmath=True, inline="always")
def _onb(nx: float, ny: float, nz: float) -> tuple[float, float, float, float, float, float]:
    """Tangent and bitangent of a unit normal (Duff et al. 2017, branchless)."""
    s = 1.0 if nz >= 0 else -1.0
    a = -1.0 / (s + nz)
    b = nx * ny * a
    return 1 + s * nx * nx * a, s * b, -s * nx, b, s + ny * ny * a, -ny


@njit(cache=True, fastmath=True)
def cone_frame(n: np.ndarray, local: np.ndarray, out: np.ndarray) -> None:
    """The diffuse cone axes of each normal: ``out[i, k] = local[k, 0] t + local[k, 1] b +
    local[k, 2] n`` in the normal's frame (:func:`_onb`). ``out`` is (N, K, 3), ``local`` (K, 3)."""
    for i in range(n.shape[0]):
        nx, ny, nz = n[i, 0], n[i, 1], n[i, 2]
        tx, ty, tz, bx, by, bz = _onb(nx, ny, nz)
        for k in range(local.shape[0]):
            u, v, w = local[k, 0], local[k, 1], local[k, 2]
            out[i, k, 0] = u * tx + v * bx + w * nx
            out[i, k, 1] = u * ty + v * by + w * ny
            out[i, k, 2] = u * tz + v * bz + w * nz


@njit(cache=True, fastmath=True, parallel=True)
def interpolate(bary: np.ndarray, fv: np.ndarray, at: np.ndarray, out: np.ndarray) -> None:
    """``out[p] = sum_k bary[p, k] at[fv[p, k]]``: per-vertex values (V, C) at pixels (P, C)."""
    for p in prange(bary.shape[0]):
        a, b, c = fv[p, 0], fv[p, 1], fv[p, 2]
        u, v, w = bary[p, 0], bary[p, 1], bary[p, 2]
        for k in range(at.shape[1]):
            out[p, k] = u * at[a, k] + v * at[b, k] + w * at[c, k]


@njit(cache=True, parallel=True)
def scatter_pixels(idx: np.ndarray, rad: np.ndarray, img: np.ndarray) -> None:
    """``img[idx[p]] = rad[p]`` (img flat (H W, 3) float32)."""
    for p in prange(idx.shape[0]):
        q = idx[p]
        img[q, 0] = rad[p, 0]
        img[q, 1] = rad[p, 1]
        img[q, 2] = rad[p, 2]


@njit(cache=True, fastmath=True, parallel=True)
def residual_visibility(cones: np.ndarray, vis: np.ndarray, tabW: np.ndarray, out: np.ndarray) -> None:
    """``V_res`` per point and channel (N, 3): the cones' transmittances ``vis`` (N, K) along
    ``cones`` (N, K, 3, cosine-distributed about the normal) weighted by the residual light each
    carries, ``tabW`` (6, D, D, 3): the lighting filtered by one cone's visibility SG, looked up at
    the cone's axis. A point whose cones carry no light gets the cones' mean."""
    K = cones.shape[1]
    for i in prange(cones.shape[0]):
        v0 = v1 = v2 = 0.0
        s0 = s1 = s2 = 0.0
        mean = 0.0
        for c in range(K):
            w0, w1, w2 = _dir_lookup3(tabW, cones[i, c, 0], cones[i, c, 1], cones[i, c, 2])
            w0, w1, w2 = max(w0, 0.0), max(w1, 0.0), max(w2, 0.0)
            vc = vis[i, c]
            v0 += w0 * vc
            v1 += w1 * vc
            v2 += w2 * vc
            s0 += w0
            s1 += w1
            s2 += w2
            mean += vc / K
        out[i, 0] = v0 / s0 if s0 > 1e-30 else mean
        out[i, 1] = v1 / s1 if s1 > 1e-30 else mean
        out[i, 2] = v2 / s2 if s2 > 1e-30 else mean


@njit(cache=True, fastmath=True, parallel=True)
def rect_clear(pos: np.ndarray, dirs: np.ndarray, tan_half: np.ndarray, side: np.ndarray, rects: np.ndarray,
               rect_obj: np.ndarray, owner: np.ndarray, g: np.ndarray, cphi: np.ndarray, sphi: np.ndarray,
               used: np.ndarray, out: np.ndarray) -> None:
    """Multiply ``out[i, k]`` by the fraction of cone ``k``'s rays from ``pos[i]`` (axis
    ``dirs[i, k]``, ``tan(half angle) = tan_half[i, k]``; the rays uniform over the cap: cosines
    ``1 - g (1 - cos alpha)``, azimuths with cosines ``cphi`` and sines ``sphi``) that meet none of
    the rectangles ``rects`` (Q, 17): plane normal and offset (``n . x = c``), corner origin, two
    in-plane unit axes, extents ``[a0, a1] x [b0, b1]`` along them; ``side[i, q] = n . pos[i] -
    c``. Rectangle ``q`` is no occluder for points on object ``rect_obj[q]`` (``owner``); a cone
    wholly on the far side of every rectangle's plane, or not ``used``, is not tested."""
    m = g.shape[0]
    for i in prange(pos.shape[0]):
        px, py, pz = pos[i, 0], pos[i, 1], pos[i, 2]
        for k in range(dirs.shape[1]):
            if not used[i, k] or out[i, k] <= 0.0:
                continue
            ax, ay, az = dirs[i, k, 0], dirs[i, k, 1], dirs[i, k, 2]
            ca = 1.0 / math.sqrt(1.0 + tan_half[i, k] * tan_half[i, k])
            sa = math.sqrt(max(1.0 - ca * ca, 0.0))
            near = False
            for q in range(rects.shape[0]):
                if rect_obj[q] == owner[i] or side[i, q] == 0.0:
                    continue
                toward = -(rects[q, 0] * ax + rects[q, 1] * ay + rects[q, 2] * az) * (1.0 if side[i, q] > 0 else -1.0)
                if toward > -sa:
                    near = True
                    break
            if not near:
                continue
            tx, ty, tz, bx, by, bz = _onb(ax, ay, az)
            free = 0
            for r in range(m):
                ct = 1.0 - g[r] * (1.0 - ca)
                st = math.sqrt(max(1.0 - ct * ct, 0.0))
                dx = ct * ax + st * (cphi[r] * tx + sphi[r] * bx)
                dy = ct * ay + st * (cphi[r] * ty + sphi[r] * by)
                dz = ct * az + st * (cphi[r] * tz + sphi[r] * bz)
                hit = False
                for q in range(rects.shape[0]):
                    if rect_obj[q] == owner[i]:
                        continue
                    dn = rects[q, 0] * dx + rects[q, 1] * dy + rects[q, 2] * dz
                    if dn == 0.0:
                        continue
                    t = -side[i, q] / dn
                    if t <= 0.0:
                        continue
                    hx = px + t * dx - rects[q, 4]
                    hy = py + t * dy - rects[q, 5]
                    hz = pz + t * dz - rects[q, 6]
                    u = hx * rects[q, 7] + hy * rects[q, 8] + hz * rects[q, 9]
                    v = hx * rects[q, 10] + hy * rects[q, 11] + hz * rects[q, 12]
                    if rects[q, 13] <= u <= rects[q, 14] and rects[q, 15] <= v <= rects[q, 16]:
                        hit = True
                        break
                if not hit:
                    free += 1
            out[i, k] *= free / m


@njit(cache=True, fastmath=True, parallel=True)
def shade_points(nrm: np.ndarray, wo: np.ndarray, matid: np.ndarray, mats: np.ndarray,
                 gloss_slot: np.ndarray, tabE: np.ndarray, tabG: np.ndarray,
                 paxis: np.ndarray, plam: np.ndarray, pamp: np.ndarray, pF: np.ndarray,
                 vres: np.ndarray, vspec: np.ndarray, vpeak: np.ndarray, out: np.ndarray) -> None:
    """Outgoing radiance per point (see :mod:`lightprobe.hostlink.relight.sg.relighter` for the model).

    ``tabE``: exact clamped-cosine irradiance of the residual lobes per normal; ``tabG[s]``: the
    residual convolved with the Phong lobe of gloss slot ``s``; peaks: axes, sharpness,
    amplitudes and ``pF[p]`` (zonal clamped-cosine table of lobe p). Visibility: ``vres`` (N, 3)
    the residual's (:func:`residual_visibility`), ``vspec`` (N,) the reflection cone's, ``vpeak``
    (N, P) each peak's."""
    P = paxis.shape[0]
    for i in prange(nrm.shape[0]):   # scalars only in the loop body: no per-point allocation
        nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        m = matid[i]
        typ = int(mats[m, 0])
        e0, e1, e2 = _dir_lookup3(tabE, nx, ny, nz)  # may be < 0: the residual about a peak
        d0 = e0 * vres[i, 0]
        d1 = e1 * vres[i, 1]
        d2 = e2 * vres[i, 2]
        for p in range(P):
            f = _zonal(pF[p], nx * paxis[p, 0] + ny * paxis[p, 1] + nz * paxis[p, 2]) * vpeak[i, p]
            d0 += pamp[p, 0] * f
            d1 += pamp[p, 1] * f
            d2 += pamp[p, 2] * f
        out[i, 0] = mats[m, 1] / math.pi * max(d0, 0.0)
        out[i, 1] = mats[m, 2] / math.pi * max(d1, 0.0)
        out[i, 2] = mats[m, 3] / math.pi * max(d2, 0.0)
        if typ != 1:
            continue
        # Phong: ks (e + 2) / (2 pi) cos^e(r_o . w) ~ an SG of sharpness e about the reflection
        e = mats[m, 7]
        cn = nx * wo[i, 0] + ny * wo[i, 1] + nz * wo[i, 2]
        ox = 2 * cn * nx - wo[i, 0]
        oy = 2 * cn * ny - wo[i, 1]
        oz = 2 * cn * nz - wo[i, 2]
        cr = max(nx * ox + ny * oy + nz * oz, 0.0) * vspec[i]
        g0, g1, g2 = _dir_lookup3(tabG[gloss_slot[m]], ox, oy, oz)
        g0, g1, g2 = cr * g0, cr * g1, cr * g2
        for p in range(P):
            lp = plam[p]
            qx = e * ox + lp * paxis[p, 0]
            qy = e * oy + lp * paxis[p, 1]
            qz = e * oz + lp * paxis[p, 2]
            ql = math.sqrt(qx * qx + qy * qy + qz * qz)
            if ql < 1e-9:
                continue
            dp = 2 * math.pi * (math.exp(ql - e - lp) - math.exp(-ql - e - lp)) / ql
            f = dp * max((nx * qx + ny * qy + nz * qz) / ql, 0.0) * vpeak[i, p]
            g0 += pamp[p, 0] * f
            g1 += pamp[p, 1] * f
            g2 += pamp[p, 2] * f
        norm = (e + 2) * 0.5 / math.pi
        out[i, 0] += mats[m, 4] * norm * max(g0, 0.0)
        out[i, 1] += mats[m, 5] * norm * max(g1, 0.0)
        out[i, 2] += mats[m, 6] * norm * max(g2, 0.0)


# ---- voxels ------------------------------------------------------------------------------------
@njit(cache=True)
def voxelize(v: np.ndarray, faces: np.ndarray, origin: np.ndarray, vox: float, R: int,
             occ: np.ndarray) -> None:
    """Mark in ``occ`` (R^3 uint8, index (z R + y) R + x) every voxel a triangle passes through:
    each triangle sampled on a barycentric grid finer than half a voxel."""
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        e = 0.0
        for k in range(3):
            e = max(e, abs(v[b, k] - v[a, k]), abs(v[c, k] - v[a, k]), abs(v[c, k] - v[b, k]))
        n = int(np.ceil(e / (0.5 * vox))) + 1
        for i in range(n + 1):
            for j in range(n + 1 - i):
                u = i / n
                w = j / n
                s = 1.0 - u - w
                ix = int(np.floor((s * v[a, 0] + u * v[b, 0] + w * v[c, 0] - origin[0]) / vox))
                iy = int(np.floor((s * v[a, 1] + u * v[b, 1] + w * v[c, 1] - origin[1]) / vox))
                iz = int(np.floor((s * v[a, 2] + u * v[b, 2] + w * v[c, 2] - origin[2]) / vox))
                if 0 <= ix < R and 0 <= iy < R and 0 <= iz < R:
                    occ[(iz * R + iy) * R + ix] = 1


@njit(cache=True, fastmath=True, inline="always")
def _sample(pyr: np.ndarray, offs: np.ndarray, R: int, lvl: int, px: float, py: float, pz: float) -> float:
    """Trilinear occupancy at level ``lvl`` at a point given in level-0 voxel units."""
    r = R >> lvl
    s = 1.0 / (1 << lvl)
    fx = px * s - 0.5
    fy = py * s - 0.5
    fz = pz * s - 0.5
    x0 = int(np.floor(fx))
    y0 = int(np.floor(fy))
    z0 = int(np.floor(fz))
    wx = fx - x0
    wy = fy - y0
    wz = fz - z0
    o = offs[lvl]
    acc = 0.0
    for dz in range(2):
        z = z0 + dz
        if z < 0 or z >= r:
            continue
        cz = wz if dz else 1 - wz
        for dy in range(2):
            y = y0 + dy
            if y < 0 or y >= r:
                continue
            cy = wy if dy else 1 - wy
            for dx in range(2):
                x = x0 + dx
                if x < 0 or x >= r:
                    continue
                cx = wx if dx else 1 - wx
                acc += cx * cy * cz * pyr[o + (z * r + y) * r + x]
    return acc


@njit(cache=True, fastmath=True, parallel=True)
def trace_cones(orig: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan_half: np.ndarray,
                pyr: np.ndarray, offs: np.ndarray, R: int, origin: np.ndarray, vox: float,
                start: float, lift: float, gain: float, footprint: float, need: np.ndarray,
                out: np.ndarray) -> None:
    """Transmittance of cones (voxel cone tracing, Crassin et al. 2011; ``pyr`` (3, total): the
    per-axis pyramids of :func:`lightprobe.hostlink.relight.sg.relighter.anisotropic_pyramid`): for point ``i`` and cone
    ``k`` along ``dirs[i, k]`` with ``tan(half angle) = tan_half[i, k]``, from ``orig[i]`` lifted
    by ``lift`` voxels along ``nrm[i]``, starting ``start`` voxels out. Each step samples the
    pyramid at the level whose cell is ``footprint`` x the cone's diameter (a cell as wide as the
    cone reaches back to the surface it starts from) and composites ``1 - (1 - occ)^(gain step / cell)``, skipping empty space by the level-3 cells front to back. Starts where the axis enters the grid (grown by R / 4 each side: a point may lie outside it), stops at 99% opacity or where the sampled level can read nothing more. Cones with ``need[i, k]`` false are clear (1) untraced."""
    nl = offs.shape[0] - 1
    for i in prange(orig.shape[0]):
        ox = (orig[i, 0] - origin[0]) / vox + lift * nrm[i, 0]
        oy = (orig[i, 1] - origin[1]) / vox + lift * nrm[i, 1]
        oz = (orig[i, 2] - origin[2]) / vox + lift * nrm[i, 2]
        for k in range(dirs.shape[1]):
            if not need[i, k]:   # no object within the cone (the caller's bounding test): clear
                out[i, k] = 1.0
                continue
            dx, dy, dz = dirs[i, k, 0], dirs[i, k, 1], dirs[i, k, 2]
            th = tan_half[i, k]
            # the axis's span within the grid grown by a quarter of it each side (a point may lie
            # outside the grid: the grid holds the voxelised objects only; a coarse cell near the
            # edge still reads the edge's cells)
            t0, t1 = start, 1e30
            for o_, d_ in ((ox, dx), (oy, dy), (oz, dz)):
                if abs(d_) < 1e-12:
                    if o_ < -0.25 * R or o_ > 1.25 * R:
                        t1 = -1.0
                else:
                    ta = (-0.25 * R - o_) / d_
                    tb = (1.25 * R - o_) / d_
                    t0 = max(t0, min(ta, tb))
                    t1 = min(t1, max(ta, tb))
            t = t0
            a = 0.0
            while a < 0.99 and t <= t1:
                px = ox + t * dx
                py = oy + t * dy
                pz = oz + t * dz
                d = max(1.0, 2 * t * th)
                c = max(1.0, footprint * d)   # the cell sampled: a fraction of the cone's width
                e = 1.5 * c + 1.0             # beyond this outside the grid the level reads nothing
                if px < -e or py < -e or pz < -e or px > R + e or py > R + e or pz > R + e:
                    if ((px < -e and dx <= 0) or (py < -e and dy <= 0) or (pz < -e and dz <= 0)
                            or (px > R + e and dx >= 0) or (py > R + e and dy >= 0) or (pz > R + e and dz >= 0)):
                        break                 # leaving: nothing further on
                    t += max(0.5, 0.5 * c)
                    continue
                if c < 4 and nl > 3:   # empty space: nothing in the level-3 (2-) cells about the point
                    if _sample(pyr[0], offs, R, 3, px, py, pz) == 0.0:
                        t += 4.0
                        continue
                    if c < 2 and _sample(pyr[0], offs, R, 2, px, py, pz) == 0.0:
                        t += 2.0
                        continue
                lv = math.log2(c)
                if lv >= nl - 1:
                    lv = nl - 1.0
                l0 = int(lv)
                l1 = min(l0 + 1, nl - 1)
                w = lv - l0
                occ = 0.0
                for ax in range(3):     # the axis pyramids, blended by the direction's squares
                    wa = dirs[i, k, ax] * dirs[i, k, ax]
                    if wa > 1e-6:
                        sa = _sample(pyr[ax], offs, R, l0, px, py, pz)
                        if w > 1e-6 and l1 != l0:
                            sa = (1 - w) * sa + w * _sample(pyr[ax], offs, R, l1, px, py, pz)
                        occ += wa * sa
                step = max(1.0, 1.5 * c)
                if occ > 0:
                    a += (1 - a) * (1 - (1 - min(occ, 1.0)) ** (gain * step / c))
                t += step
            out[i, k] = 1 - a


# ---- lobe-to-table matrices ----------------------------------------------------------------------
@njit(cache=True, fastmath=True, parallel=True)
def sg_matrix(kind: int, lam_k: float, d: np.ndarray, axes: np.ndarray, lam: np.ndarray,
              zonal: np.ndarray, zslot: np.ndarray, out: np.ndarray) -> None:
    """``out[i, m]`` (float32): the integral of lobe ``m`` (``axes[m]``, ``lam[m]``, unit amplitude)
    against the kernel about direction ``d[i]``: ``kind`` 0 the SG of sharpness ``lam_k`` (closed
    form, paper eq. 4 with two lobes), 1 the clamped cosine (``zonal[zslot[m]]``), 2 the lobe's
    radiance at ``d[i]``."""
    for i in prange(d.shape[0]):
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        for m in range(axes.shape[0]):
            c = dx * axes[m, 0] + dy * axes[m, 1] + dz * axes[m, 2]
            la = lam[m]
            if kind == 0:
                r = math.sqrt(max(lam_k * lam_k + la * la + 2 * lam_k * la * c, 0.0))
                s = lam_k + la
                if r - s < -87.0:    # below float32's smallest normal: the lobes do not overlap
                    out[i, m] = 0.0
                elif r > 20.0:       # exp(-2 r) < 5e-18 of the first term
                    out[i, m] = 2 * math.pi * math.exp(r - s) / r
                elif r > 1e-9:
                    out[i, m] = 2 * math.pi * (math.exp(r - s) - math.exp(-r - s)) / r
                else:
                    out[i, m] = 4 * math.pi * math.exp(-s)
            elif kind == 1:
                out[i, m] = _zonal(zonal[zslot[m]], c)
            else:
                x = la * (c - 1.0)
                out[i, m] = math.exp(x) if x > -87.0 else 0.0


@njit(cache=True, fastmath=True, parallel=True)
def pyramid_levels(pyr: np.ndarray, offs: np.ndarray, R: int) -> None:
    """Fill levels 1.. of the three axis pyramids ``pyr`` (3, total) from level 0 (see
    :func:`lightprobe.hostlink.relight.sg.relighter.anisotropic_pyramid`): per axis, each pair of children along the
    axis composited (``1 - (1 - a)(1 - b)``), averaged over the other two axes."""
    for lv in range(offs.shape[0] - 2):
        r = R >> lv
        h = r >> 1
        o0 = offs[lv]
        o1 = offs[lv + 1]
        for z in prange(h):
            for y in range(h):
                for x in range(h):
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    for a in range(2):
                        for b in range(2):
                            # axis x (0): pairs along x, for (y, z) = (a, b)
                            lo = pyr[0, o0 + ((2 * z + b) * r + 2 * y + a) * r + 2 * x]
                            hi = pyr[0, o0 + ((2 * z + b) * r + 2 * y + a) * r + 2 * x + 1]
                            s0 += 1 - (1 - lo) * (1 - hi)
                            # axis y (1): pairs along y, for (x, z) = (a, b)
                            lo = pyr[1, o0 + ((2 * z + b) * r + 2 * y) * r + 2 * x + a]
                            hi = pyr[1, o0 + ((2 * z + b) * r + 2 * y + 1) * r + 2 * x + a]
                            s1 += 1 - (1 - lo) * (1 - hi)
                            # axis z (2): pairs along z, for (x, y) = (a, b)
                            lo = pyr[2, o0 + ((2 * z) * r + 2 * y + b) * r + 2 * x + a]
                            hi = pyr[2, o0 + ((2 * z + 1) * r + 2 * y + b) * r + 2 * x + a]
                            s2 += 1 - (1 - lo) * (1 - hi)
                    i = o1 + (z * h + y) * h + x
                    pyr[0, i] = 0.25 * s0
                    pyr[1, i] = 0.25 * s1
                    pyr[2, i] = 0.25 * s2
