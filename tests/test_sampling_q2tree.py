"""Q2-Tree sampler: incremental split-merge = fresh build, energy, exact counts, degenerate maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.errors import InputError
from lightprobe.core.healpix import equirect_to_healpix, vec2pix_nest
from lightprobe.core.imageio import read_hdr_image
from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import equirect_integral, equirect_solid_angle
from lightprobe.device.sampling.q2tree import (
    Q2TreeSampler,
    auto_nside,
    nodes_to_uniq,
    uniq_to_nodes,
)
from lightprobe.device.sampling.registry import make_sampler

NSIDE = 16


def _random_map(rng: np.random.Generator, nside: int = NSIDE) -> np.ndarray:
    """Log-normal radiance with a few very hot pixels (a lamp, a sun)."""
    m = rng.lognormal(0.0, 2.0, (12 * nside * nside, 3)).astype(np.float32)
    hot = rng.integers(0, len(m), int(rng.integers(0, 5)))
    m[hot] *= np.float32(1e4)
    return m


def _assert_same_lights(a: LightSet, b: LightSet) -> None:
    for field in ("directions", "rgb", "solid_angle", "ids"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


@pytest.fixture(scope="module")
def studio(envmap_paths: dict[str, Path]) -> np.ndarray:
    return read_hdr_image(envmap_paths["studio_small_03_1k.hdr"])


# -- the core property: incremental updates with zero hysteresis == a fresh build -----------------
@pytest.mark.parametrize("importance", ["integral", "mean"])
@pytest.mark.parametrize("placement", ["centroid", "jitter"])
def test_incremental_updates_equal_fresh_build(importance: str, placement: str) -> None:
    rng = np.random.default_rng(2005)
    for _ in range(12):
        inc = Q2TreeSampler(importance=importance, placement=placement, hysteresis=0.0)
        m = _random_map(rng)
        for _step in range(6):
            count = int(rng.integers(1, 900))
            # small multiplicative drift or a completely new frame
            if rng.random() < 0.6:
                m = (m * rng.lognormal(0.0, 0.3, m.shape)).astype(np.float32)
            else:
                m = _random_map(rng)
            got = inc.sample_healpix(m, NSIDE, count)
            fresh = Q2TreeSampler(importance=importance, placement=placement)
            want = fresh.sample_healpix(m, NSIDE, count)
            assert inc.stats["mode"] == ("incremental" if _step else "full")
            np.testing.assert_array_equal(inc.split_nodes, fresh.split_nodes)
            _assert_same_lights(got, want)
            assert len(got) == count


def test_incremental_equals_fresh_on_real_map_sequence(studio: np.ndarray) -> None:
    """A slowly brightening lamp region and a moving gain, on a real map (equirect path)."""
    inc = Q2TreeSampler(nside_max=64, hysteresis=0.0)
    rng = np.random.default_rng(7)
    for k in range(5):
        frame = studio * np.float32(1.0 + 0.05 * k)
        frame[100:140, 300 + 10 * k:360 + 10 * k] *= np.float32(3.0)
        count = int(rng.choice([64, 200, 256, 257, 300]))
        got = inc.sample(frame, count)
        want = Q2TreeSampler(nside_max=64).sample(frame, count)
        _assert_same_lights(got, want)


def test_unchanged_frame_needs_no_swaps_and_hysteresis_limits_restructuring() -> None:
    rng = np.random.default_rng(3)
    m = _random_map(rng)
    s0 = Q2TreeSampler(hysteresis=0.0)
    s1 = Q2TreeSampler(hysteresis=0.5)
    for s in (s0, s1):
        s.sample_healpix(m, NSIDE, 256)
        s.sample_healpix(m, NSIDE, 256)
        assert s.stats["mode"] == "incremental"
        assert s.stats["splits"] == s.stats["merges"] == 0
    swaps = {0.0: 0, 0.5: 0}
    for _ in range(10):
        m = (m * rng.lognormal(0.0, 0.2, m.shape)).astype(np.float32)
        for s in (s0, s1):
            ls = s.sample_healpix(m, NSIDE, 256)
            assert len(ls) == 256
            swaps[s.hysteresis] += s.stats["splits"]
    assert swaps[0.5] < swaps[0.0]
    assert swaps[0.0] > 0


def test_count_changes_between_frames_are_incremental() -> None:
    rng = np.random.default_rng(11)
    m = _random_map(rng)
    s = Q2TreeSampler(hysteresis=0.0)
    prev = 0
    for i, count in enumerate((300, 100, 13, 1000, 12, 5, 400)):
        ls = s.sample_healpix(m, NSIDE, count)
        assert len(ls) == count
        # after the first frame the tree is split and merged from the last one, never built afresh
        assert s.stats["mode"] == ("full" if i == 0 else "incremental")
        if i:  # the split-merge bookkeeping: 3 leaves per split, 3 fewer per merge
            assert s.stats["splits"] - s.stats["merges"] == (s.stats["leaves"] - prev) // 3
        prev = s.stats["leaves"]
        want = Q2TreeSampler().sample_healpix(m, NSIDE, count)
        _assert_same_lights(ls, want)


# -- energy, counts, directions, ids --------------------------------------------------------------
@pytest.mark.parametrize("count", [1, 5, 11, 12, 13, 14, 15, 64, 256, 1000, 3001])
def test_energy_exact_counts_unit_directions(studio: np.ndarray, count: int) -> None:
    s = Q2TreeSampler(nside_max=64)
    ls = s.sample(studio, count)
    assert len(ls) == count
    total = equirect_integral(studio)
    np.testing.assert_allclose(ls.total, total, rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(ls.directions, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(ls.solid_angle.sum(), 4 * np.pi, rtol=1e-12)
    assert ls.ids is not None
    assert len(np.unique(ls.ids)) == count
    assert np.all(ls.rgb >= 0)


def test_every_count_from_1_to_80_is_exact() -> None:
    m = _random_map(np.random.default_rng(5), 8)
    s = Q2TreeSampler()
    for count in range(1, 81):
        ls = s.sample_healpix(m, 8, count)
        assert len(ls) == count
        np.testing.assert_allclose(ls.total, m.astype(np.float64).sum(0) * 4 * np.pi / len(m),
                                   rtol=1e-12)


def test_leaf_lights_lie_inside_their_leaf_and_ids_are_nuniq() -> None:
    m = _random_map(np.random.default_rng(9))
    for placement in ("jitter", "centroid"):
        s = Q2TreeSampler(placement=placement)
        ls = s.sample_healpix(m, NSIDE, 300)  # 12 + 3 * 96: no regrouping
        assert ls.ids is not None
        level, index = uniq_to_nodes(ls.ids)
        np.testing.assert_array_equal(nodes_to_uniq(level, index), ls.ids)
        for k in np.unique(level):
            sel = level == k
            np.testing.assert_array_equal(vec2pix_nest(1 << int(k), ls.directions[sel]), index[sel])
        np.testing.assert_allclose(ls.solid_angle, 4 * np.pi / (12 * 4.0**level))
        lv, ix = s.to_nodes()
        np.testing.assert_array_equal(nodes_to_uniq(lv, ix), np.sort(ls.ids))


def test_jitter_point_stays_fixed_while_leaf_survives() -> None:
    rng = np.random.default_rng(21)
    m = _random_map(rng)
    s = Q2TreeSampler(placement="jitter", hysteresis=0.2, seed=4)
    a = s.sample_healpix(m, NSIDE, 300)
    b = s.sample_healpix((m * rng.lognormal(0, 0.5, m.shape)).astype(np.float32), NSIDE, 300)
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    assert len(common) > 100
    np.testing.assert_array_equal(a.directions[ia], b.directions[ib])
    c = Q2TreeSampler(placement="jitter", seed=5).sample_healpix(m, NSIDE, 300)
    assert not np.array_equal(a.directions, c.directions)  # the seed moves the jitter


def test_integral_importance_concentrates_leaves_on_the_light() -> None:
    """The hot quad gets the finest leaves; with b = 1/4 dim regions still get split."""
    m = np.ones((12 * NSIDE * NSIDE, 3), np.float32)
    m[1000] = 1e5
    ls = Q2TreeSampler().sample_healpix(m, NSIDE, 120)
    assert ls.ids is not None
    level, _ = uniq_to_nodes(ls.ids)
    hot = vec2pix_nest(NSIDE, ls.directions[np.argmax(ls.rgb[:, 0])])
    assert hot == 1000
    assert level.max() == 4
    assert len(np.unique(level)) >= 3


# -- degenerate maps ------------------------------------------------------------------------------
def test_all_black_map_gives_zero_power_lights_spread_evenly() -> None:
    img = np.zeros((64, 128, 3), np.float32)
    ls = Q2TreeSampler().sample(img, 48)
    assert len(ls) == 48
    assert np.all(ls.rgb == 0)
    assert np.all(np.isfinite(ls.directions))
    np.testing.assert_allclose(np.linalg.norm(ls.directions, axis=1), 1.0)
    # ties split breadth-first: 48 = 12 + 3 * 12, every base quad split once, all at level 1
    assert ls.ids is not None
    level, _ = uniq_to_nodes(ls.ids)
    assert np.all(level == 1)
    hp = Q2TreeSampler().sample_healpix(np.zeros((12 * 64, 3), np.float32), 8, 7)
    assert len(hp) == 7
    assert np.all(hp.rgb == 0)
    assert np.all(np.isfinite(hp.directions))


def test_single_hot_pixel_1e9() -> None:
    img = np.full((128, 256, 3), 0.5, np.float32)
    img[40, 77] = 1e9
    s = Q2TreeSampler(nside_max=64)
    ls = s.sample(img, 64)
    total = equirect_integral(img)
    np.testing.assert_allclose(ls.total, total, rtol=1e-6)
    hot_power = 1e9 * equirect_solid_angle(128)[40, 77]
    brightest = int(np.argmax(ls.rgb[:, 1]))
    assert ls.rgb[brightest, 1] >= hot_power
    assert ls.rgb[brightest, 1] < hot_power + 0.5 * 4 * np.pi / (12 * 64 * 64) * 64
    theta, phi = np.pi * 40.5 / 128, 2 * np.pi * 77.5 / 256
    want = np.array([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)])
    assert np.degrees(np.arccos(min(1.0, ls.directions[brightest] @ want))) < 0.1
    assert np.all(np.isfinite(ls.rgb))
    assert np.all(ls.rgb >= 0)


def test_nan_inf_and_negative_pixels_count_as_zero(studio: np.ndarray) -> None:
    dirty = studio.copy()
    dirty[10:20, 30:60] = np.nan
    dirty[200, 5] = np.inf
    dirty[300:302, 400:410] = -5.0
    clean = dirty.copy()
    clean[~np.isfinite(clean) | (clean < 0)] = 0.0
    a = Q2TreeSampler(nside_max=64).sample(dirty, 200)
    b = Q2TreeSampler(nside_max=64).sample(clean, 200)
    _assert_same_lights(a, b)
    assert np.all(np.isfinite(a.rgb))
    assert np.all(np.isfinite(a.directions))
    hp = np.ones((12 * 64, 3), np.float32)
    hp[5] = np.nan
    ls = Q2TreeSampler().sample_healpix(hp, 8, 30)
    np.testing.assert_allclose(ls.total, (12 * 64 - 1) * 4 * np.pi / (12 * 64), rtol=1e-12)


# -- inputs and plumbing --------------------------------------------------------------------------
def test_healpix_input_conserves_the_resampled_energy(studio: np.ndarray) -> None:
    hp = equirect_to_healpix(studio, 64)
    ls = Q2TreeSampler().sample_healpix(hp, 64, 256)
    np.testing.assert_allclose(ls.total, hp.astype(np.float64).sum(0) * 4 * np.pi / len(hp),
                               rtol=1e-9)
    np.testing.assert_allclose(ls.total, equirect_integral(studio), rtol=1e-6)


def test_bad_input_raises_input_error() -> None:
    s = Q2TreeSampler()
    img = np.ones((16, 32, 3), np.float32)
    for count in (0, -3, 2.5, True):
        with pytest.raises(InputError):
            s.sample(img, count)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        s.sample(np.ones((16, 16, 3), np.float32), 10)
    with pytest.raises(InputError):
        s.sample_healpix(np.ones((100, 3), np.float32), 4, 10)
    with pytest.raises(InputError):
        s.sample_healpix(np.ones((12 * 16, 3), np.float32), 4, 12 * 16 + 1)
    with pytest.raises(InputError):
        Q2TreeSampler(importance="median")
    with pytest.raises(InputError):
        Q2TreeSampler(nside_max=100)


def test_registry_builds_q2tree_and_json_round_trip(studio: np.ndarray) -> None:
    s = make_sampler("q2tree", nside_max=32, peaks=True)
    assert isinstance(s, Q2TreeSampler)
    ls = s.sample(studio, 100)
    d = ls.to_json()
    assert d["method"] == "q2tree"
    assert len(d["lights"]) == 100
    assert all("id" in li for li in d["lights"])
    assert isinstance(d["peaks"], list)
    assert len(d["peaks"]) >= 1
    back = LightSet.from_json(d)
    np.testing.assert_array_equal(back.ids, ls.ids)
    assert auto_nside(512) == 256
    assert auto_nside(180) == 64
    assert auto_nside(2) == 1


def test_reset_forgets_the_tree() -> None:
    m = _random_map(np.random.default_rng(1))
    s = Q2TreeSampler()
    s.sample_healpix(m, NSIDE, 100)
    s.reset()
    s.sample_healpix(m, NSIDE, 100)
    assert s.stats["mode"] == "full"


def test_finer_healpix_map_is_reduced_to_the_tree_level() -> None:
    rng = np.random.default_rng(17)
    m = _random_map(rng, 32)
    s = Q2TreeSampler(nside_max=8)
    ls = s.sample_healpix(m, 32, 200)
    assert s.stats["nside"] == 8
    np.testing.assert_allclose(ls.total, m.astype(np.float64).sum(0) * 4 * np.pi / len(m),
                               rtol=1e-9)
    coarse = m.astype(np.float64).reshape(-1, 16, 3).mean(axis=1)
    want = Q2TreeSampler(nside_max=8).sample_healpix(coarse.astype(np.float32), 8, 200)
    np.testing.assert_allclose(ls.rgb, want.rgb, rtol=1e-6)
    np.testing.assert_array_equal(ls.ids, want.ids)


def test_map_size_change_rebuilds(studio: np.ndarray) -> None:
    s = Q2TreeSampler()
    s.sample(studio, 300)
    assert s.stats["nside"] == 256
    small = studio[::4, ::4].copy()
    ls = s.sample(small, 300)
    assert s.stats["mode"] == "full"
    assert s.stats["nside"] == 64
    np.testing.assert_allclose(ls.total, equirect_integral(small), rtol=1e-9)
    s.sample(studio, 300)
    assert s.stats["mode"] == "full"


# -- the incremental pyramid: only changed runs are summed again, and the result is exact -------
def _equirect_frames(rng: np.random.Generator, steps: int, height: int = 48
                     ) -> list[tuple[np.ndarray, int]]:
    """A sequence of (frame, count): sparse pixel changes, NaN/inf/negative values appearing
    and healing, a brightening block, a global gain, a new frame, the same frame again."""
    frame = rng.lognormal(0.0, 1.5, (height, 2 * height, 3)).astype(np.float32)
    frame[rng.integers(0, height), rng.integers(0, 2 * height)] = 1e9
    out = []
    for _ in range(steps):
        kind = rng.integers(0, 6)
        frame = frame.copy()
        if kind == 0:  # a few pixels
            r, c = rng.integers(0, height, 5), rng.integers(0, 2 * height, 5)
            frame[r, c] *= np.float32(rng.lognormal(0.0, 1.0))
        elif kind == 1:  # old bad values heal, new ones appear
            frame[~np.isfinite(frame) | (frame < 0)] = 0.5
            r, c = rng.integers(0, height, 4), rng.integers(0, 2 * height, 4)
            frame[r, c, rng.integers(0, 3, 4)] = rng.choice([np.nan, np.inf, -np.inf, -2.0], 4)
        elif kind == 2:  # a lamp region brightens
            r, c = rng.integers(0, height - 8), rng.integers(0, 2 * height - 8)
            frame[r:r + 8, c:c + 8] *= np.float32(1.5)
        elif kind == 3:  # global gain: every pixel changes
            frame *= np.float32(1.01)
        elif kind == 4:  # a completely new frame
            frame[:] = rng.lognormal(0.0, 1.5, frame.shape)
        out.append((frame, int(rng.choice([16, 64, 100, 256, 257, 700]))))
    return out


@pytest.mark.parametrize("placement", ["centroid", "jitter"])
def test_incremental_pyramid_equals_fresh_build_on_equirect_sequences(placement: str) -> None:
    rng = np.random.default_rng(42)
    modes = []
    for _ in range(4):
        inc = Q2TreeSampler(nside_max=32, placement=placement, hysteresis=0.0)
        live = np.zeros((48, 96, 3), np.float32)  # one array modified in place frame to frame
        for frame, count in _equirect_frames(rng, 14):
            live[:] = frame
            got = inc.sample(live, count)
            modes.append((inc.stats["pyramid_mode"], inc.stats["changed_quads"]))
            want = Q2TreeSampler(nside_max=32, placement=placement).sample(frame.copy(), count)
            _assert_same_lights(got, want)
            clean = np.where(np.isfinite(frame) & (frame > 0), frame, 0)
            np.testing.assert_allclose(got.total, equirect_integral(clean), rtol=1e-9)
    inc_modes = [n for m, n in modes if m == "incremental"]
    assert len(inc_modes) > 10
    assert min(inc_modes) == 0  # an unchanged frame re-sums nothing
    assert any(0 < n < 50 for n in inc_modes)  # a sparse change re-sums a few quads


def test_incremental_pyramid_on_healpix_sequences() -> None:
    rng = np.random.default_rng(8)
    inc = Q2TreeSampler(hysteresis=0.0)
    m = _random_map(rng)
    live = m.copy()
    partial = 0
    for _step in range(30):
        choice = rng.integers(0, 4)
        if choice == 0:
            live[rng.integers(0, len(live), 3)] *= np.float32(3.0)
        elif choice == 1:
            live[rng.integers(0, len(live), 2), rng.integers(0, 3)] = np.nan
        elif choice == 2:
            live[~np.isfinite(live)] = 1.0
        count = int(rng.choice([30, 120, 400]))
        got = inc.sample_healpix(live, NSIDE, count)
        want = Q2TreeSampler().sample_healpix(live.copy(), NSIDE, count)
        _assert_same_lights(got, want)
        partial += inc.stats["pyramid_mode"] == "incremental" and inc.stats["changed_quads"] > 0
    assert partial > 5


def test_local_change_resums_only_its_quads(studio: np.ndarray) -> None:
    s = Q2TreeSampler()
    s.sample(studio, 256)
    total = s.stats["changed_quads"]
    frame = studio.copy()
    frame[200:210, 500:520] *= np.float32(2.0)
    ls = s.sample(frame, 256)
    assert s.stats["pyramid_mode"] == "incremental"
    assert 0 < s.stats["changed_quads"] <= 8 < total
    np.testing.assert_allclose(ls.total, equirect_integral(frame), rtol=1e-9)
    s.reset()
    s.sample(frame, 256)
    assert s.stats["pyramid_mode"] == "full"


def test_unchanged_frames_skip_the_update_and_equal_the_full_update() -> None:
    """A frame whose node sums did not change skips split-merge (``stats["skipped"]``); the
    lights equal those of the same sampler with the skip disabled, with and without
    hysteresis, over a sequence mixing repeated, changed and new frames and count changes."""
    rng = np.random.default_rng(31)
    for hysteresis in (0.0, 0.2):
        fast = Q2TreeSampler(hysteresis=hysteresis)
        slow = Q2TreeSampler(hysteresis=hysteresis)
        m = _random_map(rng)
        live = m.copy()
        skipped = 0
        for _step in range(40):
            kind = rng.integers(0, 5)
            if kind == 0:
                live[rng.integers(0, len(live), 3)] *= np.float32(rng.lognormal(0.0, 1.0))
            elif kind == 1:
                live[:] = _random_map(rng)
            count = int(rng.choice([100, 100, 100, 257]))
            got = fast.sample_healpix(live, NSIDE, count)
            slow._last = None  # never skip
            want = slow.sample_healpix(live.copy(), NSIDE, count)
            _assert_same_lights(got, want)
            np.testing.assert_array_equal(fast.split_nodes, slow.split_nodes)
            skipped += fast.stats["skipped"]
            if fast.stats["skipped"]:
                assert fast.stats["changed_quads"] == 0
            if hysteresis == 0.0:
                _assert_same_lights(got, Q2TreeSampler().sample_healpix(live.copy(), NSIDE, count))
        assert skipped > 5


@pytest.mark.parametrize("placement", ["centroid", "jitter"])
def test_one_pass_lights_equal_leaf_arrays_then_regrouping(placement: str) -> None:
    """``emit_lights`` (one compiled pass) gives the bits of ``leaf_arrays`` + jitter points +
    ``regroup_worst`` (the path taken when a jitter point is not memoised yet)."""
    from lightprobe.device.sampling.q2tree import _kernels
    from lightprobe.device.sampling.q2tree._nodes import level_solid_angles, state_pyramid

    rng = np.random.default_rng(12)
    m = _random_map(rng)
    m[: len(m) // 3] = 0.0  # dark leaves: centroid placement falls back to the jitter point
    s = Q2TreeSampler(placement=placement)
    for count in (12, 13, 14, 15, 100, 101, 299, 300, 301, 800):
        s.sample_healpix(m, NSIDE, count)
        s.sample_healpix(m, NSIDE, count)  # every jitter point now memoised
        assert s._state is not None
        pyr = state_pyramid(s._state)
        assert pyr.moment is not None or placement == "jitter"
        moment = pyr.moment if pyr.moment is not None else np.zeros((1, 3))
        omega_k = level_solid_angles(pyr.max_level)
        ids, rgb, omega, dirs, done = _kernels.emit_lights(
            s._split, s._in_s, s._eff, pyr.rgb, pyr.lum, moment, pyr.moment is not None,
            omega_k, *s._jitter_memo, count)
        assert done
        leaves, lrgb, lum, lomega, ldirs, missing = _kernels.leaf_arrays(
            s._split, s._in_s, pyr.rgb, pyr.lum, moment, pyr.moment is not None, omega_k)
        ldirs[missing] = s._jitter(leaves[missing])
        if len(leaves) > count:
            leaves, lrgb, lomega, ldirs = _kernels.regroup_worst(
                s._split, s._in_s, s._eff, leaves, lrgb, lum, lomega, ldirs, len(leaves) - count)
        assert len(ids) == count
        for a, b in ((ids, leaves), (rgb, lrgb), (omega, lomega), (dirs, ldirs)):
            np.testing.assert_array_equal(a, b)
