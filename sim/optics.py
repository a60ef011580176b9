"""The simulator's own optics: sphere conventions, the KB4 lens, its mounting and its fall-off.

Written from the documents, not from the probe's code, so a convention error in one is not
cancelled by the same error in the other (``tests/test_independence.py`` checks each
against the probe's model and against OpenCV, and fails if the simulator imports the probe's):

- Directions (CONVENTIONS.md): ``d = (sin t sin p, cos t, -sin t cos p)``, ``t`` the polar angle
  from +y (up), ``p`` the azimuth. An equirect map's row ``r`` spans ``t in [pi r/H, pi (r+1)/H]``,
  column ``c`` spans ``p in [2 pi c/W, 2 pi (c+1)/W]``; its pixels' exact solid angle is
  ``(2 pi / W)(cos t_top - cos t_bottom)``.
- The lens (Kannala & Brandt 2006, OpenCV's ``cv2.fisheye``): a camera-frame direction (x right,
  y down, z along the optical axis) at polar angle ``theta`` lands at distorted radius
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` in normalised
  coordinates, then ``u = fx a + skew b + cx``, ``v = fy b + cy`` with ``(a, b)`` the normalised
  point along the direction's azimuth.
- The mounting (NOTES.md, "the probe frame"): the lens looks up, so the optical axis is the probe's
  +y; image right is probe +x; image down is probe -z (azimuth 0, the housing's front mark, towards
  the bottom edge of the image). :data:`MOUNT` is that rotation, camera -> probe.
- Vignetting: ``V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6``, ``r`` the distance from the principal point
  over the image-circle radius; measured pixel values are ``V x`` the unvignetted ones.

The calibration the simulator hands out as its ground truth is written from these objects in the
calibration file's schema (CONVENTIONS.md), by :meth:`Kb4Lens.calibration_section` and
:meth:`RadialFalloff.calibration_section`.

Dtype policy: float64 throughout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "MOUNT",
    "Kb4Lens",
    "RadialFalloff",
    "angles_of",
    "direction",
    "equirect_centres",
    "equirect_integral",
    "equirect_row_omega",
]

# Camera frame (x right, y down, z optical axis) -> probe frame (+y up): columns are the camera
# axes in the probe frame: x_cam -> +x, y_cam (image down) -> -z, z_cam (optical axis) -> +y.
MOUNT = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def direction(theta: np.ndarray | float, phi: np.ndarray | float) -> np.ndarray:
    """Unit probe-frame directions (..., 3) of polar angle ``theta`` (from +y) and azimuth ``phi``."""
    t, p = np.broadcast_arrays(np.asarray(theta, dtype=np.float64), np.asarray(phi, dtype=np.float64))
    s = np.sin(t)
    return np.stack([s * np.sin(p), np.cos(t), -s * np.cos(p)], axis=-1)


def angles_of(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi in [0, 2 pi)) of probe-frame directions (..., 3), not necessarily unit."""
    d = np.asarray(d, dtype=np.float64)
    horizontal = np.hypot(d[..., 0], d[..., 2])
    theta = np.arctan2(horizontal, d[..., 1])
    phi = np.mod(np.arctan2(d[..., 0], -d[..., 2]), 2 * np.pi)
    return theta, phi


def equirect_row_omega(height: int) -> np.ndarray:
    """Exact solid angle (sr) of one pixel of each row of an (H, 2H) equirect map, shape (H,)."""
    edges = np.cos(np.linspace(0.0, np.pi, height + 1))
    return (np.pi / height) * (edges[:-1] - edges[1:])


def equirect_centres(height: int) -> np.ndarray:
    """Probe-frame directions (H, 2H, 3) of an equirect map's pixel centres."""
    theta = (np.arange(height) + 0.5) * (np.pi / height)
    phi = (np.arange(2 * height) + 0.5) * (np.pi / height)
    return direction(theta[:, None], phi[None, :])


def equirect_integral(image: np.ndarray) -> np.ndarray:
    """Radiance x solid angle of an (H, 2H, C) map over the sphere, per channel (float64)."""
    img = np.asarray(image)
    rows = img.sum(axis=1, dtype=np.float64)
    return equirect_row_omega(img.shape[0]) @ rows


@dataclass(frozen=True)
class Kb4Lens:
    """A Kannala-Brandt (KB4) fisheye: ``image_size`` (width, height), intrinsics ``K`` (3x3),
    distortion ``D`` (k1..k4), clean field of view ``fov_deg`` (what the calibration reports)."""

    image_size: tuple[int, int]
    K: np.ndarray
    D: np.ndarray
    fov_deg: float = 185.0

    def theta_d(self, theta: np.ndarray) -> np.ndarray:
        """Distorted radius (normalised coordinates) of polar angle ``theta``."""
        t = np.asarray(theta, dtype=np.float64)
        poly = np.polynomial.polynomial.polyval(t * t, np.concatenate([[1.0], self.D]))
        return t * poly

    def theta_d_prime(self, theta: np.ndarray) -> np.ndarray:
        """``d theta_d / d theta``."""
        t = np.asarray(theta, dtype=np.float64)
        coeffs = np.concatenate([[1.0], self.D * np.array([3.0, 5.0, 7.0, 9.0])])
        return np.polynomial.polynomial.polyval(t * t, coeffs)

    def theta_table(self, theta_max: float, *, required: float | None = None) -> tuple[float, np.ndarray]:
        """The inverse of :meth:`theta_d` on a uniform grid of ``theta_d``: (grid step, theta at
        each grid point), from 0 up to ``theta_max`` or to where the distortion stops increasing,
        whichever comes first. Linear interpolation in it is within 1e-8 rad. Raises if the
        distortion is not monotone up to ``required`` (default ``theta_max``)."""
        theta = np.linspace(0.0, theta_max, 100001)
        td = self.theta_d(theta)
        rising = np.diff(td) > 0
        end = theta.size if rising.all() else int(np.argmin(rising)) + 1
        if theta[end - 1] < (theta_max if required is None else required):
            raise ValueError(f"KB4 distortion {self.D.tolist()} is not monotone up to "
                             f"{np.degrees(theta_max if required is None else required):.1f} deg")
        grid = np.linspace(0.0, td[end - 1], 50001)
        return float(grid[1]), np.interp(grid, td[:end], theta[:end])

    def normalised(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image coordinates (a, b) of pixel coordinates (OpenCV: centres at integers)."""
        K = self.K
        b = (np.asarray(v, dtype=np.float64) - K[1, 2]) / K[1, 1]
        a = (np.asarray(u, dtype=np.float64) - K[0, 2] - K[0, 1] * b) / K[0, 0]
        return a, b

    def project(self, dirs_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of camera-frame directions (..., 3), also beyond 90 deg."""
        d = np.asarray(dirs_cam, dtype=np.float64)
        rho = np.hypot(d[..., 0], d[..., 1])
        theta = np.arctan2(rho, d[..., 2])
        safe = np.where(rho > 0, rho, 1.0)
        a = np.where(rho > 0, d[..., 0] / safe, 0.0) * self.theta_d(theta)
        b = np.where(rho > 0, d[..., 1] / safe, 0.0) * self.theta_d(theta)
        K = self.K
        return np.stack([K[0, 0] * a + K[0, 1] * b + K[0, 2], K[1, 1] * b + K[1, 2]], axis=-1)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit camera-frame directions (..., 3) of pixel coordinates (..., 2), via the table of
        :meth:`theta_table` up to 12 deg past the field of view or where the distortion turns
        (NaN beyond it)."""
        p = np.asarray(pixels, dtype=np.float64)
        a, b = self.normalised(p[..., 0], p[..., 1])
        rd = np.hypot(a, b)
        step, table = self.theta_table(np.radians(self.fov_deg / 2 + 12.0), required=np.radians(self.fov_deg / 2))
        pos = rd / step
        i = np.minimum(pos.astype(np.int64), table.size - 2)
        f = pos - i
        theta = np.where(pos <= table.size - 1, table[i] * (1 - f) + table[i + 1] * f, np.nan)
        s = np.where(rd > 0, np.sin(theta) / np.where(rd > 0, rd, 1.0), 1.0)
        return np.stack([a * s, b * s, np.cos(theta)], axis=-1)

    def calibration_section(self) -> dict[str, Any]:
        """This lens as the calibration file's ``fisheye`` section (CONVENTIONS.md)."""
        return {"model": "opencv-fisheye", "image_size": [int(self.image_size[0]), int(self.image_size[1])],
                "K": np.asarray(self.K, dtype=np.float64).tolist(), "D": [float(k) for k in self.D],
                "fov_deg": float(self.fov_deg)}


@dataclass(frozen=True)
class RadialFalloff:
    """Vignetting ``V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6``, ``r = |p - center| / radius_px``."""

    center: tuple[float, float]
    radius_px: float
    coeffs: tuple[float, float, float]

    def factor(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """V at pixel coordinates (float64)."""
        r2 = (np.hypot(np.asarray(u, dtype=np.float64) - self.center[0],
                       np.asarray(v, dtype=np.float64) - self.center[1]) / self.radius_px) ** 2
        return np.polynomial.polynomial.polyval(r2, np.concatenate([[1.0], self.coeffs]))

    def calibration_section(self) -> dict[str, Any]:
        """This fall-off as the calibration file's ``vignetting`` section (CONVENTIONS.md)."""
        return {"model": "radial-poly6", "center": [float(c) for c in self.center],
                "radius_px": float(self.radius_px), "coeffs": [float(c) for c in self.coeffs]}
