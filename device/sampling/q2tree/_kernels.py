"""Compiled kernels of the Q2-Tree: full greedy build and incremental split-merge.

Node addressing: a node at level k (nside 2^k) with NESTED index i has the HEALPix NUNIQ id
``u = 4 * 4^k + i``; level k occupies ``[4^(k+1), 4^(k+2))``, the parent of u is ``u >> 2`` and
its children are ``4u .. 4u+3``. Every per-node array here is dense and indexed by u (length
``16 nside_max^2``).

Ordering. Each node has a raw importance ``p(u) = L^a dw^b`` (Wan et al. 2005 eq. 1; Nikodym et
al. 2013 eq. 1) and an effective key ``key(u) = min(p(u), key(parent))`` (roots: ``p``). The
total order used everywhere is "u ranks above v" iff ``key(u) > key(v)`` or (equal keys and
``u < v``). A child therefore always ranks strictly below its parent, so the greedy build that
always splits the best leaf (Nikodym et al. 2013, Algorithm 1) splits exactly the ``s``
best-ranked nodes of the whole tree, and the incremental update can reach that same set by
swaps. For ``L`` = the node's integral the min is a no-op (a sub-quad never holds more power);
for the mean radiance it is what makes the build a function of the map alone.

Dtype policy: keys and powers float64; node ids int64; membership flags uint8.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._binning import children_stale, fill_children

__all__ = ["build_tree", "emit_lights", "leaf_arrays", "level_scale", "regroup_worst",
           "update_tree"]

NEG_INF = -np.inf


@njit(cache=True, inline="always")
def _level(u: int) -> int:
    k = -1
    while u >= 4:
        u >>= 2
        k += 1
    return k


@njit(cache=True, inline="always")
def _raw_importance(lum: np.ndarray, u: int, level: int, scale: np.ndarray, a: float) -> float:
    # p = L^a * dw^b  (Wan et al. 2005, eq. 1), as (integral L)^a * scale[level]: see level_scale
    power = lum[u]
    if a != 1.0:
        power = power ** a
    return power * scale[level]


def level_scale(dw: np.ndarray, a: float, b: float, mean: bool) -> np.ndarray:
    """Per-level factor of the importance of a quad with luminance integral Phi:
    ``p = Phi^a dw^b`` (L = integral) or ``(Phi / dw)^a dw^b = Phi^a dw^(b - a)`` (L = mean)."""
    return dw ** (b - a) if mean else dw**b


@njit(cache=True, inline="always")
def _above(k1: float, u1: int, k2: float, u2: int) -> bool:
    """Total order: higher key first, ties to the smaller id (parents before children)."""
    return k1 > k2 or (k1 == k2 and u1 < u2)


# -- a binary max-heap on (key, id) under ``_above``; min-heaps store (-key, -id) -----------------
@njit(cache=True)
def _heap_push(keys: np.ndarray, ids: np.ndarray, size: int, k: float, u: int
               ) -> tuple[np.ndarray, np.ndarray, int]:
    if size == len(keys):
        nk = np.empty(2 * len(keys) + 16, np.float64)
        ni = np.empty(2 * len(keys) + 16, np.int64)
        nk[:size] = keys[:size]
        ni[:size] = ids[:size]
        keys, ids = nk, ni
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if not _above(k, u, keys[parent], ids[parent]):
            break
        keys[i] = keys[parent]
        ids[i] = ids[parent]
        i = parent
    keys[i] = k
    ids[i] = u
    return keys, ids, size + 1


@njit(cache=True)
def _sift_down(keys: np.ndarray, ids: np.ndarray, size: int, i: int) -> None:
    k = keys[i]
    u = ids[i]
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and _above(keys[c + 1], ids[c + 1], keys[c], ids[c]):
            c += 1
        if not _above(keys[c], ids[c], k, u):
            break
        keys[i] = keys[c]
        ids[i] = ids[c]
        i = c
    keys[i] = k
    ids[i] = u


@njit(cache=True)
def _heap_pop(keys: np.ndarray, ids: np.ndarray, size: int) -> int:
    size -= 1
    if size > 0:
        keys[0] = keys[size]
        ids[0] = ids[size]
        _sift_down(keys, ids, size, 0)
    return size


@njit(cache=True)
def _heapify(keys: np.ndarray, ids: np.ndarray, size: int) -> None:
    for i in range(size // 2 - 1, -1, -1):
        _sift_down(keys, ids, size, i)


# -- tree edits shared by build and update -------------------------------------------------------
@njit(cache=True)
def _fill_stale(src: tuple, split: np.ndarray) -> None:  # type: ignore[type-arg]
    """:func:`fill_children` for the split nodes whose children are stale. Members of ``src``
    are read once here: reading them per node costs reference counts (7 us for 82 nodes)."""
    lc, stamp, qver = src[7], src[9], src[10]
    for j in range(len(split)):
        u = split[j]
        level = _level(u)
        if children_stale(lc, stamp, qver, u, level):
            fill_children(src, u, level)


@njit(cache=True, inline="always")
def _fill(src: tuple, u: int, level: int) -> None:  # type: ignore[type-arg]
    """:func:`fill_children` if it has work (the test reads 3 members of ``src`` only)."""
    if children_stale(src[7], src[9], src[10], u, level):
        fill_children(src, u, level)


@njit(cache=True, inline="always")
def _children_keys(src: tuple, lum: np.ndarray, u: int, level: int,  # type: ignore[type-arg]
                   scale: np.ndarray, a: float, eff: np.ndarray) -> None:
    _fill(src, u, level)
    for c in range(4 * u, 4 * u + 4):
        p = _raw_importance(lum, c, level + 1, scale, a)
        eff[c] = min(p, eff[u])


@njit(cache=True)
def _is_mergeable(in_s: np.ndarray, u: int) -> bool:
    ok = in_s[u] != 0
    for c in range(4 * u, 4 * u + 4):
        ok = ok and in_s[c] == 0
    return ok


@njit(cache=True)
def _is_leaf(in_s: np.ndarray, u: int, level: int, max_level: int) -> bool:
    return level < max_level and not in_s[u] and (u < 16 or in_s[u >> 2] == 1)


@njit(cache=True)
def build_tree(src: tuple, lum: np.ndarray, scale: np.ndarray,  # type: ignore[type-arg]
               a: float, max_level: int, n_splits: int, in_s: np.ndarray, eff: np.ndarray
               ) -> np.ndarray:
    """Greedy build (Nikodym et al. 2013, Algorithm 1): split the best leaf ``n_splits`` times.

    ``src`` sums nodes finer than the per-frame pyramid on demand
    (:func:`._binning.fill_children`). ``in_s`` must be all zero on entry; on return it flags
    the split (interior) nodes and ``eff`` holds the keys of the 12 roots, of every split
    node and of their children. Returns the split nodes' ids in split order.
    """
    keys = np.empty(12 + 4 * n_splits, np.float64)
    ids = np.empty(12 + 4 * n_splits, np.int64)
    size = 0
    # Evaluate the importance of the 12 base quads
    for u in range(4, 16):
        eff[u] = _raw_importance(lum, u, 0, scale, a)
        if max_level > 0:
            keys, ids, size = _heap_push(keys, ids, size, eff[u], u)
    out = np.empty(n_splits, np.int64)
    n = 0
    # Subdivide the best leaf until the required number of leaves exists
    while n < n_splits and size > 0:
        u = ids[0]
        size = _heap_pop(keys, ids, size)
        level = _level(u)
        in_s[u] = 1
        out[n] = u
        n += 1
        _children_keys(src, lum, u, level, scale, a, eff)
        if level + 1 < max_level:
            for c in range(4 * u, 4 * u + 4):
                keys, ids, size = _heap_push(keys, ids, size, eff[c], c)
    return out[:n]


@njit(cache=True)
def _candidates(src: tuple, lum: np.ndarray, scale: np.ndarray,  # type: ignore[type-arg]
                a: float, max_level: int, split: np.ndarray, in_s: np.ndarray, eff: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, int]:
    """Re-evaluate the keys of the roots, the split nodes (sorted: parents first) and their
    children in one pass, collecting the splittable leaves (lk, li, ls: max-heap entries) and
    the mergeable parents (mk, mi, ms: min-heap entries stored as (-key, -id)); not heapified."""
    cap = 16 + 4 * len(split)
    lk = np.empty(cap, np.float64)
    li = np.empty(cap, np.int64)
    mk = np.empty(cap, np.float64)
    mi = np.empty(cap, np.int64)
    ls = 0
    ms = 0
    _fill_stale(src, split)
    for u in range(4, 16):
        eff[u] = _raw_importance(lum, u, 0, scale, a)
        if max_level > 0 and not in_s[u]:
            lk[ls] = eff[u]
            li[ls] = u
            ls += 1
    for j in range(len(split)):
        u = split[j]
        level = _level(u)
        if u >= 16:
            eff[u] = min(_raw_importance(lum, u, level, scale, a), eff[u >> 2])
        e_u = eff[u]
        mergeable = True
        for c in range(4 * u, 4 * u + 4):
            eff[c] = min(_raw_importance(lum, c, level + 1, scale, a), e_u)
            if in_s[c]:
                mergeable = False
            elif level + 1 < max_level:
                lk[ls] = eff[c]
                li[ls] = c
                ls += 1
        if mergeable:
            mk[ms] = -e_u
            mi[ms] = -u
            ms += 1
    return lk, li, ls, mk, mi, ms


@njit(cache=True, inline="always")
def _swap_pays(ka: float, ua: int, kb: float, ub: int, hysteresis: float) -> bool:
    """Split leaf a for merging parent b? With a margin: key(a) > (1 + h) key(b); without:
    the exact total order (so zero hysteresis reproduces a fresh build)."""
    if hysteresis > 0.0:
        return ka > (1.0 + hysteresis) * kb
    return _above(ka, ua, kb, ub)


@njit(cache=True)
def _top(keys: np.ndarray, ids: np.ndarray, size: int) -> int:
    """Index of the best entry of an unsorted candidate array (linear scan)."""
    best = 0
    for j in range(1, size):
        if _above(keys[j], ids[j], keys[best], ids[best]):
            best = j
    return best


@njit(cache=True)
def _collect(split: np.ndarray, added: np.ndarray, n_added: int, in_s: np.ndarray,
             count: int) -> np.ndarray:
    """The new split set, sorted: survivors of ``split`` plus nodes split now (a node merged
    and re-split appears in both lists; a temporary mark 2 keeps it once)."""
    out = np.empty(count, np.int64)
    n = 0
    for j in range(len(split) + n_added):
        u = split[j] if j < len(split) else added[j - len(split)]
        if in_s[u] == 1:
            in_s[u] = 2
            out[n] = u
            n += 1
    for j in range(n):
        in_s[out[j]] = 1
    return np.sort(out[:n])


@njit(cache=True)
def update_tree(src: tuple, lum: np.ndarray, scale: np.ndarray,  # type: ignore[type-arg]
                a: float, max_level: int, split: np.ndarray, n_splits: int, hysteresis: float,
                in_s: np.ndarray, eff: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Incremental split-merge from the previous frame's tree to ``n_splits`` splits.

    ``split`` holds the previous split nodes sorted by id and ``in_s`` flags them. The keys are
    re-evaluated for the new map (O(1) per node from the pyramid), then (1) the count is adjusted
    by splitting the best leaves or merging the worst mergeable parents, then (2) the best leaf
    is split and the worst mergeable parent merged while ``_swap_pays``. With zero hysteresis
    the result is the split set of ``build_tree`` on the same map: if the sets differ, a
    best-ranked missing node is a leaf and a worst-ranked surplus node is mergeable, and it
    ranks below that leaf, so a swap is still available; every swap raises the split set in
    the total order, so the loop ends (Wan et al. 2005, incremental update).

    Returns (split ids sorted, number of splits done, number of merges done).
    """
    lk, li, ls, mk, mi, ms = _candidates(src, lum, scale, a, max_level, split, in_s, eff)
    count = len(split)
    if count == n_splits and ls > 0 and ms > 0:
        # Common case of a slowly changing map: no swap pays, nothing to sort
        ja, jb = _top(lk, li, ls), _top(mk, mi, ms)
        if not _swap_pays(lk[ja], li[ja], -mk[jb], -mi[jb], hysteresis):
            return split.copy(), 0, 0
    _heapify(lk, li, ls)
    _heapify(mk, mi, ms)
    added = np.empty(16, np.int64)
    n_added = n_split_ops = n_merge_ops = 0
    while True:
        # Drop stale heap tops (lazy deletion)
        while ls > 0 and not _is_leaf(in_s, li[0], _level(li[0]), max_level):
            ls = _heap_pop(lk, li, ls)
        while ms > 0 and not _is_mergeable(in_s, -mi[0]):
            ms = _heap_pop(mk, mi, ms)
        if count < n_splits:
            do_split, do_merge = ls > 0, False
        elif count > n_splits:
            do_split, do_merge = False, ms > 0
        else:
            do_split = ls > 0 and ms > 0 and _swap_pays(lk[0], li[0], -mk[0], -mi[0], hysteresis)
            do_merge = do_split
        if not do_split and not do_merge:
            break
        if do_split:
            # Split the best leaf: it becomes a mergeable parent, its children new leaves
            u = li[0]
            ls = _heap_pop(lk, li, ls)
            level = _level(u)
            in_s[u] = 1
            count += 1
            n_split_ops += 1
            if n_added == len(added):
                added = np.concatenate((added, np.empty(len(added), np.int64)))
            added[n_added] = u
            n_added += 1
            _children_keys(src, lum, u, level, scale, a, eff)
            if level + 1 < max_level:
                for c in range(4 * u, 4 * u + 4):
                    lk, li, ls = _heap_push(lk, li, ls, eff[c], c)
            mk, mi, ms = _heap_push(mk, mi, ms, -eff[u], -u)
        if do_merge:
            # Merge the worst mergeable parent: it becomes a leaf; its parent may become mergeable
            while ms > 0 and not _is_mergeable(in_s, -mi[0]):
                ms = _heap_pop(mk, mi, ms)
            u = -mi[0]
            ms = _heap_pop(mk, mi, ms)
            in_s[u] = 0
            count -= 1
            n_merge_ops += 1
            lk, li, ls = _heap_push(lk, li, ls, eff[u], u)
            if u >= 16 and _is_mergeable(in_s, u >> 2):
                mk, mi, ms = _heap_push(mk, mi, ms, -eff[u >> 2], -(u >> 2))
    return _collect(split, added, n_added, in_s, count), n_split_ops, n_merge_ops


@njit(cache=True)
def leaf_arrays(split: np.ndarray, in_s: np.ndarray, rgb: np.ndarray, lum: np.ndarray,
                moment: np.ndarray, moments: bool, level_omega: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The leaves of the tree with split nodes ``split`` (sorted), in id order: (ids, rgb,
    luminance, solid angle, direction = normalised first moment (the luminance-weighted
    centroid) if ``moments``, and a flag for leaves without one: no power, or no moments)."""
    n = 12 + 3 * len(split)
    ids = np.empty(n, np.int64)
    out_rgb = np.empty((n, 3))
    out_lum = np.empty(n)
    omega = np.empty(n)
    dirs = np.zeros((n, 3))
    missing = np.zeros(n, np.bool_)
    k = 0
    for j in range(-12, len(split)):
        # roots (ids 4..15) first, then the children of each split node (sorted parents)
        lo = j + 16 if j < 0 else 4 * split[j]
        hi = lo + 1 if j < 0 else lo + 4
        for u in range(lo, hi):
            if in_s[u]:
                continue
            ids[k] = u
            out_rgb[k, 0], out_rgb[k, 1], out_rgb[k, 2] = rgb[u, 0], rgb[u, 1], rgb[u, 2]
            out_lum[k] = lum[u]
            omega[k] = level_omega[_level(u)]
            norm = 0.0
            if moments:
                norm = np.sqrt(moment[u, 0] ** 2 + moment[u, 1] ** 2 + moment[u, 2] ** 2)
            if norm > 0.0:
                dirs[k, 0] = moment[u, 0] / norm
                dirs[k, 1] = moment[u, 1] / norm
                dirs[k, 2] = moment[u, 2] / norm
            else:
                missing[k] = True
            k += 1
    return ids[:k], out_rgb[:k], out_lum[:k], omega[:k], dirs[:k], missing[:k]


@njit(cache=True)
def _merged_children(split: np.ndarray, in_s: np.ndarray, eff: np.ndarray, excess: int
                     ) -> tuple[int, np.ndarray]:
    """The worst mergeable parent (the node a merge would take first: lowest key, ties to the
    larger id) and, sorted by id, the ``excess + 1`` of its children that become one light
    (all but its 3 - excess best: highest key, ties to the smaller id)."""
    worst = -1
    for j in range(len(split)):
        u = split[j]
        if in_s[4 * u] or in_s[4 * u + 1] or in_s[4 * u + 2] or in_s[4 * u + 3]:
            continue
        if worst < 0 or eff[u] < eff[worst] or (eff[u] == eff[worst] and u > worst):
            worst = u
    kids = np.arange(4 * worst, 4 * worst + 4)
    for a in range(1, 4):  # insertion sort, best first
        c = kids[a]
        b = a - 1
        while b >= 0 and (eff[kids[b]] < eff[c] or (eff[kids[b]] == eff[c] and kids[b] > c)):
            kids[b + 1] = kids[b]
            b -= 1
        kids[b + 1] = c
    return worst, np.sort(kids[3 - excess:])


@njit(cache=True)
def regroup_worst(split: np.ndarray, in_s: np.ndarray, eff: np.ndarray, leaves: np.ndarray,
                  rgb: np.ndarray, lum: np.ndarray, omega: np.ndarray, dirs: np.ndarray,
                  excess: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact light count when the leaves exceed it by ``excess`` in {1, 2}: the children of the
    worst mergeable parent (the node a merge would take first: lowest key, ties to the larger
    id) keep their 3 - excess best as lights (highest key, ties to the smaller id) and the
    other excess + 1 become one light with the parent's id: power and solid angle summed,
    direction the luminance-weighted mean of theirs (equal weights if dark), normalised.
    Returns (ids, rgb, solid angle, directions), sorted by id."""
    worst, merged = _merged_children(split, in_s, eff, excess)
    pos = np.searchsorted(leaves, merged)
    wsum = 0.0
    for p in pos:
        wsum += lum[p]
    g_rgb = np.zeros(3)
    g_dir = np.zeros(3)
    g_omega = 0.0
    for p in pos:
        w = lum[p] if wsum > 0.0 else 1.0
        for ch in range(3):
            g_rgb[ch] += rgb[p, ch]
            g_dir[ch] += w * dirs[p, ch]
        g_omega += omega[p]
    norm = np.sqrt(g_dir[0] ** 2 + g_dir[1] ** 2 + g_dir[2] ** 2)
    n = len(leaves) - excess
    ids = np.empty(n, np.int64)
    out_rgb = np.empty((n, 3))
    out_omega = np.empty(n)
    out_dirs = np.empty((n, 3))
    k = 0
    placed = False
    m = 0  # next merged position to skip
    for i in range(len(leaves) + 1):
        if not placed and (i == len(leaves) or leaves[i] > worst):
            ids[k] = worst
            out_omega[k] = g_omega
            for ch in range(3):
                out_rgb[k, ch] = g_rgb[ch]
                out_dirs[k, ch] = g_dir[ch] / norm if norm > 0.0 else dirs[pos[0], ch]
            k += 1
            placed = True
        if i == len(leaves):
            break
        if m < len(pos) and pos[m] == i:
            m += 1
            continue
        ids[k] = leaves[i]
        out_omega[k] = omega[i]
        for ch in range(3):
            out_rgb[k, ch] = rgb[i, ch]
            out_dirs[k, ch] = dirs[i, ch]
        k += 1
    return ids, out_rgb, out_omega, out_dirs


@njit(cache=True, inline="always")
def _leaf_direction(u: int, moment: np.ndarray, moments: bool, memo_ids: np.ndarray,
                    memo_dirs: np.ndarray, d: np.ndarray) -> bool:
    """``d`` = the leaf's normalised first moment, else its memoised jitter point (False if
    not memoised): :func:`leaf_arrays`' rule."""
    norm = 0.0
    if moments:
        norm = np.sqrt(moment[u, 0] ** 2 + moment[u, 1] ** 2 + moment[u, 2] ** 2)
    if norm > 0.0:
        for ch in range(3):
            d[ch] = moment[u, ch] / norm
        return True
    at = np.searchsorted(memo_ids, u)
    if at == len(memo_ids) or memo_ids[at] != u:
        return False
    for ch in range(3):
        d[ch] = memo_dirs[at, ch]
    return True


@njit(cache=True)
def emit_lights(split: np.ndarray, in_s: np.ndarray, eff: np.ndarray, rgb: np.ndarray,
                lum: np.ndarray, moment: np.ndarray, moments: bool, level_omega: np.ndarray,
                memo_ids: np.ndarray, memo_dirs: np.ndarray, count: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """The lights of the tree in one pass, straight into the output arrays: what
    :func:`leaf_arrays` then :func:`regroup_worst` give (same arithmetic, same order, so the
    same bits), with the fixed jitter point of each leaf without a centroid read from the memo
    (``memo_ids`` sorted, ``memo_dirs``). Returns (ids, rgb, solid angle, directions, done);
    ``done`` is False, and the arrays are not to be used, when a jitter point is not memoised
    or the count needs the base-face grouping (N < 12): the caller then takes the slow path."""
    n_leaves = 12 + 3 * len(split)
    excess = n_leaves - count
    empty = (np.empty(0, np.int64), np.empty((0, 3)), np.empty(0), np.empty((0, 3)))
    if excess > 0 and len(split) == 0:
        return empty[0], empty[1], empty[2], empty[3], False
    # Choose the children merged into one light (regroup_worst's rule)
    worst = -1
    merged = np.full(3, -1, np.int64)
    if excess > 0:
        worst, group = _merged_children(split, in_s, eff, excess)
        merged[:excess + 1] = group
    n = n_leaves - max(excess, 0)
    ids = np.empty(n, np.int64)
    out_rgb = np.empty((n, 3))
    omega = np.empty(n)
    dirs = np.empty((n, 3))
    d = np.empty(3)
    g_rgb = np.zeros(3)
    g_dir = np.zeros(3)  # luminance-weighted
    g_dir1 = np.zeros(3)  # equal weights (a dark group)
    first_dir = np.zeros(3)
    g_omega = wsum = 0.0
    g_at = -1  # the group light's slot
    m = 0  # merged members seen
    k = 0
    for j in range(-12, len(split)):
        # roots (ids 4..15) first, then the children of each split node (sorted parents)
        lo = j + 16 if j < 0 else 4 * split[j]
        hi = lo + 1 if j < 0 else lo + 4
        for u in range(lo, hi):
            if in_s[u]:
                continue
            if not _leaf_direction(u, moment, moments, memo_ids, memo_dirs, d):
                return empty[0], empty[1], empty[2], empty[3], False
            if worst >= 0 and g_at < 0 and u > worst:
                g_at = k
                k += 1
            if m <= excess and worst >= 0 and merged[m] == u:
                # a member of the group light (regroup_worst: sums in id order)
                if m == 0:
                    first_dir[:] = d
                wsum += lum[u]
                for ch in range(3):
                    g_rgb[ch] += rgb[u, ch]
                    g_dir[ch] += lum[u] * d[ch]
                    g_dir1[ch] += 1.0 * d[ch]
                g_omega += level_omega[_level(u)]
                m += 1
                continue
            ids[k] = u
            omega[k] = level_omega[_level(u)]
            for ch in range(3):
                out_rgb[k, ch] = rgb[u, ch]
                dirs[k, ch] = d[ch]
            k += 1
    if worst >= 0:
        if g_at < 0:
            g_at = k
        gd = g_dir if wsum > 0.0 else g_dir1
        norm = np.sqrt(gd[0] ** 2 + gd[1] ** 2 + gd[2] ** 2)
        ids[g_at] = worst
        omega[g_at] = g_omega
        for ch in range(3):
            out_rgb[g_at, ch] = g_rgb[ch]
            dirs[g_at, ch] = gd[ch] / norm if norm > 0.0 else first_dir[ch]
    return ids, out_rgb, omega, dirs, True
