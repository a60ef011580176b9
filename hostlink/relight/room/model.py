"""The room as the method models it (the state every step reads): room.obj's patches, the camera's
item buffer of them and each pixel's footprint, the lamps' direct light on patches and pixels
(each lamp's geometry term cached)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.room.io import CameraCV, Light, load_camera, load_lights
from lightprobe.hostlink.relight.room.item_buffer import (
    footprints,
    moved_groups,
    raster_cv,
    subdivide,
)

__all__ = ["RoomModel"]


class RoomModel:
    """A photographed room as the method models it: patches, the item buffer, each lamp's direct
    light (the first step of :class:`.room.Room`; its description is :mod:`.room`'s)."""

    def __init__(self, directory: str | Path, *, patch_size: float | None = None, light_samples: int = 16,
                 offsets: dict[str, Any] | None = None, camera: CameraCV | None = None) -> None:
        from lightprobe.hostlink.relight.rays import build_embree
        from lightprobe.hostlink.relight.scene import load_obj_groups

        d = Path(directory)
        if not d.is_dir():
            raise InputError(f"{d}: not a folder", param="room")
        mesh, fg, names = load_obj_groups(d / "room.obj")
        self.directory = d
        self.cam = load_camera(d / "camera.json") if camera is None else camera
        self.group_names = names
        self.model_vertices, self.model_faces, self.model_groups = mesh.vertices, mesh.faces, fg
        self.offsets = {str(k): tuple(float(x) for x in np.asarray(o, np.float64).reshape(3))
                        for k, o in (offsets or {}).items()}
        verts = moved_groups(mesh.vertices, mesh.faces, fg, names, self.offsets, d / "room.obj")
        diag = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        self.eps = 1e-4 * diag
        self.patch_size = float(patch_size or diag / 16)
        self.light_samples = int(light_samples)
        self.v, self.f, self.fgroup = subdivide(verts, mesh.faces, fg, self.patch_size)
        a, b, c = (self.v[self.f[:, k]] for k in range(3))
        cr = np.cross(b - a, c - a)
        self.area = 0.5 * np.linalg.norm(cr, axis=1)
        self.pn = cr / np.maximum(2 * self.area, 1e-300)[:, None]
        self.pc = (a + b + c) / 3
        self._es = build_embree([(self.v, self.f)])
        tri, bary = raster_cv(self.cam, self.v, self.f)
        self.cover = tri >= 0
        if not self.cover.any():
            raise InputError(f"{d / 'camera.json'}: the camera sees no geometry of room.obj", param="camera")
        self.patch = tri[self.cover]
        bw = bary[self.cover].astype(np.float64)
        fv = self.f[self.patch]
        self.X = np.einsum("pk,pkj->pj", bw, self.v[fv])
        n = self.pn[self.patch]
        flip = np.einsum("ij,ij->i", n, self.cam.center - self.X) < 0
        self.N = np.where(flip[:, None], -n, n)
        self.group = self.fgroup[self.patch]
        # patch normals face the camera side where the camera sees them; elsewhere the room's inside
        self._orient_patches()
        self.fp = footprints(self.cam, self.cover, self.X, self.N, self.group, self._es, np.arange(len(self.f)), self.pn)
        self.src = np.arange(len(self.X))       # the pixel whose geometry shades each pixel (:meth:`_snap`)
        self.snapped = 0                         # pixels shaded by another pixel's geometry
        self.align_misfit: tuple[float, float] | None = None   # (the model's, the aligned model's) (:meth:`align`)
        self.captures = []
        cap = d / "captures"
        files = sorted(cap.glob("*.exr")) if cap.is_dir() else []
        for p in files:
            lights = load_lights(p.with_suffix(".json"))
            for L in lights:
                self._check_light(L, p.with_suffix(".json"))
            self.captures.append((p.stem, p, lights))
        self._geo: dict[tuple[tuple[float, float, float], float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._F: np.ndarray | None = None
        self._pairs: tuple[np.ndarray, ...] | None = None   # (i, j) with F[i, j] > 0
        self._F_rows: np.ndarray | None = None
        self._last_B: tuple[tuple[Light, ...], np.ndarray] | None = None
        self._tri = np.ascontiguousarray(np.stack([self.v[self.f[:, k]] for k in range(3)], axis=1))   # (P, 3, 3)
        self._unit: dict[Light, np.ndarray] = {}
        self._unit_key: bytes | None = None
        self.reflectance: np.ndarray | None = None
        self.confidence: np.ndarray | None = None
        self.patch_reflectance: np.ndarray | None = None
        self.object_mask: np.ndarray | None = None     # pixels the last render's objects cover
        self.render_cover: np.ndarray = self.cover      # pixels the last render shaded

    # ---- geometry ------------------------------------------------------------------------------
    def _orient_patches(self) -> None:
        seen = np.zeros(len(self.f), bool)
        seen[self.patch] = True
        flip_seen = np.zeros(len(self.f), bool)
        np.logical_or.at(flip_seen, self.patch, np.einsum("ij,ij->i", self.pn[self.patch], self.N) < 0)
        self.pn[seen & flip_seen] *= -1
        # a patch the camera does not see faces the side from which more of the seen patches are
        # in view (a block's top and far sides face out, not into the block); a patch that sees
        # none from either side faces the room's centroid
        unseen = np.flatnonzero(~seen)
        if not len(unseen):
            return
        rng = np.random.default_rng(0)
        seen_idx = np.flatnonzero(seen)
        S = seen_idx if len(seen_idx) <= 128 else rng.choice(seen_idx, 128, replace=False)
        w = self.pc[S][None] - self.pc[unseen][:, None]                 # (u, s, 3)
        dist = np.linalg.norm(w, axis=2)
        wd = w / np.maximum(dist, 1e-300)[..., None]
        cu = np.einsum("usk,uk->us", wd, self.pn[unseen])
        facing = np.einsum("usk,sk->us", wd, self.pn[S]) < 0          # the seen patch's front faces it
        votes = np.zeros((len(unseen), 2))
        for side, sign in enumerate((1.0, -1.0)):
            ui, si = np.nonzero((sign * cu > 1e-3) & facing)
            o = self.pc[unseen[ui]] + sign * self.eps * self.pn[unseen[ui]]
            free = ~self._occluded(o, wd[ui, si], dist[ui, si] - 2 * self.eps)
            votes[:, side] = np.bincount(ui[free], minlength=len(unseen))
        centroid = self.v.mean(axis=0)
        inward = np.einsum("ij,ij->i", self.pn[unseen], centroid - self.pc[unseen]) < 0
        flip = np.where(votes.sum(axis=1) > 0, votes[:, 1] > votes[:, 0], inward)
        self.pn[unseen[flip]] *= -1

    def _check_light(self, L: Light, where: Path) -> None:
        c = np.asarray(L.position)
        # distance from the centre to every patch (point-triangle, via the closest of centre / vertices / plane)
        d_plane = np.abs(np.einsum("ij,ij->i", c - self.pc, self.pn))
        near = np.linalg.norm(self.pc - c, axis=1) < 2 * np.sqrt(self.area) + L.radius
        if (near & (d_plane < L.radius)).any():
            raise InputError(f"{where}: light at {list(L.position)} (radius {L.radius}) is inside a surface of room.obj",
                             param="lights")

    def _geometry(self, L: Light) -> tuple[np.ndarray, np.ndarray]:
        """Irradiance per watt of a light: (pixels,) over each pixel's footprint, (patches,), cached."""
        g = self._geometry_parts(L)
        return g[0], g[1]

    def _geometry_parts(self, L: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pixels, patches, pixel centres, edge pixels' samples) irradiance per watt, cached."""
        key = (L.position, L.radius)          # the power does not change the geometry
        g = self._geo.get(key)
        if g is None:
            gc = self._irradiance(L, self.X, self.N)
            gs = self._irradiance(L, self.fp.X, self.fp.N)
            g = (self.fp.pixels(gc, gs), self._irradiance(L, self.pc, self.pn), gc, gs)
            self._geo[key] = g
        return g

    def _irradiance(self, L: Light, P: np.ndarray, N: np.ndarray, es: Any = None) -> np.ndarray:
        """Irradiance per watt at points ``P`` with normals ``N``: a uniformly emitting sphere's
        field is its centre's, ``1 / (4 pi d^2)`` at distance d; the cosine and the visibility
        averaged over the points of the cap facing the receiver (of ``light_samples`` x 2
        Fibonacci points on the sphere), one shadow ray each (adaptively: the rest only where the
        first quarter disagree), so a sphere partly below a receiver's horizon or partly hidden
        lights it partly."""
        from lightprobe.hostlink.relight.room.kernels import sphere_light_rays

        m = self.light_samples
        k = np.arange(2 * m) + 0.5
        z = 1 - 2 * k / (2 * m)
        ph = k * math.pi * (3 - math.sqrt(5))
        u = np.stack([np.sqrt(1 - z * z) * np.cos(ph), z, np.sqrt(1 - z * z) * np.sin(ph)], 1)
        c = np.asarray(L.position, np.float64)
        S = c + L.radius * u
        P = np.ascontiguousarray(P, np.float64)
        N = np.ascontiguousarray(N, np.float64)
        dc = np.linalg.norm(c - P, axis=1)
        # adaptive (the paper's adaptive rays to an area light): every 4th point first; a receiver
        # whose first rays all agree (wholly lit or wholly hidden) takes that answer for the rest
        stages = (np.flatnonzero(np.arange(len(u)) % 4 == 0), np.flatnonzero(np.arange(len(u)) % 4 != 0))
        out = np.zeros(len(P))
        for s0 in range(0, len(P), 32768):
            Pc, Nc = P[s0:s0 + 32768], N[s0:s0 + 32768]
            n = len(Pc)
            free, cnt = np.zeros(n), np.zeros(n)
            n_free, n_ray = np.zeros(n, np.int64), np.zeros(n, np.int64)
            for stage, cols in enumerate(stages):
                m_ = len(cols)
                o, d, t = np.empty((n, m_, 3)), np.empty((n, m_, 3)), np.empty((n, m_))
                cos, st = np.zeros((n, m_)), np.empty((n, m_), np.uint8)
                sphere_light_rays(Pc, Nc, S, u, c, float(L.radius), float(self.eps), cols, o, d, t, cos, st)
                ray = st == 1
                occ = np.ones((n, m_), bool)
                if stage == 1:
                    uniform = (n_ray >= 2) & ((n_free == 0) | (n_free == n_ray))
                    guess = ray & uniform[:, None]
                    occ[guess] = np.broadcast_to((n_free == 0)[:, None], occ.shape)[guess]
                    ray &= ~uniform[:, None]
                ri, ki = np.nonzero(ray)
                occ[ri, ki] = self._occluded(o[ri, ki], d[ri, ki], t[ri, ki], es)
                if stage == 0:
                    n_ray += ray.sum(axis=1)
                    n_free += (ray & ~occ).sum(axis=1)
                counted = st > 0
                free += np.where(counted & ~occ, cos, 0.0).sum(axis=1)
                cnt += counted.sum(axis=1)
            out[s0:s0 + n] = np.where(cnt > 0, free / np.maximum(cnt, 1), 0.0)
        # cosine per sample (a sphere across the horizon lights the receiver partly), distance
        # to the centre (the sphere's field; distances to its surface points overstate it)
        return out / (4 * math.pi * np.maximum(dc, 1e-12) ** 2)

    def _occluded(self, o: np.ndarray, d: np.ndarray, tfar: np.ndarray, es: Any = None) -> np.ndarray:
        """Occlusion of the segments ``o + t d``, ``t < tfar`` (two threads: Embree releases the GIL)."""
        n = len(o)
        if not n:
            return np.zeros(0, bool)
        scene = es or self._es
        o32, d32 = np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)
        t32 = np.ascontiguousarray(np.maximum(tfar, 0), np.float32)

        def part(a: int, b: int) -> np.ndarray:
            return np.asarray(scene.run(o32[a:b], d32[a:b], dists=t32[a:b], query="OCCLUDED")) == 0

        if n < 16384:
            return part(0, n)
        from concurrent.futures import ThreadPoolExecutor

        h = n // 2
        with ThreadPoolExecutor(2) as ex:
            lo, hi = ex.submit(part, 0, h), ex.submit(part, h, n)
            return np.concatenate([lo.result(), hi.result()])
