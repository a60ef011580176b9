"""numba kernels of the SG relighting (:mod:`hostlink.relight.sg`): direction-table lookups,
per-point shading from SG tables and peaks, voxelisation and voxel cone tracing.

Conventions. Direction tables are (H, 2H, 3) grids over the sphere: row ``i`` at polar angle
``theta = i pi / (H - 1)`` from +y (rows 0 and H - 1 on the poles), column ``j`` at azimuth ``phi = (j + 0.5) pi / H`` with
``d = (sin theta cos phi, cos theta, sin theta sin phi)``; lookups are bilinear (clamped in
theta, periodic in phi). Zonal tables are (K,) samples of a function of ``t = a . p`` on
``t_k = -1 + 2 k / (K - 1)``, looked up linearly.

A voxel pyramid is one flat float32 array: level ``l`` holds ``(R >> l)^3`` occupancies (x
fastest, z slowest: index ``(z * r + y) * r + x``) from ``offsets[l]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["cone_frame", "shade_points", "trace_cones", "voxelize"]

LAM_COS = 2.133     # the clamped cosine as one SG (Wang et al. 2009): mu 1.17, lambda 2.133
MU_COS = 1.17


@njit(cache=True, fastmath=True, inline="always")
def _dir_lookup(tab: np.ndarray, x: float, y: float, z: float, ch: int) -> float:
    H = tab.shape[0]
    W = tab.shape[1]
    th = math.acos(min(1.0, max(-1.0, y)))
    ph = math.atan2(z, x)
    if ph < 0:
        ph += 2 * math.pi
    fi = th * (H - 1) / math.pi
    fj = ph * H / math.pi - 0.5
    i0 = int(np.floor(fi))
    j0 = int(np.floor(fj))
    wi = fi - i0
    wj = fj - j0
    i1 = min(i0 + 1, H - 1)
    i0 = max(i0, 0)
    if i1 < 0:
        i1 = 0
    j0m = j0 % W
    j1m = (j0 + 1) % W
    return ((1 - wi) * ((1 - wj) * tab[i0, j0m, ch] + wj * tab[i0, j1m, ch])
            + wi * ((1 - wj) * tab[i1, j0m, ch] + wj * tab[i1, j1m, ch]))


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
def cone_frame(n: np.ndarray, ring_cos: float, ring_sin: float, out: np.ndarray) -> None:
    """The 7 diffuse cone axes of each normal: ``out[i, 0] = n``, ``out[i, 1..6]`` tilted by the
    ring angle at azimuths k 60 deg about n. ``out`` is (N, 7, 3)."""
    for i in range(n.shape[0]):
        nx, ny, nz = n[i, 0], n[i, 1], n[i, 2]
        tx, ty, tz, bx, by, bz = _onb(nx, ny, nz)
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = nx, ny, nz
        for k in range(6):
            c = math.cos(k * math.pi / 3)
            s = math.sin(k * math.pi / 3)
            out[i, k + 1, 0] = ring_cos * nx + ring_sin * (c * tx + s * bx)
            out[i, k + 1, 1] = ring_cos * ny + ring_sin * (c * ty + s * by)
            out[i, k + 1, 2] = ring_cos * nz + ring_sin * (c * tz + s * bz)


@njit(cache=True, fastmath=True, parallel=True)
def shade_points(nrm: np.ndarray, wo: np.ndarray, matid: np.ndarray, mats: np.ndarray,
                 gloss_slot: np.ndarray, tabE: np.ndarray, tabWc: np.ndarray, tabWr: np.ndarray,
                 kc: float, kr: float, lam_cos: float, lam_cone: float, tabG: np.ndarray,
                 paxis: np.ndarray, plam: np.ndarray, pamp: np.ndarray, pF: np.ndarray,
                 cones: np.ndarray, vis7: np.ndarray, vspec: np.ndarray, vpeak: np.ndarray,
                 out: np.ndarray) -> None:
    """Outgoing radiance per point (see :mod:`hostlink.relight.sg` for the model).

    ``tabE``: exact clamped-cosine irradiance of the residual lobes per normal; ``tabWc`` /
    ``tabWr``: the residual light through the centre / ring visibility lobes (SG kernels of the
    products cosine x cone lobe), ``kc`` / ``kr`` their amplitude factors; ``tabG[s]``: the
    residual convolved with the Phong lobe of gloss slot ``s``; peaks: axes, sharpness,
    amplitudes and ``pF[p]`` (zonal clamped-cosine table of lobe p). Visibility: ``vis7`` (N, 7)
    cone transmittances, ``vspec`` (N,) the reflection cone's, ``vpeak`` (N, P) each peak's."""
    P = paxis.shape[0]
    for i in prange(nrm.shape[0]):
        nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        m = matid[i]
        typ = int(mats[m, 0])
        # the residual's visibility: the cones' transmittances weighted by the light they carry
        v = np.zeros(3)
        wsum = np.zeros(3)
        for c in range(7):
            ax, ay, az = cones[i, c, 0], cones[i, c, 1], cones[i, c, 2]
            rx = lam_cos * nx + lam_cone * ax
            ry = lam_cos * ny + lam_cone * ay
            rz = lam_cos * nz + lam_cone * az
            rl = math.sqrt(rx * rx + ry * ry + rz * rz)
            for ch in range(3):
                if c == 0:
                    w = kc * _dir_lookup(tabWc, rx / rl, ry / rl, rz / rl, ch)
                else:
                    w = kr * _dir_lookup(tabWr, rx / rl, ry / rl, rz / rl, ch)
                w = max(w, 0.0)
                v[ch] += w * vis7[i, c]
                wsum[ch] += w
        mean7 = 0.0
        for c in range(7):
            mean7 += vis7[i, c] / 7.0
        diff = np.zeros(3)
        for ch in range(3):
            vres = v[ch] / wsum[ch] if wsum[ch] > 1e-30 else mean7
            diff[ch] = _dir_lookup(tabE, nx, ny, nz, ch) * vres  # may be < 0: the peaks' residual
        for p in range(P):
            cp = nx * paxis[p, 0] + ny * paxis[p, 1] + nz * paxis[p, 2]
            f = _zonal(pF[p], cp) * vpeak[i, p]
            for ch in range(3):
                diff[ch] += pamp[p, ch] * f
        for ch in range(3):
            out[i, ch] = mats[m, 1 + ch] / math.pi * max(diff[ch], 0.0)
        if typ != 1:
            continue
        # Phong: ks (e + 2) / (2 pi) cos^e(r_o . w) ~ an SG of sharpness e about the reflection
        e = mats[m, 7]
        cn = nx * wo[i, 0] + ny * wo[i, 1] + nz * wo[i, 2]
        ox = 2 * cn * nx - wo[i, 0]
        oy = 2 * cn * ny - wo[i, 1]
        oz = 2 * cn * nz - wo[i, 2]
        cr = max(nx * ox + ny * oy + nz * oz, 0.0)
        norm = (e + 2) * 0.5 / math.pi
        spec = np.zeros(3)
        s = gloss_slot[m]
        for ch in range(3):
            spec[ch] = cr * _dir_lookup(tabG[s], ox, oy, oz, ch) * vspec[i]
        for p in range(P):
            lp = plam[p]
            qx = e * ox + lp * paxis[p, 0]
            qy = e * oy + lp * paxis[p, 1]
            qz = e * oz + lp * paxis[p, 2]
            ql = math.sqrt(qx * qx + qy * qy + qz * qz)
            if ql < 1e-9:
                continue
            dp = 2 * math.pi * (math.exp(ql - e - lp) - math.exp(-ql - e - lp)) / ql
            cq = max((nx * qx + ny * qy + nz * qz) / ql, 0.0)
            for ch in range(3):
                spec[ch] += pamp[p, ch] * dp * cq * vpeak[i, p]
        for ch in range(3):
            out[i, ch] += mats[m, 4 + ch] * norm * max(spec[ch], 0.0)


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
                start: float, lift: float, gain: float, footprint: float, out: np.ndarray) -> None:
    """Transmittance of cones (voxel cone tracing, Crassin et al. 2011; ``pyr`` (3, total): the
    per-axis pyramids of :func:`hostlink.relight.sg.anisotropic_pyramid`): for point ``i`` and cone
    ``k`` along ``dirs[i, k]`` with ``tan(half angle) = tan_half[i, k]``, from ``orig[i]`` lifted
    by ``lift`` voxels along ``nrm[i]``, starting ``start`` voxels out. Each step samples the
    pyramid at the level whose cell is ``footprint`` x the cone's diameter (a cell as wide as the
    cone reaches back to the surface it starts from) and composites ``1 - (1 - occ)^(gain step / cell)`` front to back. Stops at 99% opacity or the grid's edge."""
    nl = offs.shape[0] - 1
    for i in prange(orig.shape[0]):
        ox = (orig[i, 0] - origin[0]) / vox + lift * nrm[i, 0]
        oy = (orig[i, 1] - origin[1]) / vox + lift * nrm[i, 1]
        oz = (orig[i, 2] - origin[2]) / vox + lift * nrm[i, 2]
        for k in range(dirs.shape[1]):
            dx, dy, dz = dirs[i, k, 0], dirs[i, k, 1], dirs[i, k, 2]
            th = tan_half[i, k]
            t = start
            a = 0.0
            while a < 0.99:
                px = ox + t * dx
                py = oy + t * dy
                pz = oz + t * dz
                if px < -1 or py < -1 or pz < -1 or px > R + 1 or py > R + 1 or pz > R + 1:
                    break
                d = max(1.0, 2 * t * th)
                c = max(1.0, footprint * d)   # the cell sampled: a fraction of the cone's width
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
                        occ += wa * ((1 - w) * _sample(pyr[ax], offs, R, l0, px, py, pz)
                                     + w * _sample(pyr[ax], offs, R, l1, px, py, pz))
                step = max(0.5, 0.5 * c)
                if occ > 0:
                    a += (1 - a) * (1 - (1 - min(occ, 1.0)) ** (gain * step / c))
                t += step
            out[i, k] = 1 - a
