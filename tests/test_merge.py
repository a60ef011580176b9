"""Merging several probes (lightprobe.hostlink.merge, Nikodym et al. 2013 §4): the paper's empirical check
(merging complete Q2-Trees with equal weights gives the lights of sampling the per-pixel mean
map), energy (merged energy = weighted mean of the inputs' energies, to 1e-9), the structure of
the merged tree, distance weights, index interpolation for Pharr/Hemigon and failed probes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.core.lightset import LightSet
from lightprobe.core.q2wire import Q2Tree, decode_q2tree, encode_q2tree
from lightprobe.device.sampling.q2tree import Q2TreeSampler
from lightprobe.device.sampling.q2tree._nodes import pyramid_from_equirect
from lightprobe.hostlink.merge import (
    MergeError,
    ProbeInput,
    merge_indexed,
    merge_probes,
    merge_q2trees,
    merge_tree_nodes,
    probe_weights,
)

LEVEL = 5  # complete trees at nside 32: 12288 leaves
MAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "lebombo_1k.hdr"]


def _small(img: np.ndarray, height: int = 128) -> np.ndarray:
    import cv2

    return np.ascontiguousarray(cv2.resize(img, (2 * height, height), interpolation=cv2.INTER_AREA))


def complete_tree(img: np.ndarray, level: int = LEVEL) -> Q2Tree:
    """Every quad at ``level`` as a leaf, with the map's integral over it (exact pixel binning)."""
    pyr = pyramid_from_equirect(np.ascontiguousarray(img, np.float32), 1 << level, False)
    u = np.arange(4 << (2 * level), 16 << (2 * level), dtype=np.int64)
    return Q2Tree(u, pyr.rgb[u], level)


@pytest.fixture(scope="module")
def maps(envmap_paths: dict[str, Path]) -> list[np.ndarray]:
    from lightprobe.core.imageio import read_hdr_image

    return [_small(read_hdr_image(envmap_paths[n])) for n in MAPS]


def _reference(img: np.ndarray, count: int, level: int = LEVEL) -> LightSet:
    return Q2TreeSampler(1 << level, hysteresis=0.0, placement="jitter").sample(img, count)


def _assert_same_lights(got: LightSet, ref: LightSet, rtol: float) -> None:
    assert np.array_equal(got.ids, ref.ids)
    np.testing.assert_allclose(got.rgb, ref.rgb, rtol=rtol, atol=rtol * np.abs(ref.rgb).max())
    np.testing.assert_allclose(got.solid_angle, ref.solid_angle, rtol=1e-12)
    np.testing.assert_allclose(got.directions, ref.directions, atol=1e-7)


@pytest.mark.parametrize("count", [256, 255, 64, 7])
def test_complete_trees_merge_like_sampling_the_mean_map(maps: list[np.ndarray], count: int) -> None:
    """Nikodym et al. §6: merged trees == a Q2-Tree built on the per-pixel average of the maps."""
    trees = [complete_tree(m) for m in maps]
    merged = merge_q2trees(trees, count)
    mean = (maps[0].astype(np.float64) + maps[1] + maps[2]) / 3.0
    ref = _reference(mean.astype(np.float32), count)
    assert len(merged) == len(ref) == count
    _assert_same_lights(merged, ref, rtol=1e-6)  # float32 mean map vs float64 merge
    # the same through the wire format (float32 leaves)
    wired = merge_q2trees([decode_q2tree(encode_q2tree(t)) for t in trees], count)
    _assert_same_lights(wired, ref, rtol=1e-6)


def test_target_on_a_probe_gives_that_probe_alone(maps: list[np.ndarray]) -> None:
    trees = [complete_tree(m) for m in maps[:2]]
    w = probe_weights(np.array([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]), np.array([1.0, 1.0, 0.0]))
    assert w.tolist() == [0.0, 1.0]
    _assert_same_lights(merge_q2trees(trees, 100, w), _reference(maps[1], 100), rtol=1e-9)


def test_missing_nodes_take_an_even_share_of_their_leaf() -> None:
    a = Q2Tree(np.arange(4, 16), np.full((12, 3), 8.0), 0)
    kids = np.array([16, 17, 18, 19])  # children of base quad 4
    b = Q2Tree(np.r_[kids, np.arange(5, 16)], np.r_[np.array([[4.0], [0.0], [2.0], [2.0]]) * np.ones(3),
                                                    np.full((11, 3), 4.0)], 1)
    m = merge_tree_nodes([a, b])
    leaf_ids = m.nodes[m.leaf]
    assert set(leaf_ids.tolist()) == set(kids.tolist()) | set(range(5, 16))
    rgb = dict(zip(m.nodes.tolist(), m.rgb[:, 0].tolist(), strict=True))
    # child value = (8 / 4 + b_child) / 2; base quad 4 = (8 + 8) / 2
    assert [rgb[k] for k in kids.tolist()] == [3.0, 1.0, 2.0, 2.0]
    assert rgb[4] == 8.0
    assert rgb[5] == 6.0
    np.testing.assert_allclose(m.root, [0.5 * (96 + 8 + 44)] * 3)


def _random_tree(rng: np.random.Generator, splits: int, max_level: int = 6) -> Q2Tree:
    leaves = set(range(4, 16))
    for _ in range(splits):
        cand = sorted(u for u in leaves if u < (4 << (2 * max_level)))
        u = cand[int(rng.integers(len(cand)))]
        leaves.remove(u)
        leaves.update(range(4 * u, 4 * u + 4))
    uniq = np.array(sorted(leaves), np.int64)
    scale = 10.0 ** rng.uniform(-3, 6, (len(uniq), 1))  # many orders of magnitude, like a sun
    rgb = rng.random((len(uniq), 3)) * scale * (rng.random((len(uniq), 1)) < 0.9)
    return Q2Tree(uniq, rgb, max_level)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 4), count=st.integers(1, 300),
       splits=st.lists(st.integers(0, 80), min_size=4, max_size=4))
def test_merged_energy_is_the_weighted_mean(seed: int, k: int, count: int, splits: list[int]) -> None:
    rng = np.random.default_rng(seed)
    trees = [_random_tree(rng, splits[i]) for i in range(k)]
    w = rng.random(k) + 1e-3
    expected = sum(wi * t.total for wi, t in zip(w / w.sum(), trees, strict=True))
    m = merge_tree_nodes(trees, w)
    np.testing.assert_allclose(m.rgb[m.leaf].sum(axis=0), expected, rtol=1e-9, atol=0)
    # every interior node equals the sum of its children (Algorithm 2, step 3)
    inner = m.nodes[~m.leaf]
    pos = np.searchsorted(m.nodes, 4 * inner[:, None] + np.arange(4))
    np.testing.assert_allclose(m.rgb[pos].sum(axis=1), m.rgb[~m.leaf], rtol=1e-12, atol=1e-300)
    lights = merge_q2trees(trees, count, w)
    np.testing.assert_allclose(lights.total, expected, rtol=1e-9, atol=0)
    assert len(lights) == min(count, m.leaf.sum()) or "short" in lights.extra
    assert len(lights) <= count
    assert np.all(np.isfinite(lights.directions))
    np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(lights.solid_angle.sum(), 4 * np.pi, rtol=1e-12)


def test_too_shallow_inputs_give_fewer_lights_flagged() -> None:
    base = Q2Tree(np.arange(4, 16), np.ones((12, 3)), 0)
    lights = merge_q2trees([base, base], 100)
    assert len(lights) == 12
    assert lights.extra["short"] == 88
    np.testing.assert_allclose(lights.total, [12.0] * 3)


def test_all_black_trees_give_dark_lights_without_nan() -> None:
    black = complete_tree(np.zeros((32, 64, 3), np.float32), level=3)
    lights = merge_q2trees([black, black, black], 64)
    assert len(lights) == 64
    assert np.all(lights.rgb == 0)
    assert np.all(np.isfinite(lights.directions))


def test_probe_weights() -> None:
    pos = np.array([[0.0, 0, 0], [2.0, 0, 0], [0.0, 0, 4.0]])
    np.testing.assert_allclose(probe_weights(pos), [1 / 3] * 3)
    w = probe_weights(pos, np.array([1.0, 0, 0]))
    inv = 1 / np.array([1.0, 1.0, np.sqrt(17)])
    np.testing.assert_allclose(w, inv / inv.sum(), rtol=1e-15)
    assert probe_weights(pos, pos[2]).tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(MergeError):
        probe_weights(np.zeros((0, 3)))
    with pytest.raises(MergeError):
        probe_weights(pos, np.array([np.nan, 0, 0]))
    with pytest.raises(MergeError):
        merge_q2trees([Q2Tree(np.arange(4, 16), np.ones((12, 3)), 0)], 12, np.array([-1.0]))


def _pharr(img: np.ndarray, count: int) -> LightSet:
    from lightprobe.device.sampling.registry import make_sampler

    return make_sampler("pharr").sample(img, count)


def test_index_merge_interpolates_lights_with_the_same_index(maps: list[np.ndarray]) -> None:
    a, b = _pharr(maps[0], 64), _pharr(maps[2], 64)
    w = np.array([0.25, 0.75])
    m = merge_indexed([a, b], w)
    np.testing.assert_allclose(m.rgb, 0.25 * a.rgb + 0.75 * b.rgb, rtol=1e-12)
    np.testing.assert_allclose(m.total, 0.25 * a.total + 0.75 * b.total, rtol=1e-12)
    d = 0.25 * a.directions + 0.75 * b.directions
    np.testing.assert_allclose(m.directions, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)
    # a probe mounted rotated: its directions are turned into the world frame first
    rot = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    b_rot = LightSet(b.directions @ rot, b.rgb, b.solid_angle, pose={"rotation": rot.tolist(),
                                                                      "position": [0, 0, 0]})
    np.testing.assert_allclose(merge_indexed([a, b_rot], w).directions, m.directions, atol=1e-12)
    with pytest.raises(MergeError, match="equal light counts"):
        merge_indexed([a, _pharr(maps[1], 32)])


def test_opposite_directions_fall_back_to_the_heaviest_probe() -> None:
    up = LightSet([[0.0, 1, 0]], [[1.0, 1, 1]], [1.0])
    down = LightSet([[0.0, -1, 0]], [[3.0, 3, 3]], [1.0])
    m = merge_indexed([up, down], np.array([0.5, 0.5 + 1e-16]))
    assert np.all(np.isfinite(m.directions))
    np.testing.assert_allclose(np.abs(m.directions[0, 1]), 1.0)


def test_failed_probes_drop_out_and_are_flagged(maps: list[np.ndarray]) -> None:
    trees = [complete_tree(m, level=4) for m in maps]
    fresh = LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    stale = LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), stale=True)
    inputs = [ProbeInput("a", fresh, trees[0]), ProbeInput("b", stale, trees[1]),
              ProbeInput("c", fresh, trees[2]), ProbeInput("d", None, None)]
    out = merge_probes(inputs, 64)
    assert out.extra["merged_from"] == ["a", "c"]
    assert out.extra["dropped"] == ["b", "d"]
    assert out.extra["merge"] == "q2tree"
    ref = merge_q2trees([trees[0], trees[2]], 64)
    assert np.array_equal(out.ids, ref.ids)
    np.testing.assert_allclose(out.rgb, ref.rgb, rtol=1e-15)
    with pytest.raises(MergeError, match="no usable probe"):
        merge_probes([inputs[1], inputs[3]], 64)
    # Pharr probes (no trees) merge by index
    pa, pc = _pharr(maps[0], 16), _pharr(maps[2], 16)
    out = merge_probes([ProbeInput("a", pa), ProbeInput("b", stale), ProbeInput("c", pc)], 16)
    assert out.extra["merge"] == "index"
    assert out.extra["dropped"] == ["b"]
    np.testing.assert_allclose(out.total, 0.5 * (pa.total + pc.total), rtol=1e-12)
