"""Visibility for the SG relighting: the scene's objects (posed, deformed, versioned), their voxels,
rectangles and Embree scene, and the cones' and peaks' transmittances, traced through voxels or
with rays."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.sg.kernels import (
    cone_frame,
    rect_clear,
    residual_visibility,
    trace_cones,
    voxelize,
)
from lightprobe.hostlink.relight.sg.objects import SGScene
from lightprobe.hostlink.relight.sg.settings import (
    CONE_HALF,
    DIFFUSE_CONES,
    PEAK0,
    PEAK_RAYS,
    RAYS_PER_CONE,
    RAYS_PER_PEAK,
    REFLECTION,
    RESIDUAL_RAYS,
    THIN_PEAK_VOXELS,
)
from lightprobe.hostlink.relight.sg.tables import (
    PATTERN,
    RECT_COS,
    RECT_G,
    RECT_SIN,
    anisotropic_pyramid,
    fibonacci,
    table_lookup,
)

__all__ = ["SGVisibility"]


class SGVisibility(SGScene):
    """The scene\'s visibility: cones through the voxels and the rectangles, or rays; the peaks\'
    shadow rays (a step of :class:`.relighter.SGRelighter`)."""


    def _pyramid(self) -> tuple[np.ndarray, np.ndarray]:
        R = self.R
        if self._dirty:
            self._fit_grid()
        if self._dirty or self._pyr is None:
            rect = self._rects()[1]
            for k in sorted(self._dirty):
                ob = self.objects[k]
                if k in rect:   # an exact occluder of the cones (rect_clear), not voxels
                    self._occ[k] = None
                    continue
                occ = np.zeros(R ** 3, np.uint8)
                voxelize(self.vertices[ob.base:ob.base + len(ob.rest)], ob.faces, self.origin, self.vox, R, occ)
                # surfaces only (filling closed meshes' interiors was tried: worse, self-occlusion)
                self._occ[k] = occ
            self._dirty.clear()
            tot = np.zeros(R ** 3, np.uint8)
            for o in self._occ:
                if o is not None:
                    np.bitwise_or(tot, o, out=tot)
            self._pyr = anisotropic_pyramid(tot.reshape(R, R, R), None if self._pyr is None else self._pyr[0])
        return self._pyr

    def _cone_dirs(self, pos: np.ndarray, nrm: np.ndarray, wo: np.ndarray,
                   matid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, PEAK0 + P, 3) axes and (n, PEAK0 + P) tan(half-angle): the DIFFUSE_CONES diffuse
        cones, the reflection cone (its Phong lobe's half-angle, per material), one per peak lobe."""
        pax, plam = self._peaks[0], self._peaks[1]
        n = len(pos)
        dirs = np.zeros((n, PEAK0 + len(plam), 3))
        cones = np.zeros((n, DIFFUSE_CONES, 3))
        cone_frame(nrm, PATTERN, cones)
        dirs[:, :REFLECTION] = cones
        cn = np.einsum("ij,ij->i", nrm, wo)
        dirs[:, REFLECTION] = 2 * cn[:, None] * nrm - wo
        dirs[:, PEAK0:] = pax[None]
        tan = np.empty((n, PEAK0 + len(plam)))
        tan[:, :REFLECTION] = math.tan(CONE_HALF)
        e = self.mats[np.asarray(matid, np.int64), 7]
        tan[:, REFLECTION] = np.tan(np.arccos(np.clip(1 - math.log(2) / np.maximum(e, 1.0), -1, 1)))
        tan[:, PEAK0:] = self._peak_half_tan()[None]
        return dirs, tan

    def _thin(self) -> np.ndarray:
        """(P,) bool: peaks narrower than THIN_PEAK_VOXELS across the whole grid (the sun: 0.4 deg),
        whose shadow is one ray along the axis; the broader ones get PEAK_RAYS lobe-distributed rays."""
        return np.asarray(2 * self.R * self._peak_half_tan() < THIN_PEAK_VOXELS, bool)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per object its bounding sphere: centres (K, 3), radii (K,)."""
        if self._bound_cache is None or self._bound_cache[0] != self._geometry:
            c = np.zeros((len(self.objects), 3))
            r = np.zeros(len(self.objects))
            for k in range(len(self.objects)):
                _, _, c[k], r[k] = self._object_bounds(k)
            self._bound_cache = (self._geometry, c, r)
        return self._bound_cache[1], self._bound_cache[2]

    def _needs_cone(self, pos: np.ndarray, dirs: np.ndarray, tan: np.ndarray,
                    owner: np.ndarray | None) -> np.ndarray:
        """(n, k) uint8: 1 where cone ``dirs[:, j]`` (half-angle ``atan(tan)``) from a point meets
        some object's bounding sphere, other than the planar object the point lies on (a plane
        cannot hide anything above it from its own points). The others are clear: not traced, and
        free of the voxels' self-occlusion."""
        need = np.zeros(tan.shape, bool)
        centres, radii = self._bounds()
        planes = self._planes()
        rect = self._rects()[1]
        half = np.arctan(tan)
        for j in range(len(self.objects)):
            if j in rect:   # not in the voxels (rect_clear)
                continue
            v = centres[j] - pos
            dist = np.linalg.norm(v, axis=1)
            inside = dist <= radii[j] * (1 + 1e-9)
            u = v / np.maximum(dist, 1e-300)[:, None]
            ang = np.arccos(np.clip(np.einsum("nkc,nc->nk", dirs, u), -1, 1))
            reach = np.arcsin(np.clip(radii[j] / np.maximum(dist, 1e-300), 0, 1))
            hit = inside[:, None] | (ang <= half + reach[:, None] + 1e-6)
            if owner is not None and planes[j] is not None:
                hit[owner == j] = False
            need |= hit
        return need.astype(np.uint8)

    def _trace(self, pos: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan: np.ndarray, first: int = 0,
               owner: np.ndarray | None = None, matid: np.ndarray | None = None) -> np.ndarray:
        """Transmittance of the cones ``dirs[:, j]`` (cone ``first + j`` of the layout: diffuse
        below REFLECTION, then the reflection cone, peaks from PEAK0) by the instance's visibility
        method; ``owner``: the object each point lies on, if known (its own plane is then no
        occluder); ``matid``: the points' materials, if known (a Lambert point's reflection cone
        is not traced: 1)."""
        if self.visibility == "voxels":
            pyr, offs = self._pyramid()
            out = np.empty(tan.shape)
            # the peaks' shadows are Embree rays, not cones: a lamp's cone (0.2-4 deg) marched
            # through the grid is a voxel-wide blur that over-occludes near surfaces (studio_small_03,
            # Lambert: 9.9% per vertex with peak cones, 4.0% with 8 rays per broad peak)
            peak = first + np.arange(tan.shape[1]) >= PEAK0
            cones = np.flatnonzero(~peak)
            if len(cones):
                sub = np.empty((len(pos), len(cones)))
                cd, ct = np.ascontiguousarray(dirs[:, cones]), np.ascontiguousarray(tan[:, cones])
                used = np.ones(ct.shape, np.uint8)
                if matid is not None and first + cones[-1] >= REFLECTION:   # the reflection cone: Phong only
                    used[self.mats[np.asarray(matid, np.int64), 0] != 1, REFLECTION - first] = 0
                need = self._needs_cone(pos, cd, ct, owner) & used
                trace_cones(np.ascontiguousarray(pos), np.ascontiguousarray(nrm), cd, ct, pyr, offs, self.R,
                            self.origin, self.vox, self.cone_start, self.cone_lift, self.cone_gain,
                            self.cone_footprint, need, sub)
                rects, _, robj = self._rects()
                if len(rects):
                    side = pos @ rects[:, :3].T - rects[:, 3]           # (n, Q): each point's side of each plane
                    rect_clear(np.ascontiguousarray(pos), cd, ct, np.ascontiguousarray(side), rects, robj,
                               np.full(len(pos), -1, np.int64) if owner is None else np.asarray(owner, np.int64),
                               RECT_G, RECT_COS, RECT_SIN, used, sub)
                out[:, cones] = sub
            thin = self._thin()
            for j in np.flatnonzero(peak):
                p = first + j - PEAK0
                if thin[p]:
                    out[:, j] = self._shadow_rays(pos, nrm, dirs[:, j])
                else:
                    out[:, j] = self._lobe_rays(pos, nrm, self._peaks[0][p], float(self._peaks[1][p]), PEAK_RAYS)
            return out
        return self._ray_visibility(pos, nrm, dirs, tan, first)

    def _lobe_rays(self, pos: np.ndarray, nrm: np.ndarray, axis: np.ndarray, lam: float, m: int) -> np.ndarray:
        """Visibility of one peak lobe from each point: ``m`` rays drawn from the lobe's own
        distribution (a stratified vMF inverse CDF, Fibonacci azimuths), each weighted by its cosine
        at the point; the fraction of that light that escapes."""
        from lightprobe.hostlink.relight.rays import occluded, scene_eps

        eps = scene_eps(self.scene)
        n = len(pos)
        g, phi = fibonacci(m)
        ct = np.clip(1 + np.log(g + (1 - g) * math.exp(-2 * min(lam, 700.0))) / max(lam, 1e-9), -1, 1)
        st = np.sqrt(1 - ct * ct)
        ax = np.asarray(axis, np.float64)
        t1 = np.cross(ax, [1.0, 0, 0] if abs(ax[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(ax, t1)
        d = ct[:, None] * ax + (st * np.cos(phi))[:, None] * t1 + (st * np.sin(phi))[:, None] * t2   # (m, 3)
        cos = nrm @ d.T
        up = cos > 0
        occ = np.ones((n, m), bool)
        vi, ri = np.nonzero(up)
        if len(vi):
            o = pos[vi] + eps * nrm[vi]
            es = self._occluders(o, d)
            occ[vi, ri] = False if es is None else occluded(es, o, d[ri])
        w = np.where(up, cos, 0.0)
        tot = w.sum(axis=1)
        return np.where(tot > 0, (w * ~occ).sum(axis=1) / np.where(tot > 0, tot, 1), 0.0)

    def _embree_scene(self, skip: frozenset[int] = frozenset()) -> Any:
        """The Embree scene of every object but ``skip`` (None when nothing is left), rebuilt
        after a deformation or move."""
        from lightprobe.hostlink.relight.rays import build_embree

        if self._embree is None or self._embree[0] != self._geometry:
            self._embree = (self._geometry, {})
        scenes = self._embree[1]
        if skip not in scenes:
            meshes = [(self.vertices[ob.base:ob.base + len(ob.rest)], ob.faces)
                      for k, ob in enumerate(self.objects) if k not in skip]
            scenes[skip] = build_embree(meshes) if meshes else None
        return scenes[skip]


    def _occluders(self, origins: np.ndarray, dirs: np.ndarray) -> Any:
        """The Embree scene for rays from ``origins`` along any of ``dirs``, without the planar
        objects none of them can reach (every origin on one side, every direction pointing away:
        a floor under a sun's shadow rays). None: nothing can occlude them."""
        skip = []
        for k, pl in enumerate(self._planes()):
            if pl is None or not len(origins):
                continue
            n, c = pl
            side = origins @ n - c
            away = dirs @ n
            if (side.min() > 0 and away.min() > 0) or (side.max() < 0 and away.max() < 0):
                skip.append(k)
        return self._embree_scene(frozenset(skip))

    def _shadow_rays(self, pos: np.ndarray, nrm: np.ndarray, d: np.ndarray) -> np.ndarray:
        """1 where the ray from each point along ``d`` escapes (and ``d`` is above its horizon), else 0."""
        from lightprobe.hostlink.relight.rays import occluded, scene_eps

        d = np.ascontiguousarray(np.broadcast_to(d, pos.shape))
        up = np.einsum("ij,ij->i", d, nrm) > 0
        out = np.zeros(len(pos))
        rows = np.flatnonzero(up)
        eps = scene_eps(self.scene)
        o = pos[rows] + eps * nrm[rows]
        es = self._occluders(o, d[rows])
        out[rows] = 1.0 if es is None else ~occluded(es, o, d[rows])
        return out

    def _ray_visibility(self, pos: np.ndarray, nrm: np.ndarray, dirs: np.ndarray, tan: np.ndarray,
                        first: int = 0) -> np.ndarray:
        from lightprobe.hostlink.relight.rays import occluded, scene_eps

        es = self._embree_scene()
        eps = scene_eps(self.scene)
        n, k = tan.shape
        out = np.empty((n, k))
        pax, plam = self._peaks[0], self._peaks[1]
        diffuse = [j for j in range(k) if first + j < REFLECTION]
        if diffuse:   # the residual's visibility, measured: one light-weighted fraction for all cones
            out[:, diffuse] = self._residual_ray_visibility(es, eps, pos, nrm)[:, None]
        for j in range(k):
            c = first + j
            if c >= PEAK0:
                out[:, j] = self._lobe_rays(pos, nrm, pax[c - PEAK0], float(plam[c - PEAK0]), RAYS_PER_PEAK)
            elif c == REFLECTION:   # the reflection cone: rays uniform within it
                m = RAYS_PER_CONE
                g, phi = fibonacci(m)
                ca = 1 / np.sqrt(1 + tan[:, j] ** 2)
                ct = np.clip(1 - g[None] * (1 - ca[:, None]), -1, 1)
                st = np.sqrt(1 - ct * ct)
                ax = dirs[:, j]
                t1 = np.cross(ax, np.where(np.abs(ax[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
                t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
                t2 = np.cross(ax, t1)
                d = (ct[..., None] * ax[:, None] + (st * np.cos(phi))[..., None] * t1[:, None]
                     + (st * np.sin(phi))[..., None] * t2[:, None])
                up = np.einsum("nmk,nk->nm", d, nrm) > 0
                occ = np.ones((n, m), bool)
                vi, ri = np.nonzero(up)
                occ[vi, ri] = occluded(es, pos[vi] + eps * nrm[vi], d[vi, ri])
                out[:, j] = (~occ).mean(axis=1)
        return out

    def _residual_ray_visibility(self, es: Any, eps: float, pos: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        """``V_res`` by rays: RESIDUAL_RAYS cosine-distributed rays over each point's
        hemisphere (a Fibonacci pattern, turned per point), each weighted by the residual's
        radiance along it; the fraction of that light that escapes. The cones' partition is the
        voxel method's approximation; with rays the residual's visibility needs none."""
        from lightprobe.hostlink.relight.rays import occluded

        n = len(pos)
        m = RESIDUAL_RAYS
        g, phi = fibonacci(m)
        ct = np.sqrt(1 - g)                       # cosine-weighted: pdf cos / pi
        st = np.sqrt(g)
        t1 = np.cross(nrm, np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(nrm, t1)
        turn = (np.arange(n) * 0.618034 % 1.0)[:, None] * 2 * math.pi   # decorrelate neighbours
        cp, sp = np.cos(phi[None] + turn), np.sin(phi[None] + turn)
        d = (ct[None, :, None] * nrm[:, None] + (st[None] * cp)[..., None] * t1[:, None]
             + (st[None] * sp)[..., None] * t2[:, None])
        L = self._tables.L if self._tables is not None else None
        w = np.ones((n, m)) if L is None else np.maximum(table_lookup(L, d.reshape(-1, 3)).reshape(n, m), 0.0)
        free = ~occluded(es, np.repeat(pos + eps * nrm, m, axis=0), d.reshape(-1, 3)).reshape(n, m)
        tot = w.sum(axis=1)
        return np.where(tot > 0, (w * free).sum(axis=1) / np.where(tot > 0, tot, 1), free.mean(axis=1))

    def _residual_weights(self, cones: np.ndarray, vis: np.ndarray) -> np.ndarray:
        """``V_res`` (n, 3): the cones' transmittances weighted by the light each carries now."""
        assert self._tables is not None
        out = np.empty((len(cones), 3))
        residual_visibility(np.ascontiguousarray(cones), np.ascontiguousarray(vis), self._tables.W, out)
        return out

    def _visibility_rows(self, matid: np.ndarray, pos: np.ndarray, nrm: np.ndarray, wo: np.ndarray,
                         owner: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(``V_res`` (n, 3), reflection cone (n,), peaks (n, P)) of points (on objects ``owner``)."""
        if self._tables is None:
            raise InputError("no lighting yet: call set_sg or set_equirect first", param="lights")
        dirs, tan = self._cone_dirs(pos, nrm, wo, matid)
        out = self._trace(pos, nrm, dirs, tan, owner=owner, matid=matid)
        return (self._residual_weights(dirs[:, :REFLECTION], out[:, :REFLECTION]), out[:, REFLECTION].copy(),
                out[:, PEAK0:].copy())

    def _peak_half_tan(self) -> np.ndarray:
        """tan of each peak cone's half-angle (paper eq. 5-6; 89 deg for lobes too broad for it)."""
        plam = self._peaks[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            ca = np.where(plam >= math.log(2) / 2, 1 + math.log(0.5) / np.maximum(plam, 1e-9), -1.0)
        return np.asarray(np.tan(np.minimum(np.arccos(np.clip(ca, -1, 1)), math.radians(89))))

    def _peak_visibility(self, pos: np.ndarray, nrm: np.ndarray,
                         which: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """(n, len(which)) visibility of peaks ``which`` (all by default) from each point, and the
        number of peak visibilities traced: a peak wholly below a point's horizon is not traced
        there (it lights nothing: 0)."""
        pax = self._peaks[0]
        ids = np.arange(len(pax)) if which is None else np.asarray(which, np.int64)
        out = np.zeros((len(pos), len(ids)))
        tan = self._peak_half_tan()
        sin_half = tan / np.sqrt(1 + tan * tan)
        count = 0.0
        for j, p in enumerate(ids):
            rows = np.flatnonzero(nrm @ pax[p] > -sin_half[p])
            if len(rows):
                out[rows, j] = self._trace(pos[rows], nrm[rows], np.broadcast_to(pax[p], (len(rows), 1, 3)),
                                           np.full((len(rows), 1), tan[p]), first=PEAK0 + int(p))[:, 0]
            count += len(rows)
        return out, count
