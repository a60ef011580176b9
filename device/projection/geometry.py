"""Geometry for the projection: KB4 unprojection, subpixel solid angles, output grids.

Dtype policy: float64 throughout (directions, solid angles).

References
----------
Van Oosterom, A. & Strackee, J. 1983, "The solid angle of a plane triangle", IEEE Trans. Biomed.
Eng. 30(2), eq. (VOS): tan(Omega/2) = |a.(b x c)| / (1 + a.b + b.c + c.a).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from lightprobe.core.calibration import FisheyeModel
from lightprobe.core.errors import InputError
from lightprobe.core.healpix import face_xy_to_directions, nest_to_xyf, npix, vec2pix_nest
from lightprobe.core.sphere import CAMERA_TO_PROBE, angles_from_directions, equirect_row_solid_angle

__all__ = [
    "fisheye_pixel_directions",
    "fisheye_pixel_solid_angles",
    "fisheye_valid_mask",
    "spherical_triangle_solid_angle",
]


# ------------------------------------------------------------------------------------------------
# Pure geometry helpers
# ------------------------------------------------------------------------------------------------
def spherical_triangle_solid_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Solid angle (sr) of spherical triangles with unit vertices ``a, b, c`` (..., 3), float64.

    Van Oosterom & Strackee 1983, eq. (VOS); orientation-free (absolute triple product).
    """
    num = np.abs(np.einsum("...k,...k->...", a, np.cross(b, c)))
    den = 1.0 + np.einsum("...k,...k->...", a, b) + np.einsum("...k,...k->...", b, c) \
        + np.einsum("...k,...k->...", c, a)
    return 2.0 * np.arctan2(num, den)  # (VOS)


def _theta_table(fisheye: FisheyeModel) -> tuple[np.ndarray, np.ndarray]:
    """Monotone table (theta_d, theta) over the range where KB4 is increasing (float64)."""
    theta = np.linspace(0.0, np.pi, 100001)
    theta_d = fisheye.distort_theta(theta)
    bad = np.flatnonzero(np.diff(theta_d) <= 0)
    if bad.size:
        theta, theta_d = theta[: bad[0] + 1], theta_d[: bad[0] + 1]
    if theta.size < 2:
        raise InputError("fisheye.D gives a non-increasing distortion", param="fisheye.D")
    return theta_d, theta


def _unproject(fisheye: FisheyeModel, table: tuple[np.ndarray, np.ndarray],
               u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Probe-frame unit directions (..., 3) and camera polar angle of pixel coordinates.

    KB4 inverted by interpolation in a monotone table (OpenCV pixel centres at integers).
    """
    K = fisheye.K
    my = (v - K[1, 2]) / K[1, 1]
    mx = (u - K[0, 2] - K[0, 1] * my) / K[0, 0]
    rd = np.hypot(mx, my)
    theta = np.interp(rd, table[0], table[1])
    s = np.where(rd > 1e-15, np.sin(theta) / np.where(rd > 1e-15, rd, 1.0), 1.0)
    cam = np.stack(np.broadcast_arrays(mx * s, my * s, np.cos(theta)), axis=-1)
    return cam @ CAMERA_TO_PROBE.T, theta


def fisheye_pixel_directions(fisheye: FisheyeModel) -> np.ndarray:
    """Probe-frame directions (h, w, 3) of the fisheye pixel centres (float64)."""
    w, h = fisheye.image_size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    return _unproject(fisheye, _theta_table(fisheye), uu, vv)[0]


def fisheye_valid_mask(fisheye: FisheyeModel, ring_margin_deg: float = 0.5) -> np.ndarray:
    """Pixels (h, w) bool whose centre lies within ``fov_deg / 2 - ring_margin_deg`` of the axis."""
    w, h = fisheye.image_size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    _, theta = _unproject(fisheye, _theta_table(fisheye), uu, vv)
    limit = np.deg2rad(fisheye.fov_deg / 2.0 - ring_margin_deg)
    return np.asarray(theta <= min(limit, float(_theta_table(fisheye)[1][-1]) - 1e-9))


@dataclass(frozen=True)
class _Chunk:
    """Subpixels of a band of fisheye rows: the valid ones, with their corner lattice."""

    pix: np.ndarray  # (n,) flat fisheye pixel index of each subpixel
    omega: np.ndarray  # (n,) solid angle (sr)
    centre: np.ndarray  # (n, 3) probe-frame centre direction
    lattice: np.ndarray  # (k, 3) probe-frame corner directions
    corners: np.ndarray  # (n, 4) indices into lattice


def _subpixel_chunks(fisheye: FisheyeModel, valid: np.ndarray, s: int,
                     rows: int = 24) -> Iterator[_Chunk]:
    """Yield the s x s subpixels of the valid pixels, a band of fisheye rows at a time.

    Subpixel solid angles come from their corner directions, two triangles each (VOS), so the
    subpixels of a pixel sum to its solid angle.
    """
    w, h = fisheye.image_size
    table = _theta_table(fisheye)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        cols = np.flatnonzero(valid[r0:r1].any(axis=0))
        if cols.size == 0:
            continue
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        nu, nv = (c1 - c0) * s, (r1 - r0) * s
        uu = c0 - 0.5 + np.arange(nu + 1) / s
        vv = r0 - 0.5 + np.arange(nv + 1) / s
        p, _ = _unproject(fisheye, table, uu[None, :], vv[:, None])
        a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, 1:], p[1:, :-1]
        omega = spherical_triangle_solid_angle(a, b, c) + spherical_triangle_solid_angle(a, c, d)
        centre = a + b + c + d
        centre /= np.linalg.norm(centre, axis=-1, keepdims=True)
        sr = r0 + np.arange(nv) // s
        sc = c0 + np.arange(nu) // s
        keep = valid[sr][:, sc]
        pix = (sr[:, None] * w + sc[None, :])[keep]
        ia = (np.arange(nv)[:, None] * (nu + 1) + np.arange(nu)[None, :])[keep]
        corners = np.stack([ia, ia + 1, ia + nu + 2, ia + nu + 1], axis=1)
        yield _Chunk(pix, omega[keep], centre[keep], p.reshape(-1, 3), corners)


def fisheye_pixel_solid_angles(fisheye: FisheyeModel, subdiv: int = 4,
                               valid: np.ndarray | None = None) -> np.ndarray:
    """Solid angle (sr) of each fisheye pixel's footprint, (h, w) float64 (0 where not valid).

    Sum over ``subdiv x subdiv`` subpixel quadrilaterals of their spherical solid angle (VOS).
    ``valid`` defaults to every pixel whose footprint is inside the monotone range of the lens.
    """
    w, h = fisheye.image_size
    if valid is None:
        valid = fisheye_valid_mask(fisheye.__class__(fisheye.image_size, fisheye.K, fisheye.D,
                                                     fov_deg=360.0), 0.0)
    out = np.zeros(h * w)
    for ch in _subpixel_chunks(fisheye, valid, subdiv):
        out += np.bincount(ch.pix, weights=ch.omega, minlength=h * w)
    return out.reshape(h, w)


# ------------------------------------------------------------------------------------------------
# Output grids
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _LatLong:
    """Equirect-style grid: ``rows`` rows of ``pi / full_rows`` rad from the zenith, ``cols`` cols."""

    rows: int
    cols: int
    full_rows: int  # rows of the whole sphere at this spacing (polar map: 2 x rows)

    @property
    def size(self) -> int:
        return self.rows * self.cols

    def solid_angle(self) -> np.ndarray:
        row = equirect_row_solid_angle(self.full_rows, self.cols)[: self.rows]
        return np.repeat(row, self.cols)

    def bin(self, d: np.ndarray) -> np.ndarray:
        theta, phi = angles_from_directions(d)
        r = np.minimum((theta * (self.full_rows / np.pi)).astype(np.int64), self.full_rows - 1)
        c = (phi * (self.cols / (2 * np.pi))).astype(np.int64) % self.cols
        return np.where(r < self.rows, r * self.cols + c, -1)

    def points(self, fr: np.ndarray, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """Directions (hi - lo, len(fr)**2, 3) at fractional positions ``fr`` inside pixels
        ``lo .. hi`` (row-major; default every pixel)."""
        hi = self.size if hi is None else hi
        p = np.arange(lo, hi)
        r = (p // self.cols)[:, None, None] + fr[None, :, None]
        c = (p % self.cols)[:, None, None] + fr[None, None, :]
        theta = r * (np.pi / self.full_rows)
        phi = c * (2 * np.pi / self.cols)
        st = np.sin(theta)
        d = np.stack(np.broadcast_arrays(st * np.sin(phi), np.cos(theta), -st * np.cos(phi)), -1)
        return d.reshape(hi - lo, fr.size**2, 3)


@dataclass(frozen=True)
class _Healpix:
    nside: int

    @property
    def size(self) -> int:
        return npix(self.nside)

    def solid_angle(self) -> np.ndarray:
        return np.full(self.size, 4 * np.pi / self.size)

    def bin(self, d: np.ndarray) -> np.ndarray:
        return vec2pix_nest(self.nside, d)

    def points(self, fr: np.ndarray, lo: int = 0, hi: int | None = None) -> np.ndarray:
        hi = self.size if hi is None else hi
        ix, iy, face = nest_to_xyf(self.nside, np.arange(lo, hi))
        x = (ix[:, None, None] + fr[None, :, None]) / self.nside
        y = (iy[:, None, None] + fr[None, None, :]) / self.nside
        f = np.broadcast_to(face[:, None, None], (*x.shape[:1], fr.size, fr.size))
        return face_xy_to_directions(f, np.broadcast_to(x, f.shape), np.broadcast_to(y, f.shape)
                                     ).reshape(hi - lo, fr.size**2, 3)


_Grid = _LatLong | _Healpix
