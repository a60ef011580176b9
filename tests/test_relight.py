"""Relighting with visibility cuts: directions, cuts, coding, traversal, lighting, scenes, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.core.sphere import equirect_integral
from lightprobe.hostlink.relight.cuts import coding as C
from lightprobe.hostlink.relight.cuts.directions import (
    LEAF_SOLID_ANGLE,
    NDIR,
    direction_to_leaf,
    leaf_directions,
    node_directions,
)

# ---- random cuts ---------------------------------------------------------------------------------


def random_cut(rng: np.random.Generator, p_split: float, binary: bool) -> tuple[np.ndarray, np.ndarray]:
    """A random cut: descend from the root, splitting each node with probability p_split."""
    hs: list[int] = []
    stack = [15]
    while stack:
        h = stack.pop()
        if h > 0 and rng.random() < p_split:
            stack += [h - 1, h - 1]
        else:
            hs.append(h)
    h = np.array(hs, np.uint8)
    v = rng.integers(0, 2, len(h)).astype(np.uint8) if binary else rng.random(len(h)).astype(np.float32)
    return h, v


def leaf_from_pattern(rng: np.random.Generator) -> np.ndarray:
    """Visibility x cosine of a random normal with a random spherical-cap occluder."""
    d = leaf_directions()
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    c = rng.normal(size=3)
    c /= np.linalg.norm(c)
    vis = (d @ c) < rng.uniform(0.3, 0.95)
    return np.maximum(d @ n, 0) * vis


# ---- directions -----------------------------------------------------------------------------------


def test_directions_round_trip_and_equal_area() -> None:
    d = leaf_directions()
    assert d.shape == (NDIR, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-12)
    assert np.array_equal(direction_to_leaf(d), np.arange(NDIR))
    rng = np.random.default_rng(1)
    v = rng.normal(size=(1_000_000, 3))
    counts = np.bincount(direction_to_leaf(v / np.linalg.norm(v, axis=1, keepdims=True)), minlength=NDIR)
    mean = counts.mean()
    # equal-area cells: counts are Poisson(mean) (std sqrt(mean)); unequal cells would add spread
    assert abs(counts.std() / np.sqrt(mean) - 1) < 0.05


def test_tree_nodes_are_compact_and_hemispheres_split_at_root() -> None:
    d = leaf_directions()
    assert np.all(d[: NDIR // 2, 1] >= 0)
    assert np.all(d[NDIR // 2:, 1] <= 0)
    nd = node_directions().astype(np.float64)
    # level-13 nodes (4 leaves): each leaf within 3 degrees of the node's mean direction
    k = (1 << 13) + (np.arange(NDIR) >> 2)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", nd[k], d), -1, 1)))
    assert ang.max() < 3.0


# ---- cut selection ---------------------------------------------------------------------------------


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), tau=st.sampled_from([1e-6, 1e-5, 1e-4, 1e-3, 1e-2]))
def test_select_cut_is_a_cut_with_threshold_property(seed: int, tau: float) -> None:
    rng = np.random.default_rng(seed)
    leaf = leaf_from_pattern(rng)
    h, v = C.select_cut(leaf, tau)
    assert C.is_cut(h)
    # every node: err <= tau (leaves excepted) and parent err > tau
    start = np.concatenate([[0], np.cumsum(np.left_shift(1, h.astype(np.int64)))[:-1]])
    for hh, s, vv in zip(h[:50].tolist(), start[:50].tolist(), v[:50].tolist(), strict=True):
        seg = leaf[s:s + (1 << hh)]
        assert abs(seg.mean() - vv) < 1e-5
        assert ((seg - seg.mean()) ** 2).sum() * LEAF_SOLID_ANGLE <= tau * (1 + 1e-9) or hh == 0
        if hh < 15:
            ps = (s >> (hh + 1)) << (hh + 1)
            pseg = leaf[ps:ps + (1 << (hh + 1))]
            assert ((pseg - pseg.mean()) ** 2).sum() * LEAF_SOLID_ANGLE > tau


def test_select_cut_degenerate_inputs() -> None:
    h, v = C.select_cut(np.zeros(NDIR), 1e-4)
    assert list(h) == [15]
    assert v[0] == 0
    spike = np.zeros(NDIR)
    spike[12345] = 1.0                                          # single hot leaf: isolated to a leaf
    h, v = C.select_cut(spike, 0.0)
    assert C.is_cut(h)
    assert np.array_equal(C.dense(h, v), spike)
    bad = np.full(NDIR, np.nan)
    h, _ = C.select_cut(bad, 1e-4)
    assert C.is_cut(h)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_binary_cut_is_lossless_and_minimal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    bits = (leaf_from_pattern(rng) > 0).astype(np.uint8)
    h, v = C.binary_cut(bits)
    assert C.is_cut(h)
    assert np.array_equal(C.dense(h, v), bits)
    # minimal: no two sibling nodes with equal values at the same height remain unmerged
    start = np.concatenate([[0], np.cumsum(np.left_shift(1, h.astype(np.int64)))[:-1]])
    hl = h.astype(np.int64)
    for i in range(len(h) - 1):
        if hl[i] == hl[i + 1] and hl[i] < 15 and start[i] % (1 << (hl[i] + 1)) == 0:
            assert v[i] != v[i + 1]


# ---- coding ------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), p=st.floats(0.05, 0.97), kind=st.sampled_from(["binary", "f16", "u8"]))
def test_encode_decode_round_trip(seed: int, p: float, kind: str) -> None:
    rng = np.random.default_rng(seed)
    h, v = random_cut(rng, p, kind == "binary")
    assert C.is_cut(h)
    data = C.encode_height(h, v, kind)
    assert len(data) == C.height_coded_nbytes(len(h), kind)
    h2, v2 = C.decode_height(data, kind)
    assert np.array_equal(h2, h)
    if kind == "binary":
        np.testing.assert_array_equal(v2, v)
    elif kind == "f16":
        np.testing.assert_array_equal(v2, v.astype(np.float16).astype(np.float32))
    else:                                   # 8-bit codes, float16 scale >= max: step <= max / 255
        assert np.abs(v2 - v).max() <= 0.5 / 255 * v.max() * (1 + 2e-3) + 1e-9
        np.testing.assert_array_equal(v2, C.quantize_cuts_u8(np.array([0, len(v)]), v))
    idata = C.encode_index(h, v, kind)
    assert len(idata) == 4 + C.index_coded_nbytes(len(h), kind)
    h3, v3 = C.decode_index(idata, kind)
    assert np.array_equal(h3, h)
    assert np.array_equal(v3, v2)


def test_u8_quantisation_of_many_cuts_and_degenerate_cuts() -> None:
    rng = np.random.default_rng(11)
    cuts = [random_cut(rng, 0.6, False) for _ in range(20)]
    cuts.append((np.array([15], np.uint8), np.zeros(1, np.float32)))          # all-dark cut
    offs = np.concatenate([[0], np.cumsum([len(h) for h, _ in cuts])])
    q = C.quantize_cuts_u8(offs, np.concatenate([v for _, v in cuts]))
    for k, (h, v) in enumerate(cuts):
        np.testing.assert_array_equal(q[offs[k]:offs[k + 1]], C.decode_height(C.encode_height(h, v, "u8"), "u8")[1])
    assert q[-1] == 0
    # same value encoding on both sides: height-coded u8 = (n/2 + n + 2) vs index-coded (2n + n + 2)
    assert C.height_coded_nbytes(1000, "u8") / C.index_coded_nbytes(1000, "u8") == pytest.approx(1502 / 3002)


def test_is_cut_rejects_holes_and_overlaps() -> None:
    assert C.is_cut(np.array([14, 14]))
    assert not C.is_cut(np.array([14]))                  # hole
    assert not C.is_cut(np.array([14, 14, 0]))           # overlap / too many leaves
    assert not C.is_cut(np.array([0, 1] + [14] * 1))     # misaligned height-1 node at leaf 1


# ---- counter-based traversal ------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), m=st.integers(1, 9))
def test_product_of_cuts_equals_dense(seed: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    cuts = [random_cut(rng, rng.uniform(0.3, 0.95), binary=bool(k % 2)) for k in range(m)]
    h, v = C.cut_product(cuts)
    assert C.is_cut(h)
    dense = np.prod([C.dense(hh, vv).astype(np.float64) for hh, vv in cuts], axis=0)
    np.testing.assert_allclose(C.dense(h, v), dense, rtol=1e-12, atol=1e-12)
    assert len(h) <= sum(len(c[0]) for c in cuts)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_trilinear_interpolation_of_8_cuts_equals_dense(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cuts = [random_cut(rng, rng.uniform(0.3, 0.95), binary=True) for _ in range(8)]
    fr, fx, fy = rng.random(3)
    w = np.array([(fr if a else 1 - fr) * (fy if b else 1 - fy) * (fx if c else 1 - fx)
                  for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    h, v = C.cut_interpolate(cuts, w)
    assert C.is_cut(h)
    dense = sum(wi * C.dense(hh, vv).astype(np.float64) for wi, (hh, vv) in zip(w, cuts, strict=True))
    np.testing.assert_allclose(C.dense(h, v), dense, atol=1e-12)


# ---- lighting --------------------------------------------------------------------------------------


def test_leaf_light_conserves_energy_and_prefix_sums(envmap_paths: dict[str, Path]) -> None:
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.core.lightset import LightSet
    from lightprobe.hostlink.relight.cuts.lighting import (
        leaf_light_from_equirect,
        leaf_light_from_lightset,
        prefix_sums,
    )

    img = read_hdr_image(envmap_paths["rooitou_park_1k.hdr"])
    leaf = leaf_light_from_equirect(img)
    np.testing.assert_allclose(leaf.sum(axis=0), equirect_integral(img), rtol=1e-9)
    P = prefix_sums(leaf)
    h, s = 9, 37 << 9                                  # any node's integral in O(1)
    np.testing.assert_allclose(P[s + (1 << h)] - P[s], leaf[s:s + (1 << h)].sum(axis=0), rtol=1e-9)
    bad = img.copy()
    bad[0, 0] = np.nan
    bad[1, 1] = -5
    assert np.isfinite(leaf_light_from_equirect(bad)).all()
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ls = LightSet(dirs, rng.random((50, 3)), np.full(50, 0.01))
    binned = leaf_light_from_lightset(ls)
    np.testing.assert_allclose(binned.sum(axis=0), ls.rgb.sum(axis=0))
    assert np.array_equal(np.nonzero(binned[:, 0])[0], np.unique(direction_to_leaf(dirs)))


def test_blinn_phong_and_ward_are_reciprocal() -> None:
    from lightprobe.hostlink.relight.cuts.kernels import brdf_spec

    rng = np.random.default_rng(5)
    n = np.array([0.0, 1.0, 0.0])
    for _ in range(50):
        a, b = rng.normal(size=(2, 3))
        a[1], b[1] = abs(a[1]), abs(b[1])
        a /= np.linalg.norm(a)
        b /= np.linalg.norm(b)
        for typ, p in ((1, 20.0), (2, 30.0), (3, 0.3)):
            assert brdf_spec(typ, p, n, *a, *b) == pytest.approx(brdf_spec(typ, p, n, *b, *a), rel=1e-9, abs=1e-12)
