"""The compact Q2-Tree encoding (lightprobe.core.q2wire): round trips of real sampler trees, the size
budget (<= 8 KB at 256 lights), and damage (byte flips, truncation, extension) that must raise
Q2DecodeError and never decode into a different tree."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lightprobe.core.q2wire import MAGIC, Q2DecodeError, Q2Tree, decode_q2tree, encode_q2tree
from lightprobe.device.sampling.q2tree import Q2TreeSampler, nodes_to_uniq
from lightprobe.device.sampling.q2tree._nodes import pyramid_from_equirect


def _small(img: np.ndarray, height: int = 128) -> np.ndarray:
    import cv2

    return cv2.resize(img, (2 * height, height), interpolation=cv2.INTER_AREA)


def sampler_tree(img: np.ndarray, count: int, nside: int = 64) -> Q2Tree:
    """The leaves of a Q2-Tree sampler run on ``img`` with their rgb (integral x solid angle)."""
    s = Q2TreeSampler(nside, hysteresis=0.0, placement="jitter")
    s.sample(img, count)
    level, index = s.to_nodes()
    uniq = nodes_to_uniq(level, index)
    pyr = pyramid_from_equirect(np.ascontiguousarray(img, np.float32), nside, False)
    return Q2Tree(uniq, pyr.rgb[uniq], pyr.max_level)


@pytest.fixture(scope="module")
def studio_tree(envmap_paths: dict[str, Path]) -> Q2Tree:
    from lightprobe.core.imageio import read_hdr_image

    return sampler_tree(_small(read_hdr_image(envmap_paths["studio_small_03_1k.hdr"])), 256)


def test_round_trip_and_size_at_256_lights(envmap_paths: dict[str, Path]) -> None:
    from lightprobe.core.imageio import read_hdr_image

    for name, path in envmap_paths.items():
        tree = sampler_tree(_small(read_hdr_image(path)), 256)
        assert 256 <= len(tree) <= 258
        data = encode_q2tree(tree)
        assert len(data) <= 8 * 1024, (name, len(data))
        back = decode_q2tree(data)
        assert np.array_equal(back.uniq, tree.uniq)
        assert back.max_level == tree.max_level
        # float32 on the wire: relative 6e-8 per leaf
        np.testing.assert_allclose(back.rgb, tree.rgb, rtol=1e-7, atol=0)
        # a second round trip is bit-exact
        assert decode_q2tree(encode_q2tree(back)).same_tree(back)
        half = encode_q2tree(back, half=True)
        assert len(half) < len(data)


def test_half_precision_and_its_range(studio_tree: Q2Tree) -> None:
    scaled = Q2Tree(studio_tree.uniq, studio_tree.rgb / studio_tree.rgb.max() * 1000.0,
                    studio_tree.max_level)
    back = decode_q2tree(encode_q2tree(scaled, half=True))
    np.testing.assert_allclose(back.rgb, scaled.rgb, rtol=1e-3, atol=1e-7)
    too_big = Q2Tree(scaled.uniq, scaled.rgb * 1e3, scaled.max_level)
    with pytest.raises(ValueError, match="float16"):
        encode_q2tree(too_big, half=True)


def test_encoder_refuses_what_is_not_a_tree(studio_tree: Q2Tree) -> None:
    t = studio_tree
    with pytest.raises(Q2DecodeError, match="tile"):  # a leaf missing: a hole in the sphere
        encode_q2tree(Q2Tree(t.uniq[1:], t.rgb[1:], t.max_level))
    parent = t.uniq[-1] >> 2
    with pytest.raises(Q2DecodeError, match="tile"):  # a parent listed beside its children
        encode_q2tree(Q2Tree(np.append(t.uniq, parent), np.vstack([t.rgb, t.rgb[:1]]), t.max_level))
    bad = t.rgb.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        encode_q2tree(Q2Tree(t.uniq, bad, t.max_level))
    bad[3, 1] = -1.0
    with pytest.raises(ValueError, match="non-negative"):
        encode_q2tree(Q2Tree(t.uniq, bad, t.max_level))


def test_the_twelve_base_quads_and_an_all_black_map() -> None:
    base = Q2Tree(np.arange(4, 16), np.zeros((12, 3)), 0)
    back = decode_q2tree(encode_q2tree(base))
    assert back.same_tree(base)
    black = sampler_tree(np.zeros((32, 64, 3), np.float32), 64, nside=16)
    assert decode_q2tree(encode_q2tree(black)).same_tree(black)
    assert np.all(black.rgb == 0)


def test_header_errors_are_typed(studio_tree: Q2Tree) -> None:
    data = encode_q2tree(studio_tree)
    assert data[:4] == MAGIC
    for blob, msg in [(b"", "too short"), (b"XXXX" + data[4:], "magic"), (data[:-1], "CRC"),
                      (data + b"\0", "CRC")]:
        with pytest.raises(Q2DecodeError, match=msg):
            decode_q2tree(blob)
    # a well-formed CRC over a wrong version / count still fails on the structure
    body = bytearray(data[:-4])
    body[4] = 2
    with pytest.raises(Q2DecodeError, match="version"):
        decode_q2tree(bytes(body) + struct.pack("<I", zlib.crc32(bytes(body))))
    body = bytearray(data[:-4])
    body[8:12] = struct.pack("<I", len(studio_tree) - 1)
    with pytest.raises(Q2DecodeError):
        decode_q2tree(bytes(body) + struct.pack("<I", zlib.crc32(bytes(body))))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), min_size=1, max_size=4),
       cut=st.one_of(st.none(), st.integers(0, 10**6)))
def test_damage_never_decodes_to_a_different_tree(studio_tree: Q2Tree,
                                                  flips: list[tuple[int, int]],
                                                  cut: int | None) -> None:
    data = encode_q2tree(studio_tree)
    original = decode_q2tree(data)
    buf = bytearray(data)
    for pos, xor in flips:
        buf[pos % len(buf)] ^= xor
    if cut is not None:
        buf = buf[: cut % len(buf)]
    try:
        back = decode_q2tree(bytes(buf))
    except Q2DecodeError:
        return
    assert back.same_tree(original)  # only a no-op damage (flips that cancel) may decode


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), splits=st.integers(0, 60))
def test_random_trees_round_trip(seed: int, splits: int) -> None:
    rng = np.random.default_rng(seed)
    leaves = set(range(4, 16))
    for _ in range(splits):  # split random leaves above level 6
        cand = sorted(u for u in leaves if u < (4 << 12))
        u = cand[int(rng.integers(len(cand)))]
        leaves.remove(u)
        leaves.update(range(4 * u, 4 * u + 4))
    uniq = np.array(sorted(leaves), np.int64)
    rgb = rng.exponential(1.0, (len(uniq), 3)) * (rng.random((len(uniq), 1)) < 0.8)
    tree = Q2Tree(uniq, rgb.astype(np.float32).astype(np.float64), 7)
    assert decode_q2tree(encode_q2tree(tree)).same_tree(tree)
