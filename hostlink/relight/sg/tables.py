"""Kernels over the sphere and the lighting's direction tables: ray patterns, the zonal
clamped-cosine integral, cube-map direction tables of the lobes against each kernel (cached per
lobe set) and the voxel grid's occupancy pyramids."""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass

import numpy as np

from lightprobe.hostlink.relight.sg.kernels import (
    pyramid_levels,
    sg_matrix,
)
from lightprobe.hostlink.relight.sg.settings import DIFFUSE_CONES, RECT_RAYS, ZONAL_SAMPLES

__all__ = ["PATTERN", "RECT_COS", "RECT_G", "RECT_SIN", "TableCache", "Tables", "anisotropic_pyramid", "diffuse_pattern", "fibonacci", "gauss_legendre", "grid_dirs", "table_lookup", "zonal_cosine"]


# ---- kernels over the sphere -------------------------------------------------------------------
def fibonacci(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Stratified fractions ``(k + 1/2) / m`` and golden-angle azimuths of an ``m``-point
    Fibonacci pattern."""
    return (np.arange(m) + 0.5) / m, np.arange(m) * math.pi * (3 - math.sqrt(5))


def diffuse_pattern(K: int) -> np.ndarray:
    """(K, 3) cone axes in a normal's frame (tangent, bitangent, normal): a cosine-distributed
    Fibonacci pattern, so each cone stands for an equal share of the unshadowed irradiance."""
    g, phi = fibonacci(K)
    st = np.sqrt(g)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.sqrt(1 - g)], axis=1)


PATTERN = diffuse_pattern(DIFFUSE_CONES)
RECT_G, RECT_PHI = fibonacci(RECT_RAYS)
RECT_COS, RECT_SIN = np.cos(RECT_PHI), np.sin(RECT_PHI)


def grid_dirs(N: int) -> np.ndarray:
    """(6 N N, 3) texel directions of a cube map (layout of :mod:`lightprobe.hostlink.relight.sg.kernels`):
    face ``f`` on axis ``f // 2`` (sign + for even f), texel ``[i, j]`` at ``u_j, v_i`` on the next
    two axes; N odd puts a texel on each axis (normals cluster there: up, the walls)."""
    u = -1 + (2 * np.arange(N) + 1) / N
    V, U = np.meshgrid(u, u, indexing="ij")
    out = np.empty((6, N, N, 3))
    for f in range(6):
        a = f // 2
        out[f, ..., a] = 1.0 if f % 2 == 0 else -1.0
        out[f, ..., (a + 1) % 3] = U
        out[f, ..., (a + 2) % 3] = V
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out.reshape(-1, 3)


@functools.cache
def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    x.flags.writeable = w.flags.writeable = False
    return x, w


def zonal_cosine(lam: float, samples: int = ZONAL_SAMPLES) -> np.ndarray:
    """``C(t) = integral exp(lam (p . w - 1)) max(a . w, 0) dw`` on ``t = a . p`` in
    ``linspace(-1, 1, samples)``. In coordinates about ``p`` the azimuthal integral of the clamped
    cosine is closed form (``2 (A sin f + B f)``, ``f = acos(-B / A)``); the polar one is
    Gauss-Legendre in ``u = 1 - cos theta`` over where the lobe is above 1e-22 of its peak."""
    t = np.linspace(-1.0, 1.0, samples)
    umax = min(2.0, 50.0 / max(lam, 1e-9))
    x, w = gauss_legendre(256)
    u = (x + 1) * 0.5 * umax
    wu = w * 0.5 * umax * np.exp(-lam * u)
    ct = 1 - u
    stt = np.sqrt(np.clip(1 - ct * ct, 0, None))
    cb, sb = t[:, None], np.sqrt(np.clip(1 - t * t, 0, None))[:, None]
    A, B = sb * stt[None], cb * ct[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(A > 1e-12, -B / np.where(A > 1e-12, A, 1), np.where(B > 0, -2.0, 2.0))
    f = np.arccos(np.clip(c, -1, 1))
    g = np.where(c <= -1, 2 * np.pi * B, np.where(c >= 1, 0.0, 2 * (A * np.sin(f) + B * f)))
    return np.asarray(g @ wu)


def table_lookup(tab: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a (6, N, N) cube-map table at unit directions ``d`` (n, 3)."""
    N = tab.shape[1]
    a = np.argmax(np.abs(d), axis=1)
    m = np.abs(d[np.arange(len(d)), a])
    f = 2 * a + (d[np.arange(len(d)), a] < 0)
    u = d[np.arange(len(d)), (a + 1) % 3] / m
    v = d[np.arange(len(d)), (a + 2) % 3] / m
    fj = np.clip((u + 1) * 0.5 * N - 0.5, 0, N - 1)
    fi = np.clip((v + 1) * 0.5 * N - 0.5, 0, N - 1)
    j0 = np.minimum(fj.astype(np.int64), N - 2)
    i0 = np.minimum(fi.astype(np.int64), N - 2)
    wj, wi = fj - j0, fi - i0
    return ((1 - wi) * ((1 - wj) * tab[f, i0, j0] + wj * tab[f, i0, j0 + 1])
            + wi * ((1 - wj) * tab[f, i0 + 1, j0] + wj * tab[f, i0 + 1, j0 + 1]))


def anisotropic_pyramid(occ: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Three occupancy mip pyramids of an (R, R, R) [z, y, x] grid, one per axis: level l + 1 of
    the axis-``k`` pyramid combines each pair of children along axis k as one occluder after the
    other (``1 - (1 - a)(1 - b)``) and averages across the other two axes, so a cell holds about
    the probability that a ray crossing it along k is blocked (a floor stays opaque to rays through
    it at every level, and thin to rays along it). Returned flat, (3, total) float32, with the
    level offsets (:func:`~lightprobe.hostlink.relight.sg.kernels.pyramid_levels` fills them); into ``out``
    when it has the shape (a deforming scene's frames reuse one buffer: 24 MB at 128^3, whose
    fresh pages cost more than the levels)."""
    R = occ.shape[0]
    sizes = [(R >> lv) ** 3 for lv in range(R.bit_length())]
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    shape = (3, int(offs[-1]))
    flat = out if out is not None and out.shape == shape and out.dtype == np.float32 else np.empty(shape, np.float32)
    flat[:, :sizes[0]] = np.asarray(occ, np.float32).reshape(1, -1)
    pyramid_levels(flat, offs, R)
    return flat, offs


@dataclass
class Tables:
    E: np.ndarray           # (6, N, N, 3) cube maps
    W: np.ndarray           # the residual through one diffuse cone's visibility SG
    G: np.ndarray           # (slots, 6, N, N, 3)
    L: np.ndarray | None = None   # (6, N, N) the residual's luminance (ray visibility weights)


class TableCache:
    """Per lobe set (axes, sharpness) and kernel: the (D, M) float32 matrix mapping the lobes'
    amplitudes to a direction table. A probe's residual grids are fixed, so after the first
    frame every light change is matrix-vector products only."""

    def __init__(self) -> None:
        self._key: bytes | None = None
        self._mats: dict[tuple[str, float, int], np.ndarray] = {}
        self._zonal: dict[float, np.ndarray] = {}

    def zonal(self, lam: float) -> np.ndarray:
        key = float(np.float32(lam))
        z = self._zonal.get(key)
        if z is None:
            if len(self._zonal) > 4096:
                self._zonal.clear()
            z = self._zonal[key] = zonal_cosine(key)
        return z

    def matrix(self, axes: np.ndarray, lam: np.ndarray, kind: str, lam_k: float, H: int) -> np.ndarray:
        key = hashlib.blake2b(np.ascontiguousarray(axes).tobytes() + np.ascontiguousarray(lam).tobytes(),
                              digest_size=16).digest()
        if key != self._key:
            self._key, self._mats = key, {}
        mk = (kind, float(lam_k), H)
        m = self._mats.get(mk)
        if m is None:
            d = grid_dirs(H)
            m = np.empty((len(d), len(lam)), np.float32)
            uniq, slot = np.unique(lam, return_inverse=True)
            zon = np.stack([self.zonal(float(u)) for u in uniq]) if kind == "cos" else np.zeros((1, ZONAL_SAMPLES))
            sg_matrix({"sg": 0, "cos": 1, "radiance": 2}[kind], float(lam_k), d, np.ascontiguousarray(axes, np.float64),
                      np.ascontiguousarray(lam, np.float64), zon,
                      slot.astype(np.int64) if kind == "cos" else np.zeros(len(lam), np.int64), m)
            self._mats[mk] = m
        return m
