"""HEALPix in the NESTED scheme, written here so the service has no GPL dependency.

Angles follow the probe convention of ``device.sphere``: ``theta`` is the polar angle from +y and
``phi`` the azimuth, so a HEALPix map here is the standard one with (theta, phi) read in the probe
frame. A pixel p at nside N has children 4p .. 4p+3 at nside 2N, so the descendants of any quad
are one contiguous index range at a finer level.

References
----------
Gorski et al. 2005, "HEALPix: a framework for high-resolution discretization", ApJ 622.
Healpix_cxx ``loc2pix`` / ``pix2loc`` / ``xyf2loc`` (the face-coordinate formulas below).
"""

from __future__ import annotations

import numpy as np

from .sphere import angles_from_directions, directions_from_angles

__all__ = [
    "JPLL",
    "JRLL",
    "ang2pix_nest",
    "face_xy_to_directions",
    "nest_to_xyf",
    "npix",
    "pix2ang_nest",
    "pix2vec_nest",
    "pixel_solid_angle",
    "vec2pix_nest",
    "xyf_to_nest",
]

JRLL = np.array([2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4], dtype=np.int64)
JPLL = np.array([1, 3, 5, 7, 0, 2, 4, 6, 1, 3, 5, 7], dtype=np.int64)


def _check_nside(nside: int) -> int:
    nside = int(nside)
    if nside < 1 or nside & (nside - 1) or nside > 1 << 13:
        raise ValueError(f"nside must be a power of two in [1, 8192], got {nside}")
    return nside


def npix(nside: int) -> int:
    """Number of pixels, 12 nside^2."""
    return 12 * _check_nside(nside) ** 2


def pixel_solid_angle(nside: int) -> float:
    """Solid angle of every pixel at this nside: 4 pi / (12 nside^2)."""
    return 4.0 * np.pi / npix(nside)


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert a zero bit between each of the low 16 bits of v (Morton interleave)."""
    v = v.astype(np.int64) & 0xFFFF
    v = (v | (v << 8)) & 0x00FF00FF
    v = (v | (v << 4)) & 0x0F0F0F0F
    v = (v | (v << 2)) & 0x33333333
    v = (v | (v << 1)) & 0x55555555
    return v


def _compress_bits(v: np.ndarray) -> np.ndarray:
    """Inverse of ``_spread_bits``: keep the even bits of v."""
    v = v.astype(np.int64) & 0x55555555
    v = (v | (v >> 1)) & 0x33333333
    v = (v | (v >> 2)) & 0x0F0F0F0F
    v = (v | (v >> 4)) & 0x00FF00FF
    v = (v | (v >> 8)) & 0x0000FFFF
    return v


def xyf_to_nest(nside: int, ix: np.ndarray, iy: np.ndarray, face: np.ndarray) -> np.ndarray:
    """NESTED index from in-face coordinates (ix, iy) and face number."""
    nside = _check_nside(nside)
    return np.asarray(face, np.int64) * nside * nside + (_spread_bits(ix) | (_spread_bits(iy) << 1))


def nest_to_xyf(nside: int, ipix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In-face coordinates (ix, iy) and face of NESTED indices."""
    nside = _check_nside(nside)
    ipix = np.asarray(ipix, np.int64)
    nsq = nside * nside
    face = ipix // nsq
    p = ipix - face * nsq
    return _compress_bits(p), _compress_bits(p >> 1), face


def ang2pix_nest(nside: int, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """NESTED pixel containing each (theta, phi)."""
    nside = _check_nside(nside)
    theta = np.asarray(theta, np.float64)
    z = np.cos(theta)
    za = np.abs(z)
    tt = np.mod(np.asarray(phi, np.float64), 2 * np.pi) * (2 / np.pi)  # in [0, 4)
    tt = np.where(tt >= 4.0, 0.0, tt)
    shape = np.broadcast(z, tt).shape
    z, za, tt = (np.broadcast_to(a, shape).ravel() for a in (z, za, tt))
    ix = np.empty(z.shape, np.int64)
    iy = np.empty(z.shape, np.int64)
    face = np.empty(z.shape, np.int64)

    # Equatorial region: |z| <= 2/3
    eq = za <= 2.0 / 3.0
    t1 = nside * (0.5 + tt[eq])
    t2 = nside * z[eq] * 0.75
    jp = (t1 - t2).astype(np.int64)
    jm = (t1 + t2).astype(np.int64)
    ifp = jp // nside
    ifm = jm // nside
    face[eq] = np.where(ifp == ifm, ifp | 4, np.where(ifp < ifm, ifp, ifm + 8))
    ix[eq] = jm & (nside - 1)
    iy[eq] = nside - (jp & (nside - 1)) - 1

    # Polar caps
    po = ~eq
    ttp = tt[po]
    ntt = np.minimum(ttp.astype(np.int64), 3)
    tp = ttp - ntt
    # sqrt(3 (1 - |z|)) computed from sin(theta) near the poles for precision
    s = np.sin(np.broadcast_to(theta, shape).ravel()[po])
    one_minus_za = np.where(za[po] > 0.99, s * s / (1 + za[po]), 1 - za[po])
    tmp = nside * np.sqrt(3 * one_minus_za)
    jp = np.minimum((tp * tmp).astype(np.int64), nside - 1)
    jm = np.minimum(((1 - tp) * tmp).astype(np.int64), nside - 1)
    north = z[po] > 0
    face[po] = np.where(north, ntt, ntt + 8)
    ix[po] = np.where(north, nside - jm - 1, jp)
    iy[po] = np.where(north, nside - jp - 1, jm)
    return xyf_to_nest(nside, ix, iy, face).reshape(shape)


def vec2pix_nest(nside: int, vec: np.ndarray) -> np.ndarray:
    """NESTED pixel containing each probe-frame direction (..., 3)."""
    theta, phi = angles_from_directions(vec)
    return ang2pix_nest(nside, theta, phi)


def face_xy_to_directions(face: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Directions of continuous face coordinates (x, y) in [0, 1]^2 of base face ``face``.

    Healpix_cxx ``xyf2loc``: jr = jrll[f] - x - y; north cap (jr < 1), south cap (jr > 3) or
    equatorial belt; phi = (pi/4)(jpll[f] nr + x - y) / nr.
    """
    face = np.asarray(face, np.int64)
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    jr = JRLL[face] - x - y
    north = jr < 1
    south = jr > 3
    nr = np.where(north, jr, np.where(south, 4 - jr, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(north, 1 - nr * nr / 3, np.where(south, nr * nr / 3 - 1, (2 - jr) * 2 / 3))
        phi = np.where(nr > 0, (np.pi / 4) * (JPLL[face] * nr + x - y) / np.where(nr > 0, nr, 1), 0.0)
    theta = np.arccos(np.clip(z, -1, 1))
    return directions_from_angles(theta, phi)


def pix2vec_nest(nside: int, ipix: np.ndarray) -> np.ndarray:
    """Directions (..., 3) of pixel centres."""
    nside = _check_nside(nside)
    ix, iy, face = nest_to_xyf(nside, ipix)
    return face_xy_to_directions(face, (ix + 0.5) / nside, (iy + 0.5) / nside)


def pix2ang_nest(nside: int, ipix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of pixel centres."""
    return angles_from_directions(pix2vec_nest(nside, ipix))
