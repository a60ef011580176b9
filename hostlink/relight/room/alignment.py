"""Where the model is off: pixels snapped to the geometry that explains their captures, and the
model's objects moved sideways to where the captures put them (opt-in)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import luminance
from lightprobe.hostlink.relight.room.item_buffer import misfit, movable_groups
from lightprobe.hostlink.relight.room.settings import (
    ALIGN_BOUND,
    ALIGN_GAIN,
    ALIGN_STEP_GAIN,
    ALIGN_STEPS,
    ALIGN_WIDTH,
    SNAP_CAP,
    SNAP_GAIN,
    SNAP_MIN,
    SNAP_RADIUS,
)

__all__ = ["AlignmentMixin"]


class AlignmentMixin:
    """The snapping and object alignment of :class:`.room.Room`."""

    def _snap(self, B: list[np.ndarray], S: list[np.ndarray], U: list[np.ndarray]) -> np.ndarray:
        """Which pixel's geometry shades each pixel: itself, unless the model is off there.

        ``B``, ``S``, ``U``: per capture the measured radiance, the modelled irradiance (direct +
        indirect) and the usable pixels. A pixel's captures under lamps at several positions say
        which surface it shows: the measured radiance must be one reflectance times the
        modelled irradiance in every capture. Its misfit with the best reflectance (relative,
        squared) is taken for its own modelled irradiance and for each pixel's within
        ``SNAP_RADIUS``; where its own exceeds ``SNAP_MIN`` and a neighbour's is under
        ``SNAP_GAIN`` of it, the neighbour's geometry shades it, in the recovery and in every
        edit. That fixes a silhouette or an edge the approximate model puts a pixel or two off
        (the model shows the block where the photographs show the wall behind it)."""
        H, W = self.cam.height, self.cam.width
        n = len(self.X)
        idx = self._pixel_index()
        yy, xx = np.nonzero(self.cover)
        Bl = np.stack([luminance(b) for b in B])
        Sl = np.stack([luminance(x) for x in S])
        Uw = np.stack(U).astype(np.float64)
        b2 = (Uw * Bl * Bl).sum(axis=0)
        best_e = np.full(n, np.inf)
        best_j = np.arange(n)
        own_e = np.full(n, np.inf)
        for dy in range(-SNAP_RADIUS, SNAP_RADIUS + 1):
            for dx in range(-SNAP_RADIUS, SNAP_RADIUS + 1):
                y2, x2 = yy + dy, xx + dx
                ok = (y2 >= 0) & (y2 < H) & (x2 >= 0) & (x2 < W)
                j = np.full(n, -1)
                j[ok] = idx[y2[ok], x2[ok]]
                ok = j >= 0
                Sj = Sl[:, np.maximum(j, 0)]
                sbs = (Uw * Bl * Sj).sum(axis=0)
                sss = (Uw * Sj * Sj).sum(axis=0)
                e = np.where(ok, misfit(b2, sbs, sss, np.inf), np.inf)
                if dy == 0 and dx == 0:
                    own_e = e
                better = e < best_e
                best_e[better] = e[better]
                best_j[better] = j[better]
        switch = (own_e > SNAP_MIN) & (best_e < SNAP_GAIN * own_e)
        self.snapped = int(switch.sum())
        return np.where(switch, best_j, np.arange(n))

    def align(self, *, bound: float | None = None) -> dict[str, tuple[float, float, float]]:
        """Offsets that move the room's objects (:func:`movable_groups`) sideways, as the
        camera sees them, to where the captures put them; ``{}`` when nothing moves the
        captures' misfit below ``ALIGN_GAIN`` of the model's own (see the module notes).

        ``bound``: the largest move, default ``ALIGN_BOUND`` of the room's largest extent (the
        modelling error the paper allows). Every candidate is a room built with the offsets and
        scored by :meth:`_misfit_image` against the captures, with the indirect light of this
        model's recovery held fixed."""
        import cv2

        from lightprobe.core.imageio import read_hdr_image

        if not self.captures:
            raise InputError("captures/: no NAME.exr with NAME.json", param="captures")
        groups = movable_groups(self.model_vertices, self.model_faces, self.model_groups, self.group_names)
        if not groups:
            return {}
        size = float(np.ptp(self.model_vertices, axis=0).max())
        bound = ALIGN_BOUND * size if bound is None else float(bound)
        fwd = self.cam.R[2].astype(np.float64).copy()
        fwd[1] = 0.0
        if np.linalg.norm(fwd) < 1e-6:          # looking straight down or up: the camera's x axis
            fwd = np.cross(self.cam.R[0], [0.0, 1.0, 0.0])
        lat = np.cross([0.0, 1.0, 0.0], fwd)
        lat /= np.linalg.norm(lat)
        if self.reflectance is None:
            self.recover(snap=False)
        assert self.patch_reflectance is not None
        H, W = self.cam.height, self.cam.width
        # the candidates are scored on a camera at most ALIGN_WIDTH pixels wide (the indirect
        # light and the captures area-averaged to it): silhouettes move by whole pixels there too
        cam = self.cam.scaled(ALIGN_WIDTH / W) if W > ALIGN_WIDTH else self.cam
        size2 = (cam.width, cam.height)
        B, Ei = [], []
        for _name, p, lights in self.captures:
            b = luminance(np.asarray(read_hdr_image(p), np.float64))
            Ed_patch = np.sum([np.outer(self._geometry(L)[1], L.rgb) for L in lights], axis=0)
            e = np.zeros((H, W))
            e[self.cover] = luminance(self._indirect(Ed_patch, self.patch_reflectance))
            if cam is not self.cam:
                b = np.asarray(cv2.resize(b, size2, interpolation=cv2.INTER_AREA), np.float64)
                e = np.asarray(cv2.resize(e, size2, interpolation=cv2.INTER_AREA), np.float64)
            B.append(b)
            Ei.append(e)
        fine = bound / 96          # positions in units of the finest step, so candidates are found again

        def model(offs: dict[str, Any]) -> Any:  # the room, its objects placed otherwise
            return type(self)(self.directory, patch_size=self.patch_size, light_samples=self.light_samples,
                                offsets=offs, camera=cam)

        unmoved = model({})
        scored = unmoved.cover          # the pixels the model itself covers
        pos = dict.fromkeys(groups, 0)
        cache = {tuple(pos.values()): unmoved._misfit_image(B, Ei, scored)}

        def cost(pos: dict[str, int]) -> float:
            key = tuple(pos[g] for g in groups)
            if key not in cache:
                try:
                    cache[key] = model({g: tuple(lat * pos[g] * fine) for g in groups if pos[g]})._misfit_image(
                        B, Ei, scored)
                except InputError:      # a capture's lamp inside a moved object
                    cache[key] = math.inf
            return cache[key]

        # coordinate descent over each object's sideways offset, the step halving
        f0 = best = cost(pos)
        for frac in ALIGN_STEPS:
            k = max(1, round(frac * 96))
            moved = True
            while moved:
                moved = False
                for g in groups:
                    for sgn in (1, -1):
                        trial = dict(pos)
                        trial[g] += sgn * k
                        if abs(trial[g]) > 96:
                            continue
                        c = cost(trial)
                        if c < best - ALIGN_STEP_GAIN * f0:
                            pos, best, moved = trial, c, True
        self.align_misfit = (f0, best)
        if not best <= ALIGN_GAIN * f0:
            return {}
        return {g: (float(lat[0] * pos[g] * fine), float(lat[1] * pos[g] * fine), float(lat[2] * pos[g] * fine))
                for g in groups if pos[g]}

    def _misfit_image(self, B: list[np.ndarray], Ei: list[np.ndarray], scored: np.ndarray) -> float:
        """How badly this model explains the captures ``B`` (luminance images) with the indirect
        light ``Ei`` (images) held: per pixel of ``scored``, the relative squared misfit of the
        best reflectance over the captures (capped at ``SNAP_CAP``; a pixel the model no longer
        covers counts the cap), summed."""
        H, W = self.cam.height, self.cam.width
        b2 = np.zeros((H, W))
        sbs = np.zeros((H, W))
        sss = np.zeros((H, W))
        for (_name, _p, lights), b, ei in zip(self.captures, B, Ei, strict=True):
            s = ei.copy()
            s[self.cover] += luminance(np.sum([np.outer(self._geometry(L)[0], L.rgb) for L in lights], axis=0))
            u = np.ones((H, W), bool)
            u[self.cover] = ~self._in_view_of_lights(lights)
            b2 += np.where(u, b * b, 0.0)
            sbs += np.where(u, b * s, 0.0)
            sss += np.where(u, s * s, 0.0)
        e = np.where(self.cover, np.minimum(misfit(b2, sbs, sss, SNAP_CAP), SNAP_CAP), SNAP_CAP)
        return float(e[scored].sum())

