"""The simulated image sensor: photons to electrons to digital numbers, with noise.

Signal chain for one pixel and channel (``L`` sensor-plane radiance in scene units, ``V`` the
vignetting factor, ``t`` exposure in seconds, ``g`` analogue gain)::

    mu    = L V t S                            expected electrons, S = sensitivity   (S1)
    e     ~ Poisson(mu)     (its Gaussian approximation N(mu, mu), see below)            (S2)
    e'    = min(e + N(0, sigma_read^2), FW)      a saturated pixel reads full scale    (S3)
    x     = min(e' g / FW, 1)                    normalised linear exposure            (S4)
    RGB8  : z = round(255 f_c(max(x, 0)))        f_c the per-channel response curve    (S5)
    RAWb  : z = clip(round(black + x (white - black)), 0, white), white = 2^b - 1     (S6)

``x`` is what the calibration's response table (its ``inverse``) gives for a code, so fused values ``x / (t g) / V = L S / FW`` and the
photometric scale of the truth calibration is ``FW / S`` (fused x scale = scene radiance).

Default parameters (typical of a small CMOS module): full well 6000 e-, read noise 2.5 e-,
sensitivity S = 1e4 e- per (radiance unit x second): the module behind a small aperture / a
neutral-density filter, as sky probes are built so the sun fits the sensor's range (Stumpfel et
al. 2004). With exposures 1e-5 .. 1 s and gain 1 .. 16 a pixel collects a few electrons from
radiance 3e-4 (1 s, gain 1) and saturates from radiance 6e4 in the shortest exposure (6000 e- at
1e-5 s), so all six shared maps are capturable: the unclipped sun of ``rooitou_park`` (peak
equirect pixel 6.9e4) averages to ~4.5e4 over a VGA pixel's footprint and reads ~75% of full
scale at 1e-5 s. A brighter scene (``scene_scale``) saturates in
every exposure; the fusion flags it and fills a lower bound.

The response curve f_c (S5) is an sRGB-like OETF (linear toe, power segment with a per-channel
exponent) followed by a rational filmic shoulder ``(1 + b) u / (u + b)``; both steps have
closed-form inverses, so the truth inverse table is exact. It is smooth and strictly increasing,
slightly different per channel.

Determinism and cost: a noisy frame is one compiled pass over the pixels (:func:`_expose`): each
pixel's random numbers are a counter-based hash of ``(seed, sequence, pixel)`` (splitmix64), the
normal deviate from a table of the inverse normal CDF (Acklam's formula), shot plus read noise as
one Gaussian N(mu, mu + sigma_read^2): Poisson's mean and variance exactly; its skew (1/sqrt(mu))
is left out, which the 2.5 e- read noise dominates wherever it is large; so a
frame is the same whatever thread computes it and costs ~5 ms of CPU at VGA (a camera's cost,
not a renderer's). Dtype policy: radiance float32 in, electrons float64, output uint8 / uint16.

References
----------
EMVA Standard 1288 (release 4.0, 2021), the linear camera model: mean and variance of the
digital signal, eqs. (S1)-(S4) here. IEC 61966-2-1 (sRGB) for the form of the toe and power law.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np

from lightprobe.drivers.base import PixelFormat

__all__ = ["ResponseCurve", "SensorModel", "raw_levels"]

_X0 = 0.0031308  # sRGB toe/power break point, all channels
_LUT_BINS = 1 << 13  # bins of x in the 8-bit code lookup table (thresholds are >= 1.5e-4 apart)
_GAUSS_ABOVE = 50.0  # electrons (numpy reference, capture()): above this the Poisson draw is Gaussian


@dataclass(frozen=True)
class ResponseCurve:
    """Per-channel processed-output response f_c: normalised exposure x in [0, 1] -> [0, 1].

    ``u = s_c x`` below ``x0`` else ``(1 + a_c) x^(1/gamma_c) - a_c`` (the sRGB form; ``a_c, s_c``
    make the joint at ``x0 = 0.0031308`` continuous in value and slope), then ``y = (1 + b_c) u / (u + b_c)`` (filmic shoulder, y(1) = 1).
    """

    gamma: tuple[float, float, float] = (2.3, 2.4, 2.5)
    shoulder: tuple[float, float, float] = (1.2, 1.0, 1.1)

    def _params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(gamma, b, a, s): toe slope s and offset a making the toe/power joint C1 at x0."""
        gamma = np.asarray(self.gamma, dtype=np.float64)
        b = np.asarray(self.shoulder, dtype=np.float64)
        # Value and slope continuity at x0: s x0 = (1+a) x0^(1/g) - a, s = (1+a)/g x0^(1/g-1)
        c = _X0 ** (1 / gamma) * (1 - 1 / gamma)
        a = c / (1 - c)
        s = (1 + a) / gamma * _X0 ** (1 / gamma - 1)
        return gamma, b, a, s

    def forward(self, x: np.ndarray) -> np.ndarray:
        """y = f_c(x) for x (..., 3) in [0, 1] (float64)."""
        gamma, b, a, s = self._params()
        x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
        u = np.where(x < _X0, s * x, (1 + a) * np.power(x, 1 / gamma) - a)
        return (1 + b) * u / (u + b)

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """x = f_c^-1(y) for y (..., 3) in [0, 1] (float64)."""
        gamma, b, a, s = self._params()
        y = np.clip(np.asarray(y, dtype=np.float64), 0.0, 1.0)
        u = b * y / (1 + b - y)
        return np.where(u < s * _X0, u / s, np.power((u + a) / (1 + a), gamma))

    def inverse_table(self) -> np.ndarray:
        """The exact inverse table for 8-bit output, (256, 3): ``[z, c] = f_c^-1(z / 255)``."""
        z = np.arange(256, dtype=np.float64) / 255.0
        inv = self.inverse(np.repeat(z[:, None], 3, axis=1))
        inv[0], inv[-1] = 0.0, 1.0  # exact ends (rounding in the closed form)
        return inv


def raw_levels(fmt: PixelFormat) -> tuple[float, float]:
    """(black, white) levels of a raw format: 64 @ 10 bit, 256 @ 12 bit, 4096 @ 16 bit."""
    bits = fmt.bit_depth
    black = {10: 64.0, 12: 256.0, 16: 4096.0}.get(bits, 0.0)
    return black, float((1 << bits) - 1)


@dataclass(frozen=True)
class SensorModel:
    """Noise and quantisation parameters of the simulated sensor (see the module docstring)."""

    sensitivity: float = 1e4  # electrons per (radiance unit x second), all channels
    full_well: float = 6000.0  # electrons
    read_noise: float = 2.5  # electrons rms
    response: ResponseCurve = ResponseCurve()

    def electrons(self, irradiance: np.ndarray, exposure_s: float, rng: np.random.Generator | None
                  ) -> np.ndarray:
        """Electrons (float64) for sensor-plane radiance x vignetting, eqs. (S1)-(S3).

        NaN or negative input counts as 0 (no light). ``rng=None`` gives the noise-free mean.
        """
        # Expected electrons (S1)
        mu = np.array(irradiance, dtype=np.float64)
        np.nan_to_num(mu, copy=False, nan=0.0, posinf=1e30, neginf=0.0)
        np.clip(mu, 0.0, 1e30, out=mu)
        mu *= exposure_s * self.sensitivity
        if rng is None:
            return np.minimum(mu, self.full_well)
        # Shot (S2) and read (S3) noise: for mu >= _GAUSS_ABOVE one Gaussian N(mu, mu + r^2);
        # below it Poisson(mu) plus the read noise N(0, r^2) (reusing the same normal draw)
        r = self.read_noise
        z = rng.standard_normal(mu.shape, dtype=np.float32)
        e = mu + r * r
        np.sqrt(e, out=e)
        e *= z
        e += mu
        small = np.flatnonzero(((mu > 0) & (mu < _GAUSS_ABOVE)).ravel())  # mu = 0: read noise only
        if small.size:
            e.ravel()[small] = rng.poisson(mu.ravel()[small]) + r * z.ravel()[small]
        # Full well: a saturated pixel reads exactly full scale
        return np.minimum(e, self.full_well)

    def digitise(self, electrons: np.ndarray, gain: float, fmt: PixelFormat) -> np.ndarray:
        """Digital numbers from electrons, eqs. (S4)-(S6): uint8 (RGB8) or uint16 (RAW*)."""
        x = np.minimum(electrons * (gain / self.full_well), 1.0)  # (S4)
        if fmt is PixelFormat.RGB8:
            x = np.maximum(x, 0.0)  # the ISP subtracts the black level and clips
            # (S5) as a threshold search: round(255 f(x)) = z  <=>  x in [f^-1((z - 1/2)/255), ...)
            return self._code_lookup(x)
        # (S6): raw keeps the noise below the black level (clipped only at DN 0)
        black, white = raw_levels(fmt)
        return np.clip(np.rint(black + x * (white - black)), 0, white).astype(np.uint16)

    def capture(self, irradiance: np.ndarray, exposure_s: float, gain: float, fmt: PixelFormat,
                rng: np.random.Generator | None) -> np.ndarray:
        """One frame from sensor-plane radiance x vignetting (H, W, 3), noise drawn from ``rng``
        (None: noise-free). The numpy reference of :meth:`expose`."""
        return self.digitise(self.electrons(irradiance, exposure_s, rng), gain, fmt)

    def expose(self, irradiance: np.ndarray, exposure_s: float, gain: float, fmt: PixelFormat,
               seed: int, sequence: int) -> np.ndarray:
        """One noisy frame, eqs. (S1)-(S6), in one compiled pass (module docstring): the noise of
        pixel ``i`` depends only on ``(seed, sequence, i)``."""
        irr = np.ascontiguousarray(irradiance, dtype=np.float32)
        if irr.ndim != 3 or irr.shape[2] != 3:
            raise ValueError(f"irradiance must be (H, W, 3), got {irr.shape}")
        raw = fmt is not PixelFormat.RGB8
        black, white = raw_levels(fmt) if raw else (0.0, 255.0)
        out = np.empty(irr.shape, np.uint16 if raw else np.uint8)
        lut, thr = self._code_table
        key = ((int(seed) * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF) ^ (int(sequence) & 0xFFFFFFFFFFFFFFFF)
        args = (irr.reshape(-1), float(exposure_s) * self.sensitivity, self.full_well, self.read_noise,
                float(gain) / self.full_well, np.uint64(key))
        if raw:
            _expose_raw(*args, float(black), float(white), _ppf_table(), out.reshape(-1))
        else:
            _expose_rgb8(*args, lut, thr, _ppf_table(), out.reshape(-1))
        return out

    @functools.cached_property
    def _code_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(lut, thr): lut[k, c] = number of code thresholds <= k / _LUT_BINS, thr padded by inf.

        Every bin holds at most one threshold (checked), so one comparison finishes the search.
        """
        thr = self._thresholds()
        if np.diff(thr, axis=0).min() <= 1.0 / _LUT_BINS:  # pragma: no cover - curve-dependent
            raise ValueError("response curve too steep for the code lookup table")
        edges = np.arange(_LUT_BINS + 1, dtype=np.float64) / _LUT_BINS
        lut = np.stack([np.searchsorted(thr[:, c], edges, side="right") for c in range(3)], axis=1)
        pad = np.vstack([thr, np.full((1, 3), np.inf)])
        return lut.astype(np.uint8).ravel(), pad.ravel()

    def _code_lookup(self, x: np.ndarray) -> np.ndarray:
        """8-bit codes of x in [0, 1] (..., 3): the exact result of a threshold search."""
        lut, thr = self._code_table
        ch = np.arange(3)
        k = np.minimum((x * _LUT_BINS).astype(np.int64), _LUT_BINS)
        base = lut[k * 3 + ch].astype(np.int64)
        return (base + (x >= thr[base * 3 + ch])).astype(np.uint8)

    def _thresholds(self) -> np.ndarray:
        """x at which the 8-bit code steps from z to z + 1, (255, 3) float64."""
        y = (np.arange(255, dtype=np.float64) + 0.5) / 255.0
        return self.response.inverse(np.repeat(y[:, None], 3, axis=1))

    def truth_inverse(self, fmt: PixelFormat) -> np.ndarray:
        """Pixel value -> x of eq. (S4) for ``fmt``, (2^bits, 3) float64: the exact inverse of
        the 8-bit curve, or ``(z - black) / (white - black)`` clipped at 0 for raw."""
        if fmt is PixelFormat.RGB8:
            return self.response.inverse_table()
        black, white = raw_levels(fmt)
        z = np.arange(1 << fmt.bit_depth, dtype=np.float64)
        return np.repeat(np.clip((z - black) / (white - black), 0.0, None)[:, None], 3, axis=1)

    def truth_response_section(self, fmt: PixelFormat) -> dict[str, object]:
        """The response for ``fmt`` as the calibration file's ``response`` section (CONVENTIONS.md):
        ``inverse`` is channel-major, 3 rows of 2^bits values."""
        return {"model": "linear" if fmt.is_raw else "table", "bits": fmt.bit_depth, "method": "truth",
                "inverse": self.truth_inverse(fmt).T.tolist()}

    @property
    def photometric_scale(self) -> float:
        """Fused value (x / (t g) / V) times this = scene radiance."""
        return self.full_well / self.sensitivity


# ---- the compiled frame -------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True, inline="always")
def _mix(x):  # type: ignore[no-untyped-def]
    """splitmix64 finaliser (uint64 -> uint64)."""
    x = (x ^ (x >> numba.uint64(30))) * numba.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> numba.uint64(27))) * numba.uint64(0x94D049BB133111EB)
    return x ^ (x >> numba.uint64(31))


@numba.njit(cache=True, nogil=True, inline="always")
def _unit(x):  # type: ignore[no-untyped-def]
    """A uint64 hash -> uniform float in (0, 1)."""
    return (float(x >> numba.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, nogil=True)
def _norm_ppf(p):  # type: ignore[no-untyped-def]
    """Inverse standard normal CDF (P. J. Acklam's rational approximation, |rel. err| < 1.2e-9)."""
    if p < 0.02425:
        q = math.sqrt(-2.0 * math.log(p))
        return (((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                  - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00) / \
            ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
              + 3.754408661907416e+00) * q + 1.0)
    if p > 1.0 - 0.02425:
        q = math.sqrt(-2.0 * math.log(1.0 - p))
        return -(((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                   - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00) / \
            ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
              + 3.754408661907416e+00) * q + 1.0)
    q = p - 0.5
    r = q * q
    return (((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02) * r
              + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q / \
        (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02) * r
           + 6.680131188771972e+01) * r - 1.328068155111930e+01) * r + 1.0)


_PPF_CELLS = 1 << 16


@numba.njit(cache=True, nogil=True)
def _ppf_fill(u, out):  # type: ignore[no-untyped-def]
    for k in range(u.shape[0]):
        out[k] = _norm_ppf(u[k])


@functools.cache
def _ppf_table() -> np.ndarray:
    """Phi^-1 at u = k / 2^16, k = 0..2^16 (float64; the ends use the exact ppf at half a cell),
    filled by one compiled loop (65,537 calls from Python took 0.23 s of the camera's open)."""
    u = np.arange(_PPF_CELLS + 1, dtype=np.float64) / _PPF_CELLS
    u[0], u[-1] = 0.5 / _PPF_CELLS, 1 - 0.5 / _PPF_CELLS
    out = np.empty_like(u)
    _ppf_fill(u, out)
    out.flags.writeable = False
    return out


@numba.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _table_normal(h, ppf, cells):  # type: ignore[no-untyped-def]
    """A standard normal deviate from a uint64 hash: the inverse CDF interpolated in its table
    (the outermost cells exactly)."""
    f = float(h >> numba.uint64(11)) * (cells / 9007199254740992.0)
    k = int(f)
    if k == 0 or k >= cells - 1:
        return _norm_ppf((float(h >> numba.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0))
    return ppf[k] + (f - k) * (ppf[k + 1] - ppf[k])


@numba.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _electrons(irr, i, scale, fw, rn2, key, ppf, cells):  # type: ignore[no-untyped-def]
    """Electrons of value ``i`` (S1)-(S3): N(mu, mu + r^2) from the hash of (key, i), clipped at
    the full well."""
    mu = np.float64(irr[i])
    if not (mu > 0.0):  # NaN, negative, zero: no light
        mu = 0.0
    mu = min(mu * scale, 1e30)
    z = _table_normal(_mix(key + numba.uint64(i) * numba.uint64(0x9E3779B97F4A7C15)), ppf, cells)
    return min(mu + math.sqrt(mu + rn2) * z, fw)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _expose_rgb8(irr, scale, fw, rn, gain_fw, key, lut, thr, ppf, out):  # type: ignore[no-untyped-def]
    """8-bit codes (S4)-(S5) of every value of ``irr`` (flat, channel-interleaved) through the
    threshold table (``SensorModel._code_table``)."""
    bins = (lut.size // 3) - 1
    cells = ppf.size - 1
    rn2 = rn * rn
    for p in range(irr.size // 3):
        for c in range(3):
            i = 3 * p + c
            x = max(min(_electrons(irr, i, scale, fw, rn2, key, ppf, cells) * gain_fw, 1.0), 0.0)
            base = lut[min(int(x * bins), bins) * 3 + c]
            out[i] = np.uint8(base + (x >= thr[base * 3 + c]))


@numba.njit(cache=True, nogil=True, fastmath=True)
def _expose_raw(irr, scale, fw, rn, gain_fw, key, black, white, ppf, out):  # type: ignore[no-untyped-def]
    """Raw digital numbers (S4), (S6) of every value of ``irr``."""
    cells = ppf.size - 1
    rn2 = rn * rn
    span = white - black
    for i in range(irr.size):
        x = min(_electrons(irr, i, scale, fw, rn2, key, ppf, cells) * gain_fw, 1.0)
        v = min(max(black + x * span, 0.0), white)
        out[i] = np.uint16(v + 0.5)
