"""Where the model is off, its objects: moved sideways to where the captures put them (opt-in;
the pixels' own snapping is the recovery's, :mod:`.recovery`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import luminance
from lightprobe.hostlink.relight.room.item_buffer import movable_groups
from lightprobe.hostlink.relight.room.recovery import RoomRecovery
from lightprobe.hostlink.relight.room.settings import (
    ALIGN_BOUND,
    ALIGN_GAIN,
    ALIGN_STEP_GAIN,
    ALIGN_STEPS,
    ALIGN_WIDTH,
)

__all__ = ["RoomAlignment"]


class RoomAlignment(RoomRecovery):
    """Objects moved sideways to where the captures put them (a step of :class:`.room.Room`)."""


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


