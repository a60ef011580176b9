"""Light on the room's patches: each spherical lamp's direct term (with its shadow rays, cached
per lamp), the patch-to-patch form factors and the radiosity solve of the indirect term."""

from __future__ import annotations

import math

import numpy as np

from lightprobe.hostlink.relight.room.io import Light
from lightprobe.hostlink.relight.room.item_buffer import mat_vec
from lightprobe.hostlink.relight.room.model import RoomModel

__all__ = ["RoomRadiosity"]


class RoomRadiosity(RoomModel):
    """The room's model with its indirect light: form factors and the radiosity solve (a step of
    :class:`.room.Room`)."""


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
