"""HDR fusion of an exposure stack: response-weighted, noise-aware, ghost-robust merge.

Every frame ``i`` of a stack gives, per pixel and channel, an estimate of the scene radiance
``X_i = E(z_i) / (t_i g_i)`` (Debevec & Malik 1997, eq. 6) where ``E`` is the inverse camera
response (``lightprobe.core.calibration.Response.inverse``: pixel value -> relative linear exposure; for RAW
frames ``E(z) = (z - black) / (white - black)``), ``t_i`` the exposure time and ``g_i`` the gain.
The fused value is the weighted mean ``X = sum_i w_i X_i / sum_i w_i`` with

    w_i(z) = h(z) * (t_i g_i)^2 / Var[E(z)]                                  (Granados et al. 2010)

``h`` a *broad hat* that is zero near black (clipping at 0 biases the estimate) and near
saturation (clipping at full scale biases it, Reinhard et al. 2010 sec. 4.7 "broad hat"), and
``Var[E]`` the noise of a sample: for a response measured on a bracket, the scatter it showed
there per code (``Response.log_sigma``: ``Var[E] = (E sigma)^2``, the real camera's noise, JPEG
and quantisation included, and the response's own error); otherwise the sensor noise model (shot
+ read, :class:`NoiseModel`) plus the quantisation of the response (``(dE/dz)^2 / 12``): the
inverse-variance weights of Granados et al. / Hasinoff et al., which make long exposures weigh
more for the same pixel value.

The measured scatter is in log exposure: each sample is ``X exp(eps_i)``, ``eps_i ~ N(0,
sigma(z_i)^2)``, with ``X`` the pixel's radiance, the same for all its samples. Its maximum
likelihood estimate is the precision-weighted mean of the logarithms,
``ln X = sum_i w_i ln X_i / sum_i w_i`` with ``w_i = h(z_i) / sigma(z_i)^2`` (Debevec & Malik's
eq. 6 is this log mean, with their hat as the weights), and that is what the merge computes for
such a response. Weighting each sample by the variance of its *own* value (``1 / (X_i sigma)^2``)
favoured the samples that came out low: the image came out ``1.5 sigma^2`` low, the more so at
the codes that scatter more, and on a phone's stack (sigma ~0.3) it correlated 0.974 with
OpenCV's merge instead of 0.995.
On real photographs that scatter is heavy-tailed (edges, sub-pixel misregistration, things that
moved), so the weights take the typical sample's spread (``Response.log_sigma_core``, the 68.3%
half-width) while the deghosting's test, which is about the tails, keeps the root mean square
(``log_sigma``): weighting by the rms let a code's few wild samples decide how much all its
samples count, and made makehdr's even and odd halves disagree 5% more (0.0094 against 0.0090).

Everything that depends only on the pixel value is a look-up table with one row per level
(``(F, L + 1, 3)`` float32, row ``L`` = "invalid sample" for NaN/Inf from float drivers), so the
merge is a handful of table reads per pixel (:func:`_merge_kernel`, numba, parallel over pixels).

Ghosts (lights that move between exposures). Per pixel a *reference* frame is chosen: the shortest
exposure in which no channel is saturated and one has weight; when that sample is poorly exposed
(relative noise above ``ref_max_rel_sigma``, a nearly black pixel of the shortest frame) the most
precise well-exposed sample (largest weight) stands in. Any other frame whose estimate
disagrees with the reference by more than ``k sigma + rel_tol X_ref`` (sigma: the two samples'
combined noise) in any channel is dropped at that pixel, so a moving lamp appears once, where the
reference saw it, never as a double or a smear (Granados et al. 2013 use the same consistency test).
The threshold is only as good as sigma: with a generic sensor model on real JPEG photographs
(whose noise, tone curve and response error it does not describe) it rejected most samples of a
static scene; with the bracket's measured scatter a static scene keeps its samples (the default
and ``deghost=False`` agree) while a moving lamp still stands out by many sigma.

Degenerate pixels (never NaN or Inf in the output):

* saturated in every exposure (at or above ``sat_frac`` of the range, where the hat is zero) ->
  ``saturated`` mask, value = the documented lower bound ``E(z_sat) / (t_min g_min)``: the
  saturation threshold ``z_sat`` of the shortest exposure divided by its exposure ("at least this
  bright");
* no frame with weight (black everywhere, NaN everywhere, ...) -> ``invalid`` mask, value = the
  unweighted estimate of the reference / shortest non-saturated finite sample (0 if there is none).

Dtype policy: LUTs and output float32, per-pixel sums in float64 registers.

References
----------
P. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997.
M. Granados, B. Ajdin, M. Wand, C. Theobalt, H.-P. Seidel, H. Lensch, "Optimal HDR reconstruction
with linear digital cameras", CVPR 2010.
S. Hasinoff, F. Durand, W. Freeman, "Noise-optimal capture for high dynamic range photography",
CVPR 2010.
M. Granados, K. Kim, J. Tompkin, C. Theobalt, "Automatic noise modeling for ghost-free HDR
reconstruction", SIGGRAPH Asia 2013.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from lightprobe.core.calibration import Response, repair_inverse
from lightprobe.core.errors import InputError

if TYPE_CHECKING:
    from lightprobe.drivers.base import Frame

__all__ = [
    "FusionResult",
    "FusionSettings",
    "NoiseModel",
    "build_luts",
    "fuse",
    "fuse_frames",
    "fuse_raw",
    "fuse_tables",
    "packed_lut",
]


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise in electrons: full-scale output = ``full_well_e / gain`` electrons.

    In units of full scale, a normalised exposure ``e`` has variance
    ``e gain / full_well + (read_noise gain / full_well)^2`` (Poisson shot + Gaussian read noise).
    Defaults are typical of small camera modules (the simulator's defaults).
    """

    full_well_e: float = 6000.0
    read_noise_e: float = 2.5


@dataclass(frozen=True)
class FusionSettings:
    """Tunable parts of the merge.

    ``black_frac`` / ``sat_frac``: the broad hat is zero at or below ``black_frac`` and at or
    above ``sat_frac`` of the pixel range (JPEG and demosaicing smear values near the ends);
    ``ghost_k`` / ``ghost_rel_tol``: a sample is a ghost when it differs from the reference by more
    than ``ghost_k`` sigma plus ``ghost_rel_tol`` x reference (the relative part absorbs response
    calibration error); ``deghost=False`` keeps every sample; a reference sample noisier than
    ``ref_max_rel_sigma`` (relative) hands over to the most precise well-exposed sample, so a
    pixel is never judged against a nearly black sample.
    """

    black_frac: float = 0.01
    sat_frac: float = 0.985
    deghost: bool = True
    ghost_k: float = 5.0
    ghost_rel_tol: float = 0.05
    ref_max_rel_sigma: float = 0.25
    noise: NoiseModel = NoiseModel()


@dataclass(frozen=True)
class FusionResult:
    """Fused radiance (float32 (H, W, 3), "fused units": x photometric scale = calibrated unit).

    ``saturated``: (H, W) bool, some channel saturated in every exposure (value = lower bound).
    ``invalid``: (H, W) bool, some channel had no usable sample (value = best guess).
    ``exposures``: the (exposure_s, gain) of each frame, in input order.
    ``rejected``: (H, W) uint8, samples (frames) the deghosting dropped at each pixel;
    ``usable``: how many samples (pixel x frame) had weight at all, so ``rejected.sum() /
    usable`` is the fraction the deghosting threw away.
    """

    radiance: np.ndarray
    saturated: np.ndarray
    invalid: np.ndarray
    exposures: tuple[tuple[float, float], ...]
    rejected: np.ndarray | None = None
    usable: int = 0

    @property
    def rejected_fraction(self) -> float:
        """Share of the usable samples the deghosting rejected (0 without deghosting)."""
        if self.rejected is None or self.usable <= 0:
            return 0.0
        return float(self.rejected.sum(dtype=np.int64)) / self.usable


# ---- Look-up tables -----------------------------------------------------------------------------
_SANITIZED: dict[tuple[object, ...], np.ndarray] = {}


def sanitized_inverse(inverse: np.ndarray) -> np.ndarray:
    """:func:`lightprobe.core.calibration.repair_inverse`, memoised on the table's bytes (one entry
    per response)."""
    inv = np.ascontiguousarray(inverse, dtype=np.float64)
    key = (hash(inv.tobytes()), inv.shape)
    hit = _SANITIZED.get(key)
    if hit is None:
        hit = repair_inverse(inv)
        hit.setflags(write=False)
        with _CACHE_LOCK:
            if len(_SANITIZED) >= 8:
                _SANITIZED.pop(next(iter(_SANITIZED)), None)
            _SANITIZED[key] = hit
    return hit


def _hat(levels: int, black: float, sat: float, settings: FusionSettings) -> np.ndarray:
    """Broad hat h(z) in [0, 1] over pixel values, zero at or below ``black + black_frac*range``
    and at or above ``black + sat_frac*range`` where range = sat - black (Reinhard et al. 2010)."""
    z = np.arange(levels, dtype=np.float64)
    span = max(sat - black, 1e-12)
    t = (z - black) / span
    lo, hi = settings.black_frac, settings.sat_frac
    u = np.clip((t - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    h = 1.0 - (2.0 * u - 1.0) ** 12  # broad hat: ~1 over most of the range
    h[(t <= lo) | (t >= hi)] = 0.0
    return h


# the live merge's black floor (build_luts' black_floor): an 8-bit camera's pedestal and dark noise
# reach codes 2-8 (a phone's and a compact's JPEGs in ../shared/data)
BLACK_FLOOR_FRAC = 0.03


def build_luts(inverse: np.ndarray, exposure_s: float, gain: float, *, black: float, sat: float,
               settings: FusionSettings, log_sigma: np.ndarray | None = None,
               log_sigma_core: np.ndarray | None = None,
               black_floor: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-level tables of one frame: value, weight, sigma (each (L + 1, 3) float64) and the
    saturation flag (L + 1, 3) bool (levels at or above ``black + sat_frac (sat - black)``);
    row L is the "invalid sample" row (weight 0).

    value   X(z) = E(z) / (t g)                                  (Debevec-Malik eq. 6)
    weight  w(z) = h(z) (t g)^2 E_fs^2 / Var[E(z)]              (Granados et al. 2010 eq. 11)
    sigma   sd(z) = sqrt(Var[E(z)]) / (t g)
    with, from the sensor noise model, Var[E] = E_fs^2 (e g / FW + (r g / FW)^2) + (dE/dz)^2 / 12,
    e = E / E_fs; or, when the response carries the scatter it was measured with
    (``log_sigma``, :func:`lightprobe.calibration.response.code_scatter`), Var[E] = (E(z) sigma(z))^2: that
    scatter already holds the camera's real noise (JPEG included), quantisation and the
    response's own error, which a generic sensor model does not know. That scatter is in log
    exposure, so the weight is then the precision of ``ln X``, ``w(z) = h(z) / sigma(z)^2``, and
    the merge averages ``ln X`` (:func:`packed_lut`, the module docstring). The weight takes the
    typical sample's spread, ``log_sigma_core`` when the response has it: that scatter is
    heavy-tailed, and its root mean square (``log_sigma``, still the variance the deghosting and
    the live map's sums use) would let the tails set every sample's precision.

    ``black_floor`` (the live merge's tables, :mod:`lightprobe.device.hdr.rolling`): with a
    measured scatter, the variance also holds the camera's black, ``E(z_b)^2`` in exposure units
    with ``z_b`` the code at :data:`BLACK_FLOOR_FRAC` of the range. The scatter is relative and
    was measured where codes are weighed; near black a camera's codes are its pedestal and dark
    noise, whatever the light (a 1/4000 s JPEG of a room reads codes 2-7 where the room gives
    1e-5 of full scale, 4.5 on average), which a relative scatter turns into a confident 8 where
    the longer exposures measured 0.07: averaged over an output pixel's samples, the pedestal's
    bias stayed while its noise went, and the live merge took every short frame for a change (a
    real bracket replayed: the published energy swung 25% with the schedule). A sensor model's
    read noise is this floor already.
    """
    inv = np.asarray(inverse, dtype=np.float64)
    levels = inv.shape[0]
    tg = float(exposure_s) * float(gain)
    isat = int(min(max(np.ceil(sat), 1), levels - 1))
    e_fs = np.maximum(inv[isat], 1e-300)  # Exposure at full scale, per channel
    e = np.clip(inv / e_fs, 0.0, 1.0)
    if log_sigma is not None:  # the bracket's own scatter per code
        var = (inv * np.asarray(log_sigma, np.float64)) ** 2 + 1e-30 * e_fs**2
        if black_floor:
            floor = inv[min(round(BLACK_FLOOR_FRAC * (levels - 1)), levels - 1)]
            var = var + np.maximum(floor, 0.0)[None, :] ** 2
    else:
        nm = settings.noise
        fw = max(nm.full_well_e, 1.0)
        var_sensor = (e * gain / fw + (nm.read_noise_e * gain / fw) ** 2) * e_fs**2
        slope = np.gradient(inv, axis=0)  # dE/dz, quantisation of the response
        var = var_sensor + slope**2 / 12.0 + 1e-30 * e_fs**2
    hat = _hat(levels, black, sat, settings)[:, None]
    if log_sigma is not None and black_floor:
        var = np.where(hat > 0, var / np.maximum(hat, 1e-3), var)
    val = np.zeros((levels + 1, 3), np.float64)
    w = np.zeros((levels + 1, 3), np.float64)
    sd = np.zeros((levels + 1, 3), np.float64)
    val[:levels] = inv / tg
    if log_sigma is not None:
        # Log-normal scatter: Var[X_i] = (X sigma(z_i))^2 with X the pixel's radiance, which all
        # its samples share: the precision of ln X_i is h / sigma^2, whatever the sample read
        spread = log_sigma if log_sigma_core is None else log_sigma_core
        w[:levels] = hat / np.maximum(np.asarray(spread, np.float64), 1e-4) ** 2
    else:
        # Weights in full-scale units (Var / E_fs^2): the same factor for every frame of a
        # response, so float32 keeps them whatever the response's scale
        w[:levels] = hat * tg**2 / (var / e_fs**2)
    sd[:levels] = np.sqrt(var) / tg
    # Saturated = at or above the hat's upper cut-off (read noise keeps clipped pixels a few
    # levels under the white level, and JPEG rings around it): exactly where h(z) is zero at the top
    top = int(min(max(np.ceil(black + settings.sat_frac * (sat - black) - 1e-9), 1), levels - 1))
    satf = np.zeros((levels + 1, 3), bool)
    satf[top:levels] = True
    return val, w, sd, satf


_LUT_CACHE: dict[tuple[object, ...], np.ndarray] = {}
_LUT_CACHE_SIZE = 64
_CACHE_LOCK = threading.Lock()  # fuse() runs in worker threads (asyncio.to_thread)


def packed_lut(inverse: np.ndarray, exposure_s: float, gain: float, *, black: float, sat: float,
               settings: FusionSettings, log_sigma: np.ndarray | None = None,
               log_sigma_core: np.ndarray | None = None, black_floor: bool = False) -> np.ndarray:
    """The kernel's table for one frame: (L + 1, 3, 5) float32 [value, weight, variance,
    saturated, merged value] (:func:`build_luts`), memoised on (response, exposure, gain, levels,
    settings): a live probe repeats the same few exposures, so the tables are built once. The
    merged value is what the weighted mean averages: ``ln X`` for a response with measured
    (log) scatter, ``X`` otherwise."""
    inv = np.ascontiguousarray(inverse, dtype=np.float64)
    sig = None if log_sigma is None else np.ascontiguousarray(log_sigma, dtype=np.float64)
    core = None if log_sigma is None or log_sigma_core is None else np.ascontiguousarray(log_sigma_core, np.float64)
    key = (hash(inv.tobytes()), inv.shape, None if sig is None else hash(sig.tobytes()),
           None if core is None else hash(core.tobytes()), float(exposure_s), float(gain), float(black),
           float(sat), settings, bool(black_floor))
    hit = _LUT_CACHE.get(key)
    if hit is not None:
        return hit
    val, w, sd, satf = build_luts(inv, exposure_s, gain, black=black, sat=sat, settings=settings, log_sigma=sig,
                                  log_sigma_core=core, black_floor=black_floor)
    fmax = float(np.finfo(np.float32).max) / 16
    lut = np.stack([val, w, sd**2, satf.astype(np.float64), val], axis=-1)
    lut = np.clip(np.nan_to_num(lut, nan=0.0, posinf=fmax), 0, fmax)
    if sig is not None:  # log-normal scatter: the merge averages ln X (a weightless 0 -> a finite floor)
        lut[..., 4] = np.log(np.maximum(lut[..., 0], np.finfo(np.float32).tiny))
    lut = np.ascontiguousarray(lut, np.float32)
    lut.setflags(write=False)
    with _CACHE_LOCK:
        if len(_LUT_CACHE) >= _LUT_CACHE_SIZE:
            _LUT_CACHE.pop(next(iter(_LUT_CACHE)), None)
        _LUT_CACHE[key] = lut
    return lut


# ---- The merge ----------------------------------------------------------------------------------
@numba.njit(cache=True, parallel=True, nogil=True)
def _merge_kernel(z, lut, lower, deghost, k2, rel, ref_rel2, logd, out, sat_mask, inv_mask, usable, rejected):  # type: ignore[no-untyped-def]
    """z: (F, N, 3) LUT rows (frames sorted by t g ascending); lut: (F, L + 1, 3, 5) float32 with
    [value, weight, variance, saturated, merged value]; lower: (3,) the lower bound for
    all-saturated channels; ``logd``: the merged value is ln X (the mean is exponentiated)."""
    nf, npx, _ = z.shape
    for p in numba.prange(npx):
        # Choose the reference: the shortest frame with no channel saturated and some weight. If
        # that sample is poorly exposed (relative sigma above ref_rel in a weighted channel) it
        # cannot judge the others: then the most precise well-exposed sample (largest weight)
        # stands in (none: no test at this pixel)
        ref = -1
        poor = False
        for i in range(nf):
            a0, a1, a2 = lut[i, z[i, p, 0], 0], lut[i, z[i, p, 1], 1], lut[i, z[i, p, 2], 2]
            if a0[3] + a1[3] + a2[3] > 0:
                continue
            if a0[1] + a1[1] + a2[1] > 0:
                ref = i
                poor = ((a0[1] > 0) & (a0[2] > ref_rel2 * a0[0] * a0[0])) | \
                       ((a1[1] > 0) & (a1[2] > ref_rel2 * a1[0] * a1[0])) | \
                       ((a2[1] > 0) & (a2[2] > ref_rel2 * a2[0] * a2[0]))
                break
        if deghost and poor:
            ref = _best_reference(lut, z, p, ref_rel2)
        rv0 = rv1 = rv2 = 0.0
        rs0 = rs1 = rs2 = 0.0
        rw0 = rw1 = rw2 = 0.0
        if ref >= 0:
            b0, b1, b2 = lut[ref, z[ref, p, 0], 0], lut[ref, z[ref, p, 1], 1], lut[ref, z[ref, p, 2], 2]
            rv0, rw0, rs0 = b0[0], b0[1], b0[2]
            rv1, rw1, rs1 = b1[0], b1[1], b1[2]
            rv2, rw2, rs2 = b2[0], b2[1], b2[2]
        n0 = n1 = n2 = 0.0
        d0 = d1 = d2 = 0.0
        for i in range(nf):
            a0, a1, a2 = lut[i, z[i, p, 0], 0], lut[i, z[i, p, 1], 1], lut[i, z[i, p, 2], 2]
            w0, w1, w2 = a0[1], a1[1], a2[1]
            if w0 + w1 + w2 <= 0:
                continue
            usable[p] += 1
            if deghost and ref >= 0 and i != ref:
                # Consistency with the reference: |X_i - X_ref| <= k sigma + rel X_ref (Granados 2013)
                e0 = abs(a0[0] - rv0) - rel * rv0
                e1 = abs(a1[0] - rv1) - rel * rv1
                e2 = abs(a2[0] - rv2) - rel * rv2
                # Branch-free: a channel counts only where both samples have weight
                g0 = (w0 * rw0 > 0) & (e0 > 0) & (e0 * e0 > k2 * (a0[2] + rs0))
                g1 = (w1 * rw1 > 0) & (e1 > 0) & (e1 * e1 > k2 * (a1[2] + rs1))
                g2 = (w2 * rw2 > 0) & (e2 > 0) & (e2 * e2 > k2 * (a2[2] + rs2))
                ghost = g0 | g1 | g2
                if ghost:
                    rejected[p] += 1
                    continue
            # Weighted mean of the estimates X_i = E(z_i) / (t_i g_i), or of their logarithms under
            # a log-normal noise model (Debevec-Malik eq. 6)
            n0 += w0 * a0[4]
            n1 += w1 * a1[4]
            n2 += w2 * a2[4]
            d0 += w0
            d1 += w1
            d2 += w2
        for c in range(3):
            num = n0 if c == 0 else (n1 if c == 1 else n2)
            den = d0 if c == 0 else (d1 if c == 1 else d2)
            if den > 0:
                out[p, c] = np.exp(num / den) if logd else num / den
            else:
                _degenerate(z, lut, lower, p, c, ref, out, sat_mask, inv_mask)


@numba.njit(cache=True, nogil=True, inline="always")
def _best_reference(lut, z, p, ref_rel2):  # type: ignore[no-untyped-def]
    """The well-exposed sample (no channel saturated, relative variance <= ref_rel2 in every
    weighted channel) with the largest weight, the most precise estimate of the pixel; -1 when
    none is well exposed."""
    best, best_w = -1, 0.0
    for i in range(z.shape[0]):
        a0, a1, a2 = lut[i, z[i, p, 0], 0], lut[i, z[i, p, 1], 1], lut[i, z[i, p, 2], 2]
        w = a0[1] + a1[1] + a2[1]
        if w <= best_w or a0[3] + a1[3] + a2[3] > 0:
            continue
        if ((a0[1] > 0) & (a0[2] > ref_rel2 * a0[0] * a0[0])) | \
           ((a1[1] > 0) & (a1[2] > ref_rel2 * a1[0] * a1[0])) | \
           ((a2[1] > 0) & (a2[2] > ref_rel2 * a2[0] * a2[0])):
            continue
        best, best_w = i, w
    return best


@numba.njit(cache=True, nogil=True, inline="always")
def _degenerate(z, lut, lower, p, c, ref, out, sat_mask, inv_mask):  # type: ignore[no-untyped-def]
    """A channel without any weighted sample (see the module docstring)."""
    nf = z.shape[0]
    # Saturated everywhere -> the documented lower bound of the shortest frame
    allsat = True
    for i in range(nf):
        if lut[i, z[i, p, c], c, 3] == 0:
            allsat = False
            break
    if allsat:
        out[p, c] = lower[c]
        sat_mask[p] = True
        return
    # No usable sample: the reference's value, else the shortest finite unsaturated one
    best = -1.0
    start = ref if ref >= 0 else 0
    for i in range(start, nf):
        q = z[i, p, c]
        if q < lut.shape[1] - 1 and lut[i, q, c, 3] == 0:
            best = lut[i, q, c, 0]
            break
    out[p, c] = best if best >= 0 else 0.0
    inv_mask[p] = True


def as_index(frame: np.ndarray, levels: int) -> np.ndarray:
    """Frame -> LUT row indices. Integers are clipped to the top level; float data are rounded and
    NaN/+Inf (and absurd values) go to row ``levels``, the "invalid sample" row."""
    a = np.asarray(frame)
    if a.dtype == np.uint8 and levels >= 256:
        return a
    if a.dtype == np.uint16 and levels >= 65536:
        return a
    if np.issubdtype(a.dtype, np.integer):
        return np.clip(a, 0, levels - 1).astype(np.uint16 if levels <= 65536 else np.int32)
    if np.issubdtype(a.dtype, np.floating):
        bad = ~np.isfinite(a) | (a > 1e12)
        idx = np.rint(np.clip(np.where(bad, 0.0, a), 0, levels - 1)).astype(np.int32)
        idx[bad] = levels
        return idx
    raise InputError(f"frame dtype {a.dtype} is not an image type", param="frames")


def _check_stack(frames: Sequence[np.ndarray], exposures: Sequence[float],
                 gains: Sequence[float] | None) -> tuple[list[float], list[float]]:
    if len(frames) == 0:
        raise InputError("no frames to fuse", param="frames")
    if len(exposures) != len(frames):
        raise InputError(f"{len(frames)} frames but {len(exposures)} exposure times", param="exposures")
    gl = [1.0] * len(frames) if gains is None else [float(g) for g in gains]
    if len(gl) != len(frames):
        raise InputError(f"{len(frames)} frames but {len(gl)} gains", param="gains")
    shape = np.shape(frames[0])
    if len(shape) != 3 or shape[2] != 3:
        raise InputError(f"frames must be (H, W, 3), got {shape}", param="frames")
    for i, f in enumerate(frames):
        if np.shape(f) != shape:
            raise InputError(f"frame {i} has shape {np.shape(f)}, frame 0 has {shape}", param="frames")
    tl = [float(t) for t in exposures]
    for i, t in enumerate(tl):
        if not (np.isfinite(t) and t > 0):
            raise InputError(f"exposure time {exposures[i]!r} (frame {i}) must be positive", param="exposures")
    for i, g in enumerate(gl):
        if not (np.isfinite(g) and g > 0):
            raise InputError(f"gain {g!r} (frame {i}) must be positive", param="gains")
    return tl, gl


def fuse_tables(frames: Sequence[np.ndarray], exposures: Sequence[float], inverses: Sequence[np.ndarray],
                blacks: Sequence[float], sats: Sequence[float], gains: Sequence[float] | None = None,
                settings: FusionSettings | None = None,
                log_sigma: np.ndarray | None = None, log_sigma_core: np.ndarray | None = None) -> FusionResult:
    """Merge frames given each frame's inverse-response table, black level and saturation level
    (and the response's measured scatter per code, ``log_sigma`` and ``log_sigma_core``, when it
    has them).

    The common core of :func:`fuse` (processed) and :func:`fuse_raw` (linear). Raises
    :class:`InputError` for an empty stack, mismatched shapes or counts, non-positive times/gains.
    """
    st = settings or FusionSettings()
    tl, gl = _check_stack(frames, exposures, gains)
    h, wd = np.shape(frames[0])[:2]
    order = sorted(range(len(frames)), key=lambda i: (tl[i] * gl[i], i))
    levels = max(np.asarray(inverses[i]).shape[0] for i in order)
    idx = [as_index(frames[i], levels) for i in order]
    z = np.empty((len(order), h * wd, 3), np.result_type(*[a.dtype for a in idx]))
    for j, a in enumerate(idx):
        z[j] = a.reshape(h * wd, 3)
    sig = None if log_sigma is None else _pad(log_sigma, levels)
    core = None if log_sigma_core is None else _pad(log_sigma_core, levels)
    lut = np.stack([packed_lut(_pad(inverses[i], levels), tl[i], gl[i], black=blacks[i], sat=sats[i],
                               settings=st, log_sigma=sig, log_sigma_core=core) for i in order])
    # Lower bound for channels saturated everywhere: E(z_sat) / (t g) of the shortest frame
    lower = np.array([lut[0, int(np.argmax(lut[0, :levels, c, 3] > 0)), c, 0] for c in range(3)],
                     np.float32)
    out = np.empty((h * wd, 3), np.float32)
    smask = np.zeros(h * wd, np.bool_)
    imask = np.zeros(h * wd, np.bool_)
    usable = np.zeros(h * wd, np.uint8)
    rejected = np.zeros(h * wd, np.uint8)
    _merge_kernel(z, lut, lower, st.deghost, float(st.ghost_k) ** 2, float(st.ghost_rel_tol),
                  float(st.ref_max_rel_sigma) ** 2, sig is not None, out, smask, imask, usable, rejected)
    return FusionResult(out.reshape(h, wd, 3), smask.reshape(h, wd), imask.reshape(h, wd),
                        tuple(zip(tl, gl, strict=True)), rejected.reshape(h, wd),
                        int(usable.sum(dtype=np.int64)))


def _pad(inverse: np.ndarray, levels: int) -> np.ndarray:
    inv = np.asarray(inverse, dtype=np.float64)
    if inv.shape[0] >= levels:
        return inv
    return np.concatenate([inv, np.repeat(inv[-1:], levels - inv.shape[0], axis=0)])


def fuse(frames: Sequence[np.ndarray], exposures: Sequence[float], response: Response, *,
         gains: Sequence[float] | None = None, settings: FusionSettings | None = None) -> FusionResult:
    """Debevec-Malik merge of processed frames ((H, W, 3) uint8, or float pixel values that may
    hold NaN/Inf) with a calibrated response. See the module docstring for weights and masks."""
    inv = sanitized_inverse(response.inverse)
    n = len(frames)
    top = float(inv.shape[0] - 1)
    return fuse_tables(frames, exposures, [inv] * n, [0.0] * n, [top] * n, gains, settings,
                       response.log_sigma, response.log_sigma_core)


def fuse_raw(frames: Sequence[np.ndarray], exposures: Sequence[float], *, bits: int,
             black_levels: Sequence[float] | float = 0.0, white_levels: Sequence[float] | float | None = None,
             gains: Sequence[float] | None = None, settings: FusionSettings | None = None) -> FusionResult:
    """Linear merge of RAW frames ((H, W, 3) uint16, demosaiced, black level still in).

    ``E(z) = max(z - black, 0) / (white - black)`` per frame; ``white`` (default ``2^bits - 1``)
    is the saturation level of that frame.
    """
    n = len(frames)
    if not 1 <= int(bits) <= 16:
        raise InputError(f"raw bit depth {bits!r} must be in [1, 16]", param="bits")
    levels = 1 << int(bits)
    bl = [float(black_levels)] * n if np.isscalar(black_levels) else [float(b) for b in black_levels]  # type: ignore[arg-type, union-attr]
    wl_in = white_levels if white_levels is not None else float(levels - 1)
    wl = [float(wl_in)] * n if np.isscalar(wl_in) else [float(x) for x in wl_in]  # type: ignore[arg-type, union-attr]
    if len(bl) != n or len(wl) != n:
        raise InputError("one black and one white level per frame", param="levels")
    invs = []
    for b, wv in zip(bl, wl, strict=True):
        if not (np.isfinite(b) and np.isfinite(wv) and 0 <= b < wv):
            raise InputError(f"raw levels black={b!r} white={wv!r} need 0 <= black < white", param="levels")
        invs.append(Response.linear(int(bits), b, min(wv, levels - 1)).inverse)
    return fuse_tables(frames, exposures, invs, bl, [min(x, levels - 1) for x in wl], gains, settings)


def fuse_frames(frames: Sequence[Frame], response: Response | None = None, *,
                settings: FusionSettings | None = None) -> FusionResult:
    """Fuse ``lightprobe.drivers.base.Frame`` objects using their metadata (exposure, gain, levels).

    RGB8 frames need ``response``; RAW frames use their own black and white levels.
    """
    if not frames:
        raise InputError("no frames to fuse", param="frames")
    fmts = {f.format for f in frames}
    if len(fmts) != 1:
        raise InputError(f"a burst mixes pixel formats {sorted(map(str, fmts))}", param="frames")
    fmt = fmts.pop()
    data = [f.data for f in frames]
    t = [f.meta.exposure_s for f in frames]
    g = [f.meta.gain for f in frames]
    if fmt.is_raw:
        return fuse_raw(data, t, bits=fmt.bit_depth, black_levels=[f.black_level for f in frames],
                        white_levels=[f.white_level for f in frames], gains=g, settings=settings)
    if response is None:
        raise InputError("processed (RGB8) frames need a camera response", param="response")
    return fuse(data, t, response, gains=g, settings=settings)
