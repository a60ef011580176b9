"""The simulated image sensor: photons to electrons to digital numbers, with noise.

Signal chain for one pixel and channel (``L`` sensor-plane radiance in scene units, ``V`` the
vignetting factor, ``t`` exposure in seconds, ``g`` analogue gain)::

    mu    = L V t S                            expected electrons, S = sensitivity   (S1)
    e     ~ Poisson(mu)     (Gaussian approximation N(mu, mu) from 50 e- on)           (S2)
    e'    = min(e + N(0, sigma_read^2), FW)      a saturated pixel reads full scale    (S3)
    x     = min(e' g / FW, 1)                    normalised linear exposure            (S4)
    RGB8  : z = round(255 f_c(max(x, 0)))        f_c the per-channel response curve    (S5)
    RAWb  : z = clip(round(black + x (white - black)), 0, white), white = 2^b - 1     (S6)

``x`` is what ``Response.inverse`` returns, so fused values ``x / (t g) / V = L S / FW`` and the
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

Determinism: every frame draws from ``np.random.default_rng((seed, sequence))``.
Dtype policy: radiance float32 in, electrons float64, output uint8 / uint16.

References
----------
EMVA Standard 1288 (release 4.0, 2021), the linear camera model: mean and variance of the
digital signal, eqs. (S1)-(S4) here. IEC 61966-2-1 (sRGB) for the form of the toe and power law.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from device.core.calibration import Response
from drivers.base import PixelFormat

__all__ = ["ResponseCurve", "SensorModel", "raw_levels"]

_X0 = 0.0031308  # sRGB toe/power break point, all channels
_LUT_BINS = 1 << 18  # bins of x in the 8-bit code lookup table
_GAUSS_ABOVE = 50.0  # electrons: above this the Poisson draw uses its Gaussian approximation


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

    def truth_response(self) -> Response:
        """The exact inverse table for 8-bit output: inverse[z] = f^-1(z / 255)."""
        z = np.arange(256, dtype=np.float64) / 255.0
        inv = self.inverse(np.repeat(z[:, None], 3, axis=1))
        inv[0], inv[-1] = 0.0, 1.0  # exact ends (rounding in the closed form)
        return Response("table", 8, inv, "truth")


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
        """One frame from sensor-plane radiance x vignetting (H, W, 3)."""
        return self.digitise(self.electrons(irradiance, exposure_s, rng), gain, fmt)

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
        return lut.astype(np.int32).ravel(), pad.ravel()

    def _code_lookup(self, x: np.ndarray) -> np.ndarray:
        """8-bit codes of x in [0, 1] (..., 3): the exact result of a threshold search."""
        lut, thr = self._code_table
        ch = np.arange(3)
        k = np.minimum((x * _LUT_BINS).astype(np.int64), _LUT_BINS)
        base = lut[k * 3 + ch]
        return (base + (x >= thr[base * 3 + ch])).astype(np.uint8)

    def _thresholds(self) -> np.ndarray:
        """x at which the 8-bit code steps from z to z + 1, (255, 3) float64."""
        y = (np.arange(255, dtype=np.float64) + 0.5) / 255.0
        return self.response.inverse(np.repeat(y[:, None], 3, axis=1))

    def truth_response(self, fmt: PixelFormat) -> Response:
        """The response the fusion should use for ``fmt`` (maps pixel value to x of eq. S4)."""
        if fmt is PixelFormat.RGB8:
            return self.response.truth_response()
        black, white = raw_levels(fmt)
        r = Response.linear(fmt.bit_depth, black, white)
        return Response(r.model, r.bits, r.inverse, "truth")

    @property
    def photometric_scale(self) -> float:
        """Fused value (x / (t g) / V) times this = scene radiance."""
        return self.full_well / self.sensitivity
