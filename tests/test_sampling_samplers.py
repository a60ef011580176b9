"""Pharr, Hemigon and median cut on the six shared maps and on degenerate maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.imageio import read_hdr_image
from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import (
    angles_from_directions,
    equirect_integral,
    equirect_row_solid_angle,
    luminance,
)
from lightprobe.device.sampling.base import sanitize_radiance
from lightprobe.device.sampling.havran import hemisphere_to_square
from lightprobe.device.sampling.hemigon import LOWER_ID_OFFSET, HemigonSampler, split_count
from lightprobe.device.sampling.metrics import ErrorReference, lights_total
from lightprobe.device.sampling.pharr import PharrSampler
from lightprobe.device.sampling.registry import available_samplers, make_sampler

METHODS = ["pharr", "hemigon", "median-cut"]


@pytest.fixture(scope="module")
def maps(envmap_paths: dict[str, Path]) -> dict[str, np.ndarray]:
    return {name: read_hdr_image(p) for name, p in envmap_paths.items()}


def _check_set(ls: LightSet, img: np.ndarray, tol: float = 1e-6) -> None:
    truth = equirect_integral(sanitize_radiance(img)[0])
    np.testing.assert_allclose(lights_total(ls), truth, rtol=tol, atol=1e-300)
    assert np.all(np.isfinite(ls.directions))
    assert np.all(np.isfinite(ls.rgb))
    if len(ls):
        np.testing.assert_allclose(np.linalg.norm(ls.directions, axis=1), 1.0, atol=1e-12)
        assert np.all(ls.rgb >= 0)
        assert np.all(ls.solid_angle > 0)


@pytest.mark.parametrize("method", METHODS)
def test_energy_conserved_and_unit_directions_on_shared_maps(method: str,
                                                             maps: dict[str, np.ndarray]) -> None:
    for img in maps.values():
        for n in (1, 7, 200):
            ls = make_sampler(method).sample(img, n)
            _check_set(ls, img)
            assert 1 <= len(ls) <= n
            assert ls.method == method


def test_acceptance_median_diffuse_error_at_256(maps: dict[str, np.ndarray]) -> None:
    """Issue 3: median over the six maps of the diffuse error at N = 256 <= 0.04 for Pharr and
    Hemigon (measured here: Pharr ~0.013, Hemigon ~0.019)."""
    errors: dict[str, list[float]] = {"pharr": [], "hemigon": [], "median-cut": []}
    for img in maps.values():
        ref = ErrorReference(img)
        for method in errors:
            errors[method].append(ref.error("diffuse", make_sampler(method).sample(img, 256)))
    med = {m: float(np.median(v)) for m, v in errors.items()}
    print("median diffuse error at N=256:", med)
    assert med["pharr"] <= 0.04
    assert med["hemigon"] <= 0.04
    assert med["median-cut"] <= 0.004  # the baseline (issue: "about 0.0016")


def _test_map(h: int = 16) -> np.ndarray:
    rng = np.random.default_rng(7)
    img = (rng.random((h, 2 * h, 3)) ** 3).astype(np.float32)
    img[3, 5] = 30.0
    return img


def test_pharr_histogram_of_1e6_lights_matches_density() -> None:
    """Light directions of a 1e6-light Pharr set binned into 4 x 8-pixel blocks: the fraction in
    each block equals its share of luminance x solid angle within 1%."""
    img = _test_map()
    h, w = img.shape[:2]
    n = 1_000_000
    ls = PharrSampler().sample(img, n)
    theta, phi = angles_from_directions(ls.directions)
    r = np.minimum((theta / np.pi * h).astype(int), h - 1) // 4
    c = np.minimum((phi / (2 * np.pi) * w).astype(int), w - 1) // 8
    hist = np.bincount(r * 4 + c, minlength=16) / n
    func = luminance(img.astype(np.float64)) * equirect_row_solid_angle(h)[:, None]
    expected = func.reshape(4, 4, 4, 8).sum(axis=(1, 3)).ravel() / func.sum()
    big = expected > 0.02
    assert np.abs(hist - expected)[big].max() / expected[big].min() < 0.01


def test_hemigon_histogram_of_1e6_lights_matches_its_pdf() -> None:
    img = _test_map(32)
    img[16:] = 0.0  # lower hemisphere dark: every light is in the upper one
    s = HemigonSampler(grid=16)
    n = 1_000_000
    ls = s.sample(img, n)
    assert len(ls) == n
    assert np.all(ls.ids < LOWER_ID_OFFSET)
    dist = s.distributions[0]
    assert dist is not None
    uv = hemisphere_to_square(ls.directions)
    bins = 4
    hist, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=bins, range=[[0, 1], [0, 1]])
    m = 2 * 16 * 16 * bins
    g = (np.arange(m) + 0.5) / m
    uu, vv = np.meshgrid(g, g)
    p = dist.pdf(np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(m, m)
    expected = p.reshape(bins, m // bins, bins, m // bins).sum(axis=(1, 3)) / (m * m)
    big = expected > 0.02
    rel = np.abs(hist / n - expected)[big] / expected[big]
    assert rel.max() < 0.01, rel


@pytest.mark.parametrize("method", METHODS)
def test_all_black_map_gives_empty_set(method: str) -> None:
    ls = make_sampler(method).sample(np.zeros((32, 64, 3), np.float32), 16)
    assert len(ls) == 0
    np.testing.assert_array_equal(lights_total(ls), 0.0)
    json = ls.to_json()
    assert json["lights"] == []


@pytest.mark.parametrize("method", METHODS)
def test_single_hot_pixel(method: str) -> None:
    img = np.zeros((64, 128, 3), np.float32)
    img[20, 40] = 1e9
    ls = make_sampler(method).sample(img, 64)
    _check_set(ls, img)
    _theta, _phi = angles_from_directions(ls.directions)
    t0, p0 = np.pi * 20.5 / 64, 2 * np.pi * 40.5 / 128
    d0 = np.array([np.sin(t0) * np.sin(p0), np.cos(t0), -np.sin(t0) * np.cos(p0)])
    angle = np.degrees(np.arccos(np.clip(ls.directions @ d0, -1, 1)))
    # Within the pixel (~2.8 deg) for Pharr / median cut; Hemigon's 128-cell grid and row
    # interpolation spread it over about one cell (~1.1 deg) around the pixel.
    assert angle.max() < (4.0 if method == "hemigon" else 2.0), angle.max()


@pytest.mark.parametrize("method", METHODS)
def test_nan_map_is_sampled_as_zero_and_flagged(method: str) -> None:
    img = _test_map(32)
    bad = img.copy()
    bad[5:7, 10:14] = np.nan
    bad[20, 3, 1] = -0.5
    bad[21, 3] = np.inf
    clean = sanitize_radiance(bad)[0]
    ls = make_sampler(method).sample(bad, 32)
    ref = make_sampler(method).sample(clean, 32)
    _check_set(ls, bad)
    assert ls.extra["sanitized"] == {"nonfinite": 2 * 4 * 3 + 3, "negative": 1}
    np.testing.assert_allclose(ls.directions, ref.directions)
    np.testing.assert_allclose(ls.rgb, ref.rgb)


def test_count_must_be_positive() -> None:
    for method in METHODS:
        with pytest.raises(ValueError, match="count"):
            make_sampler(method).sample(_test_map(), 0)


def test_hemigon_split_ground_elimination_and_clustering(maps: dict[str, np.ndarray]) -> None:
    img = maps["lebombo_1k.hdr"]
    clean = sanitize_radiance(img)[0]
    total = equirect_integral(clean)
    upper = equirect_integral(np.where(np.arange(512)[:, None, None] < 256, clean, 0))
    ls = HemigonSampler().sample(img, 300)
    n_up = int(np.sum(ls.ids < LOWER_ID_OFFSET))
    frac = float(luminance(upper) / luminance(total))
    assert abs(n_up - 300 * frac) <= 1
    assert np.all(ls.directions[ls.ids < LOWER_ID_OFFSET, 1] >= 0)
    assert np.all(ls.directions[ls.ids >= LOWER_ID_OFFSET, 1] <= 0)
    # Ground: the lower hemisphere is below the horizon -> ambient, energy still conserved
    g = HemigonSampler(ground=True).sample(img, 300)
    assert len(g) == 300
    assert np.all(g.directions[:, 1] >= 0)
    np.testing.assert_allclose(g.extra["ambient"], total - upper, rtol=1e-6)
    _check_set(g, img)
    # Negligible power -> ambient (here: everything, an explicit path)
    a = HemigonSampler(min_power_fraction=10.0).sample(img, 50)
    assert len(a) == 0
    _check_set(a, img)
    # Clustering merges close lights, conserving energy
    c = HemigonSampler(cluster_deg=10.0).sample(img, 300)
    assert 0 < len(c) < 300
    _check_set(c, img)


def test_hemigon_ids_are_stable_and_small_changes_move_lights_little(
        maps: dict[str, np.ndarray]) -> None:
    img = maps["potsdamer_platz_1k.hdr"]
    s = HemigonSampler()
    a = s.sample(img, 256)
    b = s.sample(img * np.float32(1.0 + 1e-3 * np.random.default_rng(8).random((*img.shape[:2], 1))), 256)
    np.testing.assert_array_equal(a.ids, b.ids)
    moved = np.degrees(np.arccos(np.clip(np.sum(a.directions * b.directions, axis=1), -1, 1)))
    assert np.median(moved) < 0.1
    assert np.mean(moved > 5.0) < 0.02


def test_hemigon_filters_engage_and_reset() -> None:
    img = _test_map(32)
    s = HemigonSampler(energy_alpha=0.5, energy_jump=0.5, trajectory_alpha=0.5)
    s.sample(img, 16)
    b = s.sample(img * np.float32(1.2), 16)  # +20%: smoothed to +10%
    total = equirect_integral(img)
    np.testing.assert_allclose(lights_total(b), 1.1 * total, rtol=1e-6)
    c = s.sample(img * np.float32(3.0), 16)  # a lamp switched on: reset, exact again
    np.testing.assert_allclose(lights_total(c), 3.0 * total, rtol=1e-6)
    s.reset()
    np.testing.assert_allclose(lights_total(s.sample(img, 16)), total, rtol=1e-6)


def test_split_count() -> None:
    np.testing.assert_array_equal(split_count(10, np.array([3.0, 1.0])), [8, 2])
    np.testing.assert_array_equal(split_count(10, np.array([1.0, 0.0])), [10, 0])
    np.testing.assert_array_equal(split_count(2, np.array([1e6, 1.0])), [1, 1])
    np.testing.assert_array_equal(split_count(1, np.array([1e6, 1.0])), [1, 0])
    np.testing.assert_array_equal(split_count(5, np.zeros(2)), [0, 0])


def test_median_cut_power_of_two_regions_have_equal_energy() -> None:
    img = np.ones((64, 128, 3), np.float32)
    ls = make_sampler("median-cut").sample(img, 16)
    assert len(ls) == 16
    y = luminance(ls.rgb)
    assert y.max() / y.min() < 1.2  # equal-energy splits (to the pixel)
    assert abs(ls.solid_angle.sum() - 4 * np.pi) < 1e-9


def test_registry() -> None:
    assert {"pharr", "hemigon", "median-cut"} <= set(available_samplers())
    with pytest.raises(KeyError, match="unknown sampler"):
        make_sampler("nope")
    s = make_sampler("hemigon", grid=32, cluster_deg=1.0)
    assert s.grid == 32  # type: ignore[attr-defined]


def test_lightset_json_roundtrip_keeps_ambient() -> None:
    ls = HemigonSampler(ground=True).sample(_test_map(32), 8)
    back = LightSet.from_json(ls.to_json())
    np.testing.assert_allclose(back.directions, ls.directions, atol=1e-7)
    np.testing.assert_allclose(back.rgb, ls.rgb)
    np.testing.assert_array_equal(back.ids, ls.ids)
    np.testing.assert_allclose(lights_total(back), lights_total(ls))


def test_median_cut_regions_from_energy_match_the_sampler(maps: dict[str, np.ndarray]) -> None:
    """The public ``median_cut_regions`` (energy in) and the sampler's one-pass summed-area table
    cut the same rectangles, and the lights sum each rectangle's pixels exactly."""
    from lightprobe.device.sampling.median_cut import median_cut_regions
    from lightprobe.device.sampling.pharr import prepare_density

    img = maps["lebombo_1k.hdr"]
    energy = prepare_density(img)[0]
    h = energy.shape[0]
    sin_t = np.sin(np.pi * (np.arange(h) + 0.5) / h)
    rects, e = median_cut_regions(energy, sin_t, 300)
    ls = make_sampler("median-cut").sample(img, 300)
    assert ls.extra["regions"] == len(rects[e > 0]) == len(ls)
    omega = equirect_row_solid_angle(h)
    for k in (0, 7, 150, len(ls) - 1):
        r0, r1, c0, c1 = rects[e > 0][k]
        want = (img[r0:r1, c0:c1].astype(np.float64) * omega[r0:r1, None, None]).sum(axis=(0, 1))
        np.testing.assert_allclose(ls.rgb[k], want, rtol=1e-12)
        np.testing.assert_allclose(ls.solid_angle[k], omega[r0:r1].sum() * (c1 - c0), rtol=1e-12)
