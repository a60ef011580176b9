"""HEALPix in the NESTED scheme, written here so the service has no GPL dependency.

Angles follow the probe convention of ``lightprobe.core.sphere``: ``theta`` is the polar angle from +y and
``phi`` the azimuth, so a HEALPix map here is the standard one with (theta, phi) read in the probe
frame. A pixel p at nside N has children 4p .. 4p+3 at nside 2N, so the descendants of any quad
are one contiguous index range at a finer level.

References
----------
Gorski et al. 2005, "HEALPix: a framework for high-resolution discretization", ApJ 622.
Healpix_cxx ``loc2pix`` / ``pix2loc`` / ``xyf2loc`` (the face-coordinate formulas below).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from .sphere import angles_from_directions, directions_from_angles

__all__ = [
    "JPLL",
    "JRLL",
    "ang2pix_nest",
    "equirect_to_healpix",
    "face_xy_to_directions",
    "healpix_to_equirect",
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


# ---- Resampling between equirect and HEALPix maps ------------------------------------------------
# A subpixel spans at most 1/8 of a HEALPix pixel: the covered solid angle of each HEALPix pixel
# then deviates from 4 pi / npix by ~2% rms (boundary quantisation), while energy stays exact.
_SUBPIXELS_PER_HEALPIX = 8
_MAX_SUBPIXELS = 16_000_000


def _subdivisions(pixel_extent: float, target_extent: float) -> int:
    """Subpixels per side so a subpixel spans at most 1/8 of ``target_extent``."""
    return int(max(1, np.ceil(_SUBPIXELS_PER_HEALPIX * pixel_extent / target_extent - 1e-9)))


@functools.lru_cache(maxsize=8)
def _equirect_to_healpix_matrix(height: int, width: int, nside: int) -> Any:
    """Sparse (npix, H*W) matrix of overlap solid angles (sr), float64.

    Each equirect pixel is split into s x s subpixels with their exact solid angles; every subpixel
    is binned into the HEALPix pixel holding its centre. Row sums are the covered solid angle of
    each HEALPix pixel and column sums the exact equirect pixel solid angles, so
    ``A @ L`` integrates radiance exactly.
    """
    from scipy import sparse

    hp_extent = np.sqrt(pixel_solid_angle(nside))
    s = _subdivisions(np.pi / height, hp_extent)
    s = max(1, min(s, int(np.sqrt(_MAX_SUBPIXELS / (height * width)))))  # bound the one-time cost
    sh, sw = height * s, width * s
    # Subpixel centres and exact solid angles (rows of the s-times finer equirect grid)
    theta = np.pi * (np.arange(sh) + 0.5) / sh
    phi = 2 * np.pi * (np.arange(sw) + 0.5) / sw
    omega_row = (2 * np.pi / sw) * (np.cos(np.pi * np.arange(sh) / sh) - np.cos(np.pi * np.arange(1, sh + 1) / sh))
    rows, cols, vals = [], [], []
    chunk = max(1, (1 << 21) // sw)
    for r0 in range(0, sh, chunk):
        r1 = min(sh, r0 + chunk)
        hp = ang2pix_nest(nside, theta[r0:r1, None], phi[None, :])
        src = (np.arange(r0, r1)[:, None] // s) * width + (np.arange(sw)[None, :] // s)
        rows.append(hp.ravel())
        cols.append(src.ravel())
        vals.append(np.broadcast_to(omega_row[r0:r1, None], hp.shape).ravel())
    a = sparse.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(npix(nside), height * width),
    ).tocsr()
    a.sum_duplicates()
    return a


def equirect_to_healpix(image: np.ndarray, nside: int) -> np.ndarray:
    """Area-correct resampling of an equirect map (H, W[, C]) to a NESTED HEALPix map (npix[, C]).

    Splatting: every equirect pixel is split into subpixels that carry their exact radiance x
    solid angle into the HEALPix pixel holding their centre, and each HEALPix pixel divides what
    it received by its exact solid angle 4 pi / npix. The integral of radiance x solid angle is
    therefore preserved exactly (float64 accumulation; a sun in one pixel keeps its energy); the
    price is a ~2% rms texture on smooth maps from the quantised pixel boundaries. A HEALPix pixel that no subpixel lands in (only possible when the equirect map
    is much coarser than the HEALPix grid) takes the value at its centre (nearest equirect pixel);
    with the automatic subdivision used here that does not happen for nside <= 4 H / pi.
    Output dtype float32.
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    flat = img.reshape(h * w, -1).astype(np.float64)
    a = _equirect_to_healpix_matrix(h, w, _check_nside(nside))
    covered = np.asarray(a.sum(axis=1)).ravel()
    out = np.asarray(a @ flat) / pixel_solid_angle(nside)
    holes = covered <= 0
    if np.any(holes):
        th, ph = pix2ang_nest(nside, np.nonzero(holes)[0])
        r = np.minimum((th / np.pi * h).astype(np.int64), h - 1)
        c = np.minimum((ph / (2 * np.pi) * w).astype(np.int64), w - 1)
        out[holes] = flat[r * w + c]
    out = out.astype(np.float32)
    return out.reshape((npix(nside), *img.shape[2:]))


@functools.lru_cache(maxsize=8)
def _healpix_to_equirect_matrix(nside: int, height: int, width: int) -> Any:
    """Sparse (H*W, npix) matrix M with ``M @ hp`` the equirect radiance.

    Entry (i, j) = overlap(i, j) / Omega_i x Omega_hp / covered_j: each HEALPix pixel's energy
    (L_j x Omega_hp) is shared among the equirect pixels in proportion to their overlap, so
    the energy is conserved exactly.
    """
    from scipy import sparse

    a = _equirect_to_healpix_matrix(height, width, nside)  # (npix, HW) overlaps in sr
    covered = np.asarray(a.sum(axis=1)).ravel()
    omega_eq = np.repeat(_equirect_row_omega(height, width), width)
    scale_hp = pixel_solid_angle(nside) / np.where(covered > 0, covered, 1.0)
    return (sparse.diags(1.0 / omega_eq) @ a.T @ sparse.diags(scale_hp)).tocsr()


def _equirect_row_omega(height: int, width: int) -> np.ndarray:
    t = np.pi * np.arange(height + 1) / height
    return (2 * np.pi / width) * (np.cos(t[:-1]) - np.cos(t[1:]))


def healpix_to_equirect(hp_map: np.ndarray, height: int, width: int | None = None) -> np.ndarray:
    """Area-weighted resampling of a NESTED HEALPix map (npix[, C]) to an equirect map (H, W[, C]).

    Each equirect pixel is the solid-angle-weighted mean of the HEALPix pixels it overlaps (same
    subpixel overlaps as ``equirect_to_healpix``), with each HEALPix pixel's energy shared out
    exactly, so the integral is conserved (float64 accumulation). Output float32.
    """
    m = np.asarray(hp_map)
    n = m.shape[0]
    nside = round(np.sqrt(n / 12))
    if 12 * nside * nside != n:
        raise ValueError(f"HEALPix map length {n} is not 12 nside^2")
    width = 2 * height if width is None else width
    a = _healpix_to_equirect_matrix(nside, height, width)
    out = np.asarray(a @ m.reshape(n, -1).astype(np.float64)).astype(np.float32)
    return out.reshape((height, width, *m.shape[1:]))
