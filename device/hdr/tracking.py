"""Moving lamps between the frames that measure them: a lamp's image carried at its measured velocity.

A long exposure sees a bright lamp only saturated: where the lamp is now, it gives a lower bound
far below the lamp, and where the lamp was, its halo often still saturates, so the rolling merge
cannot tell that those pixels went dark (:mod:`lightprobe.device.hdr.rolling`). Measured on the simulator's
flashlight (a 3-degree, 600:1 lamp at 40 degrees a second, one short exposure every other frame),
such frames published the lamp smeared over where the last short exposure saw it and where it is,
and the glossy error of those frames was 3-12% against 0.5-2.5% on the frames that measure it.

:class:`LampTracker` keeps, for each bright compact region of the fused map (a *lamp*: above
``relative`` of the map's brightest pixel, at most ``max_pixels``), its image above the local
background from the last frame that measured it (no saturated pixel in or next to it), its
luminance-weighted centre, and its velocity from the last two such frames (output pixels per
second between the middles of their exposures: a streaming sensor's frames end one frame time
apart, so a short exposure's middle is up to a frame time from a long one's, and frame counts
would draw a lamp up to half a frame's motion off). On a frame that sees the lamp's predicted
footprint mostly saturated (a *censored* frame)
and whose lamp moved, the image is drawn at the predicted place (bilinear, so the energy is kept):
the saturated pixels of the region become background plus the moved image; pixels this frame
measures keep their measured value. A static lamp (moved less than ``min_shift`` output pixels
since it was measured) is left to the merge, which holds it exactly; a lamp switched off leaves no
saturated footprint and is not drawn; a lamp switched on has no track yet.

The merge's own answer to a moving lamp (:func:`lightprobe.device.hdr.rolling._hold_moving` keeps back what
the pixels it left lost, :func:`lightprobe.device.hdr.rolling._place_held` puts that into the saturated
pixels nearby) is the fallback for lamps with no track. Where the tracker draws a lamp, whatever
the hold placed within ``move_reach`` of the lamp's old and new boxes is taken back first: the
image carries the lamp's whole energy, and the two together counted the moved part twice (on the
flashlight, +0.7-1.6% of the map's energy on long frames, diffuse error up to 1.94%).
Measured on the flashlight (160 frames, every frame against the truth at its time, 2026-12-06):
without the tracker diffuse max 1.19%, glossy p90 3.8%, max 11.6%; with it diffuse max 0.63%,
glossy median 0.86%, p90 1.89%, max 2.81%.

Only the ``max_lamps`` brightest compact regions that some exposure saturated within ``recent``
frames are tracked (a region every frame measures needs no tracking), so a frame costs one
compiled scan of the map, the labelling of the bright pixels' box and a compiled pass per lamp:
0.3-0.6 ms a frame on the 2-core VM (the switch scene, four tracked regions: 1.1 ms).

Columns wrap: the bright pixels are labelled in a frame cut where no bright region crosses (the
widest run of columns without one), and a lamp is measured and drawn modulo the width, so a lamp
crossing the map's 0 / 2 pi seam is one lamp (on the flashlight's crossing the merge alone gave
glossy 3.0-3.9% for six frames while the tracker could not follow it).

A lamp's energy is filtered across its measurements (:meth:`LampTracker._filter`): a lamp only
the shortest exposure measures is a handful of pixels with one frame's shot noise each, and the
merge's per-pixel averaging does not reach a lamp that moves a fraction of a pixel a frame (its
edge pixels change beyond their noise). Its energy does not change when it moves, so the
measurements that agree within ``k_sigma`` are averaged by inverse variance (the merge's
precision sums) and the published image is scaled to that, on the frames that measure the lamp
and on the ones that hold it. Daylight, 300 frames every frame against the truth: diffuse median
0.24 -> 0.12%, max 1.02 -> 0.71%; glossy max 3.12 -> 2.41%.

Limits: constant velocity between two measurements (one frame, 33 ms, apart in the live
schedule); a lamp slower than ``min_shift`` a frame (the daylight sun) is tracked but never drawn:
the merge holds it; a lamp over the top or bottom row of the map (the zenith) is left to the merge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numba
import numpy as np

from lightprobe.core.sphere import LUM_B, LUM_G, LUM_R, equirect_row_solid_angle, luminance

__all__ = ["LampTracker"]


@numba.njit(cache=True, nogil=True)
def _scan(f, sat, age, relative):  # type: ignore[no-untyped-def]
    """One frame's bookkeeping in one pass over the (rows, width) map: ``age`` (frames since
    each pixel was seen saturated, at most 255) updated in place; the brightest luminance; the
    rows ``[r0, r1)`` holding pixels above ``relative`` of it, and which columns hold any (from
    each row's and each column's brightest: the same as testing every pixel against the peak,
    without a second pass)."""
    rows, width = sat.shape
    peak = 0.0
    row_max = np.zeros(rows)
    col_max = np.zeros(width)
    for r in range(rows):
        rm = 0.0
        for c in range(width):
            a = age[r, c]
            age[r, c] = 0 if sat[r, c] else (a + 1 if a < 255 else 255)
            v = LUM_R * f[r, c, 0] + LUM_G * f[r, c, 1] + LUM_B * f[r, c, 2]
            if v > rm:
                rm = v
            if v > col_max[c]:
                col_max[c] = v
        row_max[r] = rm
        if rm > peak:
            peak = rm
    r0, r1 = rows, 0
    cols = np.zeros(width, np.bool_)
    if peak > 0:
        t = relative * peak
        for r in range(rows):
            if row_max[r] > t:
                r0 = min(r0, r)
                r1 = r + 1
        for c in range(width):
            cols[c] = col_max[c] > t
    return peak, r0, r1, cols


@numba.njit(cache=True, nogil=True)
def _box_mask(f, r0, r1, s, span, t):  # type: ignore[no-untyped-def]
    """uint8 mask of the pixels above luminance ``t`` in rows ``[r0, r1)`` and the ``span``
    columns from ``s`` on (wrapping at the seam)."""
    width = f.shape[1]
    out = np.zeros((r1 - r0, span), np.uint8)
    for r in range(r0, r1):
        for u in range(span):
            c = (s + u) % width
            if LUM_R * f[r, c, 0] + LUM_G * f[r, c, 1] + LUM_B * f[r, c, 2] > t:
                out[r - r0, u] = 1
    return out


@numba.njit(cache=True, nogil=True)
def _candidates(f, labels, stats, y0, s, g, rows, max_pixels, age, recent, max_lamps):  # type: ignore[no-untyped-def]
    """The components (rows of OpenCV's ``stats``: x, y, w, h, area, in the labelled box whose
    row 0 is map row ``y0`` and column 0 map column ``s``) that may be tracked lamps, brightest
    first, at most ``max_lamps``: at most ``max_pixels``, their box grown by ``g`` inside the
    map's rows, and some pixel of that box saturated within ``recent`` frames (one a frame
    measures every time needs no tracking)."""
    width = f.shape[1]
    n = stats.shape[0]
    peak = np.zeros(n)
    for r in range(labels.shape[0]):
        for u in range(labels.shape[1]):
            k = labels[r, u]
            if k > 0:
                c = (s + u) % width
                v = LUM_R * f[y0 + r, c, 0] + LUM_G * f[y0 + r, c, 1] + LUM_B * f[y0 + r, c, 2]
                if v > peak[k]:
                    peak[k] = v
    ok = np.zeros(n, np.bool_)
    for i in range(1, n):
        x, y, w, h, area = stats[i, 0], stats[i, 1] + y0, stats[i, 2], stats[i, 3], stats[i, 4]
        if area > max_pixels or y - g < 0 or y + h + g > rows or w + 2 * g > width:
            continue
        for r in range(y - g, y + h + g):
            for u in range(x - g, x + w + g):
                if age[r, (s + u) % width] <= recent:
                    ok[i] = True
                    break
            if ok[i]:
                break
    idx = np.flatnonzero(ok)
    order = np.argsort(-peak[idx])
    return idx[order[:max_lamps]]


@numba.njit(cache=True, nogil=True)
def _lamp_image(f, sat, labels, lab, y, c0, h, w, ly, lx, g):  # type: ignore[no-untyped-def]
    """One bright component (label ``lab`` of ``labels``, its box ``h x w`` at map row ``y``,
    column ``c0`` (any integer: columns wrap at the seam), and at ``(ly, lx)`` in ``labels``)
    measured in one pass over its box grown by ``g``: the footprint (the component grown by one
    pixel, 8-neighbours), the background (the per-channel median of the rest of the box) and the
    image above it, and the luminance-weighted centre (row, column in the same unwrapped frame
    as ``c0``). ``status``: 1 = saturated in or next to its footprint this frame (not
    measured), 2 = measured."""
    width = f.shape[1]
    bh, bw = h + 2 * g, w + 2 * g
    r0, b0 = y - g, c0 - g
    foot = np.zeros((bh, bw), np.bool_)
    img = np.zeros((bh, bw, 3), np.float32)
    base = np.zeros((bh, bw, 3), np.float32)
    centre = np.zeros(2)
    for i in range(h):
        for j in range(w):
            if labels[ly + i, lx + j] == lab:
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        foot[g + i + di, g + j + dj] = True
    n_ring = 0
    for i in range(bh):
        for j in range(bw):
            if foot[i, j]:
                for di in range(-1, 2):  # saturated in or next to the footprint
                    for dj in range(-1, 2):
                        ii, jj = i + di, j + dj
                        if 0 <= ii < bh and 0 <= jj < bw and sat[r0 + ii, (b0 + jj) % width]:
                            return 1, foot, img, base, centre
            else:
                n_ring += 1
    bg = np.zeros(3)
    if n_ring > 0:
        vals = np.empty(n_ring)
        for ch in range(3):
            k = 0
            for i in range(bh):
                for j in range(bw):
                    if not foot[i, j]:
                        vals[k] = f[r0 + i, (b0 + j) % width, ch]
                        k += 1
            bg[ch] = np.median(vals)
    tot = 0.0
    sr = 0.0
    sc = 0.0
    for i in range(bh):
        for j in range(bw):
            c = (b0 + j) % width
            for ch in range(3):
                v = np.float64(f[r0 + i, c, ch])
                if foot[i, j]:
                    base[i, j, ch] = bg[ch]
                    img[i, j, ch] = max(v - bg[ch], 0.0)
                else:
                    base[i, j, ch] = v
            wl = LUM_R * np.float64(img[i, j, 0]) + LUM_G * np.float64(img[i, j, 1]) + LUM_B * np.float64(img[i, j, 2])
            tot += wl
            sr += wl * (r0 + i)
            sc += wl * (b0 + j)
    if tot > 0:
        centre[0] = sr / tot
        centre[1] = sc / tot
    return 2, foot, img, base, centre


def _seam_offset(cols: np.ndarray) -> tuple[int, int]:
    """Where to cut the map's columns so that no bright region straddles the cut: the column
    after the widest run of columns without a bright pixel (circularly), and how many columns
    from there hold them all (the whole width if every column does)."""
    on = np.flatnonzero(cols)
    width = len(cols)
    if len(on) == 0:
        return 0, 0
    gaps = np.diff(np.concatenate([on, [on[0] + width]]))  # from each bright column to the next
    k = int(np.argmax(gaps))
    start = int(on[(k + 1) % len(on)])
    return start, width - int(gaps[k]) + 1


def _wrap_delta(d: np.ndarray, width: int) -> np.ndarray:
    """A (row, column) difference with the column taken the short way round."""
    out = np.array(d, np.float64)
    out[1] = (out[1] + width / 2) % width - width / 2
    return out


def _box(t: _Track, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The map rows and columns (modulo the width) of track ``t``'s image."""
    h, w = t.footprint.shape
    return np.arange(t.origin[0], t.origin[0] + h), np.arange(t.origin[1], t.origin[1] + w) % width


@dataclass
class _Track:
    frame: int              # the last frame that measured the lamp
    when: float             # that frame's time (``update``'s ``when``: the middle of its exposure)
    centre: np.ndarray      # (row, col) luminance-weighted, output pixels
    velocity: np.ndarray    # (row, col) output pixels per unit of ``when``
    origin: tuple[int, int]  # the image's top-left (row, col)
    image: np.ndarray       # (h, w, 3) radiance above the background
    background: np.ndarray  # (h, w, 3) the radiance around and under the lamp without it
    footprint: np.ndarray   # (h, w) bool: where the image is the lamp
    energy: float = 0.0     # the lamp's filtered energy (sum of image luminance x solid angle)
    precision: float = 0.0  # 1 / its variance (0: unknown, no filtering)
    scale: float = 1.0      # filtered / measured energy of its last measurement (the image holds it)


@dataclass
class LampTracker:
    """Tracks of the bright lamps of an (rows, width) output map (module docstring)."""

    width: int
    relative: float = 0.05   # a lamp pixel: above this share of the map's brightest
    max_pixels: int = 600    # larger bright regions are sky or windows, not lamps
    min_shift: float = 0.25  # output pixels: a lamp that moved less is left to the merge
    max_age: int = 4         # frames: a velocity from measurements further apart is not trusted
    margin: int = 3          # output pixels of background kept around a lamp's image
    recent: int = 8          # frames: only a region saturated this recently (in or near its box) is tracked
    max_lamps: int = 4       # the brightest this many such regions (a frame's cost stays bounded)
    energy_decay: float = 0.75  # a consistent measurement keeps this share of the energy's past precision
    # a measurement agrees with the filtered energy within this many sigma. The energy's variance
    # counts that neighbouring output pixels read the same fisheye pixels (``sharing`` of update:
    # x1.42-1.64 where the scenarios' lamps are). Measured |z| between consecutive measurements:
    # the flashlight median 0.73 (a Gaussian's: 0.67), the daylight sun (sub-pixel, one short
    # frame) 0.97, p99 3.4: 3 sigma reset that sun on 4.7% of its measurements; 4 keeps the
    # published lights as the former 5-sigma gate on independent pixels had them (same figures
    # to 4 digits on daylight, flashlight and switch)
    k_sigma: float = 4.0
    tracks: list[_Track] = field(default_factory=list)
    # frames since each pixel was last seen saturated (255: long ago)
    _sat_age: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.uint8), repr=False)
    _row_w: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # solid angle per row

    def update(self, frame: int, fused: np.ndarray, satnow: np.ndarray,
               placed: tuple[np.ndarray, np.ndarray] | None = None, reach: int = 0,
               precision: np.ndarray | None = None, sharing: np.ndarray | None = None,
               when: float | None = None) -> int:
        """Draw the moved lamps a censored frame cannot measure into ``fused`` (pixels, 3) in
        place, then measure the lamps this frame sees unsaturated. ``placed``: the pixels and
        amounts the merge's hold added this frame (``_place_held``); a drawn lamp takes back what
        was added within ``reach`` of it, since its image carries all its energy. ``precision``
        (pixels, 3): 1 / the variance of each fused value (the merge's sums); with it, a measured
        lamp's energy is filtered over its consistent measurements (:meth:`_filter`);
        ``sharing`` (pixels,): how much more a region's sum varies than its pixels' variances
        summed (:func:`lightprobe.device.projection.sample_sharing`; None: 1). ``when``: the
        middle of this frame's exposure on the sensor's clock (seconds), where the lamp is drawn
        and measured (None: the frame number, for frames equally spaced in time). Returns the
        lamps drawn."""
        when = float(frame) if when is None else float(when)
        rows = fused.shape[0] // self.width
        f = fused.reshape(rows, self.width, 3)
        sat = satnow.reshape(rows, self.width)
        if self._row_w.shape[0] != rows:  # the upper hemisphere of a (2 rows)-row map
            self._row_w = equirect_row_solid_angle(2 * rows)[:rows]
        dest, added = placed if placed is not None else (np.zeros(0, np.int64), np.zeros((0, 3), np.float32))
        if self._sat_age.shape != sat.shape:
            self._sat_age = np.full(sat.shape, 255, np.uint8)
        drawn = 0
        for t in self.tracks:
            if frame - t.frame > self.max_age or frame <= t.frame:
                continue
            shift = t.velocity * (when - t.when)
            if float(np.hypot(*shift)) < self.min_shift:
                self._rescale(t, f, sat)
                continue
            taken = self._draw(t, shift, f, sat, dest, added, reach)
            if taken is not None:
                drawn += 1
                dest, added = dest[~taken], added[~taken]  # taken back once
        prec = precision.reshape(rows, self.width, 3) if precision is not None else None
        share = sharing.reshape(rows, self.width) if sharing is not None else None
        self._measure(frame, when, f, sat, prec, share)
        return drawn

    # ---- the energy of a measured lamp ------------------------------------------------------
    def _filter(self, t: _Track, old: _Track | None, prec: np.ndarray | None, share: np.ndarray | None,
                f: np.ndarray) -> None:
        """Filter the energy of lamp ``t`` just measured (its image, background and footprint
        in ``t``) with its track's past: a lamp only the shortest exposure measures is a few
        pixels, each with the shot noise of one frame (the daylight sun: its energy moved +-0.5%
        of the map from one measurement to the next), and the per-pixel averaging of the merge
        does not reach it, since a lamp that moves a fraction of a pixel changes its edge
        pixels beyond their noise. Its energy does not change when it moves, so it is averaged
        here, by inverse variance with ``energy_decay`` on the past, while each measurement
        agrees with the filtered value within ``k_sigma``; a switch, a dimmer or a lamp that
        came closer resets it. The image is scaled to the filtered energy, in the published map
        (this frame) and in the track (drawn and held frames)."""
        rr, cc = _box(t, f.shape[1])
        wr = self._row_w[rr][:, None]
        e = float((luminance(t.image) * wr)[t.footprint].sum())
        if prec is None or e <= 0:
            return
        p = prec[rr][:, cc]
        with np.errstate(divide="ignore"):
            var_l = (LUM_R**2 / p[..., 0] + LUM_G**2 / p[..., 1] + LUM_B**2 / p[..., 2])
        var_l = var_l * (wr * wr)
        if share is not None:
            var_l *= share[rr][:, cc]
        var = float(var_l[t.footprint].sum())
        if not (0 < var < np.inf):
            return
        est, pr = e, 1.0 / var
        if old is not None and old.precision > 0 and (e - old.energy) ** 2 < self.k_sigma**2 * (var + 1.0 / old.precision):
            kp = self.energy_decay * old.precision
            est = (kp * old.energy + e / var) / (kp + 1.0 / var)
            pr = kp + 1.0 / var
        t.energy, t.precision, t.scale = est, pr, est / e
        if t.scale != 1.0:
            t.image *= np.float32(t.scale)
            box = f[rr][:, cc]
            box[t.footprint] = t.background[t.footprint] + t.image[t.footprint]
            f[np.ix_(rr, cc)] = box

    def _rescale(self, t: _Track, f: np.ndarray, sat: np.ndarray) -> None:
        """A static lamp on a frame that does not measure it: the merge holds its last
        measurement there; its excess over the background is scaled to the filtered energy."""
        if t.scale == 1.0:
            return
        if t.origin[0] < 0 or t.origin[0] + t.footprint.shape[0] > f.shape[0]:
            return
        rr, cc = _box(t, f.shape[1])
        lum = luminance(t.image)
        if lum[sat[np.ix_(rr, cc)] & t.footprint].sum() < 0.5 * lum[t.footprint].sum():
            return  # the frame measures most of its energy: its own value stands
        box = f[rr][:, cc]
        bg = t.background[t.footprint]
        box[t.footprint] = bg + (box[t.footprint] - bg) * np.float32(t.scale)
        f[np.ix_(rr, cc)] = box

    # ---- drawing --------------------------------------------------------------------------
    def _draw(self, t: _Track, shift: np.ndarray, f: np.ndarray, sat: np.ndarray, dest: np.ndarray,
              added: np.ndarray, reach: int) -> np.ndarray | None:
        """Draw ``t`` moved by ``shift`` if this frame sees its place saturated; returns which of
        the hold's placements (``dest``, ``added``) it took back, or None if it drew nothing."""
        rows, width = sat.shape
        h, w = t.footprint.shape
        dr, dc = int(np.floor(shift[0])), int(np.floor(shift[1]))
        fr, fc = float(shift[0] - dr), float(shift[1] - dc)
        # the moved image on a grid one pixel larger, top-left at origin + (dr, dc)
        m = np.array([[1.0, 0.0, fc], [0.0, 1.0, fr]], np.float32)
        img = cv2.warpAffine(np.ascontiguousarray(t.image, np.float32), m, (w + 1, h + 1),
                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        foot = cv2.warpAffine(t.footprint.astype(np.float32), m, (w + 1, h + 1), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0.5
        # rows as they are; columns in an unwrapped frame (the origin's column in [0, width)),
        # read and written modulo the width: a lamp crossing the seam is one lamp
        r0, c0 = t.origin[0] + dr, t.origin[1] + dc
        a0, b0 = min(t.origin[0], r0), min(t.origin[1], c0)
        a1, b1 = max(t.origin[0] + h, r0 + h + 1), max(t.origin[1] + w, c0 + w + 1)
        if a0 < 0 or a1 > rows or b1 - b0 > width:
            return None  # at the map's top or bottom: left to the merge
        cols = np.arange(b0, b1) % width
        sat_box = sat[a0:a1][:, cols]
        sat_new = sat_box[r0 - a0:r0 - a0 + h + 1, c0 - b0:c0 - b0 + w + 1]
        if not foot.any() or sat_new[foot].mean() < 0.5:
            return None  # the frame measures most of where the lamp should be (or it is gone)
        # what the merge's hold added near the lamp goes back: the image carries the lamp's energy
        pr, pc = dest // width, dest % width
        near = (pr >= a0 - reach) & (pr < a1 + reach) & ((pc - (b0 - reach)) % width < b1 - b0 + 2 * reach)
        if near.any():
            np.subtract.at(f.reshape(-1, 3), dest[near], added[near])
        # the region the lamp occupied then or now: its saturated pixels are redrawn
        region = f[a0:a1][:, cols]
        redraw = sat_box.copy()
        new = region.copy()  # saturated pixels beyond the measured box keep what the merge holds
        o0, o1 = t.origin[0] - a0, t.origin[1] - b0
        new[o0:o0 + h, o1:o1 + w] = t.background
        # the pixels this frame measures hold the lamp's rim as it is (their excess over the
        # background); the saturated ones get the rest of the lamp's energy, in the image's shape
        lamp = np.zeros(region.shape[:2], np.float32)
        lamp[r0 - a0:r0 - a0 + h + 1, c0 - b0:c0 - b0 + w + 1] = img.sum(axis=2)
        on = float(lamp[redraw].sum())
        excess = np.minimum(np.maximum(region.sum(axis=2) - new.sum(axis=2), 0.0), lamp)
        rim = float(excess[~redraw].sum())
        scale = max(float(lamp.sum()) - rim, 0.0) / on if on > 0 else 1.0
        new[r0 - a0:r0 - a0 + h + 1, c0 - b0:c0 - b0 + w + 1] += img * min(scale, 2.0)
        region[redraw] = new[redraw]
        f[a0:a1, cols] = region
        return near

    # ---- measuring ------------------------------------------------------------------------
    def _measure(self, frame: int, when: float, f: np.ndarray, sat: np.ndarray, prec: np.ndarray | None = None,
                 share: np.ndarray | None = None) -> None:
        rows, width = sat.shape
        peak, y0, y1, cols = _scan(f, sat, self._sat_age, float(self.relative))
        if not np.isfinite(peak) or peak <= 0 or y1 <= y0:
            self.tracks.clear()
            return
        # the components of the bright pixels' rows and columns only (a lamp's are few; labelling
        # the whole map cost 0.2 ms a frame), cut where no bright region crosses (not the seam)
        s0, span = _seam_offset(cols)
        sub = _box_mask(f, y0, y1, s0, span, self.relative * peak)
        _, labels_sub, stats, _ = cv2.connectedComponentsWithStats(sub, connectivity=8)
        kept: list[_Track] = []
        continued: set[int] = set()
        g = self.margin
        for i in _candidates(f, labels_sub, stats, y0, s0, g, rows, self.max_pixels, self._sat_age, self.recent,
                             self.max_lamps):
            x, y, w, h = (int(v) for v in stats[i, :4])
            status, foot, img, base, centre = _lamp_image(f, sat, labels_sub, i, y + y0, s0 + x, h, w, y, x, g)
            if status != 2 or not img.any():
                continue  # not measured by this frame (saturated in or next to it)
            centre[1] %= width
            old = self._match(when, centre, width)
            vel = np.zeros(2)
            if old is not None:
                continued.add(id(old))
                if 0 < frame - old.frame <= self.max_age and when > old.when:
                    vel = _wrap_delta(centre - old.centre, width) / (when - old.when)
            track = _Track(frame, when, centre, vel, (y + y0 - g, (s0 + x - g) % width), img, base, foot)
            if y + y0 - g >= 0 and y + y0 - g + foot.shape[0] <= rows:
                self._filter(track, old, prec, share, f)
            kept.append(track)
        # a track this frame did not measure (censored) stays until it is too old
        kept += [t for t in self.tracks if id(t) not in continued and frame - t.frame <= self.max_age]
        self.tracks = kept

    def _match(self, when: float, centre: np.ndarray, width: int) -> _Track | None:
        """The track whose predicted centre is nearest ``centre`` (columns wrap), within its reach."""
        best, dist = None, np.inf
        for t in self.tracks:
            dt = when - t.when
            d = float(np.hypot(*_wrap_delta(t.centre + t.velocity * dt - centre, width)))
            reach = 4.0 + 2.0 * float(np.hypot(*t.velocity)) * abs(dt)
            if d < reach and d < dist:
                best, dist = t, d
        return best

    def reset(self) -> None:
        self.tracks.clear()
        self._sat_age = np.zeros((0, 0), np.uint8)
