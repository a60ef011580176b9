"""The primary light: the brightest peak of a map as one directional light, its energy moved out
of the ambient SH (ARCore, WebXR ``primaryLightDirection`` / ``primaryLightIntensity``, OpenXR's
TOTAL vs AMBIENT).

Why: order-2 SH cannot hold a small bright source; its irradiance is off by several percent
wherever a sun or a strong lamp is in view. A point light can: ``E(n) = rgb max(0, n . d)`` is
exact for a source of small solid angle. So the host gets ``ambient SH + one directional light``.

The extraction (choices the hosts' documents leave open):
1. The connected bright regions (:mod:`lightprobe.device.formats.bright_regions`, as the samplers' peaks) on a
   64 x 128 energy-preserving reduction of the map (threshold ``max(2% of the brightest, 20 x the mean)``, connected components on
   the sphere); the primary is the peak with the most energy. On the reduction, so a 256-row map
   costs well under a millisecond and the choice does not flicker with pixel noise.
2. At full resolution, inside that peak's coarse blocks, each pixel gives up its *excess* over
   the threshold, ``L max(0, 1 - t / lum)`` (per channel, the colour kept): the peak region is
   left at the threshold, continuous with its surroundings, so the ambient map has no hole (a
   hole is high frequency, which order-2 SH rings on).
3. ``rgb`` is the excess's integral of radiance x solid angle (irradiance at normal incidence,
   like a light set's ``rgb``); ``direction`` its luminance-weighted centroid (unit, towards the
   light); ``solid_angle`` the pixels that gave up light. Ambient = SH(map) - SH(excess), exact
   because projection is linear.
No peak (overcast sky, all-black frame) -> no primary light; ambient = all light.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from lightprobe.core.sh import sh_basis
from lightprobe.core.sphere import (
    LUM_B,
    LUM_G,
    LUM_R,
    directions_from_angles,
    equirect_row_solid_angle,
    luminance,
)

__all__ = ["PrimaryLight", "ambient_map", "extract_primary"]

COARSE_HEIGHT = 64


@numba.njit(cache=True, nogil=True, fastmath=True)
def _coarse_luminance(top: np.ndarray, omega: np.ndarray, f: int, c_pow: np.ndarray,
                      lum: np.ndarray) -> None:  # pragma: no cover - compiled
    """Per-pixel Rec. 709 luminance (``lum``) and its integral over f x f blocks (``c_pow``)."""
    nb = top.shape[1] // f
    for r in range(top.shape[0]):
        om = omega[r]
        i = r // f
        for b in range(nb):
            acc = 0.0
            for c in range(b * f, b * f + f):
                y = LUM_R * top[r, c, 0] + LUM_G * top[r, c, 1] + LUM_B * top[r, c, 2]
                lum[r, c] = y
                acc += y
            c_pow[i, b] += acc * om


@dataclass(frozen=True)
class PrimaryLight:
    """``direction`` (3,) unit, towards the light; ``rgb`` (3,) unit x sr; ``solid_angle`` sr;
    ``energy_fraction`` of the map's luminance integral; ``sh`` (9, 3): the canonical SH of the
    light taken out of the map (subtract it from the map's SH for the ambient)."""

    direction: np.ndarray
    rgb: np.ndarray
    solid_angle: float
    energy_fraction: float
    sh: np.ndarray
    pixels: tuple[np.ndarray, np.ndarray] | None = None  # (rows, cols) that gave up light
    excess: np.ndarray | None = None  # (k, 3) radiance each gave up

    def to_json(self) -> dict[str, Any]:
        return {"direction": [round(float(x), 7) for x in self.direction],
                "rgb": [float(x) for x in self.rgb], "solid_angle": float(self.solid_angle)}


def extract_primary(equirect: np.ndarray, *, rows: int | None = None,
                    min_energy_fraction: float = 0.01) -> PrimaryLight | None:
    """The primary light of an (H, 2H, 3) map (see the module notes), or ``None``.

    ``rows``: only the first rows hold light (the probe's upper hemisphere); ``min_energy_fraction``:
    a peak carrying less of the map's luminance is not worth a light of its own.
    """
    from lightprobe.device.formats.bright_regions import block_pixels, peak_threshold
    from lightprobe.device.formats.bright_regions import sphere_labels as _sphere_labels

    a = np.asarray(equirect)
    h, w = a.shape[:2]
    rows = h if rows is None else int(rows)
    top = np.ascontiguousarray(a[:rows], np.float32)
    mn, mx = float(top.min(initial=0.0)), float(top.max(initial=0.0))
    if not (np.isfinite(mn) and np.isfinite(mx) and mn >= 0):  # NaN / inf / negative count as black
        top = np.where(np.isfinite(top) & (top > 0), top, np.float32(0))
    ch = COARSE_HEIGHT if h > COARSE_HEIGHT and h % COARSE_HEIGHT == 0 else h
    f = h // ch
    crow = -(-rows // f)  # coarse rows that hold light
    omega = equirect_row_solid_angle(h, w)
    c_omega = equirect_row_solid_angle(ch)
    c_pow = np.zeros((ch, 2 * ch))
    lum_full = np.empty((rows, w), np.float32)
    _coarse_luminance(top, omega, f, c_pow, lum_full)
    c_lum = c_pow / c_omega[:, None]  # energy-preserving block means of the luminance
    total = float(c_pow.sum())
    if not total > 0:
        return None
    t = peak_threshold(c_lum, c_omega)
    labels, n = _sphere_labels(c_lum > t)
    if n == 0:
        return None
    power = np.bincount(labels.ravel(), c_pow.ravel(), n + 1)[1:]
    best = int(np.argmax(power)) + 1
    if power[best - 1] < min_energy_fraction * total:
        return None
    # the primary's coarse blocks, at full resolution: pixels that exceed the threshold give up
    # their excess
    f = h // ch
    r_idx, c_idx = block_pixels(labels[:crow] == best, f, rows)
    lum = lum_full[r_idx, c_idx].astype(np.float64)
    sel = lum > t
    if not sel.any():
        return None
    r_idx, c_idx = r_idx[sel], c_idx[sel]
    excess = top[r_idx, c_idx].astype(np.float64) * (1.0 - t / lum[sel])[:, None]
    om = omega[r_idx]
    dirs = directions_from_angles(np.pi * (r_idx + 0.5) / h, 2 * np.pi * (c_idx + 0.5) / w)
    pw = excess * om[:, None]
    lum_p = luminance(pw)
    cen = lum_p @ dirs
    norm = float(np.linalg.norm(cen))
    if norm <= 0:
        return None
    return PrimaryLight(cen / norm, pw.sum(axis=0), float(om.sum()), float(lum_p.sum() / total),
                        sh_basis(dirs).T @ pw, (r_idx, c_idx), excess.astype(np.float32))


def ambient_map(equirect: np.ndarray, primary: PrimaryLight | None) -> np.ndarray:
    """The map without the primary light's excess (a float32 copy; the map itself if no primary)."""
    out = np.array(equirect, np.float32, copy=True)
    if primary is not None and primary.pixels is not None and primary.excess is not None:
        r, c = primary.pixels
        out[r, c] = np.maximum(out[r, c] - primary.excess, 0.0)
    return out
