"""The public projector: tables once per calibration, three maps per frame.

Dtype policy: images and maps float32; per-pixel sums float64 inside the kernels.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.core.errors import InputError
from lightprobe.core.healpix import npix
from lightprobe.device.projection.sparse import spmv_rgb

from .kernels import spmv_rgb_fix
from .tables import TABLE_CACHE, TABLE_CACHE_SIZE, TABLE_KEEP, build_all

__all__ = ["LOWER_POLICIES", "LowerPolicy", "ProbeMaps", "Projector"]

log = logging.getLogger(__name__)

LowerPolicy = Literal["zero", "mirror", "mean-horizon"]
LOWER_POLICIES: tuple[str, ...] = ("zero", "mirror", "mean-horizon")


@dataclass(frozen=True)
class ProbeMaps:
    """One frame's radiance on the sphere, probe frame, in the calibration's photometric unit.

    ``coverage_*`` are static per projector (fraction of each pixel the lens sees; 0 = no data)
    and shared read-only between frames.
    """

    polar: np.ndarray  # (Hp, 4 Hp, 3) float32, Hp = 90 by default
    equirect: np.ndarray  # (He, 2 He, 3) float32
    healpix: np.ndarray  # (12 nside^2, 3) float32, NESTED
    nside: int
    coverage_polar: np.ndarray  # (Hp, 4 Hp) float32 in [0, 1]
    coverage_equirect: np.ndarray | None = None  # (He, 2 He) float32 (before the lower fill)
    coverage_healpix: np.ndarray | None = None  # (12 nside^2,) float32
    unit: str = "relative"


class _Frame:
    """One frame's flattened input and its invalid pixels (found lazily, shared by the maps)."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = x
        self.bad: np.ndarray | None = None  # flat indices of invalid pixels inside the lens
        self.valid = np.ones(0, np.uint8)
        self.finite_checked = False

    def set_bad(self, pixels: np.ndarray) -> None:
        if self.valid.size == 0:
            self.valid = np.ones(self.x.shape[0], np.uint8)
        self.valid[pixels] = 0
        self.bad = pixels if self.bad is None else np.union1d(self.bad, pixels)


class Projector:
    """Remap tables from one calibration; :meth:`project` maps a fused fisheye radiance image.

    Parameters
    ----------
    calibration : needs ``fisheye``; ``vignetting``, ``photometric`` and ``mask`` (the clean image
        circle) are used when present; ``pose`` is not applied (maps are in the probe frame).
    polar_height : rows of the hemisphere polar map (width 4 x; 90 = one pixel per degree).
    equirect_height : rows of the full equirect map (width 2 x).
    nside : HEALPix resolution (power of two), NESTED.
    lower : lower-hemisphere policy of the equirect map, one of ``LOWER_POLICIES``.
    ground_albedo : reflectance used by ``lower="mirror"``.
    horizon_band_deg : height of the band averaged by ``lower="mean-horizon"``.
    ring_margin_deg : fisheye pixels beyond ``fov_deg / 2 - ring_margin_deg`` are not used
        (keeps the housing ring's shadow out of the maps).
    subdiv : subpixels per fisheye pixel side for the conservative remap.
    cache : reuse tables built earlier in this process for the same calibration id and
        geometry parameters (the last four are kept; they are read-only and shared).
    cache_dir : also keep the tables on disk there (the service uses its state directory), so a
        restart loads them instead of rebuilding (``lightprobe.device.projection.diskcache``).
    maps : the tables to build (a subset of polar, equirect, healpix; the live pipeline needs
        only the equirect one, a third of the build).
    balance : False builds a coarse table, balanced briefly instead of exactly (a few percent
        off per output pixel, the map's energy within ~0.1%; ~0.5 s less to build),
        never written to ``cache_dir``: the live pipeline's first lights on a fresh state dir,
        until the balanced table is built behind it.
    load_only : raise :class:`LookupError` instead of building when the tables are neither in
        memory nor in ``cache_dir``.
    """

    def __init__(self, calibration: Calibration, *, polar_height: int = 90,
                 equirect_height: int = 256, nside: int = 64, lower: str = "zero",
                 ground_albedo: float = 0.2, horizon_band_deg: float = 5.0,
                 ring_margin_deg: float = 0.5, subdiv: int = 4, cache: bool = True,
                 cache_dir: str | os.PathLike[str] | None = None,
                 maps: tuple[str, ...] = ("polar", "equirect", "healpix"), balance: bool = True,
                 load_only: bool = False) -> None:
        if calibration.fisheye is None:
            raise InputError("calibration has no fisheye section", param="fisheye")
        if lower not in LOWER_POLICIES:
            raise InputError(f"lower={lower!r} is not one of {LOWER_POLICIES}", param="lower")
        for name, val in (("polar_height", polar_height), ("equirect_height", equirect_height),
                          ("subdiv", subdiv)):
            if int(val) < 1:
                raise InputError(f"{name} must be a positive integer, got {val}", param=name)
        if nside < 1 or nside & (nside - 1):
            raise InputError(f"nside must be a power of two, got {nside}", param="nside")
        self.calibration = calibration
        self.polar_height, self.equirect_height, self.nside = polar_height, equirect_height, nside
        self.lower, self.ground_albedo = lower, float(ground_albedo)
        self.horizon_band_deg, self.ring_margin_deg = float(horizon_band_deg), float(ring_margin_deg)
        self.subdiv = int(subdiv)
        bad = [m for m in maps if m not in ("polar", "equirect", "healpix")]
        if bad or not maps:
            raise InputError(f"maps must name some of polar, equirect, healpix; got {maps!r}", param="maps")
        self.maps = tuple(sorted(set(maps), key=("polar", "equirect", "healpix").index))
        self.balanced = bool(balance)
        self._build(cache, cache_dir, load_only)

    # -- construction ---------------------------------------------------------------------------
    def _build(self, cache: bool, cache_dir: str | os.PathLike[str] | None, load_only: bool = False) -> None:
        from .diskcache import cache_path, load_built, save_built

        key = (self.calibration.id, self.polar_height, self.equirect_height, self.nside,
               self.ring_margin_deg, self.subdiv, *((self.maps,) if self.maps != ("polar", "equirect", "healpix") else ()),
               *(() if self.balanced else ("coarse",)))
        built = TABLE_CACHE.get(key) if cache else None
        path = cache_path(cache_dir, key) if cache_dir is not None and self.balanced else None
        if built is None and path is not None:
            built = load_built(path)
        if built is None and load_only:
            raise LookupError("projection tables not built yet")
        self.built_now = built is None  # built in this call (not from the memo or the disk cache)
        if built is None:
            built = build_all(self.calibration, self.polar_height, self.equirect_height,
                               self.nside, self.ring_margin_deg, self.subdiv, self.maps, self.balanced)
            if path is not None:
                try:
                    save_built(path, built)
                except OSError as e:  # a read-only or full disk costs only the next start's time
                    log.warning("cannot write projection cache %s: %s", path, e)
                else:  # serve from the mapped file (clean pages, see diskcache), not the build's arrays
                    built = load_built(path) or built
        if cache:
            TABLE_CACHE[key] = built
            if not any(b is built for b in TABLE_KEEP):  # (identity: a dataclass of arrays)
                TABLE_KEEP.append(built)
            del TABLE_KEEP[:-TABLE_CACHE_SIZE]
        self._built = built  # keeps the memo's (weak) entry while this projector lives
        self.lens_mask = built.lens_mask
        self.pixel_gain = built.pixel_gain
        self._inv_gain = built.inv_gain
        self.pixel_solid_angle = built.pixel_solid_angle
        self._tables = built.tables
        if "equirect" in self._tables:
            self._setup_lower()

    def _setup_lower(self) -> None:
        """Rows of the equirect map that need the lower-hemisphere fill, and the horizon band."""
        He = self.equirect_height
        cov = self._tables["equirect"].coverage.reshape(He, 2 * He)
        full = np.flatnonzero(cov.min(axis=1) >= 1.0)
        last_full = int(full.max()) if full.size else -1
        # Fill rows: below the last fully covered row; partly seen ones blend, unseen ones fill
        rows = np.arange(last_full + 1, He)
        seen = cov[rows].max(axis=1) > 0 if rows.size else np.zeros(0, bool)
        self._fill_rows = rows
        self._partial_rows = rows[seen]
        self._empty_rows = rows[~seen]
        self._partial_cov = np.ascontiguousarray(cov[self._partial_rows][..., None])
        n_band = max(1, round(self.horizon_band_deg / (180.0 / He)))
        first = max(0, last_full + 1 - n_band)
        self._horizon_rows = np.arange(first, last_full + 1)

    # -- per frame ------------------------------------------------------------------------------
    def _prepare(self, image: np.ndarray, valid: np.ndarray | None) -> _Frame:
        fe = self.calibration.fisheye
        assert fe is not None
        w, h = fe.image_size
        image = np.asarray(image)
        if image.shape != (h, w, 3):
            raise InputError(f"fisheye image has shape {image.shape}, calibration expects "
                             f"({h}, {w}, 3)", param="image")
        frame = _Frame(np.ascontiguousarray(image, dtype=np.float32).reshape(-1, 3))
        if valid is not None:
            valid = np.asarray(valid)
            if valid.shape != (h, w):
                raise InputError(f"valid mask has shape {valid.shape}, expected ({h}, {w})",
                                 param="valid")
            masked = np.flatnonzero(self.lens_mask.ravel() & ~valid.astype(bool, copy=False).ravel())
            if masked.size:
                frame.set_bad(masked)
        return frame

    def _apply(self, name: str, frame: _Frame) -> np.ndarray:
        """Eq. (P) for one map: the fast kernel, then the rows fed by invalid pixels (masked,
        NaN or Inf) recomputed over their valid contributions."""
        t = self._tables[name]
        out = np.empty((t.indptr.size - 1, 3), np.float32)
        finite = spmv_rgb(t.indptr, t.indices, t.data, frame.x, out)
        if not finite and not frame.finite_checked:
            nonfinite = ~np.isfinite(frame.x).all(axis=1) & self.lens_mask.ravel()
            frame.finite_checked = True
            if nonfinite.any():
                frame.set_bad(np.flatnonzero(nonfinite))
        if frame.bad is not None:
            spmv_rgb_fix(t.indptr, t.indices, t.data, self._inv_gain, t.geo_sum, t.col_ptr,
                          t.col_rows, frame.x, frame.valid, frame.bad, out)
        if not finite:  # float32 overflow of finite inputs (values near 3e38)
            np.nan_to_num(out, copy=False, nan=0.0, posinf=3.0e38, neginf=-3.0e38)
        return out

    def _fill_lower(self, eq: np.ndarray) -> np.ndarray:
        """Blend partly covered rows ``c L_seen + (1 - c) L_fill`` and fill unseen rows."""
        part, c = self._partial_rows, self._partial_cov
        if self.lower == "zero":  # unseen rows have no table entries: already 0
            eq[part] *= c
            return eq
        He = self.equirect_height
        if self.lower == "mirror":
            def fill(rows: np.ndarray) -> np.ndarray:
                return np.float32(self.ground_albedo) * eq[np.clip(He - 1 - rows, 0, He - 1)]
        else:  # mean-horizon: rows of one band have equal solid angles, so a plain mean is exact
            mean = eq[self._horizon_rows].reshape(-1, 3).mean(axis=0, dtype=np.float64)

            def fill(rows: np.ndarray) -> np.ndarray:
                return np.broadcast_to(mean.astype(np.float32), (rows.size, 2 * He, 3))
        eq[part] = c * eq[part] + (1.0 - c) * fill(part)
        eq[self._empty_rows] = fill(self._empty_rows)
        return eq

    def project_polar(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Hemisphere polar map (Hp, 4 Hp, 3) float32."""
        out = self._apply("polar", self._prepare(image, valid))
        return out.reshape(self.polar_height, 4 * self.polar_height, 3)

    def project_equirect(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Full equirect map (He, 2 He, 3) float32 with the lower-hemisphere policy applied."""
        return self._equirect(self._prepare(image, valid))

    def _equirect(self, frame: _Frame) -> np.ndarray:
        He = self.equirect_height
        return self._fill_lower(self._apply("equirect", frame).reshape(He, 2 * He, 3))

    def project_healpix(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """NESTED HEALPix map (12 nside^2, 3) float32."""
        return self._apply("healpix", self._prepare(image, valid))

    def project(self, fisheye_radiance: np.ndarray, valid: np.ndarray | None = None) -> ProbeMaps:
        """All three maps of one fused fisheye radiance image (h, w, 3); ``valid`` (h, w) bool."""
        frame = self._prepare(fisheye_radiance, valid)
        Hp = self.polar_height
        unit = "relative" if self.calibration.photometric is None else self.calibration.photometric.unit
        return ProbeMaps(
            polar=self._apply("polar", frame).reshape(Hp, 4 * Hp, 3),
            equirect=self._equirect(frame),
            healpix=self._apply("healpix", frame),
            nside=self.nside,
            coverage_polar=self.coverage_polar,
            coverage_equirect=self.coverage_equirect,
            coverage_healpix=self.coverage_healpix,
            unit=unit,
        )

    # -- static facts ---------------------------------------------------------------------------
    def _static(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        return self._tables[name].coverage.reshape(shape)  # read-only, shared

    @property
    def coverage_polar(self) -> np.ndarray:
        return self._static("polar", (self.polar_height, 4 * self.polar_height))

    @property
    def coverage_equirect(self) -> np.ndarray:
        return self._static("equirect", (self.equirect_height, 2 * self.equirect_height))

    @property
    def coverage_healpix(self) -> np.ndarray:
        return self._static("healpix", (npix(self.nside),))

    def solid_angle(self, name: str) -> np.ndarray:
        """Exact solid angle (sr) of each pixel of map ``name`` ("polar", "equirect", "healpix")."""
        return self._tables[name].solid_angle

    def table(self, name: str) -> object:
        """The CSR table of map ``name`` (``indptr``, ``indices``, ``data`` = geometric weight x
        pixel gain; read-only), for kernels that fuse while they project
        (:func:`lightprobe.device.hdr.rolling.frame_to_map`)."""
        return self._tables[name]

    @property
    def inverse_gain(self) -> np.ndarray:
        """1 / pixel gain per fisheye pixel (flat, 0 where unused; read-only)."""
        return self._inv_gain

    def nnz(self, name: str) -> int:
        """Non-zeros of a map's table (the per-frame work is proportional to it)."""
        return int(self._tables[name].indices.size)

    def balance_residual(self, name: str) -> float:
        """Max relative row-sum error of the interior rows after balancing (~1e-4): the bound on
        the energy error of eq. (E) per output pixel."""
        return self._tables[name].ipf_residual
