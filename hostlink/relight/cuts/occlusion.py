"""Shadows of movable objects from their visibility cut fields, as a correction of the static
radiance (numba kernels).

For a vertex x shadowed by one movable object, Iwasaki et al. Eq. 4 gives
``V(x, w) = Vs(x, w) sum_j t_j V_j(w)`` with ``t_j`` the trilinear weights of the 8 VCF points
around x (``sum_j t_j = 1``). Eq. 3 is linear in V, so

    B(x, w_o) = sum_k L_k Vs_k f_r  -  sum_j t_j  sum_{w : V_j(w) = 0} L(w) Vs(w) f_r(w, w_o),

the static radiance (:func:`lightprobe.hostlink.relight.cuts.kernels.shade_static`, cached until the light, the
BRDF or the view changes) minus, for each of the 8 binary VCF cuts on its own, the light of its
occluded (value 0) nodes weighted by the SVC. The VCF cuts stay height-coded (Sec. V-A-2); when a
renderer is set up, each cut is walked once leftmost-first and its consecutive 0-nodes are
merged into runs of leaves (:func:`zero_runs`: a run-time index, ~32 runs per point against ~120
nodes). At render time a run is split at the SVC's node boundaries (galloping search over the
SVC's node starts, computed once per vertex) and each piece takes its light over its leaf range
from the prefix sums ``P``, ``Q`` in O(1), with the SVC node's weight ``sw``
(:func:`lightprobe.hostlink.relight.cuts.kernels.svc_weights`: the cosine-moment correction applies per piece
exactly as it does per node). This is the sum the counter-based product of the SVC with the
interpolated cut (Steps 1-4) computes, up to where the cosine-moment correction is evaluated, but
it touches only the occluded part of each VCF cut and never builds the 8-way refinement (about
1,000 nodes per vertex near the object).

Vertices shadowed by two or more movable objects at once need the product of their
interpolated cuts (``1 - prod(1 - O_m)`` is not linear): the kernel flags them and the caller
uses the counter-based kernel (:func:`lightprobe.hostlink.relight.cuts.kernels.shade_dynamic`).

Rotated objects: the VCF and its cuts live in the object frame. A receiver x looks up the VCF at
``x' = R^T (x - c) + c`` (c the VCF centre); the visibility it gets is over object-frame
directions w' and applies to the world direction ``w = R w'``. Each occluded VCF node is split
into blocks of at most 2^``ROT_BLOCK`` leaves (compact clusters, <= ~5 deg); a block's light is
taken from the object's rotated light tables (world light binned into object-frame leaves, first
moments kept in world coordinates: :func:`lightprobe.hostlink.relight.cuts.lighting.rotated_light_tables`), its
SVC weight from the SVC node containing the world direction ``R m`` of the block's mean direction
m, and its cosine-corrected light is clamped at 0 (a rotated block may straddle the horizon).

References
----------
K. Iwasaki et al., "Interactive relighting of captured illumination with visibility cuts",
Eqs. (3), (4), Sec. V-A-2 (height-coded cuts), Sec. V-A-4 (VCF interpolation), Sec. V-B.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from lightprobe.hostlink.relight.cuts.directions import NDIR, SIDE
from lightprobe.hostlink.relight.cuts.kernels import brdf_spec

__all__ = ["ROT_BLOCK", "leaf_of", "occlusion", "zero_runs"]

ROT_BLOCK = 6
_COARSE = 5                                                  # coarse SVC index: 2^5 leaves per cell
_INV_PI = 1.0 / np.pi


@njit(cache=True, inline="always")
def _part1by1(x: int) -> int:
    x &= 0x7F
    x = (x | (x << 4)) & 0x0F0F
    x = (x | (x << 2)) & 0x3333
    return (x | (x << 1)) & 0x5555


@njit(cache=True, fastmath=True, inline="always")
def _atan2_fast(y: float, x: float) -> float:
    """atan2 to ~1e-5 rad (minimax polynomial on [0, 1]; a leaf cell spans ~0.02 rad)."""
    ax, ay = abs(x), abs(y)
    mx, mn = max(ax, ay), min(ax, ay)
    if mx == 0:
        return 0.0
    a = mn / mx
    s = a * a
    r = ((-0.0464964749 * s + 0.15931422) * s - 0.327622764) * s * a + a
    if ay > ax:
        r = np.pi / 2 - r
    if x < 0:
        r = np.pi - r
    return -r if y < 0 else r


@njit(cache=True, fastmath=True)
def leaf_of(x: float, y: float, z: float, fast: bool = False) -> int:
    """Leaf index of the cell containing the unit direction (x, y, z): scalar numba version of
    :func:`lightprobe.hostlink.relight.cuts.directions.direction_to_leaf` (same map, same clamping). ``fast``
    uses a polynomial atan2: within ~1e-5 rad of a cell border it may name the neighbour cell."""
    hemi = 1 if y < 0 else 0
    r = np.sqrt(min(max(1.0 - abs(y), 0.0), 1.0))
    psi = _atan2_fast(z, x) if fast else np.arctan2(z, x)
    if psi < -np.pi / 4:
        psi += 2 * np.pi
    q = min(max(int(np.floor((psi + np.pi / 4) / (np.pi / 2))), 0), 3)
    t = 4.0 / np.pi
    if q == 0:
        a, b = r, psi * t * r
    elif q == 1:
        a, b = (np.pi / 2 - psi) * t * r, r
    elif q == 2:
        a, b = -r, -(psi - np.pi) * t * r
    else:
        a, b = -(1.5 * np.pi - psi) * t * r, -r
    a = min(max(a, -1.0), 1.0)
    b = min(max(b, -1.0), 1.0)
    i = min(max(int((a + 1) * 0.5 * SIDE), 0), SIDE - 1)
    j = min(max(int((b + 1) * 0.5 * SIDE), 0), SIDE - 1)
    return (hemi << 14) | (_part1by1(i) << 1) | _part1by1(j)


@njit(cache=True, fastmath=True)
def _lookup8(lx: float, ly: float, lz: float, radii: np.ndarray, grid: int, pts: np.ndarray,
             wts: np.ndarray) -> None:
    """8 VCF sample points around the object-frame offset (lx, ly, lz) from the VCF centre and
    their trilinear weights (radius x cube-face s, t), as ``kernels._vcf_lookup``."""
    d = np.sqrt(lx * lx + ly * ly + lz * lz)
    inv = 1.0 / max(d, 1e-12)
    ux, uy, uz = lx * inv, ly * inv, lz * inv
    ax = abs(ux)
    a = 0
    big = ax
    if abs(uy) > big:
        a = 1
        big = abs(uy)
    if abs(uz) > big:
        a = 2
        big = abs(uz)
    u = (ux, uy, uz)
    f = 2 * a + (1 if u[a] < 0 else 0)
    s = u[(a + 1) % 3] / big
    tt = u[(a + 2) % 3] / big
    K = radii.shape[0]
    fr = 0.0 if K == 1 else (d - radii[0]) / (radii[K - 1] - radii[0]) * (K - 1)
    fr = min(max(fr, 0.0), K - 1.0)
    fx = min(max((s + 1) * 0.5 * grid - 0.5, 0.0), grid - 1.0)
    fy = min(max((tt + 1) * 0.5 * grid - 0.5, 0.0), grid - 1.0)
    k0, x0, y0 = int(fr), int(fx), int(fy)
    wr, wx, wy = fr - k0, fx - x0, fy - y0
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


@njit(cache=True, inline="always")
def _find(starts: np.ndarray, ncut: int, a: int, lo: int = 0) -> int:
    """Index k >= lo of the SVC node with starts[k] <= a < starts[k + 1] (requires
    starts[lo] <= a): galloping from lo, then binary search."""
    step = 1
    hi = lo + 1
    while hi < ncut and starts[hi] <= a:
        lo = hi
        hi = lo + step
        step <<= 1
    hi = min(hi, ncut)
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if starts[mid] <= a:
            lo = mid
        else:
            hi = mid
    return lo


@njit(cache=True, fastmath=True, inline="always")
def _piece(PQ: np.ndarray, a: int, e: int, w: float, nx: float, ny: float, nz: float,
           clamp: bool) -> tuple[float, float, float]:
    """Light of leaves [a, e) for SVC weight w (> 0 moment-corrected, < 0 plain) from the
    combined prefix table ``PQ`` (columns 0-2 P, 3-11 Q, 12-14 leaf directions)."""
    if w > 0:
        lr = w * (nx * (PQ[e, 3] - PQ[a, 3]) + ny * (PQ[e, 4] - PQ[a, 4]) + nz * (PQ[e, 5] - PQ[a, 5]))
        lg = w * (nx * (PQ[e, 6] - PQ[a, 6]) + ny * (PQ[e, 7] - PQ[a, 7]) + nz * (PQ[e, 8] - PQ[a, 8]))
        lb = w * (nx * (PQ[e, 9] - PQ[a, 9]) + ny * (PQ[e, 10] - PQ[a, 10]) + nz * (PQ[e, 11] - PQ[a, 11]))
        if clamp:
            return max(lr, 0.0), max(lg, 0.0), max(lb, 0.0)
        return lr, lg, lb
    return -w * (PQ[e, 0] - PQ[a, 0]), -w * (PQ[e, 1] - PQ[a, 1]), -w * (PQ[e, 2] - PQ[a, 2])


@njit(cache=True, fastmath=True, inline="always")
def _piece_dir(PQ: np.ndarray, a: int, e: int) -> tuple[float, float, float]:
    """Unit direction for the BRDF of leaves [a, e): light centroid, or mean leaf direction."""
    cx = PQ[e, 3] - PQ[a, 3] + PQ[e, 6] - PQ[a, 6] + PQ[e, 9] - PQ[a, 9]
    cy = PQ[e, 4] - PQ[a, 4] + PQ[e, 7] - PQ[a, 7] + PQ[e, 10] - PQ[a, 10]
    cz = PQ[e, 5] - PQ[a, 5] + PQ[e, 8] - PQ[a, 8] + PQ[e, 11] - PQ[a, 11]
    sl = np.sqrt(cx * cx + cy * cy + cz * cz)
    if sl <= 1e-300:
        cx, cy, cz = PQ[e, 12] - PQ[a, 12], PQ[e, 13] - PQ[a, 13], PQ[e, 14] - PQ[a, 14]
        sl = max(np.sqrt(cx * cx + cy * cy + cz * cz), 1e-300)
    return cx / sl, cy / sl, cz / sl


@njit(cache=True)
def zero_runs(voffs: np.ndarray, vh: np.ndarray, vv: np.ndarray, roffs: np.ndarray,
              rs: np.ndarray, re: np.ndarray) -> int:
    """Decode every binary VCF cut (height-coded, leftmost-first) into its runs of occluded
    leaves ``[rs, re)``: consecutive 0-nodes merge. Point p's runs are ``roffs[p]:roffs[p+1]``.
    ``rs``, ``re`` need room for one run per 0-node; returns the number of runs."""
    nr = 0
    for pt in range(voffs.shape[0] - 1):
        roffs[pt] = nr
        leaf = 0
        run = -1
        for q in range(voffs[pt], voffs[pt + 1]):
            if vv[q] == 0:
                if run < 0:
                    run = leaf
            elif run >= 0:
                rs[nr] = run
                re[nr] = leaf
                nr += 1
                run = -1
            leaf += 1 << vh[q]
        if run >= 0:
            rs[nr] = run
            re[nr] = leaf
            nr += 1
    roffs[voffs.shape[0] - 1] = nr
    return nr


@njit(cache=True, fastmath=True)
def _runs_light(PQ: np.ndarray, rs: np.ndarray, re: np.ndarray, r0: int, r1: int,
                starts: np.ndarray, ncut: int, o0: int, sw: np.ndarray, n: np.ndarray,
                spec: np.ndarray, wo: np.ndarray, acc: np.ndarray, tj: float) -> int:
    """acc += tj * (diffuse light, specular light) of the runs r0:r1, each split at the SVC's
    node boundaries (exact; unrotated object). ``spec`` = (glossy, type, exponent)."""
    nx, ny, nz = n[0], n[1], n[2]
    npieces = 0
    k = 0
    for r in range(r0, r1):                                # runs ascend: search from the last node
        a = rs[r]
        b = re[r]
        k = _find(starts, ncut, a, k)
        while a < b:
            e = min(b, starts[k + 1])
            w = sw[o0 + k]
            if w != 0:
                lr, lg, lb = _piece(PQ, a, e, w, nx, ny, nz, False)
                acc[0] += tj * lr
                acc[1] += tj * lg
                acc[2] += tj * lb
                if spec[0] != 0:
                    wx, wy, wz = _piece_dir(PQ, a, e)
                    f = tj * brdf_spec(int(spec[1]), spec[2], n, wx, wy, wz, wo[0], wo[1], wo[2])
                    acc[3] += lr * f
                    acc[4] += lg * f
                    acc[5] += lb * f
                npieces += 1
            a = e
            k += 1
        k -= 1                                             # the node holding leaf b - 1
    return npieces


@njit(cache=True)
def _coarse_index(starts: np.ndarray, ncut: int, coarse: np.ndarray) -> None:
    """coarse[c] = the SVC node holding leaf c * 2^COARSE (start point for :func:`_find_coarse`)."""
    k = 0
    for c in range(coarse.shape[0]):
        leaf = c << _COARSE
        while k + 1 < ncut and starts[k + 1] <= leaf:
            k += 1
        coarse[c] = k


@njit(cache=True, inline="always")
def _find_coarse(starts: np.ndarray, ncut: int, coarse: np.ndarray, leaf: int) -> int:
    """SVC node holding ``leaf``: from the coarse index, a few steps forward."""
    k = coarse[leaf >> _COARSE]
    while k + 1 < ncut and starts[k + 1] <= leaf:
        k += 1
    return k


@njit(cache=True, fastmath=True)
def _runs_light_rotated(PQ: np.ndarray, rs: np.ndarray, re: np.ndarray, r0: int, r1: int,
                        R: np.ndarray, starts: np.ndarray, ncut: int, coarse: np.ndarray, o0: int,
                        sw: np.ndarray, n: np.ndarray, spec: np.ndarray, wo: np.ndarray,
                        acc: np.ndarray, tj: float) -> int:
    """As :func:`_runs_light` for a rotated object: runs over object-frame leaves, cut into
    blocks inside aligned 2^ROT_BLOCK-leaf clusters; each block takes the SVC weight at the world
    direction R m of its mean direction m (``PQ`` = the object's rotated light tables)."""
    nx, ny, nz = n[0], n[1], n[2]
    npieces = 0
    for r in range(r0, r1):
        a = rs[r]
        b = re[r]
        while a < b:
            e = min(b, ((a >> ROT_BLOCK) + 1) << ROT_BLOCK)
            mx, my, mz = PQ[e, 12] - PQ[a, 12], PQ[e, 13] - PQ[a, 13], PQ[e, 14] - PQ[a, 14]
            k = _find_coarse(starts, ncut, coarse, leaf_of(R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz,
                                                           R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz,
                                                           R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz, True))
            w = sw[o0 + k]
            if w != 0:
                lr, lg, lb = _piece(PQ, a, e, w, nx, ny, nz, True)
                acc[0] += tj * lr
                acc[1] += tj * lg
                acc[2] += tj * lb
                if spec[0] != 0:
                    wx, wy, wz = _piece_dir(PQ, a, e)
                    f = tj * brdf_spec(int(spec[1]), spec[2], n, wx, wy, wz, wo[0], wo[1], wo[2])
                    acc[3] += lr * f
                    acc[4] += lg * f
                    acc[5] += lb * f
                npieces += 1
            a = e
    return npieces


@njit(cache=True, fastmath=True)
def _in_range(x: np.ndarray, n: np.ndarray, center: np.ndarray, r: float, outer: float) -> bool:
    """Object can shadow x: x inside its outermost VCF sphere, bounding sphere not entirely under
    x's horizon plane (Sec. V-B culling)."""
    dx = center[0] - x[0]
    dy = center[1] - x[1]
    dz = center[2] - x[2]
    if dx * dx + dy * dy + dz * dz >= outer * outer:
        return False
    return dx * n[0] + dy * n[1] + dz * n[2] >= -r


@njit(cache=True, fastmath=True)
def _object_occlusion(x: np.ndarray, n: np.ndarray, wo: np.ndarray, center: np.ndarray, R: np.ndarray,
                      slot: int, radii: np.ndarray, grid: int, pbase: int, roffs: np.ndarray,
                      rs: np.ndarray, re: np.ndarray, PQ: np.ndarray, PQR: np.ndarray,
                      starts: np.ndarray, ncut: int, o0: int, sw: np.ndarray, spec: np.ndarray,
                      acc: np.ndarray) -> int:
    """acc += the light one movable object takes from x: its 8 VCF points around x (trilinear
    weights t_j), each point's occluded runs weighted by t_j (Eq. 4 by linearity)."""
    lx, ly, lz = x[0] - center[0], x[1] - center[1], x[2] - center[2]
    coarse = np.empty(1, np.int64)
    if slot >= 0:                                             # x' = R^T (x - c) + c
        lx, ly, lz = (R[0, 0] * lx + R[1, 0] * ly + R[2, 0] * lz,
                      R[0, 1] * lx + R[1, 1] * ly + R[2, 1] * lz,
                      R[0, 2] * lx + R[1, 2] * ly + R[2, 2] * lz)
        coarse = np.empty(NDIR >> _COARSE, np.int64)
        _coarse_index(starts, ncut, coarse)
    pts = np.empty(8, np.int64)
    wts = np.empty(8)
    _lookup8(lx, ly, lz, radii, grid, pts, wts)
    npieces = 0
    for j in range(8):
        tj = wts[j]
        if tj <= 1e-12:
            continue
        pt = pbase + pts[j]
        if slot >= 0:
            npieces += _runs_light_rotated(PQR[slot], rs, re, roffs[pt], roffs[pt + 1], R, starts, ncut,
                                           coarse, o0, sw, n, spec, wo, acc, tj)
        else:
            npieces += _runs_light(PQ, rs, re, roffs[pt], roffs[pt + 1], starts, ncut, o0, sw, n, spec,
                                   wo, acc, tj)
    return npieces


@njit(cache=True)
def _svc_starts(hs: np.ndarray, o0: int, ncut: int) -> np.ndarray:
    """Leaf where each of the SVC's ``ncut`` nodes starts (leftmost-first), plus 2^15 at the end."""
    starts = np.empty(ncut + 1, np.int64)
    leaf = 0
    for q in range(ncut):
        starts[q] = leaf
        leaf += 1 << hs[o0 + q]
    starts[ncut] = NDIR
    return starts


@njit(cache=True)
def _spec_params(mats: np.ndarray, m: int) -> np.ndarray:
    """(glossy 0/1, BRDF type, exponent-or-alpha) of material row m."""
    typ = mats[m, 0]
    glossy = typ != 0 and (mats[m, 4] != 0 or mats[m, 5] != 0 or mats[m, 6] != 0)
    return np.array([1.0 if glossy else 0.0, typ, mats[m, 7]])


@njit(cache=True, parallel=True, fastmath=True)
def occlusion(vidx: np.ndarray, pos: np.ndarray, normals: np.ndarray, wo: np.ndarray,
              matid: np.ndarray, mats: np.ndarray, own: np.ndarray, offs: np.ndarray,
              hs: np.ndarray, sw: np.ndarray, centers: np.ndarray, rots: np.ndarray,
              rslot: np.ndarray, obj_r: np.ndarray, radii: np.ndarray, grid: np.ndarray,
              pbase: np.ndarray, roffs: np.ndarray, rs: np.ndarray, re: np.ndarray,
              PQ: np.ndarray, PQR: np.ndarray, linear: bool, out: np.ndarray,
              pieces: np.ndarray, multi: np.ndarray) -> None:
    """Radiance (n, 3) the movable objects take away from each vertex ``vidx[t]`` (see module
    docstring); ``pieces[t]`` counts the occluded pieces shaded; ``multi[t]`` is set (and
    ``out[t]`` left 0) when two or more objects can shadow the vertex, unless ``linear`` (then
    their occlusions are summed: exact where their shadows do not overlap).

    ``roffs``, ``rs``, ``re``: occluded leaf runs per VCF point (:func:`zero_runs`), point ids
    offset by ``pbase[object]``. ``rots`` (objects, 3, 3) object -> world rotations;
    ``rslot[m]`` >= 0 selects object m's rotated light tables ``PQR[rslot]``; -1 means unrotated
    (world table ``PQ``: columns 0-2 P, 3-11 Q, 12-14 leaf-direction prefix sums).
    """
    for t in prange(vidx.shape[0]):
        i = vidx[t]
        x = pos[i]
        n = normals[i]
        out[t, 0] = out[t, 1] = out[t, 2] = 0.0
        pieces[t] = 0
        multi[t] = False
        cnt = 0
        for mm in range(centers.shape[0]):
            if mm != own[i] and _in_range(x, n, centers[mm], obj_r[mm], radii[mm, radii.shape[1] - 1]):
                cnt += 1
        if cnt == 0:
            continue
        if cnt > 1 and not linear:
            multi[t] = True
            continue
        m = matid[i]
        spec = _spec_params(mats, m)
        o0 = offs[i]
        ncut = offs[i + 1] - o0
        starts = _svc_starts(hs, o0, ncut)
        acc = np.zeros(6)
        npieces = 0
        for mm in range(centers.shape[0]):
            if mm != own[i] and _in_range(x, n, centers[mm], obj_r[mm], radii[mm, radii.shape[1] - 1]):
                npieces += _object_occlusion(x, n, wo[t], centers[mm], rots[mm], rslot[mm], radii[mm], grid[mm],
                                             pbase[mm], roffs, rs, re, PQ, PQR, starts, ncut, o0, sw, spec, acc)
        out[t, 0] = mats[m, 1] * _INV_PI * acc[0] + mats[m, 4] * acc[3]
        out[t, 1] = mats[m, 2] * _INV_PI * acc[1] + mats[m, 5] * acc[4]
        out[t, 2] = mats[m, 3] * _INV_PI * acc[2] + mats[m, 6] * acc[5]
        pieces[t] = npieces
