"""Hemigon sampler (Havran et al. EGSR 2005): temporally coherent sampling through Havran's map.

Per hemisphere (upper = rows whose centre is at or above the horizon, lower = the rest):

1. Resample the map into an ``grid x grid`` unit square through the equal-area Havran mapping
   (:mod:`lightprobe.device.sampling.havran`): every equirect pixel (split into ``s x s`` sub-pixels when the
   map is coarser than the grid) adds its radiance x exact solid angle to the cell its centre maps
   to. Cells are equal-area (2 pi / grid^2 sr), so this is area-correct and conserves energy.
2. A bicontinuous 2D distribution on the cells' luminance (conditional CDFs interpolated between
   rows, :class:`~lightprobe.device.sampling.distribution.Distribution2D` ``interpolate=True``).
3. Light ``i`` of a hemisphere is Halton (2, 3) index ``i + 1`` pushed through the inverse CDFs,
   every frame, so a small change of the map moves it a little; ``id = i`` (upper) or
   ``LOWER_ID_OFFSET + i`` (lower). **Stratum averaging** (ours, not in the paper): light ``i``
   is the normalised mean direction of ``k x k`` sub-samples, its Halton point plus a fixed
   pattern spanning ``stratum_scale / sqrt(n)`` (about its stratum) in primary sample space;
   ``k = substeps`` or, by default, ``clip(subsample_budget // n, 1, 8)`` (8 up to 256 lights,
   2 at 1000, 1 from 2048: averaging matters when each light carries a large share). Inverse-CDF
   samples jump when the map's mass moves across a dark gap; averaging k^2 sub-samples makes
   each jump move a light by ~1/k^2 of the distance. Measured on ``flashlight`` (N = 256,
   40 frames): flicker 0.0034 (k = 1) -> 0.0011 (k = 8); it costs some static accuracy where
   a stratum straddles separate lamps (studio map diffuse error 0.020 -> 0.035). Optional
   ``mode_seeking`` mean-shift steps pull such lights to the dominant lamp (2 steps: studio
   0.035 -> 0.023) at the price of flicker (flashlight 0.0010 -> ~0.0017), so default 0.
4. Trajectory filter in the square (per id, exponential, reset on jumps), then
   ``direction = square_to_hemisphere(uv)``.
5. Equal-power lights (Havran 2005): each light gets luminance ``Y_h / n_h`` with the colour of
   its sub-samples' cells; one per-channel scale then makes the hemisphere's sum exact (float64).
6. Invisible-light elimination: with ``ground=True`` the lower hemisphere is below the horizon of
   the scene and its whole energy goes to the ambient term; lights with luminance below
   ``min_power_fraction`` x the mean light's are folded into ambient too. The ambient term
   ``extra["ambient"]`` is rgb (unit x sr) to be spread uniformly over the sphere; energy is
   conserved as ``sum(rgb) + ambient = integral``.
7. Optional clustering of lights closer than ``cluster_deg`` (power-weighted direction, summed
   rgb and solid angle, smallest id kept).
8. Energy filter on the total luminance (exponential, reset on jumps); its gain scales every
   light and the ambient term (so the *filtered* energy is conserved; the first frame and any
   frame after a reset are exact).

Both filters are **off by default** (``alpha = 1``): measured against the noise-free truth of
the simulated scenarios they only add lag (flashlight flicker 0.00104 -> 0.00156 and
mean error 0.020 -> 0.026 with alpha 0.3 / 0.5; on ``flicker`` the energy filter removes
the lamp's real ripple, 0.009 -> 0.091). Enable them for noisy camera input where jitter and
mains flicker are artefacts rather than lighting; ``bench/samplers.py`` measures the variants.

The count is split between the hemispheres in proportion to their luminance (largest
remainder), at least one light each when both carry energy and ``count >= 2``.

Degenerate maps: NaN/inf/negative -> 0 (counted in ``extra["sanitized"]``); all black -> empty set.

References
----------
Havran, Smyk, Krawczyk, Myszkowski, Seidel, "Interactive system for dynamic scene lighting using
captured video environment maps", EGSR 2005; Havran, Dmitriev, Seidel 2003 (the mapping);
Nikodym et al. 2013 (Hemigon as compared there).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import LUMINANCE_WEIGHTS, equirect_row_solid_angle, luminance

from ._pixels import clean_invalid
from .distribution import ONE_MINUS_EPSILON, Distribution2D, halton, sample_one
from .havran import PDF_UV_TO_OMEGA, hemisphere_to_square, square_to_hemisphere
from .pharr import empty_lightset, rescale_to_total
from .temporal import EnergyFilter, TrajectoryFilter

__all__ = ["LOWER_ID_OFFSET", "HemigonSampler", "cluster_lights", "split_count"]

LOWER_ID_OFFSET = 1 << 20


def split_count(count: int, energies: np.ndarray) -> np.ndarray:
    """Split ``count`` in proportion to ``energies`` (largest remainder), >= 1 for every part
    with energy when ``count`` allows."""
    e = np.maximum(np.asarray(energies, np.float64), 0.0)
    if e.sum() <= 0:
        return np.zeros(len(e), np.int64)
    share = count * e / e.sum()
    n = np.floor(share).astype(np.int64)
    for k in np.argsort(-(share - n))[: count - n.sum()]:
        n[k] += 1
    lit = e > 0
    if count >= lit.sum():
        for k in np.flatnonzero(lit & (n == 0)):
            n[np.argmax(n)] -= 1
            n[k] += 1
    return n


def cluster_lights(dirs: np.ndarray, rgb: np.ndarray, solid: np.ndarray, ids: np.ndarray,
                   max_angle_deg: float) -> tuple[np.ndarray, ...]:
    """Merge lights closer than ``max_angle_deg`` (connected components of the "close" graph):
    power-weighted mean direction, summed rgb and solid angle, smallest id."""
    if max_angle_deg <= 0 or len(dirs) < 2:
        return dirs, rgb, solid, ids
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    chord = 2.0 * np.sin(np.radians(max_angle_deg) / 2.0)
    pairs = cKDTree(dirs).query_pairs(chord, output_type="ndarray")
    if len(pairs) == 0:
        return dirs, rgb, solid, ids
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(dirs),) * 2)
    k, label = connected_components(g, directed=False)
    power = luminance(rgb)
    w = np.where(power > 0, power, 1e-300)
    d = np.zeros((k, 3))
    np.add.at(d, label, dirs * w[:, None])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out_rgb = np.zeros((k, 3))
    np.add.at(out_rgb, label, rgb)
    out_solid = np.bincount(label, solid, minlength=k)
    out_ids = np.full(k, np.iinfo(np.int64).max)
    np.minimum.at(out_ids, label, ids)
    return d, out_rgb, out_solid, out_ids


@njit(cache=True)
def _splat_kernel(img, pix, cell, weight, ncells):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out[cell[i]] += clean(img[pix[i]]) * weight[i]; NaN/inf/negative read as 0 and counted
    (once per sub-sample: divide by the sub-samples per pixel)."""
    out = np.zeros((ncells, 3))
    bad = np.zeros(2, np.int64)
    for i in range(pix.shape[0]):
        p, k, wt = pix[i], cell[i], weight[i]
        for ch in range(3):
            v = np.float64(img[p, ch])
            if v >= 0.0 and v < np.inf:
                out[k, ch] += v * wt
            elif v < 0.0:
                bad[1] += 1
            else:
                bad[0] += 1
    return out, bad


@njit(cache=True)
def _splat_rows_kernel(img, cell, omega, ncells):  # type: ignore[no-untyped-def]  # pragma: no cover
    """One sub-sample per pixel: out[cell[r, c]] += clean(img[r, c]) * omega[r]."""
    out = np.zeros((ncells, 3))
    bad = np.zeros(2, np.int64)
    for r in range(img.shape[0]):
        om = omega[r]
        for c in range(img.shape[1]):
            k = cell[r, c]
            vr = np.float64(img[r, c, 0])
            vg = np.float64(img[r, c, 1])
            vb = np.float64(img[r, c, 2])
            if not (vr >= 0.0 and vg >= 0.0 and vb >= 0.0 and vr + vg + vb < np.inf):
                vr, vg, vb = clean_invalid(vr, vg, vb, bad)
            out[k, 0] += vr * om
            out[k, 1] += vg * om
            out[k, 2] += vb * om
    return out, bad


class _Splat:
    """Precomputed pixel -> Havran-cell assignment of one map shape (both hemispheres)."""

    def __init__(self, h: int, w: int, grid: int) -> None:
        self.h_up = (h + 1) // 2  # rows whose centre is at or above the horizon
        hemi_pixels = max(1, self.h_up * w)
        s = max(1, int(np.ceil(np.sqrt(4.0 * grid * grid / hemi_pixels))))
        omega = equirect_row_solid_angle(h, w)
        sub = (np.arange(s) + 0.5) / s
        theta = np.pi * (np.arange(h)[:, None] + sub[None, :]).reshape(-1) / h  # (h s,)
        phi = 2 * np.pi * (np.arange(w)[:, None] + sub[None, :]).reshape(-1) / w  # (w s,)
        st = np.sin(theta)[:, None]
        dirs = np.stack(np.broadcast_arrays(st * np.sin(phi)[None, :], np.cos(theta)[:, None],
                                            -st * np.cos(phi)[None, :]), axis=-1)
        row = np.repeat(np.arange(h), s)
        col = np.repeat(np.arange(w), s)
        pix = (row[:, None] * w + col[None, :]).reshape(-1)
        lower = np.repeat(row >= self.h_up, w * s)
        d = dirs.reshape(-1, 3)
        uv = np.where(lower[:, None], hemisphere_to_square(d, lower=True),
                      hemisphere_to_square(d, lower=False))
        ij = np.minimum((uv * grid).astype(np.int64), grid - 1)
        cell = ij[:, 1] * grid + ij[:, 0] + lower * grid * grid  # row = v, column = u
        self.grid = grid
        self.per_pixel = s * s
        self.pix = pix
        self.cell = cell
        self.weight = np.repeat(omega, w)[pix] / (s * s)  # sub-pixel solid angle (sums exactly)
        self.omega = omega
        self.cell_map = cell.astype(np.int32).reshape(h, w) if s == 1 else None

    def __call__(self, img: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
        """Cell energies (2, grid, grid, 3) = sum of radiance x solid angle (float64) and the
        counts of non-finite / negative values (read as 0)."""
        img = np.ascontiguousarray(img, np.float32)
        n = 2 * self.grid * self.grid
        if self.cell_map is not None:  # fast path: one sub-sample per pixel, pixel order
            out, bad = _splat_rows_kernel(img, self.cell_map, self.omega, n)
        else:
            out, bad = _splat_kernel(img.reshape(-1, 3), self.pix, self.cell, self.weight, n)
        flags = {"nonfinite": int(bad[0]) // self.per_pixel, "negative": int(bad[1]) // self.per_pixel}
        return out.reshape(2, self.grid, self.grid, 3), flags


def _normalise(d: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return np.where(norm > 1e-12, d / np.where(norm > 1e-12, norm, 1.0), fallback)


def _robust_centroid(sub: np.ndarray, iterations: int) -> np.ndarray:
    """Mean direction of each light's sub-samples (n, m, 3), then ``iterations`` mean-shift
    steps with Gaussian weights ``exp(-(angle / (2 mean angle))^2)``: where a stratum
    straddles two lit places the light moves to the dominant one instead of the dark between,
    while weights stay continuous in the sub-samples (no new jumps)."""
    d = _normalise(sub.mean(axis=1), sub[:, 0])
    for _ in range(iterations):
        ang = np.arccos(np.clip(np.einsum("nmk,nk->nm", sub, d), -1.0, 1.0))
        sigma = np.maximum(2.0 * np.mean(ang, axis=1, keepdims=True), 1e-9)
        w = np.exp(-((ang / sigma) ** 2))
        d = _normalise(np.einsum("nm,nmk->nk", w, sub), d)
    return d


@njit(cache=True)
def _stratum_kernel(pts, pattern, cells, lower, mcdf, seg_start, seg_width, seg_a, seg_b, row_cdf,
                    row_int, func, interpolate):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per light: sum of its sub-samples' directions (Havran forward map, probe frame), of their
    cells' rgb and of 1 / f (unnormalised density). Same maths as ``square_to_hemisphere``."""
    n, m, g = pts.shape[0], pattern.shape[0], cells.shape[0]
    dsum = np.zeros((n, 3))
    col = np.zeros((n, 3))
    inv_f = np.zeros(n)
    for i in range(n):
        for j in range(m):
            u0 = min(max(pts[i, 0] + pattern[j, 0], 0.0), ONE_MINUS_EPSILON)
            u1 = min(max(pts[i, 1] + pattern[j, 1], 0.0), ONE_MINUS_EPSILON)
            x, y, f = sample_one(u0, u1, mcdf, seg_start, seg_width, seg_a, seg_b, row_cdf,
                                 row_int, func, interpolate)
            a, b = 2.0 * x - 1.0, 2.0 * y - 1.0  # concentric square -> disc (Shirley-Chiu)
            if abs(a) > abs(b):
                r, phi = a, (np.pi / 4) * (b / a)
            elif b != 0.0:
                r, phi = b, np.pi / 2 - (np.pi / 4) * (a / b)
            else:
                r, phi = 0.0, 0.0
            r2 = min(r * r, 1.0)  # Lambert disc -> hemisphere
            sq = np.sqrt(2.0 - r2)
            dsum[i, 0] += r * np.cos(phi) * sq
            dsum[i, 1] += (r2 - 1.0) if lower else (1.0 - r2)
            dsum[i, 2] -= r * np.sin(phi) * sq
            ci, cj = min(int(y * g), g - 1), min(int(x * g), g - 1)
            for ch in range(3):
                col[i, ch] += cells[ci, cj, ch]
            inv_f[i] += 1.0 / f if f > 0 else 0.0
    return dsum, col, inv_f


@lru_cache(maxsize=4)
def _splat_for(h: int, w: int, grid: int) -> _Splat:
    """Shared, read-only pixel -> cell tables (building one costs ~0.5 s at 1024 x 512)."""
    return _Splat(h, w, grid)


class HemigonSampler:
    """Havran et al. 2005 sampler with temporal filters; parameters as in the module docstring.

    Parameters
    ----------
    grid : resolution of the Havran square per hemisphere.
    energy_alpha, energy_jump : energy filter (1 disables; relative jump that resets).
    trajectory_alpha, trajectory_jump : trajectory filter (1 disables; square-unit jump).
    ground : fold the lower hemisphere (below the scene's horizon) into the ambient term.
    min_power_fraction : lights below this fraction of the mean light luminance -> ambient.
    cluster_deg : merge lights closer than this angle (0 disables).
    substeps, stratum_scale, subsample_budget : stratum averaging (``substeps`` x ``substeps``
        sub-samples per light over ``stratum_scale / sqrt(n)``; None = ``budget // n``, 1..8).
    mode_seeking : mean-shift steps of the stratum centroid (0 = plain centroid).
    """

    name = "hemigon"

    def __init__(self, grid: int = 128, energy_alpha: float = 1.0, energy_jump: float = 0.5,
                 trajectory_alpha: float = 1.0, trajectory_jump: float = 0.05,
                 ground: bool = False, min_power_fraction: float = 1e-3,
                 cluster_deg: float = 0.0, substeps: int | None = None,
                 stratum_scale: float = 1.0, subsample_budget: int = 2048,
                 mode_seeking: int = 0) -> None:
        if grid < 2:
            raise ValueError(f"grid must be >= 2, got {grid}")
        self.grid = int(grid)
        self.energy_filter = EnergyFilter(energy_alpha, energy_jump)
        self.trajectory_filter = TrajectoryFilter(trajectory_alpha, trajectory_jump)
        self._lower_filter = TrajectoryFilter(trajectory_alpha, trajectory_jump)
        self.ground = bool(ground)
        self.min_power_fraction = float(min_power_fraction)
        self.cluster_deg = float(cluster_deg)
        self.substeps = None if substeps is None else max(1, int(substeps))
        self.subsample_budget = int(subsample_budget)
        self.mode_seeking = max(0, int(mode_seeking))
        self.stratum_scale = float(stratum_scale)
        self.distributions: list[Distribution2D | None] = [None, None]  # last frame's, per half
        self._halton = np.zeros((0, 2))

    def reset(self) -> None:
        """Forget the temporal state (filters)."""
        self.energy_filter.reset()
        self.trajectory_filter.reset()
        self._lower_filter.reset()

    def _points(self, n: int) -> np.ndarray:
        if len(self._halton) < n:
            self._halton = halton(max(n, 2 * len(self._halton)))
        return self._halton[:n]

    def sample(self, equirect: np.ndarray, count: int) -> LightSet:
        """``count`` lights (fewer after elimination/clustering) from ``equirect`` (H, 2H, 3)."""
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        img = np.asarray(equirect)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) radiance map, got shape {img.shape}")
        h, w = img.shape[:2]
        splat = _splat_for(h, w, self.grid)
        cells, flags = splat(img)  # (2, grid, grid, 3) float64, C-contiguous halves
        extra: dict[str, object] = {"sanitized": flags} if any(flags.values()) else {}
        totals = cells.reshape(2, -1, 3).sum(axis=1)
        y_tot = totals @ LUMINANCE_WEIGHTS
        ambient = np.zeros(3)
        if self.ground:
            ambient += totals[1]
            y_tot = np.array([y_tot[0], 0.0])
        if not np.any(y_tot > 0) and not np.any(ambient > 0):
            return empty_lightset(self.name, extra)
        parts = split_count(count, y_tot)
        parts_dirs, parts_rgb, parts_solid, parts_ids = [], [], [], []
        for k in range(2):
            if parts[k] > 0:
                d, r, s, i = self._sample_filtered(cells[k], int(parts[k]), k == 1, totals[k])
                parts_dirs.append(d)
                parts_rgb.append(r)
                parts_solid.append(s)
                parts_ids.append(i)
            elif not self.ground or k == 0:
                ambient += totals[k]  # a lit hemisphere left without lights (count == 1)
        dirs = np.concatenate(parts_dirs) if parts_dirs else np.zeros((0, 3))
        rgb = np.concatenate(parts_rgb) if parts_rgb else np.zeros((0, 3))
        solid = np.concatenate(parts_solid) if parts_solid else np.zeros(0)
        ids = np.concatenate(parts_ids) if parts_ids else np.zeros(0, np.int64)
        # Invisible-light elimination: negligible power -> ambient
        power = luminance(rgb)
        if len(power) and self.min_power_fraction > 0:
            weak = power < self.min_power_fraction * power.mean()
            ambient += rgb[weak].sum(axis=0)
            dirs, rgb, solid, ids = dirs[~weak], rgb[~weak], solid[~weak], ids[~weak]
        dirs, rgb, solid, ids = cluster_lights(dirs, rgb, solid, ids, self.cluster_deg)
        # Energy filter on the total luminance
        y_all = float((rgb.sum(axis=0) + ambient) @ LUMINANCE_WEIGHTS)
        gain = self.energy_filter.gain(y_all)
        extra["ambient"] = [float(x) for x in ambient * gain]
        extra["energy_gain"] = float(gain)
        return LightSet(dirs, rgb * gain, solid, ids, method=self.name, extra=extra)

    def _sample_filtered(self, cells: np.ndarray, n: int, lower: bool, total: np.ndarray
                         ) -> tuple[np.ndarray, ...]:
        """One hemisphere: ``n`` stratum-averaged, trajectory-filtered, equal-power lights."""
        y = cells @ LUMINANCE_WEIGHTS
        dist = Distribution2D(y, interpolate=True)
        self.distributions[int(lower)] = dist
        # Push light i's sub-samples (its Halton point + a fixed k x k pattern) through the CDFs
        pts = self._points(n)
        k = self.substeps or int(np.clip(self.subsample_budget // n, 1, 8))
        if k > 1:
            off = ((np.arange(k) + 0.5) / k - 0.5) * self.stratum_scale / np.sqrt(n)
            pattern = np.stack(np.meshgrid(off, off), axis=-1).reshape(-1, 2)
        else:
            pattern = np.zeros((1, 2))
        if self.mode_seeking == 0:  # compiled path: only the sums are needed
            dsum, col, inv_f = _stratum_kernel(np.ascontiguousarray(pts), pattern, cells, lower,
                                               *dist.kernel_args())
            d = _normalise(dsum, np.array([0.0, -1.0 if lower else 1.0, 0.0]))
            inv_pdf = inv_f / len(pattern) * dist.integral
        else:
            sub = np.clip(pts[:, None, :] + pattern[None, :, :], 0.0, ONE_MINUS_EPSILON)
            sub_uv, sub_pdf = dist.sample(sub.reshape(-1, 2))
            m = len(pattern)
            sub_dirs = square_to_hemisphere(sub_uv, lower=lower).reshape(n, m, 3)
            ij = np.minimum((sub_uv * self.grid).astype(np.int64), self.grid - 1)
            col = cells[ij[:, 1], ij[:, 0]].reshape(n, m, 3).sum(axis=1)
            d = _robust_centroid(sub_dirs, self.mode_seeking)  # (robust) centroid
            inv_pdf = (1.0 / np.maximum(sub_pdf.reshape(n, m), 1e-300)).mean(axis=1)
        ids = np.arange(n, dtype=np.int64) + (LOWER_ID_OFFSET if lower else 0)
        uv = self._filter(ids, hemisphere_to_square(d, lower=lower), lower)
        dirs = square_to_hemisphere(uv, lower=lower)
        ycol = col @ LUMINANCE_WEIGHTS
        mean_col = total / max(float(total @ LUMINANCE_WEIGHTS), 1e-300)
        chroma = np.where(ycol[:, None] > 0, col / np.where(ycol > 0, ycol, 1.0)[:, None],
                          mean_col[None, :])
        rgb = rescale_to_total(chroma, total)  # equal luminance power Y_h / n, exact sums
        solid = np.minimum(inv_pdf / (n * PDF_UV_TO_OMEGA), 2 * np.pi)  # mean 1 / (n pdf_omega)
        return dirs, rgb, solid, ids

    def _filter(self, ids: np.ndarray, uv: np.ndarray, lower: bool) -> np.ndarray:
        """Trajectory filter per hemisphere (each half has its own filter state)."""
        return (self._lower_filter if lower else self.trajectory_filter).update(ids, uv)
