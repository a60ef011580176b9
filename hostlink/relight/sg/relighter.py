"""Relighting with spherical Gaussians (Michiels, Put, Bekaert 2015): no precompute, so meshes may
move or deform every frame.

The lighting is the probe's SG lobes (:class:`lightprobe.core.sg.SGLighting`: ``GET /api/v1/sg``, or
fitted here from a map with :func:`lightprobe.device.formats.sgfit.fit_sg`): a few *peak* lobes (lamps,
the sun) and many *residual* lobes on fixed HEALPix grids. Outgoing radiance at a point with
normal ``n`` towards ``w_o`` (paper eq. 1-2, the BRDF as SGs, visibility by cones)::

    B = kd / pi [E_res(n) V_res + sum_p mu_p C_p(n . p_p) v_p]
      + ks (e + 2) / (2 pi) [(n . r) G_e(r) v_r + sum_p mu_p <G_p, S(r, e)> (n . q_p)+ v_p]

Choices the paper leaves open, and why:

- **Residual lobes through tables.** Per light change the residual lobes are summed into
  direction tables, each a closed-form integral of every lobe against one kernel: ``E_res``
  against the exact clamped cosine (a zonal function of ``a . p`` per lobe sharpness, integrated
  numerically once per sharpness, so an unshadowed Lambert point is exact up to the fit), and SG
  kernels (paper eq. 4's product in closed form) for the visibility weights and the Phong lobe.
  The residual grids are fixed, so each table is one matrix-vector product with a matrix cached
  by the lobes' axes and sharpness; the cost of a light change does not depend on the mesh.
- **Visibility of the residual: 20 cones** (the paper packs 7 circles; 7 wide cones left 8.6%
  per vertex on dikhololo_night even with exactly traced transmittances, BENCHMARKS.md): the
  cones' axes a cosine-distributed Fibonacci pattern about ``n``, so each stands for an equal
  share of the unshadowed irradiance, half-angle ``acos(1 - 1/20)`` (18 deg: twenty such caps
  hold the hemisphere's solid angle). Each cone is a visibility SG ``S_c`` (sharpness from the
  half-angle by paper eq. 5-6, ``ln 2 / (1 - cos alpha)``); the light arriving through cone
  ``c`` is the lighting filtered by ``S_c`` at its axis (one table), so ``V_res`` is the cones'
  transmittances weighted by the light each carries. Unoccluded points get ``V_res = 1`` exactly.
- **Peaks** (1-3 SGs per lamp): each with its own visibility ``v_p``, the cosine exact
  (``C_p``: the zonal clamped-cosine integral of that lobe), the Phong term by the closed-form
  product of the peak with the BRDF lobe, the cosine taken at the product's axis ``q_p``.
- **Phong as one SG** of sharpness ``e`` about the reflection ``r`` of ``w_o``, ``cos^e x ~
  exp(e (cos x - 1))``; the residual's Phong term takes the cosine at ``r`` and one cone about
  ``r`` of the lobe's half-angle (paper eq. 5-6: ``acos(1 - ln 2 / e)``). Blinn-Phong and Ward
  are not offered (their SG warps vary per point): :class:`SGRelighter` refuses them by name.
- **Visibility**, two ways. ``"voxels"`` (the paper's, for the residual and the reflection
  cone): the scene voxelised (every triangle's voxels, per object, re-voxelised only for objects
  that moved or deformed: dirty flags), per-axis occupancy mip pyramids, cones traced front to
  back (:func:`~lightprobe.hostlink.relight.sg.kernels.trace_cones`, a sample every 1.5 sampled cells), each
  sample's opacity raised to ``cone_gain`` = 0.8 (compositing samples as independent occluders
  over-occludes: a cone's samples through one opaque object are correlated). **Rectangles** (a
  floor, a wall, a table top: planar objects whose area is their bounding rectangle's) are no
  voxels: each cone's share of rays that meet one is counted exactly
  (:func:`~lightprobe.hostlink.relight.sg.kernels.rect_clear`, 32 rays per cone), since a one-voxel floor
  sampled by a wide cone lets 20-30% through (the cow's belly was lit through the floor). The
  grid holds the other objects only (1.25 x their longest side, so a 3 m floor does not coarsen
  a 1.7 m object's voxels) and is refitted, all re-voxelised, when one leaves it. The peaks'
  shadows are Embree rays even here, not cones: a lamp's cone (0.2-4 deg) marched through the
  grid is a voxel-wide blur that over-occludes near surfaces (9.9% per vertex on studio_small_03
  with peak cones, 4.0% with rays): one ray along the axis for a peak under 2 voxels across the
  grid (the sun), else ``PEAK_RAYS`` = 8 drawn from the lobe; in :meth:`SGRelighter.render` the
  hard ones per pixel, the soft ones per vertex of the visible triangles, interpolated.
  ``"rays"`` (the exact baseline): Embree rays, 16 per cone uniformly within it and 32 per peak
  drawn from the lobe's own distribution, cosine-weighted; the residual's visibility by 112
  cosine-distributed rays weighted by its radiance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sg import SGLighting
from lightprobe.hostlink.relight.scene import Camera
from lightprobe.hostlink.relight.sg.kernels import (
    interpolate,
    scatter_pixels,
    shade_points,
)
from lightprobe.hostlink.relight.sg.settings import (
    DIFFUSE_GRID,
    LAM_CONE,
    PEAK0,
    RADIANCE_GRID,
    REFLECTION,
    ZONAL_SAMPLES,
)
from lightprobe.hostlink.relight.sg.tables import Tables
from lightprobe.hostlink.relight.sg.visibility import SGVisibility

__all__ = ["SGRelighter"]


class SGRelighter(SGVisibility):
    """SG relighting of a :class:`~lightprobe.hostlink.relight.scene.Scene`: no precompute.

    ``visibility``: ``"voxels"`` (voxel cone tracing, ``voxels`` cells along the scene's longest
    side) or ``"rays"`` (Embree). Lights: :meth:`set_sg` / :meth:`set_equirect`. Geometry:
    :meth:`set_vertices` (deform an object: new vertex positions, same faces), :meth:`move`
    (rigid, relative to the loaded pose). Shading: :meth:`vertex_radiance`, :meth:`render`
    (per pixel)."""


    # ---- lighting ----------------------------------------------------------------------------
    def set_equirect(self, img: np.ndarray) -> None:
        """Fit SG lobes to an (H, 2H, 3) map (as the probe does) and use them."""
        from lightprobe.device.formats.sgfit import WORK_HEIGHT, fit_sg

        a = np.asarray(img, np.float32)
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
            raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {a.shape}", param="lights")
        h = a.shape[0]
        if h > WORK_HEIGHT and h % WORK_HEIGHT:
            import cv2

            h = max(WORK_HEIGHT, h // WORK_HEIGHT * WORK_HEIGHT)
            a = np.asarray(cv2.resize(a, (2 * h, h), interpolation=cv2.INTER_AREA), np.float32)
        self.set_sg(fit_sg(a))

    def set_sg(self, sg: SGLighting) -> None:
        """Use these lobes: residual lobes go into the direction tables, peaks stay lobes."""
        peak = np.array([k == "peak" for k in sg.kinds], bool)
        res = ~peak
        ax, lam, amp = sg.axes[res], sg.sharpness[res], sg.amplitude[res]
        c = self._cache
        Ng = [self._gloss_grid(e) for e in self._gloss]
        G = max(Ng)
        D = DIFFUSE_GRID
        a32 = amp.astype(np.float32)
        tabs = Tables(
            (c.matrix(ax, lam, "cos", 0.0, D) @ a32).reshape(6, D, D, 3),
            (c.matrix(ax, lam, "sg", LAM_CONE, D) @ a32).reshape(6, D, D, 3),
            np.zeros((len(self._gloss), 6, G, G, 3), np.float32))
        for s, (e, n) in enumerate(zip(self._gloss, Ng, strict=True)):
            t = (c.matrix(ax, lam, "sg", e, n) @ a32).reshape(6, n, n, 3)
            if n != G:
                import cv2

                t = np.stack([cv2.resize(t[f], (G, G), interpolation=cv2.INTER_LINEAR) for f in range(6)])
            tabs.G[s] = t
        if self.visibility == "rays":  # the residual's radiance, to weight each cone's rays by
            lum = amp @ np.array([0.2126, 0.7152, 0.0722])
            R = RADIANCE_GRID
            tabs.L = (c.matrix(ax, lam, "radiance", 0.0, R) @ lum.astype(np.float32)).reshape(6, R, R)
        self._tables = tabs
        pl = sg.sharpness[peak]
        pF = np.stack([c.zonal(float(x)) for x in pl]) if len(pl) else np.zeros((0, ZONAL_SAMPLES))
        self._peaks = (sg.axes[peak].copy(), pl.copy(), sg.amplitude[peak].copy(), pF)
        self.sg = sg
        self._lighting += 1

    @staticmethod
    def _gloss_grid(e: float) -> int:
        return 17 if e <= 32 else 33 if e <= 128 else 65   # cube-face texels: ~5.3, 2.7, 1.4 deg


    # ---- shading -----------------------------------------------------------------------------
    def shade(self, pos: np.ndarray, nrm: np.ndarray, matid: np.ndarray, eye: np.ndarray,
              vis: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Outgoing radiance (n, 3) at points ``pos`` with unit normals ``nrm`` and materials
        ``matid`` towards ``eye``; ``vis`` = (``V_res`` (n, 3), reflection cone (n,), peaks (n, P))
        from :meth:`_visibility_rows` (traced when ``None``)."""
        if self._tables is None:
            raise InputError("no lighting yet: call set_sg or set_equirect first", param="lights")
        wo = np.asarray(eye, np.float64) - pos
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        if vis is None:
            vis = self._visibility_rows(matid, pos, nrm, wo)
        vres, vspec, vpeak = vis
        t = self._tables
        pax, plam, pamp, pF = self._peaks
        out = np.zeros((len(pos), 3))
        shade_points(np.ascontiguousarray(nrm), wo, np.asarray(matid, np.int64), self.mats, self.gloss_slot,
                     t.E, t.G, pax, plam, pamp, pF, np.ascontiguousarray(vres), vspec, vpeak, out)
        return out


    def vertex_radiance(self, eye: np.ndarray, vidx: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) outgoing radiance of vertices ``vidx`` (all by default) towards ``eye``."""
        vidx = np.arange(len(self.vertices)) if vidx is None else np.asarray(vidx, np.int64)
        pos, nrm, matid = self.vertices[vidx], self._normals[vidx], self.matid[vidx]
        wo = np.asarray(eye, np.float64) - pos
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
        return self.shade(pos, nrm, matid, eye, self._visibility_rows(matid, pos, nrm, wo, self.owner[vidx]))


    @staticmethod
    def _at_pixels(f: dict[str, Any], at: np.ndarray) -> np.ndarray:
        """Per-vertex values (V, C) interpolated at the frame's covered pixels (P, C)."""
        out = np.empty((len(f["bary"]), at.shape[1]))
        interpolate(f["bary"], f["fv"], np.ascontiguousarray(at, np.float64), out)
        return out

    def render(self, cam: Camera | None = None, background: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, float]]:
        """Image (H, W, 3) float32 linear, shaded per pixel: position, normal and reflection per
        pixel, the peaks' cones traced from every covered pixel (their shadows are the sharp
        ones); the wide cones (7 diffuse, 30 deg, and the reflection cone) from the vertices of
        the visible triangles, interpolated (their visibility is smooth across a triangle).

        Cached between calls: the raster and the wide cones until the geometry or the camera
        changes, the peaks' cones until a peak's axis or sharpness changes; a light change whose
        peaks stay put costs the direction tables and the per-pixel shading only (with voxels; the
        rays weight the residual's visibility by its light, so with rays it re-traces the wide cones)."""
        from lightprobe.hostlink.relight.raster import (
            lookup_equirect,
            rasterize,
            view_rays,
            visible_vertices,
        )

        cam = cam or self.scene.camera
        # rays weight the residual's visibility by its light: with rays a light change re-traces too
        key = (self._geometry, tuple(np.asarray(cam.position, float)), tuple(np.asarray(cam.look_at, float)),
               tuple(np.asarray(cam.up, float)), float(cam.fov_deg), int(cam.width), int(cam.height),
               self._lighting if self.visibility == "rays" else 0)
        eye = np.asarray(cam.position, np.float64)
        f = self._frame
        traced = {"wide_cones": 0.0, "peak_cones": 0.0}
        if f is None or f["key"] != key:
            ras = rasterize(cam, self.vertices, self.faces, rays=False)
            cov = ras.tri >= 0
            tri = ras.tri[cov]
            b = ras.bary[cov].astype(np.float64)
            fv = self.faces[tri]
            fv = np.ascontiguousarray(fv, np.int64)
            pos, nrm = np.empty((len(b), 3)), np.empty((len(b), 3))
            interpolate(b, fv, self.vertices, pos)
            interpolate(b, fv, self._normals, nrm)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            matid = self.matid[fv[:, 0]]
            vis_v = visible_vertices(ras.tri, self.faces, len(self.vertices))
            vp, vn = self.vertices[vis_v], self._normals[vis_v]
            wo = eye - vp
            wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-12)
            dirs, tan = self._cone_dirs(vp, vn, wo, self.matid[vis_v])
            wide = np.zeros((len(self.vertices), PEAK0))
            wide[vis_v] = self._trace(vp, vn, dirs[:, :PEAK0], tan[:, :PEAK0], owner=self.owner[vis_v],
                                      matid=self.matid[vis_v])
            traced["wide_cones"] = float(PEAK0 * len(vis_v))
            f = self._frame = {"key": key, "cov": cov, "pos": pos, "nrm": nrm, "matid": matid,
                               "vis_v": vis_v, "fv": fv, "bary": b, "cones": dirs[:, :REFLECTION].copy(),
                               "vis_d": wide[vis_v, :REFLECTION].copy(),
                               "pix": np.flatnonzero(cov),
                               "peaks": None, "vpeak": None, "lighting": None, "vres": None}
            f["vspec"] = self._at_pixels(f, wide[:, REFLECTION:PEAK0])[:, 0]
        pax, plam = self._peaks[0], self._peaks[1]
        pkey = (pax.tobytes(), plam.tobytes())
        if f["peaks"] != pkey:
            # hard shadows per pixel; with voxels a broad peak's soft shadow (its rays) is traced
            # from the vertices of the visible triangles and interpolated, like the wide cones
            per_vertex = ~self._thin() if self.visibility == "voxels" else np.zeros(len(pax), bool)
            vpeak = np.zeros((len(f["pos"]), len(pax)))
            thin = np.flatnonzero(~per_vertex)
            vpeak[:, thin], n_pix = self._peak_visibility(f["pos"], f["nrm"], thin)
            broad = np.flatnonzero(per_vertex)
            n_vert = 0.0
            if len(broad):
                vv = f["vis_v"]
                at = np.zeros((len(self.vertices), len(broad)))
                at[vv], n_vert = self._peak_visibility(self.vertices[vv], self._normals[vv], broad)
                vpeak[:, broad] = self._at_pixels(f, at)
            f["vpeak"], f["peaks"] = vpeak, pkey
            traced["peak_cones"] = n_pix + n_vert
        if f["lighting"] != self._lighting:
            # the residual's visibility weighs each cone by the light it carries: per vertex of the
            # visible triangles (their cones), interpolated (the cones' transmittances are anyway)
            at = np.zeros((len(self.vertices), 3))
            vv = f["vis_v"]
            at[vv] = self._residual_weights(f["cones"], f["vis_d"])
            f["vres"], f["lighting"] = self._at_pixels(f, at), self._lighting
        rad = self.shade(f["pos"], f["nrm"], f["matid"], eye, (f["vres"], f["vspec"], f["vpeak"]))
        img = np.zeros((*f["cov"].shape, 3), np.float32)
        scatter_pixels(f["pix"], rad, img.reshape(-1, 3))
        if background is not None:
            rays = view_rays(cam)
            img[~f["cov"]] = lookup_equirect(background, rays[~f["cov"]])
        return img, {"pixels": float(f["cov"].sum()), **traced}
