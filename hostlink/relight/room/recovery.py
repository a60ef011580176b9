"""Reflectance from the captures (eq. 2, merged with the confidences of eq. 3), the paper's filters
and ours, and the per-pixel images a user inspects (reflectance, confidence)."""

from __future__ import annotations

import math
import warnings

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import luminance
from lightprobe.hostlink.relight.room.item_buffer import misfit, normalised_fill
from lightprobe.hostlink.relight.room.radiosity import RoomRadiosity
from lightprobe.hostlink.relight.room.settings import (
    DOUBT,
    INDIRECT,
    OUTLIER,
    SNAP_CAP,
    SNAP_GAIN,
    SNAP_MIN,
    SNAP_RADIUS,
)

__all__ = ["RoomRecovery"]


class RoomRecovery(RoomRadiosity):
    """The room's reflectance recovered from its captures, pixels snapped to the geometry that
    explains them (a step of :class:`.room.Room`)."""

    def recover(self, *, filters: bool = True, passes: int = 3, indirect: str = "radiosity",
                snap: bool = True) -> np.ndarray:
        """Reflectance (H, W, 3) (0 where the camera sees no geometry); sets ``reflectance``
        (pixels, 3), ``confidence`` (pixels,) and ``patch_reflectance``.

        ``indirect``: ``"radiosity"`` (the solve over the patches, measured ones held), or an
        ambient estimate in the spirit of the paper's first one, ``"ambient"``: the room around
        a pixel taken to be as bright as the capture's mean colour ``C`` over the room, so its
        indirect irradiance is ``pi C`` times the share of its hemisphere the room's geometry
        covers (its form factors' sum; one pass, nothing refined), or ``"none"`` (all light
        taken as direct: right only for a room with black walls). ``snap``: after the first
        pass, a pixel whose captures a neighbour's geometry explains far better is shaded with
        that geometry from then on (:meth:`_snap`, ``src``)."""
        from lightprobe.core.imageio import read_hdr_image

        if indirect not in INDIRECT:
            raise InputError(f"indirect must be one of {', '.join(INDIRECT)}, not {indirect!r}", param="indirect")
        if not self.captures:
            raise InputError("captures/: no NAME.exr with NAME.json", param="captures")
        if indirect != "radiosity":
            passes = 1
        cover_ff = self.fp.gather(self.form_factors().sum(axis=1).astype(np.float64), self.patch) if indirect == "ambient" else np.zeros(0)
        H, W = self.cam.height, self.cam.width
        shots = []
        for name, p, lights in self.captures:
            img = read_hdr_image(p)
            if img.shape[:2] != (H, W):
                raise InputError(f"{p}: {img.shape[1]} x {img.shape[0]} pixels, camera.json says {W} x {H}", param="captures")
            B = np.nan_to_num(np.asarray(img, np.float64)[self.cover], nan=0.0, posinf=0.0).clip(0, None)
            Ed_pix = np.sum([np.outer(self._geometry(L)[0], L.rgb) for L in lights], axis=0)
            Ed_patch = np.sum([np.outer(self._geometry(L)[1], L.rgb) for L in lights], axis=0)
            shots.append((name, B, Ed_pix, Ed_patch, ~self._in_view_of_lights(lights)))
        P = len(self.f)
        ng = len(self.group_names)
        rho_group = np.full((ng, 3), 0.5)
        cnt = np.bincount(self.patch, minlength=P)
        seen = cnt > 0
        rho = np.zeros((len(self.X), 3))
        conf = np.zeros(len(self.X))
        self.src = np.arange(len(self.X))
        self.snapped = 0
        for pas in range(passes):
            rho_patch = rho_group[self.fgroup]
            if self.patch_reflectance is not None:
                rho_patch = np.where(seen[:, None], self.patch_reflectance, rho_patch)
            est, wts, shade = [], [], []
            for _name, B, Ed_pix, Ed_patch, usable in shots:
                Bm = np.zeros((P, 3))
                for ch in range(3):
                    Bm[:, ch] = np.bincount(self.patch[usable], B[usable, ch], minlength=P)
                cu = np.bincount(self.patch[usable], minlength=P)
                known = cu > 0
                Bm[known] /= cu[known, None]
                if indirect == "radiosity":
                    Ei = self._indirect(Ed_patch, rho_patch, known, Bm)
                elif indirect == "ambient":
                    Ei = math.pi * np.outer(cover_ff, B[usable].mean(axis=0))
                else:
                    Ei = np.zeros_like(Ed_pix)
                shade.append(Ed_pix + Ei)
            if pas == 0 and snap:
                self.src = self._snap([sh[1] for sh in shots], shade, [sh[4] for sh in shots])
            for (_name, B, Ed_pix, _ed_patch, usable), den in zip(shots, shade, strict=True):
                den = den[self.src]
                Ed_pix = Ed_pix[self.src]
                with np.errstate(divide="ignore", invalid="ignore"):
                    rk = np.where(den > 1e-12, math.pi * B / den, 0.0)
                w = luminance(Ed_pix) / np.maximum(luminance(den), 1e-300)
                w = np.where(usable & (luminance(den) > 1e-12), w, 0.0)
                est.append(rk)
                wts.append(w)
            R = np.stack(est)                # (k, n, 3)
            Wt = np.stack(wts)               # (k, n)
            if filters:
                Wt = np.stack([self._filter_confidence(w) for w in Wt])
            if filters and len(R) >= 3:
                lr = np.where(Wt > 0, luminance(R), np.nan)
                n_ok = (Wt > 0).sum(axis=0)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)   # pixels no capture lights: NaN
                    lm = np.nanmedian(lr, axis=0)
                with np.errstate(invalid="ignore"):
                    dev = np.abs(luminance(R) - lm[None]) > OUTLIER * np.abs(lm[None])
                Wt = np.where(dev & (n_ok[None] >= 3), 0.0, Wt)       # the median needs 3 votes
            tot = Wt.sum(axis=0)
            rho = np.where(tot[:, None] > 0, (Wt[..., None] * R).sum(axis=0) / np.maximum(tot, 1e-300)[:, None], 0.0)
            conf = tot / len(R)
            if filters:
                rho = self._smooth(rho, conf)
                rho = self._refill_doubtful(rho, conf)
            rho_group = self._group_reflectance(rho, conf, rho_group)
            self._set_patch_reflectance(rho, conf, rho_group)
        self.reflectance, self.confidence = rho, conf
        return self._image(rho)

    def use_reflectance(self, reflectance: np.ndarray, confidence: np.ndarray,
                        source: np.ndarray | None = None) -> None:
        """Take a recovered reflectance (H, W, 3) and confidence (H, W) (``reflectance.exr``,
        ``confidence.exr`` of :meth:`recover`) instead of recovering again, and the pixel whose
        geometry shades each pixel (``source``: (H, W, >= 2) row and column, :meth:`source_image`,
        ``shading_source.exr``; default: each its own)."""
        H, W = self.cam.height, self.cam.width
        r, c = np.asarray(reflectance, np.float64), np.asarray(confidence, np.float64)
        if r.shape[:2] != (H, W) or c.shape[:2] != (H, W):
            raise InputError(f"reflectance and confidence must be {W} x {H} (camera.json), got "
                             f"{r.shape[1]} x {r.shape[0]}", param="reflectance")
        self.src = np.arange(len(self.X))
        if source is not None:
            sr = np.asarray(source, np.float64)
            if sr.shape[:2] != (H, W) or sr.ndim != 3 or sr.shape[2] < 2:
                raise InputError(f"shading source must be {W} x {H} x 2 (camera.json), got {sr.shape}",
                                 param="shading_source")
            idx = self._pixel_index()
            rc = np.rint(np.nan_to_num(sr[self.cover][:, :2], nan=-1.0)).astype(np.int64)
            ok = (rc[:, 0] >= 0) & (rc[:, 0] < H) & (rc[:, 1] >= 0) & (rc[:, 1] < W)
            j = np.full(len(self.X), -1)
            j[ok] = idx[rc[ok, 0], rc[ok, 1]]
            self.src = np.where(j >= 0, j, self.src)
        self.snapped = int((self.src != np.arange(len(self.X))).sum())
        rho = np.nan_to_num(r[self.cover][:, :3]).clip(0, None)
        conf = np.nan_to_num(c[self.cover] if c.ndim == 2 else c[self.cover][:, 0]).clip(0, None)
        rho_group = self._group_reflectance(rho, conf, np.full((len(self.group_names), 3), 0.5))
        self._set_patch_reflectance(rho, conf, rho_group)
        self.reflectance, self.confidence = rho, conf

    def _group_reflectance(self, rho: np.ndarray, conf: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """Each group's median reflectance over its trusted pixels (``prior`` where it has none):
        what the patches the camera does not see take."""
        out = prior.copy()
        for g in range(len(self.group_names)):
            sel = (self.group == g) & (conf > 0)
            if sel.any():
                out[g] = np.median(rho[sel], axis=0)
        return out

    def _set_patch_reflectance(self, rho: np.ndarray, conf: np.ndarray, rho_group: np.ndarray) -> None:
        P = len(self.f)
        pr = np.zeros((P, 3))
        cw = np.bincount(self.patch, conf, minlength=P)
        for ch in range(3):
            pr[:, ch] = np.bincount(self.patch, rho[:, ch] * conf, minlength=P)
        ok = cw > 0
        pr[ok] /= cw[ok, None]
        pr[~ok] = rho_group[self.fgroup[~ok]]
        self.patch_reflectance = pr

    def source_image(self) -> np.ndarray:
        """(H, W, 3) float32: row and column of the pixel whose geometry shades each pixel
        (:meth:`_snap`), then 0; -1 where the camera sees no geometry."""
        img = np.full((self.cam.height, self.cam.width, 3), -1.0, np.float32)
        yy, xx = np.nonzero(self.cover)
        img[self.cover] = np.stack([yy[self.src], xx[self.src], np.zeros(len(self.src))], axis=1)
        return img

    def confidence_image(self) -> np.ndarray:
        img = np.zeros((self.cam.height, self.cam.width), np.float32)
        if self.confidence is not None:
            img[self.cover] = self.confidence
        return img

    def _filter_confidence(self, w: np.ndarray) -> np.ndarray:
        """The paper's confidence filter: ``K = min(K, kappa)``, ``kappa`` the 5 x 5 mean of the
        5 x 5 minimum of ``K`` (over the pixels that see the room), so confidence falls off
        towards a shadow's or a surface's edge, where an approximate model is most likely wrong."""
        from numpy.lib.stride_tricks import sliding_window_view

        H, W = self.cam.height, self.cam.width
        img = np.full((H + 4, W + 4), np.inf)
        img[2:-2, 2:-2][self.cover] = w
        kmin = sliding_window_view(img, (5, 5)).min(axis=(2, 3))          # (H, W)
        val = np.where(np.isfinite(kmin) & self.cover, kmin, 0.0)
        cnt = np.zeros((H + 4, W + 4))
        acc = np.zeros((H + 4, W + 4))
        cnt[2:-2, 2:-2] = self.cover
        acc[2:-2, 2:-2] = val
        s_acc = sliding_window_view(acc, (5, 5)).sum(axis=(2, 3))
        s_cnt = sliding_window_view(cnt, (5, 5)).sum(axis=(2, 3))
        kappa = (s_acc / np.maximum(s_cnt, 1.0))[self.cover]
        return np.asarray(np.minimum(w, kappa))

    def _refill_doubtful(self, rho: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """Pixels whose confidence is under ``DOUBT`` of their surface's median (edges of an
        approximate model, what no capture lit) take the surface's confident reflectance around
        them (a normalised convolution), blended by confidence: ``(c rho + c_ref fill) / (c + c_ref)``."""
        H, W = self.cam.height, self.cam.width
        flat = np.flatnonzero(self.cover)
        out = rho.copy()
        for g in np.unique(self.group):
            sel = self.group == g
            cref = DOUBT * float(np.median(conf[sel]))
            if cref <= 0:
                continue
            low = sel & (conf < cref)
            src = sel & (conf >= cref)
            if not low.any() or not src.any():
                continue
            fill = normalised_fill((H, W), flat[src], rho[src], conf[src], flat[low], rho[low])
            c = conf[low, None]
            out[low] = (c * rho[low] + cref * fill) / (c + cref)
        return out

    def _smooth(self, rho: np.ndarray, conf: np.ndarray) -> np.ndarray:
        """3 x 3 confidence-weighted smoothing within each group (the paper's last filter)."""
        H, W = self.cam.height, self.cam.width
        img = np.zeros((H, W, 3))
        cf = np.zeros((H, W))
        gr = np.full((H, W), -1)
        img[self.cover], cf[self.cover], gr[self.cover] = rho, conf, self.group
        acc = np.zeros_like(img)
        wsum = np.zeros((H, W))
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                si = np.roll(np.roll(img, dy, 0), dx, 1)
                sc = np.roll(np.roll(cf, dy, 0), dx, 1)
                sg = np.roll(np.roll(gr, dy, 0), dx, 1)
                w = np.where(sg == gr, sc, 0.0)
                acc += w[..., None] * si
                wsum += w
        out = np.where(wsum[..., None] > 0, acc / np.maximum(wsum, 1e-300)[..., None], img)
        return np.asarray(out[self.cover])

    def _image(self, per_pixel: np.ndarray) -> np.ndarray:
        img = np.zeros((self.cam.height, self.cam.width, 3), np.float32)
        img[self.cover] = per_pixel
        return img

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
