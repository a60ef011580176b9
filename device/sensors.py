"""The lighting as a building's sensors read it: illuminance on a horizontal surface at the probe
(lux once photometrically calibrated), the correlated colour temperature of that light (McCamy
1992 from CIE xy, linear Rec. 709 primaries), and the primary light's elevation and azimuth
(CONVENTIONS.md angles): the MQTT ``sensors`` payload and Home Assistant's entities."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["RGB_TO_XYZ", "cct_mccamy", "horizontal_illuminance", "primary_angles", "sensor_body"]

# linear Rec. 709 / sRGB primaries, D65 white -> CIE XYZ
RGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]])


def _planck_xy(t: float) -> tuple[float, float]:
    """CIE 1931 xy of the Planckian locus, Kim et al. 2002 cubic splines (1667 .. 25000 K)."""
    if t <= 4000:
        x = -0.2661239e9 / t ** 3 - 0.2343589e6 / t ** 2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t ** 3 + 2.1070379e6 / t ** 2 + 0.2226347e3 / t + 0.240390
    if t <= 2222:
        y = -1.1063814 * x ** 3 - 1.34811020 * x ** 2 + 2.18555832 * x - 0.20219683
    elif t <= 4000:
        y = -0.9549476 * x ** 3 - 1.37418593 * x ** 2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x ** 3 - 5.87338670 * x ** 2 + 3.75112997 * x - 0.37001483
    return x, y


def _uv(x: float, y: float) -> tuple[float, float]:
    d = -2 * x + 12 * y + 3
    return 4 * x / d, 6 * y / d


def cct_mccamy(rgb: np.ndarray | list[float]) -> float | None:
    """Correlated colour temperature (K) of linear Rec. 709 RGB by McCamy's cubic in CIE xy
    (C. S. McCamy, Color Res. Appl. 17(2), 1992; within a few K of the tabulated CCTs of D65, D50
    and A). ``None`` for black or non-finite input, outside 1667 .. 25000 K, or farther than
    Duv 0.05 from the Planckian locus (CIE 1960 uv; ANSI C78.377's limit for a CCT to mean
    anything: a saturated colour has no colour temperature)."""
    x_, y_, z_ = RGB_TO_XYZ @ np.asarray(rgb, np.float64).reshape(3)
    s = x_ + y_ + z_
    if not np.isfinite(s) or s <= 0 or y_ <= 0:
        return None
    x, y = x_ / s, y_ / s
    if abs(0.1858 - y) < 1e-9:
        return None
    n = (x - 0.3320) / (0.1858 - y)
    t = 449.0 * n ** 3 + 3525.0 * n ** 2 + 6823.3 * n + 5520.33
    if not 1667.0 <= t <= 25000.0:
        return None
    u, v = _uv(x, y)
    up, vp = _uv(*_planck_xy(t))
    return float(t) if math.hypot(u - up, v - vp) <= 0.05 else None


def horizontal_illuminance(equirect: np.ndarray) -> np.ndarray:
    """(3,) RGB of ``int L cos(theta) dw`` over the upper hemisphere (the light on an upward
    surface at the probe; Y of it is illuminance in lux when the map is in nits). Exact row
    weights; a pixel with any non-finite channel counts as zero (as in the photometric
    calibration's ``upper_irradiance``, so Y is exactly what the lux meter was matched to)."""
    from lightprobe.calibration.photometric import upper_row_weights

    img = np.asarray(equirect)
    h, w = img.shape[:2]
    rows = upper_row_weights(h, w)
    top = int(np.count_nonzero(rows))
    band = img[:top].astype(np.float64)
    band = np.where(np.isfinite(band).all(axis=-1, keepdims=True), band, 0.0)
    return rows[:top] @ band.sum(axis=1)


def primary_angles(direction: np.ndarray | list[float] | None) -> tuple[float | None, float | None]:
    """(elevation above the horizon, azimuth) in degrees of a probe-frame direction, with
    CONVENTIONS.md's azimuth: d = (sin t sin p, cos t, -sin t cos p), p in [0, 360)."""
    if direction is None:
        return None, None
    d = np.asarray(direction, np.float64).reshape(3)
    d = d / max(float(np.linalg.norm(d)), 1e-300)
    elev = math.degrees(math.asin(float(np.clip(d[1], -1.0, 1.0))))
    az = math.degrees(math.atan2(float(d[0]), float(-d[2]))) % 360.0
    return round(elev, 3), round(az, 3)


def sensor_body(rgb: np.ndarray, unit: str, primary: Any, health: str, frame: int,
                timestamp: float, captured: float | None = None) -> dict[str, Any]:
    """The ``sensors`` payload from the horizontal irradiance RGB and the primary direction."""
    from lightprobe.core.sphere import LUMINANCE_WEIGHTS

    e = float(np.asarray(rgb, np.float64) @ LUMINANCE_WEIGHTS)
    elev, az = primary_angles(primary)
    cct = cct_mccamy(rgb)
    return {"version": 1, "illuminance": round(e, 6) if math.isfinite(e) else None,
            "illuminance_unit": "lx" if unit == "nit" else unit,
            "cct": None if cct is None else round(cct, 1), "elevation": elev, "azimuth": az,
            "health": health, "frame": frame, "timestamp": timestamp,
            **({} if captured is None else {"captured": float(captured)})}
