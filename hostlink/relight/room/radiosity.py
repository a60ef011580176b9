"""Light on the room's patches: each spherical lamp's direct term (with its shadow rays, cached
per lamp), the patch-to-patch form factors and the radiosity solve of the indirect term."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lightprobe.hostlink.relight.room.io import Light
from lightprobe.hostlink.relight.room.item_buffer import mat_vec

__all__ = ["RadiosityMixin"]


class RadiosityMixin:
    """The direct and indirect light of :class:`.room.Room` (its patches, lamps and caches)."""

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

    def form_factors(self) -> np.ndarray:
        """(P, P) form factors from each patch centre to every patch: the exact unoccluded polygon
        form factor, zero when the ray between the centres is blocked."""
        if self._F is None:
            pc, pn = self.pc, self.pn
            P = len(pc)
            F = np.zeros((P, P), np.float32)
            for s in range(0, P, 256):
                rows = np.arange(s, min(P, s + 256))
                w = pc[None] - pc[rows, None]                    # (r, P, 3)
                d2 = np.einsum("rpk,rpk->rp", w, w)
                d = np.sqrt(np.maximum(d2, 1e-300))
                wd = w / d[..., None]
                ci = np.einsum("rpk,rk->rp", wd, pn[rows])
                cj = -np.einsum("rpk,pk->rp", wd, pn)
                ff = np.where((ci > 0) & (cj > 0), self._polygon_ff(rows), 0.0)
                ff[np.arange(len(rows)), rows] = 0.0
                ri, ci_ = np.nonzero(ff > 0)
                occ = self._occluded(pc[rows[ri]] + self.eps * pn[rows[ri]], wd[ri, ci_], d[ri, ci_] - 2 * self.eps)
                ff[ri[occ], ci_[occ]] = 0.0       # (4 rays per pair instead of 1: no better on the Cornell box)
                F[rows] = ff
            tot = F.sum(axis=1, keepdims=True)
            self._F = F / np.maximum(tot, 1.0)                    # energy: a patch sees at most its hemisphere
        return self._F

    def _polygon_ff(self, rows: np.ndarray) -> np.ndarray:
        """(r, P) unoccluded form factors from the centres of patches ``rows`` to every patch
        triangle, exact for a triangle above the receiver's horizon (Lambert's contour integral:
        ``1 / 2 pi sum_edges angle_i n . (R_i x R_i+1) / |R_i x R_i+1|``); near patches, where a
        point-to-point form factor fails, get their true share."""
        return self._polygon_ff_at(self.pc[rows], self.pn[rows])

    def _polygon_ff_at(self, x: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(r, P) unoccluded form factors from points ``x`` with normals ``n`` to every patch."""
        return np.abs(np.einsum("rpk,rk->rp", self._polygon_ff_vectors(x), n))

    def _polygon_ff_vectors(self, x: np.ndarray) -> np.ndarray:
        """(r, P, 3) Lambert's vectors ``g`` of every patch seen from points ``x``: the form factor
        to a receiver of normal ``n`` is ``|g . n|`` while the patch lies above its horizon
        (:func:`lightprobe.hostlink.relight.room.kernels.polygon_ff_vectors`)."""
        from lightprobe.hostlink.relight.room.kernels import polygon_ff_vectors

        out = np.empty((len(x), len(self.f), 3))
        polygon_ff_vectors(np.ascontiguousarray(x, np.float64), self._tri, out)
        return out

    def _solve(self, Ed_patch: np.ndarray, rho_patch: np.ndarray, known: np.ndarray | None = None,
               B_known: np.ndarray | None = None, iters: int = 40, F: np.ndarray | None = None) -> np.ndarray:
        """Patch radiance (P, 3) of ``B = rho / pi (E_d + pi F B)``, measured patches held fixed
        (``F``: the room's form factors unless given)."""
        F = self.form_factors() if F is None else F
        B = rho_patch / math.pi * Ed_patch
        if known is not None and B_known is not None:
            B[known] = B_known[known]
        for _ in range(iters):       # Jacobi; stops when a sweep changes B by under 1e-5 of its max
            nb = rho_patch / math.pi * (Ed_patch + math.pi * mat_vec(F, B))
            if known is not None and B_known is not None:
                nb[known] = B_known[known]
            done = float(np.abs(nb - B).max()) <= 1e-5 * max(float(np.abs(nb).max()), 1e-300)
            B = nb
            if done:
                break
        return B

    def _indirect(self, Ed_patch: np.ndarray, rho_patch: np.ndarray, known: np.ndarray | None = None,
                  B_known: np.ndarray | None = None) -> np.ndarray:
        """Indirect irradiance (pixels, 3) over each pixel's footprint: the room's radiosity under
        the patches' direct irradiance ``Ed_patch`` (:meth:`_solve`, measured patches held),
        gathered through the form factors."""
        Bp = self._solve(Ed_patch, rho_patch, known, B_known)
        return math.pi * self.fp.gather(mat_vec(self.form_factors(), Bp), self.patch)

    def _pixel_index(self) -> np.ndarray:
        """(H, W): each covered pixel's index into the per-pixel arrays, -1 elsewhere."""
        idx = np.full((self.cam.height, self.cam.width), -1)
        idx[self.cover] = np.arange(len(self.X))
        return idx

    # ---- recovery ------------------------------------------------------------------------------
    def _in_view_of_lights(self, lights: list[Light]) -> np.ndarray:
        """Pixels whose camera ray passes within a pixel and a half of a light sphere in front of
        the surface (its image, antialiased, covers neighbours too)."""
        C = self.cam.center
        ray = self.X - C
        dist = np.linalg.norm(ray, axis=1)
        rd = ray / dist[:, None]
        hit = np.zeros(len(self.X), bool)
        for L in lights:
            oc = np.asarray(L.position) - C
            tc = rd @ oc
            d2 = oc @ oc - tc * tc
            reach = 1.05 * L.radius + 1.5 * tc / self.cam.K[1, 1]   # a pixel and a half of margin
            hit |= (d2 < reach ** 2) & (tc > 0) & (tc < dist)
        return hit
