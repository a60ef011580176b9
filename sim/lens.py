"""The simulated fisheye lens: KB4 geometry, vignetting, housing ring and the area-correct render.

The lens is an OpenCV fisheye (Kannala-Brandt KB4, the simulator's own :class:`~lightprobe.sim.optics.Kb4Lens`)
looking up: camera directions go to the probe frame through :data:`lightprobe.sim.optics.MOUNT`. Its image
circle spans ``circle_deg`` (187 deg) and fits the sensor height (radius 236 px of 480); the
outermost ``ring_deg`` (1 deg of polar angle) is the dark housing ring (transmission
``ring_transmission`` = 3%), so the clean field of view, :attr:`SimLens.fov_deg`, is
``circle_deg - 2 ring_deg`` = 185 deg: that is the ``fov_deg`` of the truth calibration. Beyond
the circle the sensor sees the black lens frame (transmission 0).

Rendering is area-correct. Every sensor pixel is split into ``n x n`` subsamples; subsample ``s``
has image area ``a_s = 1/n^2`` px^2 and the solid angle per image area of the lens at its polar
angle, the Jacobian (KB4, ``r = f theta_d(theta)``)::

    j(theta) = sin(theta) / (theta_d(theta) theta_d'(theta)) / (fx fy)      [sr / px^2]   (J)

A pixel's solid angle is ``Omega_p = sum_s a_s j_s`` and its radiance is the solid-angle-weighted
mean over its footprint, ``L_p = sum_s a_s j_s L(d_s) / Omega_p`` (times the housing
transmission ``T_p``). The subsample weights, summed per (sensor pixel, nearest equirect pixel),
estimate the overlap solid angles (near the zenith, where equirect pixels are far smaller than
sensor pixels, from the map's side); they are balanced to the exact marginals (see
:meth:`SimLens.render_matrix`), so a uniform map renders exactly uniform and every equirect
pixel's energy reaches the sensor: measured at VGA, 99.9% of the equirect pixels of the upper
hemisphere within 0.4% (256 rows) and 0.23% (512 rows), a one-pixel sun at 50 deg within 0.01%
(``tests/test_sim_physics.py`` checks suns at three elevations and the shared maps' totals). The
weights form one CSR matrix (sensor pixels x equirect pixels) built once per (mode, equirect
height); a frame is one sparse matmul.

Dtype policy: geometry in float64; the matrix and images in float32.

References
----------
Kannala, Brandt 2006, "A generic camera model and calibration method for conventional,
wide-angle, and fish-eye lenses", IEEE TPAMI 28(8) (the polynomial theta_d model, as used by
OpenCV's ``cv2.fisheye``). Iterative proportional fitting: Deming, Stephan 1940.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numba
import numpy as np

from lightprobe.sim._sparse import Csr

from .optics import (
    MOUNT,
    Kb4Lens,
    RadialFalloff,
    direction,
    equirect_row_omega,
)

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["DEFAULT_D", "SUPERSAMPLE", "SimLens", "make_lens", "standard_lens"]

# KB4 distortion of the simulated lens: mildly wider than equidistant towards the rim.
DEFAULT_D = np.array([0.02, -0.008, 0.001, -0.0002])
# Radius of the image circle on a 640 x 480 sensor (fits the 480 px height).
_VGA_CIRCLE_RADIUS_PX = 236.0
# Subsamples per side of a sensor pixel for the render matrix, at least (see supersample_for)
SUPERSAMPLE = 6
# Balancing stops when every pixel's row sum is within this of its solid angle
_ROW_TOLERANCE = 2e-4
# Subsamples per side of an equirect pixel when estimating the overlap from the map side
_MAP_SUBSAMPLES = 4
# Sensor pixels per chunk when building the render matrix (bounds the temporary arrays)
_CHUNK_PIXELS = 65536
# Vignetting V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6 with r = 1 at the circle edge: V(1) = 0.65.
_VIGNETTING_COEFFS = (-0.25, -0.10, 0.0)



@dataclass(frozen=True)
class SimLens:
    """A fisheye lens on a sensor of ``width x height`` pixels.

    Attributes
    ----------
    fisheye : the KB4 model (camera frame: x right, y down, z optical axis).
    vignetting : radial fall-off, measured = V x true, centred on the principal point.
    circle_deg : full angle of the image circle; beyond it the sensor sees the black frame.
    ring_deg : width (in polar angle) of the dark housing ring inside the circle edge.
    ring_transmission : fraction of light the ring lets through.
    """

    fisheye: Kb4Lens
    vignetting: RadialFalloff
    circle_deg: float = 187.0
    ring_deg: float = 1.0
    ring_transmission: float = 0.03
    _cache: dict[tuple[int, int, bool], Csr] = field(default_factory=dict, repr=False, compare=False)
    _vig: list[np.ndarray] = field(default_factory=list, repr=False, compare=False)
    _omega: dict[int, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    @property
    def size(self) -> tuple[int, int]:
        return self.fisheye.image_size

    @property
    def fov_deg(self) -> float:
        """The clean field of view (inside the housing ring): what the calibration reports."""
        return self.circle_deg - 2 * self.ring_deg

    @property
    def circle_radius_px(self) -> float:
        """Radius of the image circle in pixels (x axis)."""
        th = np.deg2rad(self.circle_deg / 2)
        return float(self.fisheye.K[0, 0] * self.fisheye.theta_d(np.array(th)))

    @property
    def clean_radius_px(self) -> float:
        """Radius in pixels of the clean circle (inside the housing ring, ``fov_deg``)."""
        th = np.deg2rad(self.fov_deg / 2)
        return float(self.fisheye.K[0, 0] * self.fisheye.theta_d(np.array(th)))

    # -- geometry ---------------------------------------------------------------------------------
    def _theta_table(self) -> tuple[float, np.ndarray]:
        """Undistortion table on a uniform theta_d grid: (step, theta at k * step)."""
        return self.fisheye.theta_table(np.deg2rad(self.circle_deg / 2 + 10.0))

    def pixel_polar(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Polar angle from the optical axis, image azimuth (cos, sin) of pixel coords (float64).

        KB4 is inverted by linear interpolation in a uniform theta_d table (error < 1e-8 rad).
        Points beyond the table (10 deg outside the image circle) get theta = +inf.
        """
        mx, my = self.fisheye.normalised(u, v)
        rd = np.hypot(mx, my)
        step, table = self._theta_table()
        pos = rd / step
        i = np.minimum(pos.astype(np.int64), table.size - 2)
        f = pos - i
        theta = table[i] * (1 - f) + table[i + 1] * f
        theta = np.where(pos <= table.size - 1, theta, np.inf)
        safe = np.where(rd > 1e-15, rd, 1.0)
        ca = np.where(rd > 1e-15, mx / safe, 1.0)
        sa = np.where(rd > 1e-15, my / safe, 0.0)
        return theta, ca, sa

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """Solid angle per pixel area at polar angle ``theta`` (sr / px^2), eq. (J)."""
        theta = np.asarray(theta, dtype=np.float64)
        fin = np.isfinite(theta)
        t = np.where(fin, theta, 0.0)
        td = self.fisheye.theta_d(t)
        tdp = self.fisheye.theta_d_prime(t)
        ratio = np.where(t > 1e-9, np.sin(t) / np.where(t > 1e-9, td, 1.0), 1.0)
        K = self.fisheye.K
        return np.where(fin, ratio / tdp / (K[0, 0] * K[1, 1]), 0.0)

    def transmission(self, theta: np.ndarray) -> np.ndarray:
        """Housing transmission at polar angle ``theta``: 1 inside, ring, 0 on the black frame."""
        half = np.deg2rad(self.circle_deg / 2)
        ring = np.deg2rad(self.circle_deg / 2 - self.ring_deg)
        return np.where(theta <= ring, 1.0, np.where(theta <= half, self.ring_transmission, 0.0))

    def _subsamples(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel indices and subsample coordinates of all pixels near the image circle."""
        w, h = self.size
        K = self.fisheye.K
        vv, uu = np.mgrid[0:h, 0:w]
        rad = np.hypot((uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]) * K[0, 0]
        keep = np.flatnonzero(rad <= self.circle_radius_px + 2.0)
        off = (np.arange(n) + 0.5) / n - 0.5
        ou, ov = np.meshgrid(off, off)
        pu = (keep % w)[:, None] + ou.ravel()[None, :]
        pv = (keep // w)[:, None] + ov.ravel()[None, :]
        return keep, pu, pv

    def pixel_solid_angle(self, supersample: int = 4) -> np.ndarray:
        """Solid angle (sr) of each sensor pixel's footprint, (H, W) float64; 0 off the lens.

        Computed once per ``supersample`` (a read-only array is returned).
        """
        if supersample not in self._omega:
            w, h = self.size
            keep, pu, pv = self._subsamples(supersample)
            theta, _, _ = self.pixel_polar(pu, pv)
            out = np.zeros(h * w)
            out[keep] = self.jacobian(theta).sum(axis=1) / supersample**2
            out.flags.writeable = False
            self._omega[supersample] = out.reshape(h, w)
        return self._omega[supersample]

    def pixel_directions(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Probe-frame unit directions of pixel coordinates (float64, NaN where theta is inf)."""
        theta, ca, sa = self.pixel_polar(u, v)
        st = np.sin(theta)
        cam = np.stack([st * ca, st * sa, np.cos(theta)], axis=-1)
        return cam @ MOUNT.T

    # -- the render matrix ------------------------------------------------------------------------
    def render_matrix(self, eq_height: int, *, supersample: int | None = None,
                      housing: bool = True, balance_iterations: int = 300) -> Csr:
        """CSR matrix (H*W, eq_height*2*eq_height) from equirect pixels to sensor radiance.

        Built from the overlap matrix ``A[p, j]`` (solid angle shared by sensor pixel ``p`` and
        equirect pixel ``j``), estimated from ``n x n`` subsamples per sensor pixel, each adding
        ``a_s j_s`` (eq. J) to its nearest equirect pixel. Near the zenith an equirect pixel is
        ~1/100 of a sensor pixel and the subsamples miss it or hit it by chance: those columns
        (their sum off their solid angle by over 2x) are estimated from the map's side instead,
        ``4 x 4`` subsamples of each such equirect pixel (exact sub-solid angles) projected
        through the lens; without that their energy would be lost or doubled (a sun there
        rendered at nothing or twice its energy) and the balance could not meet both marginals.
        ``A`` is then balanced by iterative proportional fitting (compiled, :func:`_fit`) to the
        exact marginals: row sums ``Omega_p`` (the pixel's solid angle) and column sums
        ``Omega_j`` (the equirect pixel's exact solid angle, for every equirect row inside the
        image circle), ending on the rows, so a uniform map renders exactly uniform, with the
        columns within 0.4% for 99.9% of the equirect pixels (0.9% at most, VGA at 256 rows): a
        one-pixel sun keeps its energy at any elevation. Finally ``M = diag(T_p / Omega_p) A``,
        ``T_p`` the pixel's housing transmission (its solid-angle-weighted mean over
        subsamples).

        Cached per (equirect height, supersample, housing). ``supersample`` defaults to
        :meth:`supersample_for` the height (6 per side at VGA up to 256 rows, 10 at 512).
        """
        w, h = self.size
        n = supersample or self.supersample_for(eq_height)
        key = (eq_height, n, housing)
        if key in self._cache:
            return self._cache[key]
        import scipy.sparse as sp  # building only: a frame applies the arrays (lightprobe.sim._sparse)

        keep, pu, pv = self._subsamples(n)
        # Overlap matrix, chunk by chunk of sensor pixels (bounded memory in large modes)
        parts, omega_p, t_p = [], np.zeros(keep.size), np.zeros(keep.size)
        for lo in range(0, keep.size, _CHUNK_PIXELS):
            sl = slice(lo, min(keep.size, lo + _CHUNK_PIXELS))
            a_c, omega_p[sl], t_p[sl] = self._overlap(pu[sl], pv[sl], eq_height, housing)
            parts.append(a_c)
        a = self._support_small_pixels(sp.vstack(parts, format="csr"), keep, eq_height)
        a = self._balance(a.tocsr(), omega_p, eq_height, balance_iterations)
        # M = diag(T_p / Omega_p) A, scattered to all sensor rows
        a = (sp.diags(t_p / np.where(omega_p > 0, omega_p, 1.0)) @ a).tocoo()
        m = Csr.from_scipy(sp.csr_matrix((a.data.astype(np.float32), (keep[a.row], a.col)),
                                         shape=(h * w, 2 * eq_height * eq_height)))
        self._cache[key] = m
        return m

    def _overlap(self, pu: np.ndarray, pv: np.ndarray, eq_height: int, housing: bool
                 ) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
        """Point-sampled overlap of sensor pixels (rows of subsample coords) with equirect pixels.

        Returns the CSR overlap (pixels x equirect pixels, sr), the pixels' solid angles and
        their housing transmissions.
        """
        import scipy.sparse as sp

        n2 = pu.shape[1]
        eq_w = 2 * eq_height
        # Subsample directions and overlap weights a_s j_s (eq. J)
        theta, ca, sa = self.pixel_polar(pu, pv)
        fin = np.isfinite(theta)
        jac = self.jacobian(theta) / n2
        trans = self.transmission(theta) if housing else fin.astype(np.float64)
        omega_p = jac.sum(axis=1)
        t_p = (jac * trans).sum(axis=1) / np.where(omega_p > 0, omega_p, 1.0)
        # Probe angles: MOUNT maps (x, y, z)_cam to (x, z, -y), so the probe's polar
        # angle is the camera's and the azimuth atan2(x_p, -z_p) = atan2(cos a, sin a)
        th_p = np.where(fin, theta, 0.0)
        ph_p = np.mod(np.arctan2(ca, sa), 2 * np.pi)
        # Nearest equirect pixel (row 0 at the zenith)
        row = np.clip((th_p / np.pi * eq_height).astype(np.int64), 0, eq_height - 1)
        col = (ph_p / (2 * np.pi) * eq_w).astype(np.int64) % eq_w
        nz = (jac > 0).ravel()
        a = sp.coo_matrix(
            (jac.ravel()[nz], (np.repeat(np.arange(pu.shape[0]), n2)[nz], (row * eq_w + col).ravel()[nz])),
            shape=(pu.shape[0], eq_height * eq_w),
        ).tocsr()
        a.sum_duplicates()
        return a, omega_p, t_p

    def _support_small_pixels(self, a: sp.csr_matrix, keep: np.ndarray, eq_height: int) -> sp.csr_matrix:
        """The sensor-side overlap ``a`` with its columns that the subsamples missed or barely hit
        (an equirect pixel near the zenith is ~1/100 of a sensor pixel: its sum is off its solid
        angle by over 2x, or 0)
        replaced by the map side's estimate (:meth:`_overlap_from_map`). Without it their energy
        would be lost (a sun there rendered at nothing or twice its energy) and the balancing
        could not meet both marginals."""
        import scipy.sparse as sp

        eq_w = 2 * eq_height
        target = np.repeat(equirect_row_omega(eq_height), eq_w)
        half = np.deg2rad(self.circle_deg / 2)
        inside = np.repeat(np.pi * (np.arange(eq_height) + 1) / eq_height <= half, eq_w)
        total = np.bincount(a.indices, weights=a.data, minlength=a.shape[1])
        weak = inside & ((total < 0.5 * target) | (total > 2.0 * target))
        if not weak.any():
            return a
        m = self._overlap_from_map(keep, _MAP_SUBSAMPLES, eq_height, np.unique(np.flatnonzero(weak) // eq_w))
        keep_cols = sp.diags((~weak).astype(np.float64))
        return (a @ keep_cols + m @ sp.diags(weak.astype(np.float64))).tocsr()

    def _overlap_from_map(self, keep: np.ndarray, n: int, eq_height: int, eq_rows: np.ndarray) -> sp.csr_matrix:
        """Overlap (rows: the sensor pixels ``keep``, columns: equirect pixels) estimated from
        ``n x n`` subsamples of every equirect pixel of the rows ``eq_rows`` inside the image
        circle (exact sub-solid angles), projected through the lens to the sensor pixel they land
        in."""
        import scipy.sparse as sp

        w, h = self.size
        eq_w = 2 * eq_height
        half = np.deg2rad(self.circle_deg / 2)
        row_of_keep = np.full(w * h, -1, np.int64)
        row_of_keep[keep] = np.arange(keep.size)
        parts = []
        sub_phi = (np.arange(eq_w * n) + 0.5) * (np.pi / (eq_height * n))      # every column
        for r in (int(x) for x in eq_rows):
            edges = np.pi * (r + np.arange(n + 1) / n) / eq_height
            theta = 0.5 * (edges[:-1] + edges[1:])
            omega = (np.pi / (eq_height * n)) * (np.cos(edges[:-1]) - np.cos(edges[1:]))
            t, p = np.meshgrid(theta, sub_phi, indexing="ij")                     # (n, eq_w n)
            wgt = np.broadcast_to(omega[:, None], t.shape)
            d_probe = direction(t, p)
            uv = self.fisheye.project(d_probe @ MOUNT)                            # probe -> camera
            u = np.floor(uv[..., 0] + 0.5).astype(np.int64)
            v = np.floor(uv[..., 1] + 0.5).astype(np.int64)
            ok = (t <= half) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            pix = np.where(ok, v * w + u, 0)
            krow = np.where(ok, row_of_keep[pix], -1)
            ok &= krow >= 0
            col = r * eq_w + (np.arange(eq_w * n) // n)[None, :].repeat(n, axis=0)
            parts.append((krow[ok], col[ok], wgt[ok]))
        kr, cc, ww = (np.concatenate(x) for x in zip(*parts, strict=True))
        a = sp.coo_matrix((ww, (kr, cc)), shape=(keep.size, eq_height * eq_w)).tocsr()
        a.sum_duplicates()
        return a

    def _balance(self, a: sp.csr_matrix, omega_p: np.ndarray, eq_height: int, iterations: int
                 ) -> sp.csr_matrix:
        """Iterative proportional fitting of the overlap matrix to its exact marginals."""
        eq_w = 2 * eq_height
        row_omega = equirect_row_omega(eq_height)
        edge_bottom = np.pi * (np.arange(eq_height) + 1) / eq_height
        inside = edge_bottom <= np.deg2rad(self.circle_deg / 2)
        target = np.repeat(np.where(inside, row_omega, 0.0), eq_w)
        _fit(a.data, a.indptr, a.indices, omega_p, target, iterations, _ROW_TOLERANCE)
        return a

    def supersample_for(self, eq_height: int) -> int:
        """Subsamples per side of a sensor pixel for an ``eq_height`` map: their spacing at most
        1/8 of an equirect pixel (a sensor pixel spans ``1/fx`` rad on the axis), and at least
        :data:`SUPERSAMPLE`. Coarser, equirect pixels about as large as a sensor pixel get a few
        subsamples each, aliased with the pixel grid, and the balance leaves some of their
        columns several percent off (measured: VGA at 512 rows, 6 per side: 18%; 10: 0.9%)."""
        pixel = 1.0 / float(self.fisheye.K[0, 0])
        return max(SUPERSAMPLE, int(np.ceil(8.0 * pixel / (np.pi / eq_height))))

    def render(self, equirect: np.ndarray, **kw: object) -> np.ndarray:
        """Sensor-plane radiance (H, W, 3) float32 of an equirect map (no vignetting, no noise)."""
        eq = np.ascontiguousarray(equirect, dtype=np.float32)
        m = self.render_matrix(eq.shape[0], **kw)  # type: ignore[arg-type]
        w, h = self.size
        return m.matmul_rgb(eq.reshape(-1, 3)).reshape(h, w, 3)

    def vignetting_image(self) -> np.ndarray:
        """V at every pixel centre, (H, W) float32 (computed once, read-only)."""
        if not self._vig:
            w, h = self.size
            vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
            vig = np.clip(self.vignetting.factor(uu, vv), 0.0, None).astype(np.float32)
            vig.flags.writeable = False
            self._vig.append(vig)
        return self._vig[0]


@numba.njit(cache=True, nogil=True)
def _fit(data, indptr, indices, row_target, col_target, iterations, tol):  # type: ignore[no-untyped-def]
    """Iterative proportional fitting of a CSR matrix (in place): scale the rows to
    ``row_target``, then the columns to ``col_target`` (where > 0), until after a column step
    every row with a target is within ``tol`` of it (or ``iterations`` rounds); then a last row
    step, so the rows are exact (a uniform map renders exactly uniform) and the columns off by
    what the rows still were (float64)."""
    n_rows = indptr.size - 1
    col = np.zeros(col_target.size)
    for it in range(iterations + 1):
        worst = 0.0
        for i in range(n_rows):
            s = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                s += data[k]
            f = row_target[i] / s if s > 0 else 0.0
            if row_target[i] > 0 and s > 0:
                worst = max(worst, abs(s / row_target[i] - 1.0))
            for k in range(indptr[i], indptr[i + 1]):
                data[k] *= f
        if it == iterations or (it > 0 and worst < tol):
            return
        col[:] = 0.0
        for k in range(data.size):
            col[indices[k]] += data[k]
        for k in range(data.size):
            j = indices[k]
            if col_target[j] > 0 and col[j] > 0:
                data[k] *= col_target[j] / col[j]


def make_lens(width: int = 640, height: int = 480, *, D: np.ndarray | None = None,
              circle_deg: float = 187.0, ring_deg: float = 1.0) -> SimLens:
    """The simulated probe lens for a sensor of ``width x height`` (4:3 modes scale from VGA).

    The principal point is the image centre ``((W-1)/2, (H-1)/2)`` (OpenCV pixel centres at
    integer coordinates); ``fx = fy`` puts the ``circle_deg`` image circle at 236/480 of the height.
    """
    D = DEFAULT_D.copy() if D is None else np.asarray(D, dtype=np.float64)
    radius = _VGA_CIRCLE_RADIUS_PX * height / 480.0
    unit = Kb4Lens((width, height), np.eye(3), D)
    f = radius / float(unit.theta_d(np.array(np.deg2rad(circle_deg / 2))))
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    fisheye = Kb4Lens((width, height), K, D, fov_deg=circle_deg - 2 * ring_deg)
    vig = RadialFalloff(((width - 1) / 2, (height - 1) / 2), radius, _VIGNETTING_COEFFS)
    return SimLens(fisheye, vig, circle_deg=circle_deg, ring_deg=ring_deg)


@functools.lru_cache(maxsize=8)
def standard_lens(width: int = 640, height: int = 480) -> SimLens:
    """The default lens for a sensor size, shared (with its cached render matrices) process-wide."""
    return make_lens(width, height)
