"""Directions, spherical angles and equirectangular maps, as promised in CONVENTIONS.md.

Probe frame: right-handed, +y up. ``d = (sin t sin p, cos t, -sin t cos p)`` with ``t`` the polar
angle from +y and ``p`` the azimuth (Mitsuba 3's ``envmap`` convention).

Equirect map W x H, W = 2H: pixel (r, c) covers ``t in [pi r/H, pi (r+1)/H]`` and
``p in [2 pi c/W, 2 pi (c+1)/W]``; its solid angle is the exact
``(2 pi / W) (cos t_top - cos t_bottom)``.

Dtype policy: angles and directions are float64; images are float32; sums over whole maps are
accumulated in float64.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "CAMERA_TO_PROBE",
    "LUMINANCE_WEIGHTS",
    "LUM_B",
    "LUM_G",
    "LUM_R",
    "angles_from_directions",
    "coarse_equirect",
    "directions_from_angles",
    "equirect_directions",
    "equirect_integral",
    "equirect_row_solid_angle",
    "equirect_solid_angle",
    "lit_rows",
    "luminance",
]

# Rec. 709 / sRGB primaries, linear light.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
# The same weights as Python floats, for compiled kernels (numba folds them as constants)
LUM_R, LUM_G, LUM_B = (float(w) for w in LUMINANCE_WEIGHTS)

# The fisheye camera frame (OpenCV: x right, y down, z along the optical axis) to the probe frame.
# The lens looks up: the optical axis is the zenith (+y); image right is +x; image down is -z,
# i.e. azimuth 0 (the housing's front mark) lies towards the bottom edge of the sensor image.
CAMERA_TO_PROBE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def directions_from_angles(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) from polar angle ``theta`` (from +y) and azimuth ``phi``."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    theta, phi = np.broadcast_arrays(theta, phi)
    st = np.sin(theta)
    return np.stack([st * np.sin(phi), np.cos(theta), -st * np.cos(phi)], axis=-1)


def angles_from_directions(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(theta, phi)`` of directions (..., 3); phi in [0, 2 pi). Need not be normalised."""
    d = np.asarray(d, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1)
    n = np.where(n > 0, n, 1.0)
    theta = np.arccos(np.clip(d[..., 1] / n, -1.0, 1.0))
    phi = np.arctan2(d[..., 0], -d[..., 2])
    phi = np.where(phi < 0, phi + 2 * np.pi, phi)
    return theta, phi


def equirect_row_solid_angle(height: int, width: int | None = None) -> np.ndarray:
    """Exact solid angle (sr) of one pixel in each row of an equirect map: shape (height,)."""
    width = 2 * height if width is None else width
    t = np.pi * np.arange(height + 1, dtype=np.float64) / height
    return (2 * np.pi / width) * (np.cos(t[:-1]) - np.cos(t[1:]))


def equirect_solid_angle(height: int, width: int | None = None) -> np.ndarray:
    """Exact per-pixel solid angle (height, width); sums to 4 pi."""
    width = 2 * height if width is None else width
    return np.repeat(equirect_row_solid_angle(height, width)[:, None], width, axis=1)


def equirect_directions(height: int, width: int | None = None) -> np.ndarray:
    """Directions (height, width, 3) of pixel centres."""
    width = 2 * height if width is None else width
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    return directions_from_angles(theta[:, None], phi[None, :])


def lit_rows(equirect: np.ndarray) -> int:
    """The rows of an (H, 2H, ...) map that hold light: its upper half when the lower half is
    black (a probe's upper-hemisphere map), else all of them."""
    a = np.asarray(equirect)
    h = a.shape[0]
    return h // 2 if h >= 2 and not a[h // 2:].any() else h


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB (..., 3), computed in the input's float dtype."""
    rgb = np.asarray(rgb)
    w = LUMINANCE_WEIGHTS.astype(rgb.dtype if rgb.dtype.kind == "f" else np.float64)
    return rgb @ w


def equirect_integral(image: np.ndarray) -> np.ndarray:
    """Integral of radiance x solid angle over the sphere, per channel, float64.

    Rows are weighted by their exact solid angle; accumulation is float64 whatever the input.
    """
    image = np.asarray(image)
    h, w = image.shape[:2]
    omega = equirect_row_solid_angle(h, w)
    rows = image.astype(np.float64, copy=False).sum(axis=1)
    return np.tensordot(omega, rows, axes=(0, 0))


def coarse_equirect(equirect: np.ndarray, height: int = 64) -> np.ndarray:
    """Energy-preserving block average of an (H, 2H, 3) map down to (height, 2 height, 3).

    Each block is the solid-angle-weighted mean of its pixels, so radiance x solid angle is
    conserved exactly (float64 sums, float32 output). ``H`` must be a multiple of ``height``;
    smaller maps are returned unchanged.
    """
    h, w = equirect.shape[:2]
    if h <= height or h % height:
        return np.asarray(equirect, np.float32)
    f = h // height
    om = equirect_row_solid_angle(h, w)
    p = np.zeros((height, 2 * height, 3))
    for r0 in range(0, h, 64 * f):   # in bands: float64 copies of a band only
        band = np.asarray(equirect[r0:r0 + 64 * f], np.float64) * om[r0:r0 + 64 * f, None, None]
        n = band.shape[0] // f
        p[r0 // f:r0 // f + n] = band.reshape(n, f, 2 * height, f, 3).sum(axis=(1, 3))
    return (p / equirect_row_solid_angle(height)[:, None, None]).astype(np.float32)
