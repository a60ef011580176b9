"""Relighting at run time: per-vertex radiance from cuts, rasterised into an image from a camera.

Dynamic: lights (equirect map or light set), BRDFs (per-material rows, edited with
:meth:`Relighter.set_material`), the view, and translations of movable objects. Rotations of
movable objects at run time are **not supported**: VCF cuts are stored over world-aligned
directions and a rotated lookup would need the cut re-expressed over the rotated direction tree;
rotate an object in the scene file instead (applied before precomputation).

Culling (Iwasaki et al. Sec. V-B): only vertices of triangles visible in the ID buffer of the
rasterised view are shaded; per vertex, movable objects whose bounding sphere is under the
vertex's horizon plane, or beyond the outermost VCF sphere, are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from device.sampling.base import LightSet
from hostlink.relight.directions import node_directions, node_moments
from hostlink.relight.kernels import shade_dynamic, shade_static, svc_weights
from hostlink.relight.lighting import (
    leaf_light_from_equirect,
    leaf_light_from_lightset,
    moment_prefix_sums,
    prefix_sums,
)
from hostlink.relight.precompute import Precomputed
from hostlink.relight.scene import Camera, Material, Scene

__all__ = ["Raster", "Relighter", "camera_basis", "rasterize", "tonemap"]


@dataclass
class Raster:
    tri: np.ndarray     # (H, W) int64 triangle id, -1 for background
    bary: np.ndarray    # (H, W, 3) float32 perspective-correct barycentrics
    rays: np.ndarray    # (H, W, 3) float32 view ray directions (world)


def camera_basis(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = np.asarray(cam.look_at, float) - np.asarray(cam.position, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, float))
    if np.linalg.norm(r) < 1e-9:
        r = np.cross(f, np.array([0.0, 0.0, 1.0]))
    r /= np.linalg.norm(r)
    return r, np.cross(r, f), f


@njit(cache=True)
def _raster(sx: np.ndarray, sy: np.ndarray, z: np.ndarray, faces: np.ndarray, W: int, H: int,
            tri: np.ndarray, bary: np.ndarray, depth: np.ndarray) -> None:
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        if z[a] <= 1e-6 or z[b] <= 1e-6 or z[c] <= 1e-6:     # near clipping: drop triangle
            continue
        x0 = max(int(np.floor(min(sx[a], sx[b], sx[c]))), 0)
        x1 = min(int(np.ceil(max(sx[a], sx[b], sx[c]))), W - 1)
        y0 = max(int(np.floor(min(sy[a], sy[b], sy[c]))), 0)
        y1 = min(int(np.ceil(max(sy[a], sy[b], sy[c]))), H - 1)
        den = (sy[b] - sy[c]) * (sx[a] - sx[c]) + (sx[c] - sx[b]) * (sy[a] - sy[c])
        if abs(den) < 1e-12:
            continue
        for py in range(y0, y1 + 1):
            for px in range(x0, x1 + 1):
                l0 = ((sy[b] - sy[c]) * (px - sx[c]) + (sx[c] - sx[b]) * (py - sy[c])) / den
                l1 = ((sy[c] - sy[a]) * (px - sx[c]) + (sx[a] - sx[c]) * (py - sy[c])) / den
                l2 = 1 - l0 - l1
                if l0 < 0 or l1 < 0 or l2 < 0:
                    continue
                iz = l0 / z[a] + l1 / z[b] + l2 / z[c]          # perspective-correct 1/z
                if iz <= depth[py, px]:
                    continue
                depth[py, px] = iz
                tri[py, px] = t
                bary[py, px, 0] = l0 / z[a] / iz
                bary[py, px, 1] = l1 / z[b] / iz
                bary[py, px, 2] = l2 / z[c] / iz


def rasterize(cam: Camera, vertices: np.ndarray, faces: np.ndarray) -> Raster:
    """ID buffer with z-buffer (pixel centres, vertical field of view ``cam.fov_deg``)."""
    W, H = int(cam.width), int(cam.height)
    r, u, f = camera_basis(cam)
    rel = vertices - np.asarray(cam.position, float)
    xc, yc, zc = rel @ r, rel @ u, rel @ f
    th = np.tan(np.radians(cam.fov_deg) / 2)
    aspect = W / H
    zsafe = np.where(zc > 1e-6, zc, 1e-6)
    sx = (xc / (zsafe * th * aspect) + 1) / 2 * W - 0.5
    sy = (1 - yc / (zsafe * th)) / 2 * H - 0.5
    tri = np.full((H, W), -1, np.int64)
    bary = np.zeros((H, W, 3), np.float32)
    _raster(sx, sy, zc, faces.astype(np.int64), W, H, tri, bary, np.zeros((H, W)))
    px = ((np.arange(W) + 0.5) / W * 2 - 1) * th * aspect
    py = (1 - (np.arange(H) + 0.5) / H * 2) * th
    rays = f[None, None] + px[None, :, None] * r[None, None] + py[:, None, None] * u[None, None]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    return Raster(tri, bary, rays.astype(np.float32))


def tonemap(img: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Linear HDR -> 8-bit BGR for cv2.imwrite: exposure puts the 99th luminance percentile
    (of ``mask`` pixels) at 0.9, then sRGB encoding. All-black input -> black image."""
    x = np.nan_to_num(np.asarray(img, np.float64), nan=0.0, posinf=0.0)
    y = x @ np.array([0.2126, 0.7152, 0.0722])
    sel = y[mask] if mask is not None and mask.any() else y.ravel()
    ref = float(np.percentile(sel, 99)) if sel.size else 0.0
    x = np.clip(x * (0.9 / ref if ref > 0 else 0.0), 0, 1)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (s[..., ::-1] * 255 + 0.5).astype(np.uint8)


class Relighter:
    """Run-time state: lights, materials, object translations; shades vertices and images."""

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
        self._ndir = node_directions()
        self._M, self._thr = node_moments()
        n = len(pre.vertices)
        self._rad = np.zeros((n, 3))            # per-vertex radiance cache of render()
        self._valid = np.zeros(n, bool)
        self._eye: tuple[float, ...] | None = None
        self._cache_moment = moment
        self.set_leaf_light(np.zeros((1 << 15, 3)))
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
        self._pbase = np.array(pbase, np.int64)
        self._obj_r = np.array([f.radius for f in fs], np.float64)
        self._grid = np.array([f.grid for f in fs], np.int64)
        self._centers0 = np.array([f.center for f in fs], np.float64).reshape(-1, 3)

    # ---- dynamic state ------------------------------------------------------------------
    def set_leaf_light(self, leaf_light: np.ndarray) -> None:
        self._P = prefix_sums(leaf_light)
        self._Q = moment_prefix_sums(leaf_light)
        self._valid[:] = False

    def set_equirect(self, img: np.ndarray) -> None:
        self.set_leaf_light(leaf_light_from_equirect(img))

    def set_lightset(self, ls: LightSet) -> None:
        self.set_leaf_light(leaf_light_from_lightset(ls))

    def set_material(self, name: str, material: Material) -> None:
        """Edit a BRDF at run time (no precomputation depends on it)."""
        k = self._mat_names.index(name)
        self.mats[k] = material.row()
        self._valid[self.matid == k] = False

    def move(self, name: str, translation: np.ndarray) -> None:
        """Translate a movable object (relative to its precompute pose)."""
        k = [o.name for o in self.scene.objects].index(name)
        if k not in self.movable:
            raise ValueError(f"object {name!r} is not movable")
        self.translation[k] = np.asarray(translation, float)
        self._valid[:] = False

    @property
    def moved(self) -> bool:
        return bool(np.any(self.translation != 0))

    def positions(self) -> np.ndarray:
        return self.pre.vertices + self.translation[self.pre.object_id]

    # ---- shading ------------------------------------------------------------------------
    def _svc_weights(self) -> np.ndarray:
        """Per-SVC-node factors (light independent), recomputed when ``moment`` is toggled."""
        if getattr(self, "_sw_flag", None) is not self.moment:
            pre = self.pre
            self._sw = np.empty(len(pre.svc_values))
            svc_weights(pre.normals, pre.svc_offsets, pre.svc_heights, pre.svc_values,
                        self._M, self._thr, self.moment, self._sw)
            self._sw_flag = self.moment
        return self._sw

    def vertex_radiance(self, eye: np.ndarray, vidx: np.ndarray | None = None,
                        use_vcf: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Outgoing radiance (n, 3) float64 towards ``eye`` at vertices ``vidx`` (all if None),
        and the number of non-zero merged nodes per vertex (VCF path; SVC size otherwise)."""
        pre = self.pre
        vidx = np.arange(len(pre.vertices)) if vidx is None else np.asarray(vidx, np.int64)
        pos = self.positions()
        wo = np.asarray(eye, float) - pos[vidx]
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        out = np.zeros((len(vidx), 3))
        if use_vcf and self.movable:
            centers = self._centers0 + self.translation[self.movable]
            nodes = np.zeros(len(vidx), np.int64)
            shade_dynamic(vidx, pos, pre.normals, wo, self.matid, self.mats, pre.svc_offsets,
                          pre.svc_heights, pre.svc_values, self._ndir, self._P, self._Q, self._M, self._thr,
                          self.moment, self.own,
                          centers, self._obj_r, self._radii, self._grid, self._pbase,
                          self._voffs, self._vh, self._vv, out, nodes)
            return out, nodes
        shade_static(vidx, pre.normals, wo, self.matid, self.mats, pre.svc_offsets,
                     pre.svc_heights, self._svc_weights(), self._ndir, self._P, self._Q, out)
        return out, np.diff(pre.svc_offsets)[vidx]

    def render(self, cam: Camera | None = None, background: np.ndarray | None = None,
               raster: Raster | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Image (H, W, 3) float32 linear; background pixels show ``background`` (an equirect
        map, looked up along the view ray) or black. Returns (image, stats).

        Only vertices visible in the ID buffer are shaded, and only those whose cached radiance
        is stale: a light change or a move re-shades all, a BRDF edit that material's vertices,
        a view change the non-Lambertian ones (Lambertian radiance does not depend on w_o)."""
        cam = cam or self.scene.camera
        raster = raster or rasterize(cam, self.positions(), self.pre.faces)
        eye = tuple(float(x) for x in cam.position)
        if self.moment != self._cache_moment:
            self._valid[:] = False
            self._cache_moment = self.moment
        if eye != self._eye:
            self._valid[self.mats[self.matid, 0] != 0] = False
            self._eye = eye
        hit = raster.tri >= 0
        tris = self.pre.faces[raster.tri[hit]]
        visible = np.unique(tris)                                   # ID-buffer culling
        need = visible[~self._valid[visible]]
        nodes = np.zeros(0)
        if len(need):
            self._rad[need], nodes = self.vertex_radiance(np.asarray(eye), need, use_vcf=bool(self.movable))
            self._valid[need] = True
        img = np.zeros((*raster.tri.shape, 3), np.float32)
        img[hit] = np.einsum("pk,pkc->pc", raster.bary[hit], self._rad[tris]).astype(np.float32)
        if background is not None:
            img[~hit] = _lookup_equirect(background, raster.rays[~hit])
        return img, {"visible_vertices": float(len(visible)), "shaded_vertices": float(len(need)),
                     "mean_nodes": float(nodes.mean()) if len(nodes) else 0.0}


def _lookup_equirect(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    from device.sphere import angles_from_directions

    theta, phi = angles_from_directions(d.astype(np.float64))
    h, w = img.shape[:2]
    r = np.clip((theta / np.pi * h).astype(int), 0, h - 1)
    c = np.clip((np.mod(phi, 2 * np.pi) / (2 * np.pi) * w).astype(int), 0, w - 1)
    return img[r, c, :3]
