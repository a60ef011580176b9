"""Properties of the sampling building blocks: Distribution2D, Halton, Havran map, filters."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.device.sampling.distribution import (
    Distribution2D,
    halton,
    invert_linear_sample,
    radical_inverse,
    sample_linear,
)
from lightprobe.device.sampling.havran import (
    disc_to_square,
    hemisphere_to_square,
    square_to_disc,
    square_to_hemisphere,
)
from lightprobe.device.sampling.temporal import EnergyFilter, TrajectoryFilter


def _func(seed: int = 1, shape: tuple[int, int] = (12, 18)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = rng.random(shape) ** 4
    f[3] = 0.0  # a dark row
    f[:, 5] = 0.0  # a dark column
    f[7, 9] = 40.0  # a hot cell
    return f


def _exact_bin_mass(d: Distribution2D, bins: int) -> np.ndarray:
    """Mass of each of bins x bins equal squares, by a midpoint rule exact for this density
    (piecewise constant in u, piecewise linear in v between row centres: the fine grid is
    aligned with cells and knots)."""
    m = 2 * d.nv * d.nu * bins  # a multiple of nu, 2 nv and bins
    g = (np.arange(m) + 0.5) / m
    uu, vv = np.meshgrid(g, g)
    p = d.pdf(np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(m, m)  # [v, u]
    k = m // bins
    return p.reshape(bins, k, bins, k).sum(axis=(1, 3)) / (m * m)


@pytest.mark.parametrize("interpolate", [False, True])
def test_invert_sample_roundtrip_and_reported_pdf(interpolate: bool) -> None:
    d = Distribution2D(_func(), interpolate)
    u = np.random.default_rng(2).random((20000, 2))
    pts, pdf = d.sample(u)
    assert np.all((pts >= 0) & (pts < 1))
    np.testing.assert_allclose(d.invert(pts), u, atol=1e-9)
    np.testing.assert_allclose(pdf, d.pdf(pts), rtol=1e-12)
    assert np.all(pdf > 0)  # never samples a zero-density place


@pytest.mark.parametrize("interpolate", [False, True])
def test_histogram_of_1e6_samples_matches_pdf_within_1_percent(interpolate: bool) -> None:
    d = Distribution2D(_func(), interpolate)
    bins = 3
    expected = _exact_bin_mass(d, bins)
    assert expected.sum() == pytest.approx(1.0, abs=1e-12)
    n = 1_000_000
    pts, _ = d.sample(np.random.default_rng(3).random((n, 2)))
    hist, _, _ = np.histogram2d(pts[:, 1], pts[:, 0], bins=bins, range=[[0, 1], [0, 1]])
    big = expected > 0.05
    rel = np.abs(hist / n - expected)[big] / expected[big]
    assert rel.max() < 0.01, rel


def test_piecewise_constant_pdf_is_func_over_integral() -> None:
    f = _func()
    d = Distribution2D(f)
    nv, nu = f.shape
    centres = np.stack(np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv), -1)
    np.testing.assert_allclose(d.pdf(centres.reshape(-1, 2)).reshape(nv, nu), f / f.mean())


def test_all_zero_and_nonfinite_func_fall_back_to_uniform() -> None:
    for f in (np.zeros((4, 6)), np.full((4, 6), np.nan)):
        d = Distribution2D(f, interpolate=True)
        u = np.random.default_rng(4).random((1000, 2))
        pts, pdf = d.sample(u)
        np.testing.assert_allclose(pdf, 1.0)
        assert np.all(np.isfinite(pts))


def test_interpolated_distribution_is_bicontinuous() -> None:
    """Where the density is positive, a 1% change of one row moves every sample a little with
    interpolated conditionals; the piecewise-constant conditionals let samples hop in u when
    they cross a row boundary."""
    f = np.random.default_rng(6).random((32, 32)) ** 4 + 0.05
    g = f.copy()
    g[10] *= 1.01
    u = halton(4000)
    moves = {}
    for interpolate in (False, True):
        a, _ = Distribution2D(f, interpolate=interpolate).sample(u)
        b, _ = Distribution2D(g, interpolate=interpolate).sample(u)
        moves[interpolate] = np.abs(a - b).max()
    assert moves[True] < 0.01
    assert moves[False] > 5 * moves[True]


def test_halton_and_linear_sampling() -> None:
    np.testing.assert_allclose(radical_inverse(np.array([1, 2, 3, 4]), 2), [0.5, 0.25, 0.75, 0.125])
    np.testing.assert_allclose(radical_inverse(np.array([1, 2, 3, 4]), 3), [1 / 3, 2 / 3, 1 / 9, 4 / 9])
    h = halton(5)
    np.testing.assert_allclose(h[0], [0.5, 1 / 3])
    np.testing.assert_allclose(halton(3), h[:3])  # light i keeps its point whatever N is
    u = np.linspace(0, 1, 101)[:-1]
    for a, b in ((0.0, 1.0), (2.0, 0.5), (1.0, 1.0)):
        x = sample_linear(u, a, b)
        np.testing.assert_allclose(invert_linear_sample(x, a, b), u, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.booleans())
def test_havran_inverse_forward_is_identity(u: float, v: float, lower: bool) -> None:
    uv = np.array([[u, v]])
    back = hemisphere_to_square(square_to_hemisphere(uv, lower=lower), lower=lower)
    np.testing.assert_allclose(back, uv, atol=1e-9)


def test_havran_roundtrip_dense_edges_and_units() -> None:
    g = np.linspace(0, 1, 201)
    uv = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    for lower in (False, True):
        d = square_to_hemisphere(uv, lower=lower)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        assert np.all(d[:, 1] <= 1e-15) if lower else np.all(d[:, 1] >= -1e-15)
        np.testing.assert_allclose(hemisphere_to_square(d, lower=lower), uv, atol=1e-9)
    np.testing.assert_allclose(disc_to_square(square_to_disc(uv)), uv, atol=1e-9)
    np.testing.assert_allclose(square_to_hemisphere(np.array([0.5, 0.5])), [0, 1, 0], atol=1e-15)


def test_havran_map_is_equal_area() -> None:
    """Uniform points on the square give uniform directions on the hemisphere: cos(theta) and
    azimuth are uniform (1e6 samples, coarse bins within 1%)."""
    n = 1_000_000
    d = square_to_hemisphere(np.random.default_rng(5).random((n, 2)))
    h_cos, _ = np.histogram(d[:, 1], bins=5, range=(0, 1))
    h_phi, _ = np.histogram(np.arctan2(d[:, 0], -d[:, 2]), bins=8, range=(-np.pi, np.pi))
    assert np.abs(h_cos / (n / 5) - 1).max() < 0.01
    assert np.abs(h_phi / (n / 8) - 1).max() < 0.01


def test_energy_filter_smooths_and_resets_on_jumps() -> None:
    f = EnergyFilter(alpha=0.5, jump=0.5)
    assert f.update(10.0) == 10.0
    assert f.update(12.0) == pytest.approx(11.0)  # y + alpha (x - y)
    assert f.update(100.0) == 100.0  # a switched lamp: reset, no slow ramp
    assert f.resets == 1
    assert f.gain(0.0) == 1.0
    with pytest.raises(ValueError, match="alpha"):
        EnergyFilter(alpha=0.0)


def test_trajectory_filter_smooths_small_moves_and_resets_jumps() -> None:
    f = TrajectoryFilter(alpha=0.5, jump=0.05)
    ids = np.array([0, 1, 2])
    p0 = np.array([[0.1, 0.1], [0.5, 0.5], [0.9, 0.9]])
    np.testing.assert_allclose(f.update(ids, p0), p0)
    p1 = p0 + np.array([[0.02, 0.0], [0.3, 0.0], [0.0, 0.02]])
    out = f.update(ids, p1)
    np.testing.assert_allclose(out[0], [0.11, 0.1])  # smoothed
    np.testing.assert_allclose(out[1], [0.8, 0.5])  # jumped: reset, no ghost in between
    np.testing.assert_allclose(out[2], [0.9, 0.91])
    assert f.resets == 1
    # A new id starts at its position; a vanished id is forgotten
    out = f.update(np.array([2, 7]), np.array([[0.9, 0.92], [0.3, 0.3]]))
    np.testing.assert_allclose(out[1], [0.3, 0.3])
    f.reset()
    np.testing.assert_allclose(f.update(ids, p0), p0)
