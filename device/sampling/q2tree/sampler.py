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
Per frame only a coarse level is binned (``._binning.coarse_level``: about as many quads as
lights, at least 16 pixels each), nodes finer than that are summed from their own pixels when
the tree first reaches them, and between frames only the pixel runs whose bits changed are
summed again (``._binning.FrameState``): the result is bit for bit that of a full pass.
Measured (``lightprobe bench samplers``, six 1k maps, load 5-7): 1.98 ms per full build at
N = 1000 against 11.3 ms (same box, idle) when every quad down to nside 256 was binned each
frame. Per frame of a stream the input is checked once per shape and count, the split-merge
update is skipped when no node sum changed (it would find no swap that pays), and the lights
come from one compiled pass (leaves, memoised jitter points, exact-count regrouping). A frame
with a local change costs, end to end at N = 256 (medians over the six maps, load 1.4), 0.23
of a full build on 1k maps (0.32 / 1.39 ms; the floor is reading the new frame and the kept
one), 0.21 on the pipeline's 512 x 256 equirect (0.087 / 0.42 ms) and 0.18 on its nside-64
HEALPix map (0.041 / 0.22 ms); a frame in which every pixel changed (camera noise, a gain
change) 0.7-1.0 of a full build.

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

from lightprobe.core.errors import InputError
from lightprobe.core.lightset import LightSet
from lightprobe.core.q2wire import jitter_directions, uniq_to_nodes

from ..base import sanitize_radiance
from . import _kernels
from ._binning import FrameState, coarse_level, equirect_tables, healpix_tables
from ._nodes import Pyramid, level_solid_angles, reduce_healpix, state_pyramid

__all__ = ["MAX_NSIDE", "Q2TreeSampler", "auto_nside"]

MAX_NSIDE = 512
_JITTER_MEMO = 1 << 16  # jitter points remembered at most
_ROOTS = np.arange(4, 16, dtype=np.int64)
_NO_MOMENT = np.zeros((1, 3))


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
        :func:`lightprobe.device.sampling.peaks.choose_light_count` for this diffuse-error target.

    After each call ``stats`` holds ``mode`` ("full" or "incremental" tree),
    ``pyramid_mode`` ("full" or "incremental" binning) and ``changed_quads`` (coarse quads
    summed again), the seconds spent in ``pyramid_s`` (per-frame coarse sums), ``tree_s``
    (build or split-merge, including the finer nodes summed on demand) and ``emit_s``
    (lights), the ``splits`` / ``merges`` done, ``nside``, ``coarse_nside`` and ``skipped``
    (True when no node sum changed since the last frame, so split-merge was not run).
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
        self._state: FrameState | None = None  # the input's pyramid, kept frame to frame
        self._jitter_memo: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64),
                                                            np.zeros((0, 3)))
        # Tree state: dense per-node flags (split or not) and keys by NUNIQ id, sized on the
        # first frame of a given nside and kept across reset()
        self._nside = 0
        self._in_s: np.ndarray = np.zeros(0, np.uint8)
        self._eff: np.ndarray = np.zeros(0, np.float64)
        self._split: np.ndarray = np.zeros(0, np.int64)
        self._has_tree = False
        # the last input's checked plan: (kind, shape[, nside], count, nside_max) -> (max level,
        # coarse level)
        self._plan_key: tuple[Any, ...] = ()
        self._plan = (0, 0)
        self._scale_key: tuple[Any, ...] = ()
        self._scale = np.zeros(0)
        # (frame state, its frame number, parameters) the tree was last made for
        self._last: tuple[Any, ...] | None = None

    # -- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the tree and the previous frame: the next frame is a full build, end to end
        (work arrays and tables are kept)."""
        if self._state is not None:
            self._state.invalidate()
        self._in_s[self._split] = 0
        self._split = np.zeros(0, np.int64)
        self._has_tree = False
        self._last = None

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
        on the host (Nikodym et al. 2013, Algorithm 2). ``lightprobe.device.sampling.q2tree.nodes_to_uniq``
        turns them back into the light ids."""
        return uniq_to_nodes(self.leaf_ids())

    # -- sampling ---------------------------------------------------------------------------------
    def sample(self, equirect: np.ndarray, count: int) -> LightSet:
        """Light set of an (H, 2H, 3) radiance map; keeps the tree and the map's pyramid for the
        next frame.

        Each equirect pixel is binned whole into the HEALPix quad at ``nside_max`` holding its
        centre: exact float64 energy, true pixel directions (``._binning``). Only the coarse
        quads whose pixels changed since the previous frame are summed again.
        """
        arr = np.asarray(equirect)
        count = _check_count(count)
        plan_key = ("equirect", arr.shape, count, self.nside_max)
        if plan_key != self._plan_key:
            # checked once per input shape and count (a stream repeats them)
            if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] != 2 * arr.shape[0]:
                raise InputError(f"expected an (H, 2H, 3) equirect map, got shape {arr.shape}",
                                 param="equirect")
            nside = self.nside_max or auto_nside(arr.shape[0])
            _check_capacity(count, nside)
            k = nside.bit_length() - 1
            self._plan = (k, coarse_level(k, arr.shape[0] * arr.shape[1], count))
            self._plan_key = plan_key
        t0 = time.perf_counter()
        k, lc = self._plan
        state = self._state_for(("equirect", arr.shape[0], k, lc), equirect_tables,
                                (arr.shape[0], k, lc))
        mode = state.load(np.ascontiguousarray(arr, np.float32).reshape(-1, 3))
        t_pyr = time.perf_counter() - t0
        extra: dict[str, Any] = {}
        if self.peaks or self.error_target is not None:
            from ..peaks import choose_light_count, find_peaks

            clean, _ = sanitize_radiance(arr)
            peaks = find_peaks(clean)
            if self.error_target is not None:
                count, peaks = choose_light_count(clean, count, self.error_target, peaks=peaks,
                                                  sample=lambda c: self._fresh(state, c))
            extra["peaks"] = [p.to_json() for p in peaks]
        lights = self._sample_pyramid(state, count)
        lights.extra.update(extra)
        self.stats.update(pyramid_s=t_pyr, pyramid_mode=mode, changed_quads=state.changed)
        return lights

    def sample_healpix(self, hp_map: np.ndarray, nside: int, count: int) -> LightSet:
        """Light set of a NESTED HEALPix radiance map (12 nside^2, 3). The tree's finest level is
        ``min(nside, nside_max)`` (``nside_max`` None: 256); a finer map is first reduced to it
        by averaging NESTED descendants (exact energy). NaN/inf and negative values count as 0.
        Like ``sample``, only the coarse quads whose pixels changed are summed again.
        """
        count = _check_count(count)
        nside = int(nside)
        hp = np.asarray(hp_map)
        plan_key = ("healpix", hp.shape, nside, count, self.nside_max)
        if plan_key != self._plan_key:
            # checked once per input shape, nside and count
            if nside < 1 or nside & (nside - 1) or nside > 8192:
                raise InputError(f"nside must be a power of two in [1, 8192], got {nside}",
                                 param="nside")
            if hp.shape != (12 * nside * nside, 3):
                raise InputError(f"HEALPix map must have shape ({12 * nside * nside}, 3) for "
                                 f"nside {nside}, got {hp.shape}", param="hp_map")
            tree_nside = min(nside, self.nside_max or 256)
            _check_capacity(count, tree_nside)
            k = tree_nside.bit_length() - 1
            self._plan = (k, coarse_level(k, 12 * tree_nside * tree_nside, count))
            self._plan_key = plan_key
        t0 = time.perf_counter()
        k, lc = self._plan
        if (1 << k) < nside:
            hp = reduce_healpix(np.where(np.isfinite(hp) & (hp > 0), hp, 0), nside, 1 << k)
        elif hp.dtype not in (np.float32, np.float64):
            hp = hp.astype(np.float64)
        state = self._state_for(("healpix", k, lc), healpix_tables, (k, lc))
        mode = state.load(np.ascontiguousarray(hp))
        t_pyr = time.perf_counter() - t0
        lights = self._sample_pyramid(state, count)
        self.stats.update(pyramid_s=t_pyr, pyramid_mode=mode, changed_quads=state.changed)
        return lights

    def _state_for(self, key: tuple[Any, ...], tables: Any, args: tuple[int, ...]) -> FrameState:
        """The frame state of this input geometry (a new one, hence a full pass, if it changed)."""
        moments = self.placement == "centroid"
        state = self._state
        if state is None or state.key != key or state.moments != moments:
            state = FrameState(tables(*args), moments)
            state.key = key
            self._state = state
        return state

    def _sample_pyramid(self, state: FrameState, count: int) -> LightSet:
        pyr = state_pyramid(state)
        src = state.source()
        t1 = time.perf_counter()
        key = (count, self.importance, self.a, self.b, self.hysteresis, self.placement,
               self.seed, self.jitter_extent)
        last = self._last
        if (state.changed == 0 and last is not None and last[0] is state
                and last[1] == state.frame - 1 and last[2] == key and self._has_tree):
            # No node sum changed since the last frame, which this tree was made for: the
            # split-merge update would find no swap that pays (it stopped at none), skip it
            mode, n_split, n_merge, skipped = "incremental", 0, 0, True
        else:
            mode, n_split, n_merge = self._restructure(src, pyr, count)
            skipped = False
        t2 = time.perf_counter()
        lights = self._emit(pyr, count)
        t3 = time.perf_counter()
        self._last = (state, state.frame, key)
        self.stats = {"mode": mode, "tree_s": t2 - t1, "emit_s": t3 - t2,
                      "splits": n_split, "merges": n_merge, "nside": pyr.nside,
                      "coarse_nside": 1 << state.tables.coarse,
                      "leaves": int(12 + 3 * len(self._split)), "skipped": skipped}
        return lights

    def _fresh(self, state: FrameState, count: int) -> LightSet:
        """A full build on ``state`` by a stateless copy (leaves this sampler's tree alone)."""
        other = Q2TreeSampler(1 << state.tables.max_level, self.importance, self.a, self.b, 0.0,
                              self.placement, self.seed, self.jitter_extent)
        return other._sample_pyramid(state, count)

    def _restructure(self, src: tuple, pyr: Pyramid,  # type: ignore[type-arg]
                     count: int) -> tuple[str, int, int]:
        """Full build on the first frame (or a new nside), incremental split-merge after."""
        n_splits = max(0, -(-(count - 12) // 3))
        scale_key = (pyr.max_level, self.a, self.b, self.importance)
        if scale_key != self._scale_key:
            self._scale = _kernels.level_scale(level_solid_angles(pyr.max_level), self.a,
                                               self.b, self.importance == "mean")
            self._scale_key = scale_key
        scale = self._scale
        if self._nside != pyr.nside:
            self._nside = pyr.nside
            self._in_s = np.zeros(16 * pyr.nside * pyr.nside, np.uint8)
            self._eff = np.zeros(16 * pyr.nside * pyr.nside, np.float64)
            self._split = np.zeros(0, np.int64)
            self._has_tree = False
        if not self._has_tree:
            self._in_s[self._split] = 0
            split = _kernels.build_tree(src, pyr.lum, scale, self.a, pyr.max_level,
                                        n_splits, self._in_s, self._eff)
            self._split = np.sort(split)
            self._has_tree = True
            return "full", len(split), 0
        self._split, n_split, n_merge = _kernels.update_tree(
            src, pyr.lum, scale, self.a, pyr.max_level, self._split, n_splits,
            self.hysteresis, self._in_s, self._eff)
        return "incremental", n_split, n_merge

    # -- lights -----------------------------------------------------------------------------------
    def _emit(self, pyr: Pyramid, count: int) -> LightSet:
        """One light per leaf (rgb = the leaf's integral), then regroup to exactly ``count``."""
        if not self._has_tree:
            return LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                            np.zeros(0, np.int64), method=self.name)
        moment = pyr.moment if pyr.moment is not None else _NO_MOMENT
        memo_ids, memo_dirs = self._jitter_memo
        level_omega = level_solid_angles(pyr.max_level)
        ids, rgb, omega, dirs, done = _kernels.emit_lights(
            self._split, self._in_s, self._eff, pyr.rgb, pyr.lum, moment, pyr.moment is not None,
            level_omega, memo_ids, memo_dirs, count)
        if done:
            # the common case, one compiled call: every jitter point needed was memoised
            return LightSet(dirs, rgb, omega, ids, method=self.name, pose=_identity_pose())
        leaves, rgb, lum, omega, dirs, missing = _kernels.leaf_arrays(
            self._split, self._in_s, pyr.rgb, pyr.lum, moment, pyr.moment is not None,
            level_omega)
        if missing.any():
            # jitter placement, or a leaf without power: its fixed jitter point
            dirs[missing] = self._jitter(leaves[missing])
        excess = len(leaves) - count
        if excess > 0 and len(self._split):
            leaves, rgb, omega, dirs = _kernels.regroup_worst(
                self._split, self._in_s, self._eff, leaves, rgb, lum, omega, dirs, excess)
        elif excess > 0:
            groups = self._groups(leaves, count)
            ids, gdirs, grgb, gomega = _regroup(groups, dirs, rgb, omega, lum)
            single = np.ones(len(leaves), bool)
            for _, members in groups:
                single[members] = False
            # each group light takes its id's place among the sorted single leaves
            leaves = leaves[single]
            at = np.searchsorted(leaves, ids)
            leaves = np.insert(leaves, at, ids)
            dirs = np.insert(dirs[single], at, gdirs, axis=0)
            rgb = np.insert(rgb[single], at, grgb, axis=0)
            omega = np.insert(omega[single], at, gomega)
        return LightSet(dirs, rgb, omega, leaves, method=self.name)

    def _jitter(self, ids: np.ndarray) -> np.ndarray:
        """:func:`jitter_directions` of sorted ``ids``, memoised: a leaf's jitter point is
        fixed, and the same leaves (e.g. a black lower hemisphere) recur frame after frame."""
        known, dirs = self._jitter_memo
        at = np.minimum(np.searchsorted(known, ids), max(len(known) - 1, 0))
        hit = known[at] == ids if len(known) else np.zeros(len(ids), bool)
        out = np.empty((len(ids), 3))
        out[hit] = dirs[at[hit]]
        if not hit.all():
            new = ids[~hit]
            out[~hit] = new_dirs = jitter_directions(new, self.seed, self.jitter_extent)
            if len(known) + len(new) > _JITTER_MEMO:
                known, dirs = known[:0], dirs[:0]
            known = np.concatenate([known, new])
            order = np.argsort(known, kind="stable")
            self._jitter_memo = (known[order], np.concatenate([dirs, new_dirs])[order])
        return out

    def _groups(self, leaves: np.ndarray, count: int) -> list[tuple[int, np.ndarray]]:
        """Groups (id, leaf positions) of more than one leaf that become one light each when
        N < 12: runs of consecutive base faces (N >= 12: :func:`._kernels.regroup_worst`)."""
        return [(int(leaves[r[0]]), r) for r in np.array_split(np.arange(12), count)
                if len(r) > 1]


def _identity_pose() -> dict[str, Any]:
    """LightSet's default pose, built without ``np.eye(3).tolist()`` (1.3 us a frame)."""
    return {"rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            "position": [0.0, 0.0, 0.0]}


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
