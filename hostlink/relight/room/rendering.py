"""The room rendered under other lights: power changes, lamps added or removed, virtual objects
inserted or moved, real objects removed (their hidden surfaces refilled)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.room.io import Light, VirtualObject
from lightprobe.hostlink.relight.room.item_buffer import (
    clusters,
    footprints,
    mat_vec,
    near_segment,
    normalised_fill,
    raster_cv,
)
from lightprobe.hostlink.relight.room.recovery import RoomRecovery

__all__ = ["RoomRendering"]


class RoomRendering(RoomRecovery):
    """The recovered room under other lights, with virtual objects and removals (a step of
    :class:`.room.Room`)."""

    # ---- relighting ----------------------------------------------------------------------------
    def render(self, lights: list[Light], where: str | Path = "lights",
               objects: list[VirtualObject] | tuple[VirtualObject, ...] = (),
               remove: list[str] | tuple[str, ...] = ()) -> np.ndarray:
        """The room (H, W, 3) radiance under ``lights`` with the recovered reflectance, with
        ``objects`` inserted (their shadows on the room, their light on it and their own shading)
        or the room.obj groups ``remove`` taken out (what they hid refilled); ``where`` names the
        edit's file in errors (EDITS.json). Sets ``render_cover``: the pixels it shaded."""
        if self.reflectance is None or self.patch_reflectance is None:
            self.recover()
        if self.reflectance is None or self.patch_reflectance is None:
            raise InputError("no reflectance: recover() first", param="reflectance")
        for L in lights:
            self._check_light(L, Path(where))
        self.object_mask = None
        self.render_cover = self.cover
        if objects and remove:
            raise InputError(f"{where}: insert objects or remove groups, not both in one edit", param="remove")
        if remove:
            unknown = [n for n in remove if n not in self.group_names]
            if unknown:
                raise InputError(f"{where}: no group {unknown[0]!r} in room.obj (groups: "
                                 f"{', '.join(n for n in self.group_names if n != 'default')})", param="remove")
            return self._render_removed(lights, [self.group_names.index(n) for n in remove])
        if objects:
            img = self._render_with(lights, list(objects))
            assert self.object_mask is not None
            self.render_cover = self.cover | self.object_mask
            return img
        # light is linear: per light geometry (position, radius), the irradiance per watt of each
        # channel, direct + indirect through the radiosity solve, is cached; a power change is a sum
        key = self.patch_reflectance.tobytes()
        if self._unit_key != key:
            self._unit, self._unit_key = {}, key
        acc = np.zeros((len(self.X), 3))
        for L in lights:
            geo = Light(L.position, L.radius, (1.0, 1.0, 1.0))
            u = self._unit.get(geo)
            if u is None:
                gp, gq = self._geometry(geo)
                u = self._unit[geo] = gp[:, None] + self._indirect(np.repeat(gq[:, None], 3, axis=1),
                                                                    self.patch_reflectance)
            acc += u * np.asarray(L.rgb)
        return self._image(self.reflectance / math.pi * acc[self.src])

    def _render_with(self, lights: list[Light], objects: list[VirtualObject]) -> np.ndarray:
        """:meth:`render` with virtual objects (Loscos et al. 1999, section 5: a virtual object
        casts shadows on real surfaces and takes part in the light exchange). Only what the
        objects can change is recomputed (the paper's shaft idea, with the objects' bounding
        sphere as the shaft's end): a pixel's or patch's direct light from a lamp only where the
        segment to the lamp passes the sphere, a form factor only where the ray between patch
        centres does. The objects join the radiosity solve as clusters of their faces (a k^3
        grid times the six normal directions: :func:`clusters`): the room's patches see them
        (point-to-disc form factors, one visibility ray), they see the room (polygon form
        factors, one ray each); the objects' light on themselves is left out."""
        from lightprobe.hostlink.relight.rays import build_embree

        assert self.reflectance is not None
        assert self.patch_reflectance is not None
        ov = np.concatenate([o.vertices for o in objects])
        base = np.cumsum([0] + [len(o.vertices) for o in objects])
        of = np.concatenate([o.faces + base[k] for k, o in enumerate(objects)])
        falb = np.concatenate([np.repeat(np.asarray(o.albedo, np.float64)[None], len(o.faces), axis=0) for o in objects])
        if not (np.isfinite(ov).all() and len(of)):
            raise InputError("a virtual object has no faces or non-finite vertices", param="objects")
        es = build_embree([(self.v, self.f), (ov, of)])
        c_o = (ov.min(axis=0) + ov.max(axis=0)) / 2
        r_o = float(np.linalg.norm(ov - c_o, axis=1).max())
        # the camera: which covered pixels now show an object (nearer than the room)
        tri_o, bary_o = raster_cv(self.cam, ov, of)
        H, W = self.cam.height, self.cam.width
        room_z = np.full((H, W), np.inf)
        room_z[self.cover] = (self.X @ self.cam.R.T + self.cam.t)[:, 2]
        hit = tri_o >= 0
        Xo_all = np.einsum("pk,pkj->pj", bary_o[hit].astype(np.float64), ov[of[tri_o[hit]]])
        zo = (Xo_all @ self.cam.R.T + self.cam.t)[:, 2]
        front = zo < room_z[hit] * (1 - 1e-6)
        obj_mask = np.zeros((H, W), bool)
        obj_mask.flat[np.flatnonzero(hit)[front]] = True
        t_obj = tri_o[obj_mask]
        Xo = np.einsum("pk,pkj->pj", bary_o[obj_mask].astype(np.float64), ov[of[t_obj]])
        a, b, c = (ov[of[:, j]] for j in range(3))
        fn = np.cross(b - a, c - a)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        No = fn[t_obj]
        No = np.where((np.einsum("ij,ij->i", No, self.cam.center - Xo) < 0)[:, None], -No, No)
        label, cc, cn, ca = clusters(ov, of)
        calb = np.stack([np.bincount(label, falb[:, j] * 1.0, minlength=len(cc)) for j in range(3)], 1) \
            / np.maximum(np.bincount(label, minlength=len(cc)), 1)[:, None]
        # direct light, each lamp: cached unoccluded-by-objects terms, re-traced inside the shaft
        P = len(self.f)
        Ed_pix = np.zeros((len(self.X), 3))
        Ed_patch = np.zeros((P, 3))
        Ed_c = np.zeros((len(cc), 3))
        Ed_o = np.zeros((len(Xo), 3))
        for L in lights:
            _, gq, gp, gs = self._geometry_parts(L)
            gp, gq, gs = gp.copy(), gq.copy(), gs.copy()
            lc, reach = np.asarray(L.position), r_o + L.radius
            sp = np.flatnonzero(near_segment(self.X, lc, c_o, reach))
            gp[sp] = self._irradiance(L, self.X[sp], self.N[sp], es)
            ss = np.flatnonzero(near_segment(self.fp.X, lc, c_o, reach))
            gs[ss] = self._irradiance(L, self.fp.X[ss], self.fp.N[ss], es)
            gp = self.fp.pixels(gp, gs)
            sq = np.flatnonzero(near_segment(self.pc, lc, c_o, reach))
            gq[sq] = self._irradiance(L, self.pc[sq], self.pn[sq], es)
            rgb = np.asarray(L.rgb)
            Ed_pix += np.outer(gp, rgb)
            Ed_patch += np.outer(gq, rgb)
            Ed_c += np.outer(self._irradiance(L, cc, cn, es), rgb)
            Ed_o += np.outer(self._irradiance(L, Xo, No, es), rgb)
        # form factors: the room's own, blocked where an object stands between patch centres
        from lightprobe.hostlink.relight.room.kernels import gather_room_light, near_pairs

        F = self.form_factors()
        if self._pairs is None:
            self._pairs = tuple(np.ascontiguousarray(x, np.int64) for x in np.nonzero(F > 0))
        ri, ci = self._pairs
        near = np.zeros(len(ri), np.bool_)
        near_pairs(self.pc, ri, ci, c_o, r_o, near)
        ri, ci = ri[near], ci[near]
        if len(ri):      # the blocked links, kept apart: F itself is not copied
            w = self.pc[ci] - self.pc[ri]
            dist = np.linalg.norm(w, axis=1)
            blocked = self._occluded(self.pc[ri] + self.eps * self.pn[ri], w / dist[:, None], dist - 2 * self.eps, es)
            ri, ci = ri[blocked], ci[blocked]
        cut = np.asarray(F[ri, ci], np.float64)
        # room patch -> cluster (a disc of the cluster's area) and cluster -> room patch (polygon)
        tgt = cc
        w = tgt[None] - self.pc[:, None]                                   # (P, Q, 3)
        d2 = np.einsum("pqk,pqk->pq", w, w)
        dist = np.sqrt(d2)
        wd = w / dist[..., None]
        cos_i = np.einsum("pqk,pk->pq", wd, self.pn)
        cos_j = -np.einsum("pqk,qk->pq", wd, cn)
        Frc = np.where((cos_i > 0) & (cos_j > 0), ca[None] * cos_i * cos_j / (math.pi * d2 + ca[None]), 0.0)
        pi_, qi = np.nonzero(Frc > 0)
        if len(pi_):
            occ = self._occluded(self.pc[pi_] + self.eps * self.pn[pi_], wd[pi_, qi], dist[pi_, qi] * (1 - 1e-3), es)
            Frc[pi_[occ], qi[occ]] = 0.0
        # each cluster's view of the room: Lambert's vector per patch (the form factor to any
        # normal, for the object's pixels) and one visibility ray per patch facing the cluster
        G = self._polygon_ff_vectors(tgt)                                   # (Q, P, 3)
        vis = cos_i.T > 0
        qj, pj = np.nonzero(vis)
        if len(qj):
            occ = self._occluded(tgt[qj], -wd[pj, qj], dist[pj, qj] * (1 - 1e-3), es)
            vis[qj[occ], pj[occ]] = False
        Fcr = np.where(vis & (cos_j.T > 0), np.maximum(np.einsum("qpk,qk->qp", G, cn), 0.0), 0.0)
        if self._F_rows is None:
            self._F_rows = F.sum(axis=1, dtype=np.float64)
        tot = self._F_rows - np.bincount(ri, cut, minlength=P) + Frc.sum(axis=1)   # a hemisphere at most
        scale = 1.0 / np.maximum(tot, 1.0)
        Frc *= scale[:, None]
        Fcr /= np.maximum(Fcr.sum(axis=1, keepdims=True), 1.0)
        Frc, Fcr = Frc.astype(np.float32), Fcr.astype(np.float32)

        def room_light(B: np.ndarray) -> np.ndarray:     # (F without the blocked links) @ B, scaled
            out = mat_vec(F, B)
            for ch in range(3):
                out[:, ch] -= np.bincount(ri, cut * B[ci, ch], minlength=P)
            return out * scale[:, None]

        # radiosity over the room's patches and the objects' clusters (Jacobi)
        rho = self.patch_reflectance
        Br = rho / math.pi * Ed_patch
        if self._last_B is not None and self._last_B[0] == tuple(lights):
            Br = self._last_B[1]          # the same lamps: start from the last frame's solution
        Bc = calb / math.pi * Ed_c
        for _ in range(60):
            nr = rho / math.pi * (Ed_patch + math.pi * (room_light(Br) + mat_vec(Frc, Bc)))
            nc = calb / math.pi * (Ed_c + math.pi * mat_vec(Fcr, Br))
            done = max(float(np.abs(nr - Br).max()), float(np.abs(nc - Bc).max())) <= \
                1e-5 * max(float(np.abs(nr).max()), float(np.abs(nc).max()), 1e-300)
            Br, Bc = nr, nc
            if done:
                break
        self._last_B = (tuple(lights), Br)
        E_pix = (Ed_pix + math.pi * self.fp.gather(room_light(Br) + mat_vec(Frc, Bc), self.patch))[self.src]
        img = self._image(self.reflectance / math.pi * E_pix)
        # the object's pixels: their own normals against their cluster's view of the room
        E_o = np.empty((len(No), 3))
        gather_room_light(np.ascontiguousarray(No), np.ascontiguousarray(label[t_obj], np.int64), G, vis,
                          np.ascontiguousarray(Br, np.float64), E_o)
        E_o = Ed_o + math.pi * E_o
        img[obj_mask] = (falb[t_obj] / math.pi * E_o).astype(np.float32)
        self.object_mask = obj_mask
        return img

    def _render_removed(self, lights: list[Light], gids: list[int]) -> np.ndarray:
        """:meth:`render` with the faces of groups ``gids`` taken out of the room (the paper's
        object removal). The camera sees what they hid: a surface the captures never showed
        there, so its reflectance is refilled from the same surface around it (a normalised
        convolution of that surface's confident pixels at the finest scale that reaches the
        hole: a smooth fill, not the paper's texture synthesis). Only what the removal changes is recomputed, with the
        removed faces' bounding sphere as the shaft's end: a lamp's light where its segment to a
        pixel or patch passes the sphere (their shadows go), the form factors of links passing
        it (those the removed faces blocked come back, exact polygon form factors and a ray)."""
        from lightprobe.hostlink.relight.rays import build_embree

        assert self.reflectance is not None
        assert self.patch_reflectance is not None
        keep = ~np.isin(self.fgroup, gids)
        kidx = np.flatnonzero(keep)
        gone = self.v[np.unique(self.f[~keep])]
        c_b = (gone.min(axis=0) + gone.max(axis=0)) / 2
        r_b = float(np.linalg.norm(gone - c_b, axis=1).max())
        es = build_embree([(self.v, self.f[keep])])
        # the camera's new view: pixels that show the same patch as before keep their reflectance
        tri, bary = raster_cv(self.cam, self.v, self.f[keep])
        cover = tri >= 0
        patch = kidx[tri[cover]]
        X = np.einsum("pk,pkj->pj", bary[cover].astype(np.float64), self.v[self.f[patch]])
        N = self.pn[patch]
        N = np.where((np.einsum("ij,ij->i", N, self.cam.center - X) < 0)[:, None], -N, N)
        H, W = self.cam.height, self.cam.width
        was = self._pixel_index()[cover]
        same = (was >= 0) & (self.patch[np.maximum(was, 0)] == patch)
        rho = np.zeros((len(patch), 3))
        rho[same] = self.reflectance[was[same]]
        revealed = ~same
        if revealed.any():
            conf = np.zeros(len(patch))
            conf[same] = self.confidence[was[same]] if self.confidence is not None else 1.0
            grp = self.fgroup[patch]
            flat = np.flatnonzero(cover)
            for g in np.unique(grp[revealed]):
                rows = revealed & (grp == g)
                src = same & (grp == g) & (conf > 0)
                if not src.any():      # a surface never seen at all: its group's reflectance
                    rho[rows] = self.patch_reflectance[patch[rows]]
                    continue
                rho[rows] = normalised_fill((H, W), flat[src], rho[src], conf[src], flat[rows],
                                             self.patch_reflectance[patch[rows]])
        # direct light: the cached terms, re-traced inside the shafts to the removed faces
        fp = footprints(self.cam, cover, X, N, self.fgroup[patch], es, kidx, self.pn)
        Ed_pix = np.zeros((len(patch), 3))
        Ed_patch = np.zeros((len(kidx), 3))
        for L in lights:
            _, gq, gc, _ = self._geometry_parts(L)
            g_pix = np.where(same, gc[np.maximum(was, 0)], 0.0)
            lc, reach = np.asarray(L.position), r_b + L.radius
            redo = np.flatnonzero(~same | near_segment(X, lc, c_b, reach))
            g_pix[redo] = self._irradiance(L, X[redo], N[redo], es)
            g_pix = fp.pixels(g_pix, self._irradiance(L, fp.X, fp.N, es))   # the new view's edges
            g_q = gq[kidx].copy()
            sq = np.flatnonzero(near_segment(self.pc[kidx], lc, c_b, reach))
            g_q[sq] = self._irradiance(L, self.pc[kidx[sq]], self.pn[kidx[sq]], es)
            Ed_pix += np.outer(g_pix, L.rgb)
            Ed_patch += np.outer(g_q, L.rgb)
        # form factors among the kept patches; links passing the removed faces' sphere redone
        F = self.form_factors()[np.ix_(kidx, kidx)].astype(np.float32)
        pc, pn = self.pc[kidx], self.pn[kidx]
        for s0 in range(0, len(kidx), 256):
            rows = np.arange(s0, min(len(kidx), s0 + 256))
            w = pc[None] - pc[rows, None]
            d = np.linalg.norm(w, axis=-1)
            t = np.clip(np.einsum("rpk,rk->rp", w, c_b - pc[rows]) / np.maximum(d * d, 1e-300), 0, 1)
            near = np.linalg.norm(pc[rows, None] + t[..., None] * w - c_b, axis=-1) <= r_b
            wd = w / np.maximum(d, 1e-300)[..., None]
            near &= (np.einsum("rpk,rk->rp", wd, pn[rows]) > 0) & (np.einsum("rpk,pk->rp", wd, pn) < 0)
            near[np.arange(len(rows)), rows] = False
            ri, ci = np.nonzero(near)
            if not len(ri):
                continue
            ff = self._polygon_ff_at(pc[rows], pn[rows])[:, kidx][ri, ci]
            occ = self._occluded(pc[rows[ri]] + self.eps * pn[rows[ri]], wd[ri, ci], d[ri, ci] - 2 * self.eps, es)
            F[rows[ri], ci] = np.where(occ, 0.0, ff)
        F /= np.maximum(F.sum(axis=1, dtype=np.float64), 1.0).astype(np.float32)[:, None]
        B = self._solve(Ed_patch, self.patch_reflectance[kidx], iters=60, F=F)
        Q = np.zeros((len(self.f), 3))
        Q[kidx] = mat_vec(F, B)
        E = Ed_pix + math.pi * fp.gather(Q, patch)
        # pixels that showed the same patch before keep the geometry that explained their captures
        # (:meth:`_snap`) where that pixel is still shown as before
        new_of_old = np.full(len(self.X), -1)
        new_of_old[was[same]] = np.flatnonzero(same)
        take = new_of_old[self.src[was[same]]]
        rows = np.flatnonzero(same)[take >= 0]
        E[rows] = E[take[take >= 0]]
        out = np.zeros((H, W, 3), np.float32)
        out[cover] = rho / math.pi * E
        self.render_cover = cover
        return out

    def true_groups(self) -> np.ndarray:
        """(H, W) group index per pixel, -1 where there is no geometry (for tests and tools)."""
        g = np.full((self.cam.height, self.cam.width), -1, np.int64)
        g[self.cover] = self.group
        return g
