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

__all__ = ["bin_equirect", "build_tree", "level_scale", "sum_levels", "update_tree"]

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
def _children_keys(lum: np.ndarray, u: int, level: int, scale: np.ndarray, a: float,
                   eff: np.ndarray) -> None:
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
def build_tree(lum: np.ndarray, scale: np.ndarray, a: float, max_level: int,
               n_splits: int, in_s: np.ndarray, eff: np.ndarray) -> np.ndarray:
    """Greedy build (Nikodym et al. 2013, Algorithm 1): split the best leaf ``n_splits`` times.

    ``in_s`` must be all zero on entry; on return it flags the split (interior) nodes and
    ``eff`` holds the keys of the 12 roots, of every split node and of their children.
    Returns the split nodes' ids in split order.
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
        _children_keys(lum, u, level, scale, a, eff)
        if level + 1 < max_level:
            for c in range(4 * u, 4 * u + 4):
                keys, ids, size = _heap_push(keys, ids, size, eff[c], c)
    return out[:n]


@njit(cache=True)
def _candidates(lum: np.ndarray, scale: np.ndarray, a: float, max_level: int,
                split: np.ndarray, in_s: np.ndarray, eff: np.ndarray
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
def update_tree(lum: np.ndarray, scale: np.ndarray, a: float, max_level: int,
                split: np.ndarray, n_splits: int, hysteresis: float, in_s: np.ndarray,
                eff: np.ndarray) -> tuple[np.ndarray, int, int]:
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
    lk, li, ls, mk, mi, ms = _candidates(lum, scale, a, max_level, split, in_s, eff)
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
            _children_keys(lum, u, level, scale, a, eff)
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


# -- the per-frame pyramid of node sums ----------------------------------------------------------
@njit(cache=True)
def bin_equirect(flat: np.ndarray, order: np.ndarray, present: np.ndarray, starts: np.ndarray,
                 omega: np.ndarray, dirs: np.ndarray, weights: np.ndarray, moments: bool,
                 offset: int, n_fine: int, rgb: np.ndarray, lum: np.ndarray,
                 moment: np.ndarray) -> None:
    """Finest-level node sums from equirect pixels grouped by the HEALPix pixel holding their
    centre: ``order`` lists the (H*W) pixels sorted by that pixel, run k (from ``starts[k]``)
    belongs to node ``offset + present[k]``; ``omega`` / ``dirs`` are the sorted pixels' exact
    solid angles and centre directions. Each of the ``n_fine`` finest nodes gets radiance x
    solid angle (rgb, luminance) and, if ``moments``, luminance x direction; 0 if no pixel."""
    n = len(present)
    total = len(order)
    gap = 0  # next finest node not yet written: zero the nodes no pixel falls into
    for k in range(n + 1):
        stop = present[k] if k < n else n_fine
        for g in range(offset + gap, offset + stop):
            rgb[g, 0] = 0.0
            rgb[g, 1] = 0.0
            rgb[g, 2] = 0.0
            lum[g] = 0.0
            if moments:
                moment[g, 0] = 0.0
                moment[g, 1] = 0.0
                moment[g, 2] = 0.0
        gap = stop + 1
        if k == n:
            break
        end = starts[k + 1] if k + 1 < n else total
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        for i in range(starts[k], end):
            p = order[i]
            om = omega[i]
            p0 = flat[p, 0] * om
            p1 = flat[p, 1] * om
            p2 = flat[p, 2] * om
            a0 += p0
            a1 += p1
            a2 += p2
            if moments:
                y = weights[0] * p0 + weights[1] * p1 + weights[2] * p2
                m0 += y * dirs[i, 0]
                m1 += y * dirs[i, 1]
                m2 += y * dirs[i, 2]
        j = offset + present[k]
        rgb[j, 0] = a0
        rgb[j, 1] = a1
        rgb[j, 2] = a2
        lum[j] = weights[0] * a0 + weights[1] * a1 + weights[2] * a2
        if moments:
            moment[j, 0] = m0
            moment[j, 1] = m1
            moment[j, 2] = m2


@njit(cache=True)
def sum_levels(arr: np.ndarray, max_level: int) -> None:
    """Fill the coarser levels of a dense NUNIQ array (M, C): node u = sum of 4u .. 4u+3."""
    for k in range(max_level - 1, -1, -1):
        lo = 4 ** (k + 1)
        for u in range(lo, 4 * lo):
            for ch in range(arr.shape[1]):
                arr[u, ch] = arr[4 * u, ch] + arr[4 * u + 1, ch] + arr[4 * u + 2, ch] + arr[4 * u + 3, ch]


@njit(cache=True)
def bin_healpix(hp: np.ndarray, omega: float, dirs: np.ndarray, weights: np.ndarray,
                moments: bool, offset: int, rgb: np.ndarray, lum: np.ndarray,
                moment: np.ndarray) -> None:
    """Finest-level node sums of a NESTED radiance map at the tree's own nside: radiance x
    ``omega`` (the pixel solid angle), its luminance and, if ``moments``, luminance x the pixel
    centre direction ``dirs``."""
    for i in range(hp.shape[0]):
        j = offset + i
        p0 = hp[i, 0] * omega
        p1 = hp[i, 1] * omega
        p2 = hp[i, 2] * omega
        rgb[j, 0] = p0
        rgb[j, 1] = p1
        rgb[j, 2] = p2
        y = weights[0] * p0 + weights[1] * p1 + weights[2] * p2
        lum[j] = y
        if moments:
            moment[j, 0] = y * dirs[i, 0]
            moment[j, 1] = y * dirs[i, 1]
            moment[j, 2] = y * dirs[i, 2]
