"""The item buffer and what is built on it: the room's patches (subdivided triangles) and their
clusters, the camera's raster of them (per pixel the 3D point, patch, normal and group), each
pixel's sub-pixel footprint, the groups an edit moves, and the per-pixel fills and misfits."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.room.io import CameraCV
from lightprobe.hostlink.relight.room.settings import SUBPIXEL

__all__ = ["Footprints", "clusters", "footprints", "mat_vec", "misfit", "movable_groups", "moved_groups", "near_segment", "normalised_fill", "owned_vertices", "raster_cv", "subdivide"]


def clusters(v: np.ndarray, f: np.ndarray, k: int = 4) -> tuple[np.ndarray, ...]:
    """The object's faces grouped for the radiosity solve: a k^3 grid over its bounds times the
    six major directions of the face normal. Returns (label per face, a point on each cluster's
    surface (Q, 3), unit normal (Q, 3), area (Q,))."""
    a, b, c = (v[f[:, j]] for j in range(3))
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    n = cr / np.maximum(2 * area, 1e-300)[:, None]
    cen = (a + b + c) / 3
    lo, hi = v.min(axis=0), v.max(axis=0)
    cell = np.clip(((cen - lo) / np.maximum(hi - lo, 1e-12) * k).astype(np.int64), 0, k - 1)
    ax = np.argmax(np.abs(n), axis=1)
    sign = (n[np.arange(len(n)), ax] < 0).astype(np.int64)
    key = ((cell[:, 0] * k + cell[:, 1]) * k + cell[:, 2]) * 6 + 2 * ax + sign
    _, label = np.unique(key, return_inverse=True)
    Q = int(label.max()) + 1
    A = np.bincount(label, area, minlength=Q)
    C = np.stack([np.bincount(label, area * cen[:, j], minlength=Q) for j in range(3)], 1) / np.maximum(A, 1e-300)[:, None]
    Nq = np.stack([np.bincount(label, area * n[:, j], minlength=Q) for j in range(3)], 1).astype(np.float64)
    Nq /= np.maximum(np.linalg.norm(Nq, axis=1, keepdims=True), 1e-300)
    # a curved cluster's centroid may lie inside the mesh: it is represented by the centre of its
    # face nearest that centroid, just off the surface along that face's normal
    gap = np.linalg.norm(cen - C[label], axis=1)
    order = np.lexsort((gap, label))
    first = order[np.r_[0, np.flatnonzero(np.diff(label[order])) + 1]]
    rep = cen[first] + 1e-3 * float(np.ptp(v, axis=0).max()) * n[first]
    return label, rep, Nq, A


def mat_vec(M: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``M @ B`` in M's float32 (no float64 copy of a (P, P) form-factor matrix per product)."""
    return np.asarray(M @ B.astype(M.dtype), np.float64)


def near_segment(P: np.ndarray, q: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Segments ``P[i] -> q`` passing within ``r`` of ``c``."""
    from lightprobe.hostlink.relight.room.kernels import near_to_point

    out = np.zeros(len(P), np.bool_)
    near_to_point(np.ascontiguousarray(P, np.float64), np.asarray(q, np.float64), np.asarray(c, np.float64),
                  float(r), out)
    return out


def subdivide(v: np.ndarray, f: np.ndarray, fg: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each triangle split on a barycentric grid into n^2 triangles no longer than ``max_edge``."""
    verts, faces, groups = [], [], []
    base = 0
    for t, (a, b, c) in enumerate(f):
        A, B, C = v[a], v[b], v[c]
        e = max(np.linalg.norm(B - A), np.linalg.norm(C - A), np.linalg.norm(C - B))
        n = max(1, math.ceil(e / max_edge))
        idx: dict[tuple[int, int], int] = {}
        pts: list[np.ndarray] = []
        for i in range(n + 1):
            for j in range(n + 1 - i):
                idx[i, j] = len(pts)
                pts.append(A + (B - A) * (i / n) + (C - A) * (j / n))
        tri = []
        for i in range(n):
            for j in range(n - i):
                tri.append((idx[i, j], idx[i + 1, j], idx[i, j + 1]))
                if i + j < n - 1:
                    tri.append((idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]))
        verts.append(np.array(pts))
        faces.append(np.array(tri) + base)
        groups.append(np.full(len(tri), fg[t]))
        base += len(pts)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(groups)


def raster_cv(cam: CameraCV, v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from lightprobe.hostlink.relight.raster import raster_triangles

    xc = v @ cam.R.T + cam.t
    z = xc[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    sx = cam.K[0, 0] * xc[:, 0] / zs + cam.K[0, 1] * xc[:, 1] / zs + cam.K[0, 2]
    sy = cam.K[1, 1] * xc[:, 1] / zs + cam.K[1, 2]
    tri = np.full((cam.height, cam.width), -1, np.int64)
    bary = np.zeros((cam.height, cam.width, 3), np.float32)
    raster_triangles(sx, sy, z, f, cam.width, cam.height, tri, bary, np.zeros((cam.height, cam.width)))
    return tri, bary


def normalised_fill(shape: tuple[int, int], src: np.ndarray, value: np.ndarray, weight: np.ndarray,
                     todo: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Values (len(todo), 3) at flat pixel indices ``todo`` of an image ``shape``, from ``value``
    at ``src`` with confidences ``weight``: a normalised convolution (Knutsson, Westin 1993) at
    each pixel's finest Gaussian scale that reaches it; ``fallback`` where none does."""
    import cv2

    wimg = np.zeros(shape, np.float32)
    wimg.flat[src] = weight
    acc = np.zeros((*shape, 3), np.float32)
    acc.reshape(-1, 3)[src] = value * weight[:, None]
    fill = np.array(fallback, np.float64)
    left = np.ones(len(todo), bool)
    for sigma in (2.0, 4.0, 8.0, 16.0, 32.0, 64.0):
        wb = cv2.GaussianBlur(wimg, (0, 0), sigma).ravel()[todo]
        ab = cv2.GaussianBlur(acc, (0, 0), sigma).reshape(-1, 3)[todo]
        ok = left & (wb > 1e-3)
        fill[ok] = ab[ok] / wb[ok, None]
        left &= ~ok
        if not left.any():
            break
    return fill


def owned_vertices(f: np.ndarray, fg: np.ndarray, g: int) -> tuple[np.ndarray, bool]:
    """Group ``g``'s vertices (indices) and whether it owns them (no other group's face uses one)."""
    mine = np.unique(f[fg == g])
    return mine, not np.intersect1d(mine, np.unique(f[fg != g])).size


def moved_groups(v: np.ndarray, f: np.ndarray, fg: np.ndarray, names: list[str], offsets: dict[str, tuple[float, ...]],
           where: Path) -> np.ndarray:
    """The model's vertices with each named group's vertices translated by its offset (a group
    must own its vertices: one that shares them with another group cannot move alone)."""
    out = np.array(v, np.float64, copy=True)
    for name, off in offsets.items():
        if name not in names:
            raise InputError(f"{where}: no group {name!r} to move (groups: {', '.join(names)})", param="offsets")
        mine, owns = owned_vertices(f, fg, names.index(name))
        if not owns:
            raise InputError(f"{where}: group {name!r} shares vertices with another group: it cannot move alone",
                             param="offsets")
        out[mine] += np.asarray(off, np.float64)
    return out


def misfit(b2: np.ndarray, sbs: np.ndarray, sss: np.ndarray, missing: float) -> np.ndarray:
    """How badly one reflectance explains measured radiances ``b_k`` as ``rho s_k`` (modelled
    irradiances) over captures k, given ``b2 = sum b^2``, ``sbs = sum b s``, ``sss = sum s^2``:
    ``min_rho sum (b - rho s)^2 / sum b^2 = 1 - sbs^2 / (b2 sss)``; ``missing`` where a sum is 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((sss > 0) & (b2 > 0), (b2 - sbs * sbs / sss) / b2, missing)


def movable_groups(v: np.ndarray, f: np.ndarray, fg: np.ndarray, names: list[str]) -> list[str]:
    """Groups that are objects in the room rather than its shell: smaller than 90% of the room's
    extent along every axis and owning their vertices."""
    ext = np.ptp(v, axis=0)
    out = []
    for g, name in enumerate(names):
        if not (fg == g).any():
            continue
        mine, owns = owned_vertices(f, fg, g)
        if owns and (np.ptp(v[mine], axis=0) < 0.9 * ext).all():
            out.append(name)
    return out


@dataclass(frozen=True)
class Footprints:
    """The camera's pixels that straddle an edge (two groups, a fold, a neighbour off the pixel's
    plane, the border of the geometry): ``SUBPIXEL`` x ``SUBPIXEL`` samples over each such pixel's footprint
    (a camera's box filter: what it records there is the mean of what lands on it, not the
    light at the pixel's centre). ``pix`` indexes the covered pixels, one run of ``k`` entries
    per edge pixel; ``patch`` is -1 where a sample misses the geometry (it counts as black)."""

    edge: np.ndarray         # (e,) covered-pixel indices
    pix: np.ndarray          # (e k,)
    X: np.ndarray            # (m, 3) the samples that hit, ``hit`` of the e k
    N: np.ndarray
    patch: np.ndarray        # (m,) patch per sample that hit
    hit: np.ndarray          # (e k,) bool
    k: int
    n: int                   # covered pixels

    def pixels(self, centre: np.ndarray, sub: np.ndarray) -> np.ndarray:
        """Per covered pixel: ``centre`` (n, ...) with the edge pixels replaced by the mean of
        their samples' ``sub`` (m, ...)."""
        if not len(self.edge):
            return centre
        out = centre.copy()
        full = np.zeros((len(self.pix), *sub.shape[1:]), sub.dtype)
        full[self.hit] = sub
        out[self.edge] = full.reshape((len(self.edge), self.k, *sub.shape[1:])).mean(axis=1)
        return out

    def gather(self, Q: np.ndarray, centre_patch: np.ndarray) -> np.ndarray:
        """A per-patch quantity ``Q`` (P, ...) at each covered pixel, over its footprint."""
        return self.pixels(Q[centre_patch], Q[self.patch])


def footprints(cam: CameraCV, cover: np.ndarray, X: np.ndarray, N: np.ndarray, group: np.ndarray,
                es: Any, faces: np.ndarray, pn: np.ndarray, s: int = SUBPIXEL) -> Footprints:
    """Find the edge pixels of a view (covered pixels ``cover``, their points, normals, groups)
    and cast ``s`` x ``s`` camera rays over each one into the Embree scene ``es`` (whose
    primitive ``i`` is patch ``faces[i]``; ``pn`` the patches' normals)."""
    H, W = cover.shape
    idx = np.full((H, W), -1)
    idx[cover] = np.arange(len(X))
    z = np.zeros((H, W))
    z[cover] = (X @ cam.R.T + cam.t)[:, 2]
    ximg = np.zeros((H, W, 3))
    ximg[cover] = X
    nimg = np.zeros((H, W, 3))
    nimg[cover] = N
    gimg = np.full((H, W), -1)
    gimg[cover] = group
    edge = np.zeros((H, W), bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = (slice(max(0, -dy), H - max(0, dy)), slice(max(0, -dx), W - max(0, dx)))
        b = (slice(max(0, dy), H - max(0, -dy)), slice(max(0, dx), W - max(0, -dx)))
        d = (gimg[a] != gimg[b]) | (np.einsum("ijk,ijk->ij", nimg[a], nimg[b]) < 0.99) | \
            (np.abs(np.einsum("ijk,ijk->ij", nimg[a], ximg[b] - ximg[a])) > 0.01 * np.maximum(z[a], z[b]))   # off the plane
        edge[a] |= d
        edge[b] |= d
    edge &= cover
    ei = idx[edge]
    yy, xx = np.nonzero(edge)
    off = (np.arange(s) + 0.5) / s - 0.5
    ox, oy = (g.ravel() for g in np.meshgrid(off, off))
    px = (xx[:, None] + ox[None]).ravel()
    py = (yy[:, None] + oy[None]).ravel()
    d_cam = np.linalg.solve(cam.K, np.stack([px, py, np.ones_like(px)]))
    d = (cam.R.T @ d_cam).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(cam.center, d.shape)
    if len(d):
        res = es.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        prim, t = np.asarray(res["primID"]), np.asarray(res["tfar"], np.float64)
    else:
        prim, t = np.zeros(0, np.int64), np.zeros(0)
    hit = prim >= 0
    patch = faces[prim[hit]]
    Xs = cam.center + t[hit, None] * d[hit]
    Ns = pn[patch]
    Ns = np.where((np.einsum("ij,ij->i", Ns, cam.center - Xs) < 0)[:, None], -Ns, Ns)
    return Footprints(ei, np.repeat(ei, s * s), Xs, Ns, patch, hit, s * s, len(X))
