"""Pharr sampler: pbrt-v3 ``InfiniteAreaLight`` importance sampling of an equirect map.

The PDF over the map is proportional to luminance x solid angle per pixel (marginal over rows,
conditional within a row, :class:`~lightprobe.device.sampling.distribution.Distribution2D` piecewise
constant); a fixed Halton (2, 3) sequence is pushed through the inverse CDFs, so the result is
deterministic and light ``i`` always comes from Halton index ``i + 1`` (``ids = i``).

Light power: ``rgb_k = L(w_k) / (N pdf_omega(w_k))`` with ``pdf_omega = pdf_uv / (2 pi^2 sin
theta)`` (pbrt-v3 eq. 14.x, InfiniteAreaLight::Pdf_Li): an unbiased estimate of the map's
integral. Energy is then conserved exactly by one per-channel scale
``s_c = integral_c / sum_k rgb_k,c`` (the map integral in float64). Because the density is
luminance x solid angle, the luminance of ``L/(N p)`` is already ``integral_Y / N`` up to the
``sin theta`` variation inside a pixel, so ``s`` is 1 up to that variation: the rescaled set is
a ratio estimator (consistent, bias O(1/N)) whose total is exact.

``solid_angle`` of a light is ``1 / (N pdf_omega)``, the region a sample stands for in
expectation (its sum over the set estimates the area of the map's support), clipped to 4 pi.

Degenerate maps: NaN/inf/negative values are set to 0 and counted in ``extra["sanitized"]``; an
all-black map gives an empty light set (sum 0 = integral 0, no NaN).

References
----------
Pharr, Jakob, Humphreys, "Physically Based Rendering", 3rd ed., sec. 14.2.4 (InfiniteAreaLight
sampling) and sec. 13.6.7 (Distribution2D).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import (
    LUM_B,
    LUM_G,
    LUM_R,
    LUMINANCE_WEIGHTS,
    directions_from_angles,
    equirect_row_solid_angle,
)

from ._pixels import clean_invalid
from .distribution import Distribution2D, halton

__all__ = ["PharrSampler", "clean_lookup", "empty_lightset", "prepare_density",
           "rescale_to_total"]


@njit(cache=True)
def _prepare(img, omega):  # type: ignore[no-untyped-def]  # pragma: no cover - numba
    """func = Y x omega, its row prefix sums / W, the map integral and invalid-value counts."""
    h, w = img.shape[0], img.shape[1]
    func = np.empty((h, w))
    cum = np.empty((h, w + 1))
    total = np.zeros(3)
    bad = np.zeros(2, np.int64)
    inv_w = 1.0 / w
    for r in range(h):
        sr = 0.0
        sg = 0.0
        sb = 0.0
        acc = 0.0
        cum[r, 0] = 0.0
        om = omega[r]
        for c in range(w):
            vr = np.float64(img[r, c, 0])
            vg = np.float64(img[r, c, 1])
            vb = np.float64(img[r, c, 2])
            if not (vr >= 0.0 and vg >= 0.0 and vb >= 0.0 and vr + vg + vb < np.inf):
                vr, vg, vb = clean_invalid(vr, vg, vb, bad)
            sr += vr
            sg += vg
            sb += vb
            f = (LUM_R * vr + LUM_G * vg + LUM_B * vb) * om
            func[r, c] = f
            acc += f
            cum[r, c + 1] = acc * inv_w
        total[0] += sr * om
        total[1] += sg * om
        total[2] += sb * om
    return func, cum, total, bad


def prepare_density(img: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, int]]:
    """One pass over an equirect map: ``(func, row_cdf, total, flags)``.

    ``func`` (H, W) float64 = luminance x exact pixel solid angle, ``row_cdf`` (H, W + 1) its
    unnormalised row prefix sums divided by W (what ``Distribution2D`` needs), ``total`` (3,) float64 = the
    map integral, ``flags`` = counts of non-finite and negative values, all of which are read as 0
    (the same policy as :func:`lightprobe.device.sampling.base.sanitize_radiance`, without copying the map).
    """
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) radiance map, got shape {img.shape}")
    if img.dtype != np.float32:
        img = img.astype(np.float32)
    h, w = img.shape[:2]
    func, cum, total, bad = _prepare(np.ascontiguousarray(img), equirect_row_solid_angle(h, w))
    return func, cum, total, {"nonfinite": int(bad[0]), "negative": int(bad[1])}


def clean_lookup(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) float64 of pixels ``(rows, cols)`` with NaN/inf/negative read as 0."""
    v = np.asarray(img[rows, cols], np.float64)
    return np.where(np.isfinite(v) & (v > 0), v, 0.0)


def rescale_to_total(rgb: np.ndarray, total: np.ndarray) -> np.ndarray:
    """Scale each channel of ``rgb`` (N, 3) so its sum equals ``total`` (3,), float64.

    A channel whose lights sum to 0 while ``total`` is not gets the total spread in proportion
    to the lights' luminance (or equally), so energy is conserved in every case.
    """
    rgb = np.asarray(rgb, np.float64).copy()
    if len(rgb) == 0:
        return rgb
    s = rgb.sum(axis=0)
    for c in range(3):
        if s[c] > 0:
            rgb[:, c] *= total[c] / s[c]
        elif total[c] != 0:
            w = rgb.sum(axis=1)
            w = w / w.sum() if w.sum() > 0 else np.full(len(rgb), 1.0 / len(rgb))
            rgb[:, c] = total[c] * w
    return rgb


def empty_lightset(method: str, extra: dict[str, object]) -> LightSet:
    """The light set of an all-black map: no lights (its sum, 0, is the map's integral)."""
    return LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64),
                    method=method, extra=dict(extra))




class PharrSampler:
    """pbrt-v3 importance sampling of the whole sphere; stateless (``reset`` does nothing)."""

    name = "pharr"

    def __init__(self) -> None:
        self._halton: dict[int, np.ndarray] = {}

    def reset(self) -> None:
        """Stateless: nothing to forget."""

    def _points(self, count: int) -> np.ndarray:
        if count not in self._halton:
            self._halton = {count: halton(count)}  # keep one size: a stream uses one count
        return self._halton[count]

    def sample(self, equirect: np.ndarray, count: int) -> LightSet:
        """``count`` lights from ``equirect`` (H, 2H, 3) float32; see the module docstring."""
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        func, row_cdf, total, flags = prepare_density(equirect)
        extra: dict[str, object] = {"sanitized": flags} if any(flags.values()) else {}
        h, w = func.shape
        if not total @ LUMINANCE_WEIGHTS > 0:
            return empty_lightset(self.name, extra)
        dist = Distribution2D(func, row_cdf=row_cdf)
        uv, pdf_uv = dist.sample(self._points(count))
        theta = uv[:, 1] * np.pi
        phi = uv[:, 0] * 2 * np.pi
        dirs = directions_from_angles(theta, phi)
        # L / (N p), pdf_omega = pdf_uv / (2 pi^2 sin theta)  (pbrt-v3 InfiniteAreaLight::Pdf_Li)
        r = np.minimum((uv[:, 1] * h).astype(np.int64), h - 1)
        c = np.minimum((uv[:, 0] * w).astype(np.int64), w - 1)
        radiance = clean_lookup(equirect, r, c)
        pdf_omega = pdf_uv / (2 * np.pi**2 * np.maximum(np.sin(theta), 1e-12))
        rgb = radiance / (count * pdf_omega[:, None])
        rgb = rescale_to_total(rgb, total)
        solid = np.minimum(1.0 / (count * pdf_omega), 4 * np.pi)
        return LightSet(dirs, rgb, solid, np.arange(count, dtype=np.int64), method=self.name,
                        extra=extra)
