"""Merging the lights of several probes into the lighting at one point (Nikodym et al. 2013, §4).

- **Q2-Tree** (:func:`merge_q2trees`, Algorithm 2): reconstruct each tree from its leaves,
  traverse them in parallel summing the (weighted) rgb of corresponding nodes, normalise
  top-down, re-evaluate the importance ``p = L^a dw^b``, reduce to N leaves by cutting the least
  important subtrees and place one light per leaf.
- **Pharr / Hemigon** (:func:`merge_indexed`, §4.1): the samples of every probe come from the
  same quasi-random sequence, so light ``j`` of each probe is interpolated with light ``j`` of
  the others.
- **Weights** (:func:`probe_weights`): inverse distance from the target point to each probe's
  pose position, normalised; equal weights without a target.
- **Failures** (:func:`merge_probes`): a probe without data, or whose data is stale, drops out;
  the merge continues from the rest and says so in ``extra["dropped"]``.

Dtype policy: node values, weights and directions float64; node ids int64 (HEALPix NUNIQ,
``u = 4 4^k + i``; parent ``u >> 2``, children ``4u .. 4u + 3``).

References
----------
Nikodym, Havran, Bittner et al. 2013, "Multiple live video environment map sampling",
§4.1 (PDF-sample interpolation), §4.2 and Algorithm 2 (merging Q2-Trees), eq. (1).
Wan, Wong, Leung 2005, "Spherical Q2-tree for sampling dynamic environment sequences", EGSR.
Agarwal et al. 2003, "Structured importance sampling of environment maps" (p = L^a dw^b).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightprobe.core.errors import LightprobeError
from lightprobe.core.lightset import LightSet
from lightprobe.core.q2wire import Q2Tree, jitter_directions, uniq_levels
from lightprobe.core.sphere import LUMINANCE_WEIGHTS

__all__ = [
    "MergeError",
    "MergedTree",
    "ProbeInput",
    "merge_indexed",
    "merge_probes",
    "merge_q2trees",
    "merge_tree_nodes",
    "probe_weights",
    "reduce_merged_tree",
]

_ROOTS = np.arange(4, 16, dtype=np.int64)


class MergeError(LightprobeError, ValueError):
    """The inputs cannot be merged (none left, different light counts, bad weights)."""


# ---- weights ------------------------------------------------------------------------------------
def probe_weights(positions: np.ndarray, target: np.ndarray | None = None,
                  eps: float = 1e-9) -> np.ndarray:
    """Normalised inverse-distance weights of probes at ``positions`` (k, 3) for ``target`` (3,).

    ``w_i = (1 / |p_i - t|) / sum_j (1 / |p_j - t|)``; a target on a probe (distance <= eps)
    takes that probe alone (equal shares if several coincide); no target: equal weights.
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    k = len(pos)
    if k == 0:
        raise MergeError("no probes to weight")
    if target is None:
        return np.full(k, 1.0 / k)
    t = np.asarray(target, np.float64).reshape(3)
    if not np.all(np.isfinite(pos)) or not np.all(np.isfinite(t)):
        raise MergeError("probe positions and the target must be finite")
    d = np.linalg.norm(pos - t, axis=1)
    on = d <= eps
    if on.any():  # degenerate: the target is a probe's position
        return on / on.sum()
    inv = 1.0 / d
    return inv / inv.sum()


def _check_weights(weights: np.ndarray | Sequence[float] | None, k: int) -> np.ndarray:
    if weights is None:
        return np.full(k, 1.0 / k)
    w = np.asarray(weights, np.float64).reshape(-1)
    if len(w) != k or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise MergeError(f"weights must be {k} finite non-negative numbers with a positive sum")
    return w / w.sum()


# ---- Algorithm 2, steps 1-3: reconstruction, parallel traversal, normalisation --------------------
@dataclass
class MergedTree:
    """Every node of the merged tree: sorted NUNIQ ``nodes``, their ``rgb`` (float64, unit x sr),
    ``leaf`` flags and the weighted mean of the inputs' totals ``root`` (3,)."""

    nodes: np.ndarray
    rgb: np.ndarray
    leaf: np.ndarray
    root: np.ndarray

    @property
    def level(self) -> np.ndarray:
        return uniq_levels(self.nodes)


def _ancestors(leaves: np.ndarray) -> np.ndarray:
    """All strict ancestors of ``leaves`` (the interior nodes of the tree they span)."""
    out = []
    cur = leaves[leaves >= 16]
    while cur.size:
        cur = np.unique(cur >> 2)
        out.append(cur)
        cur = cur[cur >= 16]
    return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)


def _first_descendant(uniq: np.ndarray, level: np.ndarray, top: int) -> np.ndarray:
    """Index at level ``top`` of each node's first descendant (NESTED ranges are contiguous)."""
    index = uniq - (np.int64(4) << (2 * level))
    return index << (2 * (top - level))


def merge_tree_nodes(trees: Sequence[Q2Tree], weights: np.ndarray | None = None) -> MergedTree:
    """Steps 1-3 of Algorithm 2 (Nikodym et al. 2013).

    Step 1 rebuilds each tree from its leaves (interior = sum of children). Step 2 traverses
    them in parallel: the merged tree holds every node of every input; a node missing from
    tree i (below one of its leaves) takes that leaf's value split evenly over the four
    children per level (equal-area quads), so node values add as ``V(u) = sum_i w_i V_i(u)``.
    Step 3 normalises top-down: the root is the weighted mean of the inputs' totals and each
    child is rescaled by ``L'_c = L_c L'_P / sum_k L_k`` (§4.2), so every interior node equals
    the sum of its children.
    """
    if not trees:
        raise MergeError("no trees to merge")
    w = _check_weights(weights, len(trees))
    top = max(t.max_level for t in trees)
    # Step 1-2: the merged node set (union of all trees' nodes)
    all_leaves = np.unique(np.concatenate([t.uniq for t in trees]))
    interior = _ancestors(all_leaves)
    leaves = np.setdiff1d(all_leaves, interior, assume_unique=True)
    nodes = np.union1d(leaves, interior)
    level = uniq_levels(nodes)
    is_leaf = np.isin(nodes, leaves, assume_unique=True)
    rgb = np.zeros((len(nodes), 3))
    # Merged leaf values: sum_i w_i R_i(ancestor-or-self leaf) / 4^(level difference)
    lpos = np.flatnonzero(is_leaf)
    first = _first_descendant(nodes[lpos], level[lpos], top)
    for wi, t in zip(w, trees, strict=True):
        tl = t.level
        tfirst = _first_descendant(t.uniq, tl, top)
        order = np.argsort(tfirst, kind="stable")
        j = order[np.searchsorted(tfirst[order], first, side="right") - 1]
        share = np.ldexp(1.0, -2 * (level[lpos] - tl[j]))  # 4^-(k_u - k_a), exact
        rgb[lpos] += wi * t.rgb[j] * share[:, None]
    # Step 1 on the merged tree: interior = sum of children, deepest level first
    for k in range(int(level.max()), 0, -1):
        sel = np.flatnonzero(level == k)
        np.add.at(rgb, np.searchsorted(nodes, nodes[sel] >> 2), rgb[sel])
    root = np.sum([wi * t.total for wi, t in zip(w, trees, strict=True)], axis=0)
    _normalise_top_down(nodes, level, rgb, root)
    return MergedTree(nodes, rgb, is_leaf, root)


def _normalise_top_down(nodes: np.ndarray, level: np.ndarray, rgb: np.ndarray,
                        root: np.ndarray) -> None:
    """Step 3, in place: ``L'_c = L_c L'_P / sum_k L_k`` level by level from the root (§4.2).
    Children of a dark sum take equal shares of their parent (explicit degenerate path)."""
    for k in range(int(level.max()) + 1):
        sel = np.flatnonzero(level == k)
        if k == 0:
            groups = np.zeros(len(sel), np.int64)
            parent_val = root[None, :]
        else:
            pidx = np.searchsorted(nodes, nodes[sel] >> 2)
            uniq_p, groups = np.unique(pidx, return_inverse=True)
            parent_val = rgb[uniq_p]
        sums = np.zeros((len(parent_val), 3))
        np.add.at(sums, groups, rgb[sel])
        counts = np.bincount(groups, minlength=len(parent_val)).astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(sums > 0, parent_val / sums, 0.0)
        even = np.where(sums > 0, 0.0, parent_val / counts[:, None])
        rgb[sel] = rgb[sel] * ratio[groups] + even[groups]


# ---- steps 4-6: importance, reduction, placement --------------------------------------------------
def _effective_importance(tree: MergedTree, a: float, b: float, mean: bool) -> np.ndarray:
    """Step 4: ``p = L^a dw^b`` (L = the node's luminance integral, or its mean radiance when
    ``mean``; Nikodym et al. eq. 1), made monotone down the tree as ``min(p, key(parent))``
    exactly as the sampler orders nodes (lightprobe.device.sampling.q2tree._kernels)."""
    level = tree.level
    dw = 4.0 * np.pi / (12.0 * 4.0 ** level)
    lum = np.maximum(tree.rgb @ LUMINANCE_WEIGHTS, 0.0)
    power = lum if a == 1.0 else lum**a
    p = power * (dw ** (b - a) if mean else dw**b)
    eff = p.copy()
    for k in range(1, int(level.max()) + 1):
        sel = np.flatnonzero(level == k)
        eff[sel] = np.minimum(p[sel], eff[np.searchsorted(tree.nodes, tree.nodes[sel] >> 2)])
    return eff


def reduce_merged_tree(tree: MergedTree, count: int, *, importance: str = "integral",
                       a: float = 1.0, b: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Step 5: cut the least important subtrees until ``12 + 3 s >= count`` leaves remain
    (``s = ceil((count - 12) / 3)`` interior nodes, the s best-ranked: the ranking is monotone
    down the tree, so the least important interior node always has only leaf children and a
    cut removes exactly 3 leaves). Returns (kept interior nodes by rank, their keys-by-node).
    """
    if importance not in ("integral", "mean"):
        raise MergeError(f"importance must be 'integral' or 'mean', got {importance!r}")
    eff = _effective_importance(tree, a, b, importance == "mean")
    inner = np.flatnonzero(~tree.leaf)
    # Sort interior nodes by importance (higher first, ties to the smaller id)
    ranked = inner[np.lexsort((tree.nodes[inner], -eff[inner]))]
    s = min(max(0, -(-(count - 12) // 3)), len(ranked))
    return ranked[:s], eff


def merge_q2trees(trees: Sequence[Q2Tree], count: int, weights: np.ndarray | None = None, *,
                  importance: str = "integral", a: float = 1.0, b: float = 0.25,
                  seed: int = 0, jitter_extent: float = 0.5) -> LightSet:
    """Algorithm 2 of Nikodym et al. 2013: merged lights of several Q2-Trees.

    Steps 1-3 (:func:`merge_tree_nodes`), 4-5 (:func:`reduce_merged_tree`), then one light per
    leaf (step 6) at the fixed jittered point of ``lightprobe.device.sampling.q2tree`` (``seed``,
    ``jitter_extent``; 0 = the quad's centre), carrying the leaf's rgb. As in the sampler,
    when ``12 + 3 s`` exceeds ``count`` by e in {1, 2} the e + 1 weakest children of the weakest
    cut-able node become one light (id = that node). With equal weights and complete trees this
    gives the lights of ``Q2TreeSampler(placement="jitter", hysteresis=0)`` on the mean map.
    If the inputs are too shallow for ``count`` lights, fewer are returned
    (``extra["short"]``).
    """
    if count < 1:
        raise MergeError(f"count must be >= 1, got {count}")
    merged = merge_tree_nodes(trees, weights)
    kept, eff = reduce_merged_tree(merged, count, importance=importance, a=a, b=b)
    nodes = merged.nodes
    kept_ids = np.sort(nodes[kept])
    children = (4 * kept_ids[:, None] + np.arange(4)).ravel()
    cand = np.concatenate([_ROOTS, children])
    leaves = np.sort(cand[~np.isin(cand, kept_ids)])
    pos = np.searchsorted(nodes, leaves)
    rgb = merged.rgb[pos]
    level = uniq_levels(leaves)
    omega = 4.0 * np.pi / (12.0 * 4.0**level)
    dirs = jitter_directions(leaves, seed, jitter_extent)
    groups = _groups(leaves, count, nodes, kept, eff)
    ids = leaves
    if groups:
        ids, dirs, rgb, omega = _regroup(groups, leaves, dirs, rgb, omega)
    out = LightSet(dirs, rgb, omega, ids, method="q2tree")
    if len(out) < count:
        out.extra["short"] = count - len(out)
    return out


def _groups(leaves: np.ndarray, count: int, nodes: np.ndarray, kept: np.ndarray,
            eff: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Leaf groups (id, positions in ``leaves``) that become one light each, as the sampler."""
    excess = len(leaves) - count
    if excess <= 0:
        return []
    if len(kept) == 0:  # count < 12: runs of consecutive base faces
        return [(int(leaves[r[0]]), r) for r in np.array_split(np.arange(12), count) if len(r) > 1]
    worst = int(nodes[kept[-1]])
    kids = 4 * worst + np.arange(4)
    keff = eff[np.searchsorted(nodes, kids)]
    kids = kids[np.lexsort((kids, -keff))]  # best first
    return [(worst, np.searchsorted(leaves, np.sort(kids[3 - excess:])))]


def _regroup(groups: list[tuple[int, np.ndarray]], leaves: np.ndarray, dirs: np.ndarray,
             rgb: np.ndarray, omega: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Replace each group by one light: power and solid angle summed, direction the
    luminance-weighted mean of the members' (equal weights when dark); sorted by id."""
    single = np.ones(len(leaves), bool)
    ids, gd, gr, go = [], [], [], []
    lum = rgb @ LUMINANCE_WEIGHTS
    for gid, members in groups:
        single[members] = False
        wts = lum[members] if lum[members].sum() > 0 else np.ones(len(members))
        d = (wts[:, None] * dirs[members]).sum(axis=0)
        n = np.linalg.norm(d)
        ids.append(gid)
        gd.append(d / n if n > 0 else dirs[members[0]])
        gr.append(rgb[members].sum(axis=0))
        go.append(omega[members].sum())
    all_ids = np.concatenate([leaves[single], np.array(ids, np.int64)])
    order = np.argsort(all_ids, kind="stable")
    return (all_ids[order], np.concatenate([dirs[single], np.array(gd)])[order],
            np.concatenate([rgb[single], np.array(gr)])[order],
            np.concatenate([omega[single], np.array(go)])[order])


# ---- §4.1: index interpolation (Pharr, Hemigon) ----------------------------------------------------
def _rotation(pose: dict[str, Any] | None) -> np.ndarray:
    rot = np.eye(3) if not pose else np.asarray(pose.get("rotation", np.eye(3)), np.float64)
    if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
        raise MergeError("pose rotation must be a finite 3x3 matrix")
    return rot


def merge_indexed(sets: Sequence[LightSet], weights: np.ndarray | None = None, *,
                  to_world: bool = True) -> LightSet:
    """Interpolate light ``j`` of every set (Nikodym et al. 2013, §4.1).

    ``rgb`` and ``solid_angle`` are weighted sums (so the merged energy is the weighted mean of
    the inputs'); the direction is the normalised weighted sum of the unit directions (after
    rotating each into the world frame by its pose when ``to_world``); opposite directions that
    cancel take the direction of the heaviest probe. All sets need the same light count.
    """
    if not sets:
        raise MergeError("no light sets to merge")
    n = len(sets[0])
    if any(len(s) != n for s in sets):
        raise MergeError(f"index merging needs equal light counts, got {[len(s) for s in sets]}")
    w = _check_weights(weights, len(sets))
    dirs = np.zeros((n, 3))
    rgb = np.zeros((n, 3))
    omega = np.zeros(n)
    heaviest = int(np.argmax(w))
    d_heavy = np.zeros((n, 3))
    for i, (wi, s) in enumerate(zip(w, sets, strict=True)):
        d = s.directions @ _rotation(s.pose).T if to_world else s.directions
        dirs += wi * d
        rgb += wi * s.rgb
        omega += wi * s.solid_angle
        if i == heaviest:
            d_heavy = d
    norm = np.linalg.norm(dirs, axis=1)
    ok = norm > 1e-12
    dirs[ok] /= norm[ok, None]
    dirs[~ok] = d_heavy[~ok]
    return LightSet(dirs, rgb, omega, sets[0].ids, method=sets[0].method, unit=sets[0].unit)


# ---- several probes, some of which may have failed ---------------------------------------------
@dataclass
class ProbeInput:
    """One probe's latest data: its light set (with pose) and, for Q2-Tree merging, its tree.
    ``None`` data or ``stale`` lights mean the probe failed: it drops out of the merge."""

    probe_id: str
    lights: LightSet | None = None
    tree: Q2Tree | None = None
    pose: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def position(self) -> np.ndarray:
        pose = self.pose or (self.lights.pose if self.lights is not None else None) or {}
        return np.asarray(pose.get("position", [0.0, 0.0, 0.0]), np.float64).reshape(3)


def merge_probes(inputs: Sequence[ProbeInput], count: int, *, method: str = "auto",
                 target: np.ndarray | None = None, **q2: Any) -> LightSet:
    """Merge the usable probes among ``inputs`` for ``target`` (inverse-distance weights; equal
    without a target). ``method``: ``"q2tree"`` (Algorithm 2), ``"index"`` (§4.1) or
    ``"auto"`` (q2tree when every usable probe has a tree). Probes without data or with stale
    lights drop out and are listed in ``extra["dropped"]``; ``extra["merged_from"]`` and
    ``extra["weights"]`` describe the rest. Raises :class:`MergeError` when none is usable.
    """
    if method not in ("auto", "q2tree", "index"):
        raise MergeError(f"method must be 'auto', 'q2tree' or 'index', got {method!r}")
    live = [p for p in inputs if (p.lights is not None or p.tree is not None)
            and not (p.lights is not None and p.lights.stale)]
    use_tree = method == "q2tree" or (method == "auto" and bool(live)
                                      and all(p.tree is not None for p in live))

    def usable(p: ProbeInput) -> bool:
        if p.lights is not None and p.lights.stale:
            return False
        return p.tree is not None if use_tree else p.lights is not None

    good = [p for p in inputs if usable(p)]
    dropped = [p.probe_id for p in inputs if not usable(p)]
    if not good:
        raise MergeError(f"no usable probe to merge (dropped: {dropped})")
    w = probe_weights(np.array([p.position() for p in good]), target)
    if use_tree:
        out = merge_q2trees([p.tree for p in good if p.tree is not None], count, w, **q2)
        rots = [_rotation(p.pose or (p.lights.pose if p.lights else None)) for p in good]
        out.pose = {"rotation": rots[0].tolist(), "position": _position(target)}
        if any(not np.allclose(r, rots[0], atol=1e-6) for r in rots):
            out.extra["rotation_mismatch"] = True
    else:
        sets = [p.lights for p in good if p.lights is not None]
        out = merge_indexed(sets, w)
        out.pose = {"rotation": np.eye(3).tolist(), "position": _position(target)}
    units = {p.lights.unit for p in good if p.lights is not None}
    out.unit = units.pop() if len(units) == 1 else "relative"
    out.probe = "merged"
    out.stale = False
    out.extra.update({"merge": "q2tree" if use_tree else "index",
                      "merged_from": [p.probe_id for p in good], "weights": [float(x) for x in w],
                      "dropped": dropped})
    return out


def _position(target: np.ndarray | None) -> list[float]:
    return [0.0, 0.0, 0.0] if target is None else [float(x) for x in np.asarray(target).reshape(3)]
