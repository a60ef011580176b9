"""Photometric scale: relative probe radiance -> nits, from a lux meter beside the probe.

A horizontal illuminance meter at the probe's position measures
``E = integral over the upper hemisphere of L(w) cos(theta) dw`` [1, eq. 3.8] in lux when L is
in cd/m^2 (nit). The probe sees the same hemisphere: the top half of its equirect map (theta
from +y, CONVENTIONS.md). :func:`upper_irradiance` evaluates the integral on the map's luminance
(Rec. 709 Y) with the exact per-row weight ``(dphi / 2)(sin^2 theta_bottom - sin^2 theta_top)``
(the integral of cos(theta) sin(theta) over the pixel), so a uniform sky of L gives pi L exactly.
The scale is ``s = E_lux / E_probe`` [lux per probe unit]; published radiance is ``s x`` the fused
value, in nits on the Y channel (the same factor multiplies R, G and B so colour is kept).

Repeatability: the meter refreshes every 500 ms; :func:`lux_statistics` reports the mean, the
sample standard deviation and the coefficient of variation over several readings.

Dtype policy: maps are read as float32, every integral is accumulated in float64.

References
----------
.. [1] E. Reinhard et al., "High Dynamic Range Imaging", 2nd ed., ch. 2 (radiometry and
   photometry): illuminance as the cosine-weighted integral of luminance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lightprobe.core.calibration import Photometric
from lightprobe.core.sphere import LUMINANCE_WEIGHTS

__all__ = ["LuxStats", "lux_statistics", "photometric_scale", "upper_irradiance", "upper_row_weights"]


def upper_row_weights(height: int, width: int | None = None) -> np.ndarray:
    """Exact cosine-weighted solid angle of one pixel per row (height,), zero below the horizon.

    Row r spans theta in [pi r/H, pi (r+1)/H]; its weight is
    ``(2 pi / W)(sin^2 theta_1 - sin^2 theta_0) / 2`` for rows above the horizon (theta <= pi/2).
    For odd H the horizon row is split at pi/2.
    """
    width = 2 * height if width is None else width
    t0 = np.pi * np.arange(height, dtype=np.float64) / height
    t1 = np.minimum(np.pi * (np.arange(height, dtype=np.float64) + 1) / height, np.pi / 2)
    w = np.where(t0 < np.pi / 2, 0.5 * (np.sin(t1) ** 2 - np.sin(t0) ** 2), 0.0)
    return (2 * np.pi / width) * w


def upper_irradiance(equirect: np.ndarray) -> float:
    """Cosine-weighted integral of luminance over the upper hemisphere (E = int L cos dw).

    ``equirect`` is (H, W, 3) linear RGB (or (H, W) luminance). Non-finite pixels (NaN from a
    sensor) count as zero; an all-black map gives 0.0.
    """
    img = np.asarray(equirect)
    if img.ndim == 3:
        y = img.astype(np.float64) @ LUMINANCE_WEIGHTS
    elif img.ndim == 2:
        y = img.astype(np.float64)
    else:
        raise ValueError(f"expected an (H, W, 3) or (H, W) map, got shape {img.shape}")
    y = np.where(np.isfinite(y), y, 0.0)
    h, w = y.shape
    return float(upper_row_weights(h, w) @ y.sum(axis=1))


@dataclass(frozen=True)
class LuxStats:
    """Repeatability of meter readings: mean and sample std in lux, CV in percent."""

    values: tuple[float, ...]
    mean: float
    std: float
    cv_percent: float

    def to_json(self) -> dict[str, object]:
        return {"n": len(self.values), "mean_lux": self.mean, "std_lux": self.std,
                "cv_percent": self.cv_percent, "values": list(self.values)}


def lux_statistics(values: Sequence[float]) -> LuxStats:
    """Mean, sample standard deviation and CV% of readings; needs at least one finite value."""
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        raise ValueError("no finite lux readings")
    mean = float(v.mean())
    std = float(v.std(ddof=1)) if v.size > 1 else 0.0
    cv = 100.0 * std / mean if mean > 0 else float("inf")
    return LuxStats(tuple(float(x) for x in v), mean, std, cv)


def photometric_scale(lux: float, equirect: np.ndarray) -> Photometric:
    """Scale s with ``s x upper_irradiance(equirect) = lux`` -> Photometric(s, "nit").

    Raises ValueError when the meter reads nothing or the probe sees no light above the horizon
    (a scale from a black map would be infinite).
    """
    if not np.isfinite(lux) or lux <= 0:
        raise ValueError(f"lux reading {lux!r} must be positive")
    e_probe = upper_irradiance(equirect)
    if not np.isfinite(e_probe) or e_probe <= 0:
        raise ValueError("the probe map has no light in the upper hemisphere: cannot scale")
    return Photometric(scale=float(lux / e_probe), unit="nit")
