"""Exposure bursts: adaptive bracketing (:class:`BracketPlanner`) and verified capture
(:func:`capture_burst`).

Bracketing. The planner works on *scene exposure rates*: ``s`` such that a pixel's normalised
linear exposure (fraction of full scale) is ``e = s t g`` for exposure ``t`` and gain ``g``. From the
previous fused frame (``FusionResult`` / radiance in fused units, divided by the response's value
at full scale, :func:`exposure_rates`) or from one frame's histogram (:func:`rates_from_frame`)
it takes the brightest significant level ``s_hi`` (the ``bright_pixels``-th largest
value, so one hot pixel does not count, or a brighter pixel that alone carries a share of the
scene's light and has bright neighbours, i.e. a small lamp) and the darkest significant level ``s_lo`` (the
``dark_percentile`` of the pixels in the image circle), then

    t_short = bright_target / (s_hi g)        the brightest region lands unsaturated
    t_long  = dark_target   / (s_lo g)        the darkest region lands above the noise floor

both clamped to the camera's range, and fills ``[t_short, t_long]`` with exposures ``ev_step``
stops apart (the step grows up to ``max_ev_step`` before ``max_exposures`` is exceeded; beyond that
the dark end gives way). A dim room then needs one exposure and a sunny window several. Pixels
saturated in every exposure of the previous burst only give a lower bound, so the planner
assumes them ``saturated_headroom`` x brighter, and no history means a metering sweep over the
camera's range. (Hasinoff et al., CVPR 2010, derive noise-optimal brackets; this is a simpler
greedy rule, checked against the simulator in tests/test_hdr_sim_accuracy.py.)

Capture. :func:`capture_burst` applies each exposure and keeps reading frames until one shows
it: with per-frame metadata, ``meta.exposure_s`` (and gain) within tolerance and
``exposure_verified``; without it, ``capabilities.control_latency_frames`` frames are skipped and
the frame's brightness must have stepped by the expected ratio from the previous exposure. Stale
frames are dropped; an exposure that does not land within ``max_frames`` frames or ``timeout``
seconds raises :class:`lightprobe.drivers.base.CaptureTimeout`.

Pipelining. A camera whose frames carry verified metadata (libcamera, the simulator) takes one
control request per frame, in order (a per-frame control queue): the burst requests exposure
``i`` just before reading frame ``i``, so exposure ``i`` lands on frame ``i + latency`` and an
``n``-exposure burst costs ``n + latency`` frames instead of ``n (latency + 1)`` (a 6-exposure
metering sweep at latency 2: 8 frames, not 18). Frames are matched to requests by their
metadata, so a lost or late request is simply requested again.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numba
import numpy as np

from lightprobe.core.calibration import FisheyeModel, Response
from lightprobe.drivers.base import Camera, CaptureTimeout, Controls, Frame

__all__ = [
    "BracketPlanner",
    "capture_burst",
    "exposure_rates",
    "field_of_view_mask",
    "frame_peak_rate",
    "order_exposures",
    "rates_from_frame",
]


def exposure_rates(radiance: np.ndarray, full_scale: float | np.ndarray = 1.0) -> np.ndarray:
    """Per-pixel scene exposure rate ``s`` (1/s) from fused radiance: max over channels of
    ``radiance / full_scale``, where ``full_scale`` is the response's value at saturation
    (``Response.inverse[-1]``; 1 for RAW). float64 (H, W); non-finite -> 0."""
    r = np.asarray(radiance, dtype=np.float64)
    fs = np.maximum(np.asarray(full_scale, dtype=np.float64), 1e-300)
    s = (r / fs).max(axis=-1) if r.ndim == 3 else r / fs
    return np.where(np.isfinite(s), np.maximum(s, 0.0), 0.0)


@numba.njit(cache=True, nogil=True)
def _channel_histograms(c3, levels):  # type: ignore[no-untyped-def]
    """(3, levels) counts of each code per channel of an (H, W, 3) frame, in one pass."""
    h = np.zeros((3, levels), np.int64)
    for y in range(c3.shape[0]):
        for x in range(c3.shape[1]):
            for c in range(3):
                h[c, c3[y, x, c]] += 1
    return h


@numba.njit(cache=True, nogil=True)
def _at_or_above(c3, thr):  # type: ignore[no-untyped-def]
    """Rows and columns (row-major, as ``np.nonzero``) of the pixels with some channel ``c`` at
    or above ``thr[c]``."""
    n = 0
    for y in range(c3.shape[0]):
        for x in range(c3.shape[1]):
            if c3[y, x, 0] >= thr[0] or c3[y, x, 1] >= thr[1] or c3[y, x, 2] >= thr[2]:
                n += 1
    ys = np.empty(n, np.intp)
    xs = np.empty(n, np.intp)
    k = 0
    for y in range(c3.shape[0]):
        for x in range(c3.shape[1]):
            if c3[y, x, 0] >= thr[0] or c3[y, x, 1] >= thr[1] or c3[y, x, 2] >= thr[2]:
                ys[k] = y
                xs[k] = x
                k += 1
    return ys, xs


def frame_peak_rate(codes: np.ndarray, lut: np.ndarray, full_scale: float, *, max_isolation: float = 16.0,
                    candidates: int = 16) -> tuple[float, bool]:
    """The brightest exposure rate (1/s) a frame's *sensor pixels* show, hot pixels aside, and
    whether that pixel is saturated (the rate then a lower bound).

    ``codes``: (H, W, 3) integer codes of one frame; ``lut[z, c]``: the frame's fusion LUT (value
    per unit exposure, saturation flag; :func:`lightprobe.device.hdr.fusion.packed_lut`). Of the
    ``candidates`` brightest pixels (by their brightest channel), the first that is clipped or
    not an isolated outlier (a neighbour at least 1/``max_isolation`` as bright: a glint or a
    hot pixel below full scale has none, a sun's or a lamp's optics spread it) gives its largest
    channel value over ``full_scale``. A clipped pixel counts alone too: one frame cannot tell a
    sun beyond the sensor's range from a stuck pixel, and the shorter exposure costs an
    exposure where a clipped sun costs its light. (0, False) when every candidate is isolated.

    The planner's map rates are output pixels, each the mean of the sensor pixels it covers, so
    a sun smaller than an output pixel reads several times dimmer there than on the sensor
    pixels that saturate: planned from the map alone, the shortest exposure drifts long enough
    to clip it, the clipped pixel flags its output pixel saturated, and the plan swings back."""
    c3 = np.asarray(codes)
    w = c3.shape[1]
    levels = lut.shape[0]
    # the candidates: pixels at or above, in some channel, the code that many pixels reach
    # (a histogram per channel and one comparison pass, compiled: no sort of the frame; 0.4 ms
    # a VGA frame against numpy's 4.5)
    hist = _channel_histograms(c3, levels)
    thr = np.empty(3, np.int64)
    for c in range(3):
        at_or_above = np.cumsum(hist[c, ::-1])
        k = int(np.searchsorted(at_or_above, candidates))
        thr[c] = levels - 1 - min(k, levels - 1)
    ys, xs = _at_or_above(c3, thr)
    if ys.size == 0:
        return 0.0, False
    top = c3[ys, xs].max(axis=1)
    order = np.argsort(top, kind="stable")[::-1][: 4 * candidates]
    idx = ys[order] * w + xs[order]
    value = lut[..., 0]
    for i in idx:
        y, x = divmod(int(i), w)
        patch = c3[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].astype(np.intp)
        lin = np.stack([value[patch[..., c], c] for c in range(3)], axis=-1).max(axis=-1)  # (ph, pw)
        cy, cx = y - max(y - 1, 0), x - max(x - 1, 0)
        v = float(lin[cy, cx])
        others = np.delete(lin.ravel(), cy * lin.shape[1] + cx)
        saturated = any(bool(lut[c3[y, x, c], c, 3] > 0) for c in range(3))
        if v <= 0 or (not saturated and (others.size == 0 or float(others.max()) * max_isolation < v)):
            continue  # dark, or an isolated outlier (a hot pixel's glint)
        return v / max(full_scale, 1e-300), saturated
    return 0.0, False


def rates_from_frame(frame: Frame, response: Response | None = None,
                     sat_frac: float = 0.985) -> tuple[np.ndarray, np.ndarray]:
    """Exposure rates (H, W) and the saturated mask of ONE frame, for planning from the previous
    frame when no fused HDR exists: ``s = E(z) / E_fs / (t g)`` with the response (RGB8; a
    gamma-2.2 curve if None) or the black/white levels (RAW). Saturated pixels are lower bounds."""
    d = np.asarray(frame.data)
    tg = max(frame.meta.exposure_s * frame.meta.gain, 1e-300)
    if frame.format.is_raw:
        span = max(frame.white_level - frame.black_level, 1.0)
        e = np.clip((d.astype(np.float64) - frame.black_level) / span, 0.0, None)
        sat = d >= frame.black_level + sat_frac * span
    else:
        levels = np.arange(256, dtype=np.float64) / 255.0
        inv = (np.repeat((levels**2.2)[:, None], 3, axis=1) if response is None
               else np.asarray(response.inverse, np.float64)[:256])
        inv = inv / np.maximum(inv[-1], 1e-300)
        idx = np.clip(d, 0, 255).astype(np.intp)
        e = np.stack([inv[idx[..., c], c] for c in range(3)], axis=-1)
        sat = d >= np.ceil(sat_frac * 255)
    return exposure_rates(e / tg), np.asarray(sat.any(axis=-1))


def field_of_view_mask(fisheye: FisheyeModel, margin_deg: float = 0.5) -> np.ndarray:
    """(H, W) bool: pixels whose centre sees inside the calibrated field of view (minus
    ``margin_deg``), i.e. the clean image circle without the housing ring and the black corners.
    Pixels outside would pull the planner's longest exposure to the camera's maximum."""
    w, h = fisheye.image_size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    K = fisheye.K
    my = (v - K[1, 2]) / K[1, 1]
    mx = (u - K[0, 2] - K[0, 1] * my) / K[0, 0]
    # Compare distorted radii: KB4's inverse is not unique far outside the circle (corners)
    theta_max = np.radians(max(fisheye.fov_deg / 2 - margin_deg, 0.0))
    return np.asarray(np.hypot(mx, my) <= float(fisheye.distort_theta(np.asarray(theta_max))))


@dataclass
class BracketPlanner:
    """Chooses the exposures the scene needs (see the module docstring).

    ``exposure_range`` is the camera's (seconds); ``gain`` the gain the burst will use.
    """

    exposure_range: tuple[float, float]
    max_exposures: int = 8
    ev_step: float = 2.0
    max_ev_step: float = 3.0
    gain: float = 1.0
    bright_target: float = 0.8
    dark_target: float = 0.25
    bright_pixels: int = 2
    energy_share: float = 0.005
    max_isolation: float = 16.0
    dark_percentile: float = 2.0
    saturated_headroom: float = 8.0
    # the sensor pixels' peak (frame_peak_rate) is planned with this much more headroom: a small
    # light's brightest pixel varies with where it falls between pixels (a moving sun's by ~1.5x)
    sensor_peak_margin: float = 2.0
    sweep_ev: float = 4.0
    # What the bracket is for (module docstring): "pixels" (every pixel above the noise floor,
    # an HDR photograph) or "lighting" (the light the scene sends, energy-weighted)
    target: str = "pixels"
    dark_energy: float = 0.005  # lighting: the share of the light its darkest pixels may leave noisy
    frame_time_s: float = 0.0  # lighting: exposures up to one frame, gain first (0: no limit)
    # lighting: allow exposures beyond the frame time once the gain is at its top (each costs the
    # sensor's frame rate); off, the darkest corners stay noisier, which the integrated lighting
    # hardly sees (their noise averages over thousands of pixels and they carry dark_energy)
    long_exposures: bool = False
    gain_range: tuple[float, float] = (1.0, 1.0)
    step_s: float = 0.0  # the camera's exposure grid (0: continuous)

    def __post_init__(self) -> None:
        lo, hi = (float(x) for x in self.exposure_range)
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError(f"exposure_range {self.exposure_range!r} must be 0 < lo <= hi")
        if self.max_exposures < 1:
            raise ValueError("max_exposures must be >= 1")
        if not (self.ev_step > 0 and self.max_ev_step >= self.ev_step):
            raise ValueError("need 0 < ev_step <= max_ev_step")
        if self.target not in ("pixels", "lighting"):
            raise ValueError(f"target must be 'pixels' or 'lighting', got {self.target!r}")
        self.exposure_range = (lo, hi)

    # ---- no history ------------------------------------------------------------------------
    def metering_sweep(self) -> list[float]:
        """Effective exposures (at ``gain``) spanning the camera's range up to the longest the
        bracket may use, ``sweep_ev`` stops apart where the count allows (geometric, at most
        ``max_exposures``, shortest and longest included); :meth:`to_controls` turns them into
        what the camera takes."""
        lo, hi = self.exposure_range
        hi = min(hi, self._longest())
        span = math.log2(hi / lo) if hi > lo else 0.0
        if span <= 0:
            return [lo]
        n = min(self.max_exposures, max(2, math.ceil(span / self.sweep_ev) + 1))
        return [float(x) for x in np.geomspace(lo, hi, n)]

    def _longest(self) -> float:
        """The longest effective exposure (at ``gain``) the bracket may use: for the lighting
        with a frame time and no long exposures, one frame at the top gain."""
        lo, hi = self.exposure_range
        g = float(self.gain)
        top = hi * (max(self.gain_range[1], g) / g if self.target == "lighting" else 1.0)
        if self.target == "lighting" and self.frame_time_s > 0 and not self.long_exposures:
            top = min(top, max(self.frame_time_s, lo) * max(self.gain_range[1], g) / g)
        return top

    # ---- from history ----------------------------------------------------------------------
    def scene_levels(self, rates: np.ndarray, *, saturated: np.ndarray | None = None,
                     mask: np.ndarray | None = None, weights: np.ndarray | None = None,
                     min_peak: float = 0.0, measured: tuple[float, float] | None = None,
                     ) -> tuple[float, float] | None:
        """(s_lo, s_hi) of the significant scene range, or None when nothing is measurable.

        ``s_hi`` as in the module docstring. ``s_lo``: for ``target="pixels"`` the
        ``dark_percentile`` of the pixels; for ``target="lighting"`` the rate below which the
        pixels carry only ``dark_energy`` of the scene's light (rate x ``weights``, e.g. each
        pixel's solid angle): the darkest corners may stay noisy, they hardly light anything.
        ``min_peak``: a rate the bracket keeps unsaturated even if the scene no longer shows it
        (what was brightest a few seconds ago: a lamp switched off may come back on).
        ``measured``: :meth:`measured_levels` of the same arguments, when the caller has it (a
        replan needs the levels twice; each costs two passes and a sort of the map)."""
        m = self.measured_levels(rates, saturated=saturated, mask=mask, weights=weights) if measured is None \
            else measured
        if m is None:
            return None
        s_lo, s_hi = m[0], max(m[1], float(min_peak))
        return max(min(s_lo, s_hi), 1e-300), max(s_hi, 1e-300)

    def measured_levels(self, rates: np.ndarray, *, saturated: np.ndarray | None = None,
                        mask: np.ndarray | None = None, weights: np.ndarray | None = None,
                        ) -> tuple[float, float] | None:
        """:meth:`scene_levels` before ``min_peak`` and the clamps: (the dark rate, the peak)."""
        s = np.asarray(rates, dtype=np.float64)
        if saturated is not None:
            s = np.where(saturated, s * self.saturated_headroom, s)
        ok = np.isfinite(s) & (s > 0)
        if mask is not None:
            ok &= mask
        sel = s[ok]
        if sel.size == 0:
            return None
        k = min(self.bright_pixels, sel.size)
        s_hi = max(float(np.partition(sel, sel.size - k)[sel.size - k]), self._significant_peak(s, mask))
        if self.target == "lighting":
            w = np.ones_like(sel) if weights is None else np.asarray(weights, np.float64)[ok]
            order = np.argsort(sel)
            energy = np.cumsum(sel[order] * w[order])
            cut = int(np.searchsorted(energy, self.dark_energy * energy[-1], side="right"))
            s_lo = float(sel[order[min(cut, sel.size - 1)]])
        else:
            s_lo = float(np.percentile(sel, self.dark_percentile))
        return s_lo, s_hi

    def _significant_peak(self, s: np.ndarray, mask: np.ndarray | None) -> float:
        """Brightest pixel that alone carries >= ``energy_share`` of the scene and is not an
        isolated outlier (a neighbour at least 1/``max_isolation`` as bright), else 0.

        The ``bright_pixels`` rule lets the single brightest pixel saturate so that a hot pixel
        does not drive the shortest exposure; a small lamp whose peak pixel holds a tenth of the
        room's light must not be clipped for that, and real optics spread it over neighbours.
        """
        if s.ndim != 2 or self.energy_share <= 0:
            return 0.0
        v = np.where(np.isfinite(s) & (s > 0), s, 0.0)
        if mask is not None:
            v = np.where(mask, v, 0.0)
        total = float(v.sum())
        if total <= 0:
            return 0.0
        cand = np.flatnonzero(v >= self.energy_share * total)
        if cand.size == 0:
            return 0.0
        r, c = np.divmod(cand, v.shape[1])
        best = 0.0
        for ri, ci in zip(r, c, strict=True):
            win = v[max(ri - 1, 0):ri + 2, max(ci - 1, 0):ci + 2].copy()
            win[min(ri, 1), min(ci, 1)] = 0.0  # the pixel itself
            if win.max() * self.max_isolation >= v[ri, ci]:
                best = max(best, float(v[ri, ci]))
        return best

    def controls(self, rates: np.ndarray | None = None, *, saturated: np.ndarray | None = None,
                 mask: np.ndarray | None = None, weights: np.ndarray | None = None,
                 min_peak: float = 0.0, measured: tuple[float, float] | None = None) -> list[tuple[float, float]]:
        """(exposure, gain) pairs, ascending in exposure x gain, on the camera's grid.

        The bracket in effective exposure ``t g`` is :meth:`plan`'s; with ``frame_time_s`` set,
        an effective exposure longer than one frame takes gain first (up to ``gain_range``'s
        top) and only the rest as exposure, so the sensor keeps its frame rate when it can.
        Exposures are snapped to ``step_s`` (the shortest one down, to keep its headroom)."""
        return self.to_controls(self.plan(rates, saturated=saturated, mask=mask, weights=weights,
                                          min_peak=min_peak, measured=measured))

    def to_controls(self, taus: Sequence[float]) -> list[tuple[float, float]]:
        """Effective exposures (at ``gain``) as (exposure, gain) pairs on the camera's grid, gain
        first beyond the frame time (:meth:`controls`)."""
        g_lo, g_hi = (float(x) for x in self.gain_range)
        lo, hi = self.exposure_range
        out: list[tuple[float, float]] = []
        base = max(self.gain, g_lo)
        for n, tau in enumerate(taus):  # tau: exposure at the base gain; tau x base is what counts
            g = base
            if self.frame_time_s > 0 and tau > self.frame_time_s and g_hi > g:
                g = min(g_hi, tau * base / self.frame_time_s)
            t = min(max(tau * base / g, lo), hi)
            if self.step_s > 0:
                k = (math.floor(t / self.step_s + 1e-9) if n == 0 else round(t / self.step_s))
                k = max(math.ceil(lo / self.step_s - 1e-9), min(math.floor(hi / self.step_s + 1e-9), k))
                t = k * self.step_s
            pair = (float(t), float(g))
            if pair not in out:
                out.append(pair)
        return sorted(out, key=lambda p: p[0] * p[1])

    def plan(self, rates: np.ndarray | None = None, *, saturated: np.ndarray | None = None,
             mask: np.ndarray | None = None, weights: np.ndarray | None = None,
             min_peak: float = 0.0, measured: tuple[float, float] | None = None) -> list[float]:
        """Exposures (ascending, seconds) for the next burst.

        ``rates``: per-pixel exposure rates from the previous HDR frame (:func:`exposure_rates`),
        None for a metering sweep. ``saturated``: pixels that were saturated in every exposure
        (their rate is a lower bound). ``mask``: the pixels that count (the image circle; the
        housing ring is black and would otherwise pull the longest exposure to the maximum).
        """
        if rates is None:
            return self.metering_sweep()
        levels = self.scene_levels(rates, saturated=saturated, mask=mask, weights=weights, min_peak=min_peak,
                                   measured=measured)
        lo, hi = self.exposure_range
        if levels is None:  # Black everywhere: the longest exposure is all we can do
            return [hi]
        s_lo, s_hi = levels
        g = float(self.gain)
        # In effective exposure t g when the planner may raise the gain (controls())
        top = self._longest()
        t_short = min(max(self.bright_target / (s_hi * g), lo), hi)
        t_long = min(max(self.dark_target / (s_lo * g), t_short), top)
        span = math.log2(t_long / t_short)
        n = math.ceil(span / self.ev_step - 1e-9) + 1
        if n > self.max_exposures:
            n = self.max_exposures
            step = min(span / max(n - 1, 1), self.max_ev_step)
        else:
            step = span / max(n - 1, 1)
        out = [t_short * 2.0 ** (step * i) for i in range(n)]
        return [float(min(max(t, lo), top)) for t in out]


def order_exposures(exposures: Sequence[float], current: float | None = None) -> list[float]:
    """Order a burst to minimise control changes: start from the end nearest the camera's current
    exposure (log distance), so consecutive bursts alternate ascending / descending and the last
    exposure of one burst is reused as the first of the next."""
    asc = sorted(float(t) for t in exposures)
    if current is None or len(asc) < 2 or current <= 0:
        return asc
    c = math.log(current)
    if abs(math.log(asc[-1]) - c) < abs(math.log(asc[0]) - c):
        return asc[::-1]
    return asc


# ---- capture ------------------------------------------------------------------------------------
def _matches(frame: Frame, exposure: float, gain: float | None, rel_tol: float, abs_tol: float) -> bool:
    m = frame.meta
    if not math.isclose(m.exposure_s, exposure, rel_tol=rel_tol, abs_tol=abs_tol):
        return False
    return gain is None or math.isclose(m.gain, gain, rel_tol=rel_tol, abs_tol=1e-6)


def _linear(frame: Frame) -> np.ndarray:
    """A rough linear brightness per pixel (mean over channels), for the settling check only:
    RAW minus black level, processed through an sRGB-like gamma 2.2."""
    d = np.asarray(frame.data, dtype=np.float32)
    if frame.format.is_raw:
        span = max(frame.white_level - frame.black_level, 1.0)
        return (np.clip(d.mean(axis=-1) - frame.black_level, 0, None) / span)
    return (np.clip(d.mean(axis=-1), 0, 255) / 255.0) ** 2.2


def brightness_ratio(frame: Frame, reference: Frame, *, min_pixels: int = 64) -> float | None:
    """Median ratio of linear brightness between two frames over pixels well exposed in both
    (5%..90% of full scale); None when too few such pixels exist to judge."""
    a, b = _linear(frame), _linear(reference)
    ok = (a > 0.05) & (a < 0.9) & (b > 0.05) & (b < 0.9)
    if int(ok.sum()) < min_pixels:
        # Judge from the mean when one of the two is mostly out of range
        ma, mb = float(a.mean()), float(b.mean())
        if mb > 1e-4 and ma > 1e-4 and (ma < 0.9 and mb < 0.9):
            return ma / mb
        return None
    return float(np.median(a[ok] / b[ok]))


def _stepped(frame: Frame, before: Frame, min_ratio: float = 1.25) -> bool:
    """True when the brightness changed between two consecutive frames (an exposure landed)."""
    r = brightness_ratio(frame, before)
    return r is not None and r > 0 and abs(math.log(r)) > math.log(min_ratio)


def _step_landed(frame: Frame, reference: Frame, expected_ratio: float) -> bool:
    """Settling rule's brightness check: the step from the reference frame is closer (in stops) to
    the expected exposure ratio than to no change at all."""
    if abs(math.log(expected_ratio)) < math.log(1.05):
        return True
    r = brightness_ratio(frame, reference)
    if r is None or r <= 0:
        return True
    lr, le = math.log(r), math.log(expected_ratio)
    return abs(lr - le) < abs(lr)


class _Settling:
    """The settling rule for cameras without per-frame metadata, for one requested exposure.

    Skip ``latency`` frames after the request; then, with a reference frame of known exposure
    (the previous exposure of the burst), accept once the brightness has stepped by the expected
    ratio; without one (first exposure of a burst, the camera's current exposure unknown), accept
    once a brightness step between consecutive frames has been seen, or after ``2 latency + 2``
    frames without any step (the request equalled the old exposure).
    """

    def __init__(self, latency: int, reference: Frame | None, expected_ratio: float) -> None:
        self.latency, self.reference, self.ratio = latency, reference, expected_ratio
        self.frames = 0
        self.last: Frame | None = None
        self.step_seen = False

    def accept(self, frame: Frame) -> bool:
        self.frames += 1
        if self.last is not None and not self.step_seen:
            self.step_seen = _stepped(frame, self.last)
        self.last = frame
        if self.frames <= self.latency:
            return False
        if self.reference is not None:
            return _step_landed(frame, self.reference, self.ratio)
        return self.step_seen or self.frames > 2 * self.latency + 2


async def capture_burst(camera: Camera, exposures: Sequence[float], *, gain: float | None = None,
                        timeout: float = 2.0,  # noqa: ASYNC109 (per-exposure budget, like Camera.capture)
                        max_frames: int | None = None, rel_tol: float = 0.02,
                        abs_tol: float = 2e-5, pipelined: bool = True,
                        first_timeout: float | None = None) -> list[Frame]:
    """Capture one verified frame per exposure, in the given order.

    For each exposure: ``camera.apply(Controls(exposure_s, gain))``, then read frames, dropping
    stale ones, until one shows the requested exposure (and gain): ``meta.exposure_s`` within
    ``rel_tol`` / ``abs_tol`` of the request with ``exposure_verified``; for cameras without
    frame metadata (``capabilities.has_frame_metadata`` False, or frames not verified), the
    settling rule instead: skip ``control_latency_frames`` frames after the request, then require
    the brightness to have stepped from the previous exposure's frame by the expected ratio.

    ``pipelined`` (default): with verified frame metadata, request one exposure per frame ahead
    of the frames that show them (see the module docstring); the frames come back in the order
    of ``exposures``. ``first_timeout``: a longer wait for the very first frame (the first frame
    after stream-on is slow on real sensors).

    Raises
    ------
    CaptureTimeout
        An exposure did not land within ``max_frames`` frames (default: 2 latency + 8) or
        ``timeout`` seconds plus ``max_frames`` times the exposure itself; also whatever ``camera.capture`` raises (CaptureTimeout,
        CameraDisconnected) and ``camera.apply`` raises (ControlOutOfRange).
    """
    caps = camera.capabilities
    latency = max(int(caps.control_latency_frames), 0)
    limit = max_frames if max_frames is not None else 2 * latency + 8
    if pipelined and caps.has_frame_metadata and len(exposures) > 0:
        return await _capture_pipelined(camera, [float(t) for t in exposures], gain, timeout, limit,
                                        latency, rel_tol, abs_tol, first_timeout)
    loop = asyncio.get_running_loop()
    first_extra = max(0.0, (first_timeout or 0.0) - timeout)
    out: list[Frame] = []
    prev: Frame | None = None
    for exposure in exposures:
        t = float(exposure)
        await camera.apply(Controls(exposure_s=t, gain=gain))
        # The frames themselves take at least their exposure time each
        deadline = loop.time() + timeout + limit * t + (first_extra if not out else 0.0)
        ratio = t / prev.meta.exposure_s if prev is not None else 1.0
        settling = _Settling(latency, prev, ratio)
        since_apply = 0
        while True:
            remaining = deadline - loop.time()
            if remaining <= 0 or since_apply >= limit:
                raise CaptureTimeout(
                    f"exposure {t:.6g} s did not land within {since_apply} frames / {timeout:g} s",
                    device=camera.name)
            frame = await camera.capture(timeout=remaining)
            since_apply += 1
            verified = caps.has_frame_metadata and frame.meta.exposure_verified
            if not verified and not settling.accept(frame):
                continue  # Settling rule: not landed yet
            if not _matches(frame, t, gain, rel_tol, abs_tol):
                continue  # Stale: the sensor still runs the previous controls
            break
        out.append(frame)
        prev = frame
    return out


async def _capture_pipelined(camera: Camera, exposures: list[float], gain: float | None,
                             timeout: float,  # noqa: ASYNC109 (per-exposure budget, as capture_burst)
                             limit: int, latency: int, rel_tol: float, abs_tol: float,
                             first_timeout: float | None) -> list[Frame]:
    """One request per frame, frames matched to requests by their verified metadata.

    Budget: the sequential path's, summed over the burst (``timeout`` + ``limit`` frames of
    each exposure; ``n limit`` frames in all). A request that has not shown ``latency + 2``
    frames after it was made is made again (a dropped request or frame)."""
    loop = asyncio.get_running_loop()
    n = len(exposures)
    deadline = loop.time() + n * timeout + limit * sum(exposures) + max(0.0, (first_timeout or 0.0) - timeout)
    got: list[Frame | None] = [None] * n
    asked_at: list[int | None] = [None] * n  # frame count when exposure i was last requested
    frames = 0
    while True:
        # Request: the next exposure not yet asked for, else re-ask the oldest overdue one
        todo = [i for i in range(n) if got[i] is None]
        if not todo:
            return [f for f in got if f is not None]
        fresh = [i for i in todo if asked_at[i] is None]
        overdue = [i for i in todo if frames - (asked_at[i] or 0) > latency + 2]
        pick = fresh[0] if fresh else (overdue[0] if overdue else None)
        if pick is not None:
            await camera.apply(Controls(exposure_s=exposures[pick], gain=gain))
            asked_at[pick] = frames
        remaining = deadline - loop.time()
        if remaining <= 0 or frames >= n * limit:
            missing = ", ".join(f"{exposures[i]:.6g}" for i in todo)
            raise CaptureTimeout(f"exposure {missing} s did not land within {frames} frames / "
                                 f"{timeout:g} s per exposure", device=camera.name)
        # Read: a frame showing an outstanding exposure fills the first such slot
        frame = await camera.capture(timeout=remaining)
        frames += 1
        if not frame.meta.exposure_verified:
            continue
        for i in todo:
            if _matches(frame, exposures[i], gain, rel_tol, abs_tol):
                got[i] = frame
                break


KEEP_EV = 0.2  # a replanned exposure this close (in EV, time and gain each) to one in use keeps it


def ev_distance(a: tuple[float, float], b: tuple[float, float]) -> float:
    """How far apart two (exposure, gain) controls are: the larger of the two in EV."""
    return max(abs(math.log2(a[0] / b[0])), abs(math.log2(a[1] / b[1])))


def keep_in_use(controls: list[tuple[float, float]], in_use: list[tuple[float, float]]
                ) -> list[tuple[float, float]]:
    """The schedule's hysteresis: a replanned exposure within ``KEEP_EV`` (~15%) of one in use
    stays as it is, so a scene's noise does not re-time the bracket every plan; ascending, once
    each."""
    kept = [min(in_use, key=lambda o: ev_distance(o, c))
            if min(ev_distance(o, c) for o in in_use) < KEEP_EV else c for c in controls]
    return sorted(set(kept), key=lambda c: c[0] * c[1])


@dataclass
class ExposureSchedule:
    """The exposures the camera cycles through: the shortest every other frame, or, for a camera
    without per-frame metadata (``hold`` > 1), each exposure for ``hold`` frames in turn."""

    controls: list[tuple[float, float]]  # ascending t g
    sweep: bool = False
    order: list[int] = field(default_factory=list)
    pos: int = 0
    hold: int = 1

    def __post_init__(self) -> None:
        n = len(self.controls)
        if self.sweep:
            self.order = list(range(n))
        elif self.hold > 1:  # every change costs settling frames: change seldom
            self.order = [k for k in range(n) for _ in range(self.hold)]
        elif n <= 2:
            self.order = list(range(n))
        else:  # S, E1, S, E2, ...: the shortest measures a lamp within two frames
            self.order = [k for i in range(1, n) for k in (0, i)]

    def next(self) -> tuple[float, float]:
        c = self.controls[self.order[self.pos % len(self.order)]]
        self.pos += 1
        return c

    @property
    def cycle_done(self) -> bool:
        return self.pos >= len(self.order)
