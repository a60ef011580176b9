"""Q2-Tree light sampler (Wan, Wong, Leung 2005) with incremental split-merge between frames.

The sphere is cut into the 12 HEALPix base quads; a quadtree is grown by splitting the most
important leaf, importance ``p = L^a dw^b`` (a = 1, b = 1/4); one directional light per leaf
carries the leaf's integral of radiance x solid angle (Nikodym et al. 2013, Algorithm 1 and
eq. 1). Between frames the tree is kept and repaired by split-merge swaps with a hysteresis
margin instead of rebuilt (see :func:`._kernels.update_tree`); with zero hysteresis the result
after any sequence of updates equals a fresh build on the last frame, exactly.

Defaults, chosen by measurement (six shared maps, N = 256, exact map-based errors, medians):
``importance="integral"`` (occluded 0.0085, diffuse 0.00085) beats ``"mean"`` (0.057, 0.018:
the bright lamp soaks up the leaves); ``placement="centroid"`` beats the fixed jitter
(occluded 0.0132, diffuse 0.0049 with jitter_extent 0.5). ``hysteresis=0.2``: on the simulated
flashlight (N = 256, 60 frames) it lowers flicker to 0.00021 from 0.00027 at 0 and the mean
light displacement to 0.153 from 0.178 degrees, at unchanged error (0.00087). With centroid
placement a light moves inside its leaf as the map changes; with jitter placement it stays put
while its leaf survives.

Input. ``sample`` bins every equirect pixel whole into the quad at ``nside_max`` that holds
its centre (exact float64 power, true pixel directions); ``sample_healpix`` takes a NESTED map.

Exact light counts. Every split adds 3 leaves, so the tree holds ``12 + 3 s`` leaves with
``s = ceil((N - 12) / 3)``. When that exceeds N by e in {1, 2}, the children of the worst
mergeable parent (the node a merge would take first) are partly regrouped: its 3 - e best
children stay single lights and the other e + 1 become one light (id = the parent's id,
solid angle and power summed, direction the luminance-weighted mean of theirs). For N < 12 the
12 base quads are grouped into N runs of consecutive faces in the same way.

Degenerate maps. NaN/inf and negative values count as 0 (``sanitize_radiance``). An all-black
map gives N lights of zero power: every key is 0, ties go to the smaller id, so splits proceed
breadth-first and the lights are spread evenly; no NaN anywhere. A single hot pixel is reached
by splitting straight down to it: one leaf at ``nside_max`` carries its power.

References
----------
Wan, Wong, Leung 2005, "Spherical Q2-tree for sampling dynamic environment sequences", EGSR.
Nikodym, Havran, Bittner et al. 2013, "Multiple live video environment map sampling",
Algorithm 1, eq. (1).
Agarwal et al. 2003, "Structured importance sampling of environment maps" (p = L^a dw^b).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from device.errors import InputError

from ..base import LightSet, sanitize_radiance
from . import _kernels
from ._nodes import (
    Pyramid,
    centroid_directions,
    jitter_directions,
    level_solid_angles,
    pyramid_from_equirect,
    pyramid_from_healpix,
    reduce_healpix,
    uniq_to_nodes,
)

__all__ = ["MAX_NSIDE", "Q2TreeSampler", "auto_nside"]

MAX_NSIDE = 512
_ROOTS = np.arange(4, 16, dtype=np.int64)


def auto_nside(height: int) -> int:
    """The power-of-two nside whose pixel count is nearest an (H, 2H) map's, capped at 256.

    A 1024 x 512 map -> 256 (0.23 degree quads), a 360 x 180 map -> 64. Measured on the six
    shared maps at N = 256 (centroid placement), median occluded error 0.0085 at 256 against
    0.0098 at 128 and 0.0100 at 64: a small sun needs quads as fine as the map's pixels.
    """
    nside = 2 ** int(np.round(np.log2(np.sqrt(2.0 * height * height / 12.0))))
    return int(min(max(nside, 1), 256))


class Q2TreeSampler:
    """Spherical Q2-Tree sampler (``make_sampler("q2tree", ...)``).

    Parameters
    ----------
    nside_max : finest HEALPix resolution the tree may reach (power of two <= 512); ``None``
        picks :func:`auto_nside` from the equirect height (``sample_healpix`` uses the map's).
    importance : ``"integral"`` (L = the quad's integral of luminance x solid angle) or
        ``"mean"`` (L = its mean luminance).
    a, b : exponents of ``p = L^a dw^b`` (Wan et al.: a = 1, b = 1/4).
    hysteresis : relative margin of the incremental update: a leaf is split in exchange for a
        merge only if its key exceeds the parent's by the factor 1 + hysteresis (0: exactly a
        fresh build; count changes are always honoured).
    placement : ``"jitter"`` (a fixed hashed point inside the leaf, ``jitter_extent`` of its
        size around the centre) or ``"centroid"`` (luminance-weighted centroid of the leaf).
    seed : seed of the jitter hash.
    peaks : also run peak detection on equirect input and publish ``extra["peaks"]``.
    error_target : if set, ``sample`` may use fewer lights than asked, chosen by
        :func:`device.sampling.peaks.choose_light_count` for this diffuse-error target.

    After each call ``stats`` holds ``mode`` ("full" or "incremental"), the seconds spent in
    ``pyramid_s`` (per-frame node sums), ``tree_s`` (build or split-merge) and ``emit_s``
    (lights), and the ``splits`` / ``merges`` done.
    """

    name = "q2tree"

    def __init__(self, nside_max: int | None = None, importance: str = "integral",
                 a: float = 1.0, b: float = 0.25, hysteresis: float = 0.2,
                 placement: str = "centroid", seed: int = 0, jitter_extent: float = 0.5,
                 peaks: bool = False, error_target: float | None = None) -> None:
        if importance not in ("integral", "mean"):
            raise InputError(f"importance must be 'integral' or 'mean', got {importance!r}",
                             param="importance")
        if placement not in ("jitter", "centroid"):
            raise InputError(f"placement must be 'jitter' or 'centroid', got {placement!r}",
                             param="placement")
        if nside_max is not None:
            nside_max = int(nside_max)
            if nside_max < 1 or nside_max & (nside_max - 1) or nside_max > MAX_NSIDE:
                raise InputError(f"nside_max must be a power of two in [1, {MAX_NSIDE}], "
                                 f"got {nside_max}", param="nside_max")
        if a < 0 or b < 0 or hysteresis < 0 or not 0 <= jitter_extent <= 1:
            raise InputError("a, b, hysteresis must be >= 0 and jitter_extent in [0, 1]",
                             param="a/b/hysteresis/jitter_extent")
        self.nside_max = nside_max
        self.importance = importance
        self.a = float(a)
        self.b = float(b)
        self.hysteresis = float(hysteresis)
        self.placement = placement
        self.seed = int(seed)
        self.jitter_extent = float(jitter_extent)
        self.peaks = bool(peaks)
        self.error_target = error_target
        self.stats: dict[str, Any] = {}
        self._buffer: Pyramid | None = None  # pyramid arrays reused frame to frame
        # Tree state: dense per-node flags (split or not) and keys by NUNIQ id, sized on the
        # first frame of a given nside and kept across reset()
        self._nside = 0
        self._in_s: np.ndarray = np.zeros(0, np.uint8)
        self._eff: np.ndarray = np.zeros(0, np.float64)
        self._split: np.ndarray = np.zeros(0, np.int64)
        self._has_tree = False

    # -- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the tree: the next frame is a full build (work arrays are kept)."""
        self._in_s[self._split] = 0
        self._split = np.zeros(0, np.int64)
        self._has_tree = False

    @property
    def split_nodes(self) -> np.ndarray:
        """NUNIQ ids of the interior (split) nodes, sorted."""
        return self._split.copy()

    def leaf_ids(self) -> np.ndarray:
        """NUNIQ ids of the current leaves, sorted (before exact-count regrouping)."""
        if not self._has_tree:
            return np.zeros(0, np.int64)
        # roots (ids 4..15) precede all children, and children of sorted parents are sorted
        children = (4 * self._split[:, None] + np.arange(4)).ravel()
        cand = np.concatenate([_ROOTS, children])
        return cand[self._in_s[cand] == 0]

    def to_nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """The leaf set as (level, NESTED index) int64 arrays, for serialising and merging trees
        on the host (Nikodym et al. 2013, Algorithm 2). ``device.sampling.q2tree.nodes_to_uniq``
        turns them back into the light ids."""
        return uniq_to_nodes(self.leaf_ids())

    # -- sampling ---------------------------------------------------------------------------------
    def sample(self, equirect: np.ndarray, count: int) -> LightSet:
        """Light set of an (H, 2H, 3) radiance map; keeps the tree for the next frame.

        Each equirect pixel is binned whole into the HEALPix quad at ``nside_max`` holding its
        centre (``pyramid_from_equirect``): exact float64 energy, true pixel directions.
        """
        arr = np.asarray(equirect)
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] != 2 * arr.shape[0]:
            raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {arr.shape}",
                             param="equirect")
        count = _check_count(count)
        clean, _ = sanitize_radiance(arr)
        nside = self.nside_max or auto_nside(arr.shape[0])
        _check_capacity(count, nside)
        t0 = time.perf_counter()
        pyr = pyramid_from_equirect(clean, nside, self.placement == "centroid", reuse=self._buffer)
        self._buffer = pyr
        t_pyr = time.perf_counter() - t0
        extra: dict[str, Any] = {}
        if self.peaks or self.error_target is not None:
            from ..peaks import choose_light_count, find_peaks

            peaks = find_peaks(clean)
            if self.error_target is not None:
                count, peaks = choose_light_count(clean, count, self.error_target, peaks=peaks,
                                                  sample=lambda c: self._fresh(pyr, c))
            extra["peaks"] = [p.to_json() for p in peaks]
        lights = self._sample_pyramid(pyr, count)
        lights.extra.update(extra)
        self.stats["pyramid_s"] = t_pyr
        return lights

    def sample_healpix(self, hp_map: np.ndarray, nside: int, count: int) -> LightSet:
        """Light set of a NESTED HEALPix radiance map (12 nside^2, 3). The tree's finest level is
        ``min(nside, nside_max)`` (``nside_max`` None: 256); a finer map is first reduced to it
        by averaging NESTED descendants (exact energy). NaN/inf and negative values count as 0.
        """
        count = _check_count(count)
        nside = int(nside)
        if nside < 1 or nside & (nside - 1) or nside > 8192:
            raise InputError(f"nside must be a power of two in [1, 8192], got {nside}",
                             param="nside")
        hp = np.asarray(hp_map)
        if hp.shape != (12 * nside * nside, 3):
            raise InputError(f"HEALPix map must have shape ({12 * nside * nside}, 3) for nside "
                             f"{nside}, got {hp.shape}", param="hp_map")
        tree_nside = min(nside, self.nside_max or 256)
        _check_capacity(count, tree_nside)
        t0 = time.perf_counter()
        hp = np.where(np.isfinite(hp) & (hp > 0), hp, 0)
        if tree_nside < nside:
            hp = reduce_healpix(hp, nside, tree_nside)
        pyr = pyramid_from_healpix(hp, tree_nside, self.placement == "centroid",
                                   reuse=self._buffer)
        self._buffer = pyr
        t_pyr = time.perf_counter() - t0
        lights = self._sample_pyramid(pyr, count)
        self.stats["pyramid_s"] = t_pyr
        return lights

    def _sample_pyramid(self, pyr: Pyramid, count: int) -> LightSet:
        t1 = time.perf_counter()
        mode, n_split, n_merge = self._restructure(pyr, count)
        t2 = time.perf_counter()
        lights = self._emit(pyr, count)
        t3 = time.perf_counter()
        self.stats = {"mode": mode, "tree_s": t2 - t1, "emit_s": t3 - t2,
                      "splits": n_split, "merges": n_merge, "nside": pyr.nside,
                      "leaves": int(12 + 3 * len(self._split))}
        return lights

    def _fresh(self, pyr: Pyramid, count: int) -> LightSet:
        """A full build on ``pyr`` by a stateless copy (leaves this sampler's tree alone)."""
        other = Q2TreeSampler(pyr.nside, self.importance, self.a, self.b, 0.0, self.placement,
                              self.seed, self.jitter_extent)
        return other._sample_pyramid(pyr, count)

    def _restructure(self, pyr: Pyramid, count: int) -> tuple[str, int, int]:
        """Full build on the first frame (or a new nside), incremental split-merge after."""
        n_splits = max(0, -(-(count - 12) // 3))
        scale = _kernels.level_scale(level_solid_angles(pyr.max_level), self.a, self.b,
                                     self.importance == "mean")
        if self._nside != pyr.nside:
            self._nside = pyr.nside
            self._in_s = np.zeros(16 * pyr.nside * pyr.nside, np.uint8)
            self._eff = np.zeros(16 * pyr.nside * pyr.nside, np.float64)
            self._split = np.zeros(0, np.int64)
            self._has_tree = False
        if not self._has_tree:
            self._in_s[self._split] = 0
            split = _kernels.build_tree(pyr.lum, scale, self.a, pyr.max_level,
                                        n_splits, self._in_s, self._eff)
            self._split = np.sort(split)
            self._has_tree = True
            return "full", len(split), 0
        self._split, n_split, n_merge = _kernels.update_tree(
            pyr.lum, scale, self.a, pyr.max_level, self._split, n_splits,
            self.hysteresis, self._in_s, self._eff)
        return "incremental", n_split, n_merge

    # -- lights -----------------------------------------------------------------------------------
    def _directions(self, pyr: Pyramid, uniq: np.ndarray) -> np.ndarray:
        if self.placement == "jitter":
            return jitter_directions(uniq, self.seed, self.jitter_extent)
        return centroid_directions(pyr, uniq, self.seed, self.jitter_extent)

    def _emit(self, pyr: Pyramid, count: int) -> LightSet:
        """One light per leaf (rgb = the leaf's integral), then regroup to exactly ``count``."""
        leaves = self.leaf_ids()
        level, _ = uniq_to_nodes(leaves)
        rgb = pyr.rgb[leaves]
        omega = level_solid_angles(pyr.max_level)[level]
        dirs = self._directions(pyr, leaves)
        excess = len(leaves) - count
        if excess > 0:
            lum = pyr.lum[leaves]
            groups = self._groups(leaves, count)
            ids, gdirs, grgb, gomega = _regroup(groups, dirs, rgb, omega, lum)
            single = np.ones(len(leaves), bool)
            for _, members in groups:
                single[members] = False
            ids = np.concatenate([leaves[single], ids])
            order = np.argsort(ids, kind="stable")
            leaves = ids[order]
            dirs = np.concatenate([dirs[single], gdirs])[order]
            rgb = np.concatenate([rgb[single], grgb])[order]
            omega = np.concatenate([omega[single], gomega])[order]
        return LightSet(dirs, rgb, omega, leaves, method=self.name)

    def _groups(self, leaves: np.ndarray, count: int) -> list[tuple[int, np.ndarray]]:
        """Groups (id, leaf positions) of more than one leaf that become one light each."""
        if len(self._split) == 0:
            # N < 12: runs of consecutive base faces
            return [(int(leaves[r[0]]), r) for r in np.array_split(np.arange(12), count)
                    if len(r) > 1]
        excess = len(leaves) - count
        # The worst mergeable parent (the node a merge would take first)
        split = self._split
        has_split_child = self._in_s[(4 * split[:, None] + np.arange(4))].any(axis=1)
        mergeable = split[~has_split_child]
        worst = mergeable[np.lexsort((-mergeable, self._eff[mergeable]))[0]]
        kids = 4 * worst + np.arange(4)
        kids = kids[np.lexsort((kids, -self._eff[kids]))]  # best first
        merged = np.searchsorted(leaves, np.sort(kids[3 - excess:]))
        return [(int(worst), merged)]


def _check_capacity(count: int, nside: int) -> None:
    if count > 12 * nside * nside:
        raise InputError(f"count {count} exceeds the {12 * nside * nside} quads of nside {nside}",
                         param="count")


def _check_count(count: int) -> int:
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise InputError(f"count must be an integer >= 1, got {count!r}", param="count")
    return int(count)


def _regroup(groups: list[tuple[int, np.ndarray]], dirs: np.ndarray, rgb: np.ndarray,
             omega: np.ndarray, lum: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One light per group: power and solid angle summed, direction the luminance-weighted mean
    of the members' directions (equal weights when the group is dark)."""
    ids = np.array([g[0] for g in groups], np.int64)
    out_dirs = np.empty((len(groups), 3))
    out_rgb = np.empty((len(groups), 3))
    out_omega = np.empty(len(groups))
    for j, (_, members) in enumerate(groups):
        w = lum[members]
        w = w if w.sum() > 0 else np.ones(len(members))
        d = (w[:, None] * dirs[members]).sum(axis=0)
        n = np.linalg.norm(d)
        out_dirs[j] = d / n if n > 0 else dirs[members[0]]
        out_rgb[j] = rgb[members].sum(axis=0)
        out_omega[j] = omega[members].sum()
    return ids, out_dirs, out_rgb, out_omega
