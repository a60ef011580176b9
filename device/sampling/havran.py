"""Havran's hemisphere mapping: unit square <-> concentric disc <-> Lambert equal-area hemisphere.

Forward (``square_to_hemisphere``), with ``a = 2u - 1``, ``b = 2v - 1``:

1. concentric square-to-disc (Shirley-Chiu): if ``|a| > |b|``: ``r = a``,
   ``phi = (pi/4)(b/a)``; else ``r = b``, ``phi = pi/2 - (pi/4)(a/b)`` (zenith at ``a = b = 0``);
2. Lambert equal-area disc-to-hemisphere: ``z = 1 - r^2``,
   ``(x, y) = r sqrt(2 - r^2) (cos phi, sin phi)``.

The composition is equal-area: the unit square covers 2 pi sr uniformly, so
``pdf_omega = pdf_uv / (2 pi)`` with no sin(theta) factor. The mapping is bicontinuous, which is
what lets a continuous 2D distribution on the square move lights smoothly on the sky.

Local frame -> probe frame (CONVENTIONS.md, +y up): ``X = x``, ``Y = z``, ``Z = -y`` for the
upper hemisphere (a rotation); the lower hemisphere mirrors ``Y = -z``.

Dtype policy: float64 in and out. Inverse(forward(u)) = u to ~1e-15 (tested to 1e-9).

References
----------
Havran, Dmitriev, Seidel, "Goniometric diagram mapping for hemisphere", Eurographics 2003 short
papers (the four-map composition); Shirley, Chiu, "A low distortion map between disk and
square", JGT 1997; Havran et al., "Interactive system for dynamic scene lighting using captured
video environment maps", EGSR 2005. Formulas **reconstructed** (see NOTES.md).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "PDF_UV_TO_OMEGA",
    "disc_to_square",
    "hemisphere_to_square",
    "square_to_disc",
    "square_to_hemisphere",
]

PDF_UV_TO_OMEGA = 1.0 / (2.0 * np.pi)  # pdf_omega = pdf_uv / (2 pi)


def square_to_disc(uv: np.ndarray) -> np.ndarray:
    """Concentric map (Shirley-Chiu) of points (..., 2) in [0,1]^2 to the unit disc (..., 2)."""
    uv = np.asarray(uv, np.float64)
    a = 2.0 * uv[..., 0] - 1.0
    b = 2.0 * uv[..., 1] - 1.0
    first = np.abs(a) > np.abs(b)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(first, a, b)
        phi = np.where(first, (np.pi / 4) * (b / np.where(a == 0, 1.0, a)),
                       np.pi / 2 - (np.pi / 4) * (a / np.where(b == 0, 1.0, b)))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)


def disc_to_square(p: np.ndarray) -> np.ndarray:
    """Inverse of :func:`square_to_disc` for points (..., 2) of the closed unit disc."""
    p = np.asarray(p, np.float64)
    r = np.hypot(p[..., 0], p[..., 1])
    th = np.arctan2(p[..., 1], p[..., 0])
    th = np.where(th < -np.pi / 4, th + 2 * np.pi, th)  # th in [-pi/4, 7pi/4)
    k = 4.0 / np.pi
    # Find the sector, then undo phi = (pi/4) b/a or phi = pi/2 - (pi/4) a/b
    s0 = th < np.pi / 4
    s1 = ~s0 & (th < 3 * np.pi / 4)
    s2 = ~s0 & ~s1 & (th < 5 * np.pi / 4)
    a = np.where(s0, r, np.where(s1, (np.pi / 2 - th) * k * r,
                                 np.where(s2, -r, -(np.pi / 2 - (th - np.pi)) * k * r)))
    b = np.where(s0, k * r * th, np.where(s1, r, np.where(s2, -k * r * (th - np.pi), -r)))
    return np.stack([(a + 1.0) / 2.0, (b + 1.0) / 2.0], axis=-1)


def square_to_hemisphere(uv: np.ndarray, lower: bool = False) -> np.ndarray:
    """Directions (..., 3) in the probe frame of square points (..., 2): equal-area, zenith at
    the centre (nadir for ``lower``)."""
    d = square_to_disc(uv)
    r2 = np.minimum(d[..., 0] ** 2 + d[..., 1] ** 2, 1.0)
    z = 1.0 - r2
    s = np.sqrt(2.0 - r2)  # (x, y) = r sqrt(2 - r^2) (cos phi, sin phi)
    y_up = -z if lower else z
    return np.stack([d[..., 0] * s, y_up, -d[..., 1] * s], axis=-1)


def hemisphere_to_square(dirs: np.ndarray, lower: bool = False) -> np.ndarray:
    """Inverse of :func:`square_to_hemisphere`; directions need not be exactly unit length."""
    d = np.asarray(dirs, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    z = np.clip(-d[..., 1] if lower else d[..., 1], 0.0, 1.0)
    s = np.sqrt(1.0 + z)  # |(x, y)| / r = sqrt(2 - r^2) = sqrt(1 + z)
    return disc_to_square(np.stack([d[..., 0] / s, -d[..., 2] / s], axis=-1))
