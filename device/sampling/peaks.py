"""Peak detection of strong area lights and the light count a scene needs (Michiels et al. 2015).

``find_peaks`` thresholds the luminance of an equirect map and groups the pixels above the
threshold into connected components (8-connectivity on the sphere: the map wraps at phi = 0 and
every pixel of the first (last) row touches the zenith (nadir)). Each component is a peak: its
integral of radiance x solid angle, its solid angle, its luminance-weighted centroid direction
and its pixel count.

``choose_light_count`` uses the peaks to skip what a scene does not need: when a few peaks carry
most of the energy, it returns the smallest light count (of a geometric ladder up to the
requested maximum) whose light set already meets an error target; otherwise the maximum.

Degenerate maps: NaN/inf and negative values count as 0 (``sanitize_radiance``); an all-black
map has no peaks (and keeps the requested count).

Dtype policy: the map is read as float32; sums, centroids and solid angles are float64.

References
----------
Michiels, Jorissen, Put, Bekaert 2015, "Interactive relighting of virtual objects under
environment lighting", GRAPP, Section 6 (threshold + connected components, Figure 6).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import (
    coarse_equirect,
    directions_from_angles,
    equirect_row_solid_angle,
    lit_rows,
    luminance,
)
from lightprobe.device.formats.bright_regions import (
    DEFAULT_CONTRAST,
    DEFAULT_RELATIVE,
    peak_threshold,
)
from lightprobe.device.formats.bright_regions import sphere_labels as _sphere_labels

from .base import sanitize_radiance

__all__ = ["Peak", "choose_light_count", "find_peaks", "peak_threshold"]



@dataclass(frozen=True)
class Peak:
    """One strong area light: ``direction`` (3,) unit (luminance centroid), ``rgb`` (3,) its
    integral of radiance x solid angle (unit x sr), ``solid_angle`` (sr), ``pixel_count``,
    ``max_luminance`` (the brightest pixel, radiance unit) and ``energy_fraction`` (its share of
    the whole map's luminance integral)."""

    direction: np.ndarray
    rgb: np.ndarray
    solid_angle: float
    pixel_count: int
    max_luminance: float
    energy_fraction: float

    def to_json(self) -> dict[str, Any]:
        return {"direction": [round(float(x), 7) for x in self.direction],
                "rgb": [float(x) for x in self.rgb], "solid_angle": float(self.solid_angle),
                "pixel_count": int(self.pixel_count), "max_luminance": float(self.max_luminance),
                "energy_fraction": float(self.energy_fraction)}


def find_peaks(equirect: np.ndarray, *, threshold: float | None = None,
               relative: float = DEFAULT_RELATIVE, contrast: float = DEFAULT_CONTRAST,
               min_energy_fraction: float = 1e-3, max_peaks: int = 32) -> list[Peak]:
    """Strong area lights of an (H, 2H, 3) radiance map, brightest (most energy) first.

    Parameters
    ----------
    threshold : luminance (radiance unit) a pixel must exceed; ``None`` -> :func:`peak_threshold`,
        its mean taken over the rows that hold light (:func:`lightprobe.core.sphere.lit_rows`: a
        probe's hemisphere map, lower half black, is not a sphere with a black half, whose halved
        mean made its bright sky peaks).
    relative, contrast : parameters of the automatic threshold.
    min_energy_fraction : drop components carrying less of the map's luminance integral.
    max_peaks : keep at most this many (by energy).
    """
    clean, _ = sanitize_radiance(equirect)
    h, w = clean.shape[:2]
    if w != 2 * h:
        raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {clean.shape}",
                         param="equirect")
    omega_row = equirect_row_solid_angle(h, w)
    lum = luminance(clean)
    total = float((lum.astype(np.float64).sum(axis=1) * omega_row).sum())
    if total <= 0:
        return []
    t = peak_threshold(lum, omega_row, relative, contrast, lit_rows(clean)) if threshold is None else threshold
    labels, n = _sphere_labels(lum > t)
    if n == 0:
        return []
    # Per-component sums over the selected pixels only: power, solid angle, centroid
    rows, cols = np.nonzero(labels)
    lab_s = labels[rows, cols]
    om = omega_row[rows]
    rgb_s = clean[rows, cols].astype(np.float64) * om[:, None]
    lum_px = lum[rows, cols].astype(np.float64)
    lum_s = lum_px * om
    dirs = directions_from_angles(np.pi * (rows + 0.5) / h, 2 * np.pi * (cols + 0.5) / w)
    rgb = np.stack([np.bincount(lab_s, rgb_s[:, c], n + 1) for c in range(3)], 1)[1:]
    lpow = np.bincount(lab_s, lum_s, n + 1)[1:]
    cen = np.stack([np.bincount(lab_s, lum_s * dirs[:, c], n + 1) for c in range(3)], 1)[1:]
    sa = np.bincount(lab_s, om, n + 1)[1:]
    cnt = np.bincount(lab_s, minlength=n + 1)[1:]
    peak_lum = np.zeros(n + 1)
    np.maximum.at(peak_lum, lab_s, lum_px)
    peak_lum = peak_lum[1:]
    norms = np.linalg.norm(cen, axis=1)
    peaks = []
    for i in np.argsort(-lpow, kind="stable")[:max_peaks]:
        if lpow[i] < min_energy_fraction * total or norms[i] <= 0:
            continue
        peaks.append(Peak(cen[i] / norms[i], rgb[i], float(sa[i]), int(cnt[i]),
                          float(peak_lum[i]), float(lpow[i] / total)))
    return peaks


def choose_light_count(equirect: np.ndarray, max_count: int, error_target: float, *,
                       sample: Callable[[int], LightSet],
                       peaks: list[Peak] | None = None, peak_energy: float = 0.5,
                       kind: str = "diffuse", min_count: int = 12
                       ) -> tuple[int, list[Peak]]:
    """The light count a scene needs, at most ``max_count``, and the peaks found.

    If the peaks carry at least ``peak_energy`` of the map's luminance integral, the counts
    ``min_count * 2^j`` (never fewer than the number of peaks) below ``max_count`` are tried in
    increasing order and the first whose light set meets ``error_target`` (``kind`` error of
    :mod:`lightprobe.device.sampling.metrics`, evaluated exactly against a 64 x 128 energy-preserving
    reduction of the map) is returned. Otherwise, or if none meets it, ``max_count``.
    ``sample(count)`` builds the light set to judge with the caller's sampler (the Q2-Tree passes
    a fresh build of its own tree).
    """
    from .metrics import ErrorReference

    if max_count < 1:
        raise InputError(f"max_count must be >= 1, got {max_count}", param="max_count")
    clean, _ = sanitize_radiance(equirect)
    found = find_peaks(clean) if peaks is None else peaks
    if sum(p.energy_fraction for p in found) < peak_energy:
        return max_count, found
    ref = ErrorReference(coarse_equirect(clean))
    count = max(min_count, len(found))
    while count < max_count:
        if ref.error(kind, sample(count)) <= error_target:
            return count, found
        count *= 2
    return max_count, found
