"""Bright regions of an equirect map: the automatic peak threshold and connected components on
the sphere (the map wraps in phi; each pole row is one neighbourhood). Shared by the samplers'
peak detection (``lightprobe.device.sampling.peaks``) and the primary light (``lightprobe.device.formats.primary``).

Michiels, Jorissen, Put, Bekaert 2015, Section 6 (threshold + connected components).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["DEFAULT_CONTRAST", "DEFAULT_RELATIVE", "block_pixels", "peak_threshold", "sphere_labels"]

DEFAULT_RELATIVE = 0.02
DEFAULT_CONTRAST = 20.0


def peak_threshold(lum: np.ndarray, omega_row: np.ndarray, relative: float = DEFAULT_RELATIVE,
                   contrast: float = DEFAULT_CONTRAST, lit_rows: int | None = None) -> float:
    """Automatic luminance threshold ``max(relative * max, contrast * mean)``.

    ``mean`` is the solid-angle-weighted mean luminance (integral / 4 pi): a peak must stand
    ``contrast`` times above the average sky and within ``1/relative`` of the brightest pixel.
    ``lit_rows``: only the first rows hold light (a probe's hemisphere), so the mean is over
    their solid angle, not the sphere's (which would halve it and make a bright sky a peak).
    """
    lum64 = lum.astype(np.float64)
    area = 4 * np.pi if lit_rows is None else float(omega_row[:lit_rows].sum()) * lum.shape[1]
    mean = float((lum64.sum(axis=1) * omega_row).sum() / max(area, 1e-300))
    return max(relative * float(lum.max(initial=0.0)), contrast * mean)


def sphere_labels(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected components of ``mask`` (H, W) on the sphere: 8-connected, wrapping in phi,
    all pixels of row 0 (row H-1) joined through the pole. Labels 1..n, 0 = background."""
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return labels, 0
    # Join labels across the phi seam (same row and diagonal neighbours) and through the poles
    left, right = labels[:, 0], labels[:, -1]
    pairs = [np.stack([left, right], 1), np.stack([left[1:], right[:-1]], 1),
             np.stack([left[:-1], right[1:]], 1)]
    for row in (labels[0], labels[-1]):
        present = np.unique(row[row > 0])
        if len(present) > 1:
            pairs.append(np.stack([present[:-1], present[1:]], 1))
    p = np.concatenate(pairs)
    p = p[(p[:, 0] > 0) & (p[:, 1] > 0) & (p[:, 0] != p[:, 1])]
    if len(p) == 0:
        return labels, n
    # union-find over the few labels the seam and the poles join (no graph library needed)
    parent = np.arange(n + 1)

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = int(parent[a])
        return a

    for a, b in np.unique(np.sort(p, axis=1), axis=0):
        ra, rb = root(int(a)), root(int(b))
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([root(i) for i in range(n + 1)])
    # relabel so that 0 stays background and components are numbered 1..m
    uniq, relabel = np.unique(roots[1:], return_inverse=True)
    lut = np.concatenate([[0], relabel + 1])
    return lut[labels], len(uniq)


def block_pixels(mask: np.ndarray, f: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution (row, col) of every pixel of the f x f blocks a coarse ``mask`` selects,
    rows below ``rows`` only (a region found on a reduction, read back at full resolution)."""
    br, bc = np.nonzero(mask)
    r_idx = (br[:, None, None] * f + np.arange(f)[None, :, None] + np.zeros(f, np.int64)[None, None, :]).reshape(-1)
    c_idx = (bc[:, None, None] * f + np.zeros(f, np.int64)[None, :, None] + np.arange(f)[None, None, :]).reshape(-1)
    keep = r_idx < rows
    return r_idx[keep], c_idx[keep]
