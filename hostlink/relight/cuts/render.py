"""Relighting at run time: per-vertex radiance from cuts, rasterised into an image from a camera.

Dynamic: lights (equirect map or light set), BRDFs (per-material rows, edited with
:meth:`Relighter.set_material`), the view, and the pose (rotation about the VCF centre, then
translation) of movable objects (:meth:`Relighter.move`).

Per vertex, ``B = B_static - B_occluded``: the static radiance from the SVC alone
(:func:`~lightprobe.hostlink.relight.cuts.kernels.shade_static`, recomputed only when the light, the vertex's
BRDF, the view (glossy vertices) or the vertex's own object's pose change) minus the light the
movable objects take away (:func:`~lightprobe.hostlink.relight.cuts.occlusion.occlusion`, recomputed only for
vertices within the outermost VCF sphere of an object that moved, before or after the move).
Vertices two objects can shadow at once use the counter-based product of all cuts
(:func:`~lightprobe.hostlink.relight.cuts.kernels.shade_dynamic`; translations only).

Rotated objects (see :mod:`lightprobe.hostlink.relight.cuts.occlusion` for the VCF lookup): their own vertices
are shaded in the object frame (precompute-pose normals, ``R^T w_o``) under the light rotated
into the object frame, so their self-shadowing (SVC) is exact under rotation; the static
geometry's shadows on them are those of the precompute pose (exact for a ground plane and
rotations about its normal). Shadows of other movable objects on a rotated object are not
computed, and with any rotation, vertices two objects shadow at once add the two occlusions
(exact where the shadows do not overlap).

Culling (Iwasaki et al. Sec. V-B): only vertices of triangles visible in the ID buffer of the
rasterised view are shaded by :meth:`Relighter.render`; per vertex, movable objects whose
bounding sphere is under the vertex's horizon plane, or beyond the outermost VCF sphere, are
skipped.
"""

from __future__ import annotations

import numpy as np

from lightprobe.core.lightset import LightSet
from lightprobe.hostlink.relight.cuts.directions import NDIR, node_directions, node_moments
from lightprobe.hostlink.relight.cuts.kernels import shade_dynamic, shade_static, svc_weights
from lightprobe.hostlink.relight.cuts.lighting import (
    LightTables,
    leaf_light_from_equirect,
    leaf_light_from_lightset,
    light_tables,
    rotated_light_tables,
)
from lightprobe.hostlink.relight.cuts.occlusion import occlusion, zero_runs
from lightprobe.hostlink.relight.cuts.precompute import Precomputed
from lightprobe.hostlink.relight.raster import (
    Raster,
    camera_basis,
    lookup_equirect,
    rasterize,
    resolve,
    tonemap,
    view_rays,
    visible_vertices,
)
from lightprobe.hostlink.relight.scene import Camera, Material, Scene, rotation_matrix

__all__ = ["Raster", "Relighter", "camera_basis", "rasterize", "tonemap",]


def _interleave(n: int) -> np.ndarray:
    """Permutation dealing vertices round-robin to the numba threads: neighbouring vertices cost
    alike (a glossy object's, or those near a moving occluder), and prange splits its range into
    one contiguous block per thread, so contiguous ids would leave one thread with the costly ones."""
    from numba import get_num_threads

    t = max(get_num_threads(), 1)
    return np.concatenate([np.arange(k, n, t) for k in range(t)]) if n else np.zeros(0, np.int64)


def _as_rotation(rotation: np.ndarray | None) -> np.ndarray:
    """3x3 rotation matrix from None (identity), XYZ Euler degrees (3,) or a matrix."""
    if rotation is None:
        return np.eye(3)
    r = np.asarray(rotation, np.float64)
    if r.shape == (3,):
        return rotation_matrix(r)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError("rotation must be 3 Euler angles (degrees) or a proper 3x3 rotation matrix")
    return r


class Relighter:
    """Run-time state: lights, materials, object poses; shades vertices and images."""

    def __init__(self, scene: Scene, pre: Precomputed, moment: bool = True) -> None:
        self.scene = scene
        self.moment = moment
        self.pre = pre
        names = list(scene.materials)
        self._mat_names = names
        self.mats = np.stack([scene.materials[n].row() for n in names])
        obj_mat = np.array([names.index(o.material) for o in scene.objects], np.int64)
        self.matid = obj_mat[pre.object_id]
        self.movable = [k for k, o in enumerate(scene.objects) if o.movable and k in pre.vcf]
        mindex = {k: i for i, k in enumerate(self.movable)}
        self.own = np.array([mindex.get(int(k), -1) for k in pre.object_id], np.int64)
        self.translation = np.zeros((len(scene.objects), 3))
        self.rotation = np.tile(np.eye(3), (len(scene.objects), 1, 1))
        self._ndir = node_directions()
        self._M, self._thr = node_moments()
        n = len(pre.vertices)
        self._stat = np.zeros((n, 3))          # static (SVC) radiance cache of render()
        self._occ = np.zeros((n, 3))           # occlusion by movable objects, cache of render()
        self._svalid = np.zeros(n, bool)
        self._ovalid = np.zeros(n, bool)
        self._eye: tuple[float, ...] | None = None
        self._cache_moment = moment
        self._rtabs: dict[int, tuple[bytes, LightTables, LightTables]] = {}
        self.set_leaf_light(np.zeros((NDIR, 3)))
        self._pack_vcf()

    def _pack_vcf(self) -> None:
        fs = [self.pre.vcf[k] for k in self.movable]
        K = max([len(f.radii) for f in fs], default=1)
        self._radii = np.zeros((len(fs), K))
        offs, hs, vs, pbase = [], [], [], []
        shift = npts = 0
        for i, f in enumerate(fs):
            self._radii[i] = np.pad(f.radii, (0, K - len(f.radii)), mode="edge")
            pbase.append(npts)
            offs.append(f.offsets[:-1] + shift)
            hs.append(f.heights)
            vs.append(f.values)
            shift += int(f.offsets[-1])
            npts += len(f.offsets) - 1
        offs.append(np.array([shift]))
        self._voffs = np.concatenate(offs).astype(np.int64)
        self._vh = np.concatenate(hs) if hs else np.zeros(1, np.uint8)
        self._vv = np.concatenate(vs) if vs else np.zeros(1, np.uint8)
        nz = max(int((self._vv == 0).sum()), 1)          # occluded runs, decoded once
        self._roffs = np.zeros(len(self._voffs), np.int64)
        rs, re = np.zeros(nz, np.int32), np.zeros(nz, np.int32)
        nr = zero_runs(self._voffs, self._vh, self._vv, self._roffs, rs, re)
        self._rs, self._re = rs[:nr].copy(), re[:nr].copy()
        self._pbase = np.array(pbase, np.int64)
        self._obj_r = np.array([f.radius for f in fs], np.float64)
        self._grid = np.array([f.grid for f in fs], np.int64)
        self._centers0 = np.array([f.center for f in fs], np.float64).reshape(-1, 3)

    # ---- dynamic state ------------------------------------------------------------------
    def set_leaf_light(self, leaf_light: np.ndarray) -> None:
        """New lighting (2^15, 3) leaf integrals: per-node table and prefix sums, computed once
        and shared by every vertex."""
        self._leaf = np.asarray(leaf_light, np.float64)
        self._tab = light_tables(self._leaf)
        self._rtabs.clear()
        self._svalid[:] = False
        self._ovalid[:] = False

    def set_equirect(self, img: np.ndarray) -> None:
        self.set_leaf_light(leaf_light_from_equirect(img))

    def set_lightset(self, ls: LightSet) -> None:
        self.set_leaf_light(leaf_light_from_lightset(ls))

    def set_material(self, name: str, material: Material) -> None:
        """Edit a BRDF at run time (no precomputation depends on it)."""
        k = self._mat_names.index(name)
        self.mats[k] = material.row()
        sel = self.matid == k
        self._svalid[sel] = False
        self._ovalid[sel] = False

    def move(self, name: str, translation: np.ndarray, rotation: np.ndarray | None = None) -> None:
        """Set a movable object's pose relative to its precompute pose: rotation about its VCF
        centre (None = none, XYZ Euler degrees, or a 3x3 matrix), then translation."""
        k = [o.name for o in self.scene.objects].index(name)
        if k not in self.movable:
            raise ValueError(f"object {name!r} is not movable")
        t = np.asarray(translation, float)
        r = _as_rotation(rotation)
        mi = self.movable.index(k)
        pos = self.positions()
        for c in (self._centers0[mi] + self.translation[k], self._centers0[mi] + t):
            near = np.einsum("ij,ij->i", pos - c, pos - c) < self._radii[mi, -1] ** 2
            self._ovalid[near] = False                 # VCF lookup changes (old or new pose)
        ownv = self.pre.object_id == k
        self._svalid[ownv] = False                     # own vertices: view direction / rotation
        self._ovalid[ownv] = False
        self.translation[k] = t
        self.rotation[k] = r

    @property
    def moved(self) -> bool:
        return bool(np.any(self.translation != 0)) or self._rotated()

    def _rotated(self) -> bool:
        return bool(np.any(self.rotation != np.eye(3)))

    def _centers(self) -> np.ndarray:
        return self._centers0 + self.translation[self.movable]

    def positions(self) -> np.ndarray:
        """(N, 3) vertex positions at the current poses."""
        pos = self.pre.vertices + self.translation[self.pre.object_id]
        for mi, k in enumerate(self.movable):
            if np.any(self.rotation[k] != np.eye(3)):
                sel = self.pre.object_id == k
                c = self._centers0[mi]
                pos[sel] = (self.pre.vertices[sel] - c) @ self.rotation[k].T + c + self.translation[k]
        return pos

    def normals(self) -> np.ndarray:
        """(N, 3) world normals at the current poses."""
        return np.einsum("nij,nj->ni", self.rotation[self.pre.object_id], self.pre.normals)

    def _rot_tables(self, k: int) -> tuple[LightTables, LightTables]:
        key = self.rotation[k].tobytes()
        hit = self._rtabs.get(k)
        if hit is None or hit[0] != key:
            hit = (key, *rotated_light_tables(self._leaf, self.rotation[k]))
            self._rtabs[k] = hit
        return hit[1], hit[2]

    # ---- shading ------------------------------------------------------------------------
    def _svc_weights(self) -> np.ndarray:
        """Per-SVC-node factors (light independent), recomputed when ``moment`` is toggled."""
        if getattr(self, "_sw_flag", None) is not self.moment:
            pre = self.pre
            self._sw = np.empty(len(pre.svc_values), np.float32)
            svc_weights(pre.normals, pre.svc_offsets, pre.svc_heights, pre.svc_values,
                        self._M, self._thr, self.moment, self._sw)
            self._sw_flag = self.moment
        return self._sw

    def _static(self, vidx: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """SVC-only radiance (n, 3) at ``vidx`` (load-balanced order, see :func:`_interleave`)."""
        order = _interleave(len(vidx))
        out = np.empty((len(vidx), 3))
        out[order] = self._static_impl(vidx[order], wo[order])
        return out

    def _occlusion(self, vidx: np.ndarray, wo: np.ndarray, pos: np.ndarray,
                   static: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Light taken away by movable objects (n, 3), and the pieces (or merged nodes) shaded."""
        order = _interleave(len(vidx))
        occ, nodes = self._occlusion_impl(vidx[order], wo[order], pos, static[order])
        o2, n2 = np.empty_like(occ), np.empty_like(nodes)
        o2[order] = occ
        n2[order] = nodes
        return o2, n2

    def _static_impl(self, vidx: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """SVC-only radiance; a rotated object's own vertices in its frame (rotated light)."""
        pre = self.pre
        out = np.zeros((len(vidx), 3))
        rot = [k for k in self.movable if np.any(self.rotation[k] != np.eye(3))]
        plain = ~np.isin(pre.object_id[vidx], rot)
        groups = [(plain, self._tab, wo)]
        for k in rot:
            sel = pre.object_id[vidx] == k
            groups.append((sel, self._rot_tables(k)[0], wo @ self.rotation[k]))
        for sel, tab, w in groups:
            if sel.any():
                res = np.zeros((int(sel.sum()), 3))
                shade_static(vidx[sel], pre.normals, np.ascontiguousarray(w[sel]), self.matid, self.mats,
                             pre.svc_offsets, pre.svc_heights, self._svc_weights(), tab.T, res)
                out[sel] = res
        return out

    def _occlusion_impl(self, vidx: np.ndarray, wo: np.ndarray, pos: np.ndarray,
                        static: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pre = self.pre
        rot = [mi for mi, k in enumerate(self.movable) if np.any(self.rotation[k] != np.eye(3))]
        rslot = np.full(len(self.movable), -1, np.int64)
        PQR = np.zeros((1, 1, 16))
        if rot:
            rslot[rot] = np.arange(len(rot))
            PQR = np.stack([self._rot_tables(self.movable[mi])[1].PQ for mi in rot])
        own = self.own
        rot_obj = [self.movable[mi] for mi in rot]
        sub = ~np.isin(pre.object_id[vidx], rot_obj)          # rotated receivers: not computed
        receivers = vidx[sub]
        occ = np.zeros((len(vidx), 3))
        nodes = np.zeros(len(vidx), np.int64)
        if not len(receivers):
            return occ, nodes
        wo_r = np.ascontiguousarray(wo[sub])
        res = np.zeros((len(receivers), 3))
        pieces = np.zeros(len(receivers), np.int64)
        multi = np.zeros(len(receivers), bool)
        occlusion(receivers, pos, pre.normals, wo_r, self.matid, self.mats, own,
                  pre.svc_offsets, pre.svc_heights, self._svc_weights(), self._centers(),
                  np.ascontiguousarray(self.rotation[self.movable]), rslot, self._obj_r, self._radii,
                  self._grid, self._pbase, self._roffs, self._rs, self._re, self._tab.PQ, PQR,
                  bool(rot), res, pieces, multi)
        if multi.any():                                # two or more shadowing objects: exact product
            mv = receivers[multi]
            full = np.zeros((len(mv), 3))
            cnt = np.zeros(len(mv), np.int64)
            shade_dynamic(mv, pos, pre.normals, np.ascontiguousarray(wo_r[multi]), self.matid, self.mats,
                          pre.svc_offsets, pre.svc_heights, pre.svc_values, self._ndir, self._tab.P,
                          self._tab.Q, self._M, self._thr, self.moment, own, self._centers(), self._obj_r,
                          self._radii, self._grid, self._pbase, self._voffs, self._vh, self._vv, full, cnt)
            res[multi] = static[sub][multi] - full
            pieces[multi] = cnt
        occ[sub] = res
        nodes[sub] = pieces
        return occ, nodes

    def vertex_radiance(self, eye: np.ndarray, vidx: np.ndarray | None = None,
                        use_vcf: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Outgoing radiance (n, 3) float64 towards ``eye`` at vertices ``vidx`` (all if None,
        sorted), and per vertex the number of occluded pieces shaded (VCF path) or the SVC size."""
        pre = self.pre
        vidx = np.arange(len(pre.vertices)) if vidx is None else np.asarray(vidx, np.int64)
        pos = self.positions()
        wo = self._wo(eye, pos, vidx)
        static = self._static(vidx, wo)
        if use_vcf and self.movable:
            occ, nodes = self._occlusion(vidx, wo, pos, static)
            return np.maximum(static - occ, 0.0), nodes
        return static, np.diff(pre.svc_offsets)[vidx]

    @staticmethod
    def _wo(eye: np.ndarray, pos: np.ndarray, vidx: np.ndarray) -> np.ndarray:
        wo = np.asarray(eye, float) - pos[vidx]
        return wo / np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)

    def _invalidate_view(self, eye: tuple[float, ...]) -> None:
        if self.moment != self._cache_moment:
            self._svalid[:] = False
            self._ovalid[:] = False
            self._cache_moment = self.moment
        if eye != self._eye:
            glossy = self.mats[self.matid, 0] != 0
            self._svalid[glossy] = False
            self._ovalid[glossy] = False
            self._eye = eye

    def render(self, cam: Camera | None = None, background: np.ndarray | None = None,
               raster: Raster | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Image (H, W, 3) float32 linear; background pixels show ``background`` (an equirect
        map, looked up along the view ray) or black. Returns (image, stats).

        Only vertices visible in the ID buffer are shaded, and of those only the stale parts: the
        static radiance after a light change, a BRDF edit (that material), a view change
        (non-Lambertian vertices) or a move of the vertex's own object; the occlusion after any
        of these or a move of an object whose VCF reaches the vertex."""
        cam = cam or self.scene.camera
        pos = self.positions()
        raster = raster or rasterize(cam, pos, self.pre.faces, rays=background is not None)
        eye = tuple(float(x) for x in cam.position)
        self._invalidate_view(eye)
        visible = visible_vertices(raster.tri, self.pre.faces, len(pos))   # ID-buffer culling
        need_s = visible[~self._svalid[visible]]
        if len(need_s):
            self._stat[need_s] = self._static(need_s, self._wo(np.asarray(eye), pos, need_s))
            self._svalid[need_s] = True
        need_o = visible[~self._ovalid[visible]] if self.movable else np.zeros(0, np.int64)
        nodes = np.zeros(0)
        if len(need_o):
            self._occ[need_o], nodes = self._occlusion(need_o, self._wo(np.asarray(eye), pos, need_o),
                                                       pos, self._stat[need_o])
            self._ovalid[need_o] = True
        rad = np.maximum(self._stat - self._occ, 0.0) if self.movable else self._stat
        img = np.zeros((*raster.tri.shape, 3), np.float32)
        resolve(raster.tri, raster.bary, self.pre.faces, rad, img)
        if background is not None:
            miss = raster.tri < 0
            rays = raster.rays if raster.rays is not None else view_rays(cam)
            img[miss] = lookup_equirect(background, rays[miss])
        return img, {"visible_vertices": float(len(visible)), "shaded_vertices": float(len(need_s)),
                     "occlusion_vertices": float(len(need_o)),
                     "mean_nodes": float(nodes.mean()) if len(nodes) else 0.0}


