"""Order-2 spherical harmonics of a radiance map, and each host engine's own SH convention.

Canonical convention (what ``GET /api/v1/sh?convention=canonical`` serves)
------------------------------------------------------------------------
- *Radiance* coefficients ``c_i = integral L(w) Y_i(w) dw`` (the map's unit x sr, like a light's
  ``rgb``), 9 per channel (RGB), index ``i = l(l+1)+m``.
- The real, orthonormal basis *without* the Condon-Shortley phase, written in the probe frame's
  own axes (right-handed, +y up; CONVENTIONS.md):
  ``Y0 = k0``, ``Y1 = k1 y``, ``Y2 = k1 z``, ``Y3 = k1 x``, ``Y4 = k2 xy``, ``Y5 = k2 yz``,
  ``Y6 = k3 (3 z^2 - 1)``, ``Y7 = k2 xz``, ``Y8 = k4 (x^2 - y^2)`` with
  ``k0 = sqrt(1/4pi)``, ``k1 = sqrt(3/4pi)``, ``k2 = sqrt(15/4pi)``, ``k3 = sqrt(5/16pi)``,
  ``k4 = sqrt(15/16pi)``. This is three.js's ``SphericalHarmonics3`` basis; the probe frame and
  three.js's world share their axes, so three.js takes these coefficients unchanged.
- Irradiance (Ramamoorthi and Hanrahan 2001): ``E(n) = sum_i A_l(i) c_i Y_i(n)`` with
  ``A_0 = pi``, ``A_1 = 2 pi / 3``, ``A_2 = pi / 4``. A Lambertian surface of albedo ``rho`` then
  has radiance ``rho E / pi``.

Projection: exact per-pixel solid angles (CONVENTIONS.md), basis at pixel centres, float64 sums.
:class:`SHProjector` keeps the map it last saw and updates the sums from the changed pixels only
(``c += B[:, changed] (new - old)``), re-summing everything every ``refresh`` frames so float64
drift never accumulates.

Host conventions (:func:`to_convention`; facts and sources in ``../shared/NOTES.md``)
- ``threejs``: the canonical coefficients (``LightProbe.sh``; ``getIrradianceAt`` = E).
- ``webxr``: the same 27 numbers flattened ``[r0, g0, b0, r1, ...]``: three.js's
  ``XREstimatedLight`` copies ``sphericalHarmonicsCoefficients`` straight into its
  ``SphericalHarmonics3``, so that is the normalisation a WebXR consumer reads.
- ``filament``: ``IndirectLight.irradiance(3, sh)``: pre-convolved, ``sh_i = L_i K_i`` with
  ``L_i`` on Filament's Condon-Shortley basis (signs on 1, 3, 5, 7) and
  ``K = 0.282095, -0.325735, 0.325735, -0.325735, 0.273137, -0.273137, 0.078848, -0.273137,
  0.136569``; the two sign sets cancel, so ``sh_i = c_i |K_i|`` and the shader's plain
  polynomial returns ``E / pi``. Right-handed, +y up: the probe frame's axes.
- ``unity``: ``SphericalHarmonicsL2`` holds the same pre-convolved numbers in Unity's
  left-handed world (``z_unity = -z_probe``), so the terms odd in z (2: z, 5: yz, 7: xz) change
  sign; ``SHEvalLinearL0L1 + SHEvalLinearL2`` then return ``E / pi``. Served as ``[[r, g, b] x 9]``;
  Unity indexes ``sh[channel, i]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.core.sphere import equirect_directions, equirect_row_solid_angle

__all__ = [
    "BAND",
    "BASIS_CONSTANTS",
    "CONVENTIONS",
    "FILAMENT_K",
    "ZONAL_IRRADIANCE",
    "PrimaryLight",
    "SHLighting",
    "SHProjector",
    "irradiance",
    "project",
    "sh_basis",
    "to_convention",
]

K0 = math.sqrt(1.0 / (4.0 * math.pi))
K1 = math.sqrt(3.0 / (4.0 * math.pi))
K2 = math.sqrt(15.0 / (4.0 * math.pi))
K3 = math.sqrt(5.0 / (16.0 * math.pi))
K4 = math.sqrt(15.0 / (16.0 * math.pi))
BASIS_CONSTANTS = np.array([K0, K1, K1, K1, K2, K2, K3, K2, K4])
BAND = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])
# Clamped-cosine convolution per band (Ramamoorthi and Hanrahan 2001)
ZONAL_IRRADIANCE = np.array([math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0])[BAND]
# Filament's table as its docs print it (signed: Condon-Shortley basis)
FILAMENT_K = np.array([0.282095, -0.325735, 0.325735, -0.325735, 0.273137, -0.273137,
                       0.078848, -0.273137, 0.136569])
# Exact magnitudes of that table: A_l / pi x basis constant
_PRECONVOLVED = ZONAL_IRRADIANCE / math.pi * BASIS_CONSTANTS
_Z_ODD = np.array([1, 1, -1, 1, 1, -1, 1, -1, 1], np.float64)  # z -> -z (Unity's left hand)

CONVENTIONS = ("canonical", "threejs", "webxr", "filament", "unity")
SPARSE_LIMIT = 0.02  # share of changed pixels up to which the update goes pixel by pixel


def sh_basis(d: np.ndarray) -> np.ndarray:
    """The canonical basis (..., 9) at unit directions ``d`` (..., 3), float64."""
    d = np.asarray(d, np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    one = np.ones_like(x)
    return np.stack([K0 * one, K1 * y, K1 * z, K1 * x, K2 * x * y, K2 * y * z,
                     K3 * (3.0 * z * z - 1.0), K2 * x * z, K4 * (x * x - y * y)], axis=-1)


def _weights(height: int, rows: int) -> np.ndarray:
    """``Y_i(centre) x solid angle`` for the first ``rows`` rows of a (height, 2 height) map:
    (9, rows * 2 height) float64."""
    d = equirect_directions(height)[:rows]
    omega = equirect_row_solid_angle(height)[:rows]
    w = sh_basis(d) * omega[:, None, None]
    return np.ascontiguousarray(w.reshape(-1, 9).T)


class _Separable:
    """The projection as two small products: every basis function is a sum of (function of the
    row) x (function of the column) terms, with column functions ``1, sin p, cos p, cos^2 p,
    sin p cos p, sin^2 p``. ``project(rows x cols x 3)`` = per-row column sums (one BLAS product,
    float64), then a (9 x 6 x rows) contraction: O(pixels x 6) instead of O(pixels x 9)."""

    def __init__(self, height: int, rows: int) -> None:
        w = 2 * height
        p = 2 * np.pi * (np.arange(w) + 0.5) / w
        sp, cp = np.sin(p), np.cos(p)
        self.cols = np.ascontiguousarray(np.stack([np.ones(w), sp, cp, cp * cp, sp * cp, sp * sp], 1))  # (W, 6)
        t = np.pi * (np.arange(rows) + 0.5) / height
        st, ct = np.sin(t), np.cos(t)
        om = equirect_row_solid_angle(height)[:rows]
        r = np.zeros((9, 6, rows))
        r[0, 0] = K0
        r[1, 0] = K1 * ct  # y
        r[2, 2] = -K1 * st  # z = -st cp
        r[3, 1] = K1 * st  # x = st sp
        r[4, 1] = K2 * st * ct  # xy
        r[5, 2] = -K2 * ct * st  # yz
        r[6, 3] = 3.0 * K3 * st * st  # 3 z^2 - 1
        r[6, 0] = -K3
        r[7, 4] = -K2 * st * st  # xz
        r[8, 5] = K4 * st * st  # x^2 - y^2
        r[8, 0] = -K4 * ct * ct
        self.rows = np.ascontiguousarray(r * om[None, None, :])  # (9, 6, rows)

    def project(self, img: np.ndarray) -> np.ndarray:
        """(rows, W, 3) float -> (9, 3) float64."""
        a = np.asarray(img, np.float64)
        s = np.einsum("rwc,wk->krc", a, self.cols, optimize=True)  # (6, rows, 3)
        return np.einsum("ikr,krc->ic", self.rows, s, optimize=True)


def project(equirect: np.ndarray) -> np.ndarray:
    """Canonical radiance coefficients (9, 3) float64 of an (H, 2H, 3) map (NaN/inf and
    negative values count as 0, like every sampler's input)."""
    a = _check(equirect)
    clean = np.where(np.isfinite(a) & (a > 0), a, 0)
    return _Separable(a.shape[0], a.shape[0]).project(clean)


def irradiance(coefficients: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (..., 3) at unit ``normals`` (..., 3) of canonical coefficients (9, 3)."""
    c = np.asarray(coefficients, np.float64) * ZONAL_IRRADIANCE[:, None]
    return sh_basis(normals) @ c


def to_convention(coefficients: np.ndarray, convention: str) -> np.ndarray:
    """Canonical coefficients (9, 3) -> the host convention's (9, 3) (``webxr``: flatten the
    result row-major for its 27 floats)."""
    c = np.asarray(coefficients, np.float64)
    if convention in ("canonical", "threejs", "webxr"):
        return c.copy()
    if convention == "filament":
        return c * _PRECONVOLVED[:, None]
    if convention == "unity":
        return c * (_PRECONVOLVED * _Z_ODD)[:, None]
    raise InputError(f"convention must be one of {', '.join(CONVENTIONS)}, got {convention[:40]!r}",
                     param="convention")


def direction_to_convention(d: np.ndarray, convention: str) -> np.ndarray:
    """A probe-frame direction in the host's world axes (Unity: z flips)."""
    v = np.asarray(d, np.float64).copy()
    if convention == "unity":
        v[..., 2] = -v[..., 2]
    return v


def _check(equirect: Any) -> np.ndarray:
    a = np.asarray(equirect)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[1] != 2 * a.shape[0]:
        raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {a.shape}", param="equirect")
    return a


class SHProjector:
    """Incremental canonical SH of successive maps of one size.

    ``rows``: only the first ``rows`` rows are read (the probe's maps are zero below the
    horizon: ``rows = H // 2`` halves the work; default all). ``update(map)`` returns the
    coefficients (9, 3) float64 and counts the pixels it re-read in ``last_changed``.
    """

    def __init__(self, height: int, rows: int | None = None, refresh: int = 256) -> None:
        if height < 2 or height % 2:
            raise InputError(f"equirect height must be even and >= 2, got {height}", param="equirect_height")
        self.height = int(height)
        self.rows = self.height if rows is None else int(rows)
        if not 1 <= self.rows <= self.height:
            raise InputError(f"rows must be in [1, {self.height}], got {rows}", param="rows")
        self.refresh = int(refresh)
        self._sep = _Separable(self.height, self.rows)
        self._w: np.ndarray | None = None  # (9, P) per-pixel weights, built on the first sparse update
        self._prev: np.ndarray | None = None  # (P, 3) float32, cleaned
        self.coefficients = np.zeros((9, 3))
        self.last_changed = 0
        self._since_full = 0

    @property
    def nbytes(self) -> int:
        w = self._w.nbytes if self._w is not None else 0
        return int(w + self._sep.rows.nbytes + (self._prev.nbytes if self._prev is not None else 0))

    def update(self, equirect: np.ndarray) -> np.ndarray:
        a = _check(equirect)
        if a.shape[0] != self.height:
            raise InputError(f"map height {a.shape[0]} != projector height {self.height}", param="equirect")
        img = np.asarray(a[: self.rows], np.float32)
        if not np.isfinite(img.min(initial=0.0) + img.max(initial=0.0)) or img.min(initial=0.0) < 0:
            img = np.where(np.isfinite(img) & (img >= 0), img, np.float32(0))
        cur = img.reshape(-1, 3)
        prev = self._prev
        self._since_full += 1
        if prev is None or self._since_full >= self.refresh:
            self._full(img)
        else:
            ne = cur.ravel() != prev.ravel()
            n_values = int(np.count_nonzero(ne))
            if n_values > 3 * SPARSE_LIMIT * cur.shape[0]:  # a dense update costs more than a re-sum
                self._full(img)
                self.last_changed = min(n_values, cur.shape[0])
            elif n_values:
                changed = np.unique(np.flatnonzero(ne) // 3)
                self.last_changed = int(changed.size)
                if self._w is None:
                    self._w = _weights(self.height, self.rows)
                delta = cur[changed].astype(np.float64) - prev[changed]
                self.coefficients = self.coefficients + self._w[:, changed] @ delta
            else:
                self.last_changed = 0
        if prev is None or prev.shape != cur.shape:
            self._prev = np.array(cur, copy=True)
        else:
            np.copyto(prev, cur)
        return self.coefficients

    def _full(self, img: np.ndarray) -> None:
        self.coefficients = self._sep.project(img)
        self.last_changed, self._since_full = img.shape[0] * img.shape[1], 0


# -- the /sh body as a host reads it ------------------------------------------------------------
@dataclass(frozen=True)
class PrimaryLight:
    """Towards the light (unit, the convention's axes); ``rgb`` irradiance at normal incidence."""

    direction: np.ndarray
    rgb: np.ndarray
    solid_angle: float


@dataclass
class SHLighting:
    """``GET /api/v1/sh``: all light and ambient SH (9, 3) plus the primary light."""

    convention: str
    coefficients: np.ndarray
    ambient: np.ndarray
    primary: PrimaryLight | None
    probe: str = ""
    frame: int = 0
    timestamp: float = 0.0
    unit: str = "relative"
    stale: bool = False
    raw: dict[str, Any] = field(default_factory=dict, repr=False)
    captured: float | None = None  # wall-clock middle of the newest frame's exposure (LightSet)

    @classmethod
    def from_json(cls, d: Any) -> SHLighting:
        if not isinstance(d, dict) or d.get("version") != 1:
            raise InputError("not an SH body: not a version-1 JSON object", param="sh")
        try:
            c = np.asarray(d["coefficients"], np.float64)
            a = np.asarray(d["ambient_coefficients"], np.float64)
            p = d.get("primary_light")
            prim = None
            if p is not None:
                prim = PrimaryLight(np.asarray(p["direction"], np.float64).reshape(3),
                                    np.asarray(p["rgb"], np.float64).reshape(3), float(p["solid_angle"]))
            if c.shape != (9, 3) or a.shape != (9, 3) or not (np.isfinite(c).all() and np.isfinite(a).all()):
                raise InputError(f"not an SH body: coefficients must be 9 x 3 finite numbers, got {c.shape} "
                                 f"and {a.shape}", param="sh")
            return cls(str(d["convention"]), c, a, prim, str(d.get("probe", "")), int(d.get("frame", 0)),
                       float(d.get("timestamp", 0.0)), str(d.get("unit", "relative")), bool(d.get("stale", False)), d,
                       None if d.get("captured") is None else float(d["captured"]))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not an SH body: {e}", param="sh") from None
