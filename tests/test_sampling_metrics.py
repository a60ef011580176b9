"""The exact, map-based error metrics."""

from __future__ import annotations

import numpy as np
import pytest

from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import equirect_row_solid_angle
from lightprobe.device.sampling.metrics import (
    ErrorReference,
    diffuse_irradiance_error,
    fibonacci_normals,
    glossy_error,
    occluded_irradiance_error,
    relative_rmse,
)


def _pixel_light(img: np.ndarray, r: int, c: int) -> LightSet:
    """The exact light of one pixel: its centre direction, radiance x exact solid angle."""
    h, w = img.shape[:2]
    t, p = np.pi * (r + 0.5) / h, 2 * np.pi * (c + 0.5) / w
    d = [np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)]
    rgb = img[r, c].astype(np.float64) * equirect_row_solid_angle(h, w)[r]
    return LightSet([d], [rgb], [equirect_row_solid_angle(h, w)[r]])


def test_fibonacci_normals_are_unit_and_even() -> None:
    n = fibonacci_normals(512)
    assert n.shape == (512, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(n.mean(axis=0), 0.0, atol=5e-3)
    assert fibonacci_normals(0).shape == (0, 3)


def test_pixel_sums_are_exact_for_a_pixel_light() -> None:
    """A light set that *is* the map (one lit pixel) has zero error for all three metrics."""
    img = np.zeros((32, 64, 3), np.float32)
    img[9, 17] = (3.0, 2.0, 1.0)
    ls = _pixel_light(img, 9, 17)
    ref = ErrorReference(img)
    for kind in ("diffuse", "occluded", "glossy"):
        assert ref.error(kind, ls) < 1e-12, kind
        assert np.any(ref.truth(kind) > 0)


def test_uniform_map_irradiance_is_pi_and_ambient_is_counted() -> None:
    img = np.ones((128, 256, 3), np.float32)
    ref = ErrorReference(img)
    np.testing.assert_allclose(ref.truth("diffuse"), np.pi, rtol=1e-3)
    # Phong lobe normalised to integrate to 1 over the hemisphere of r: L = 1 -> 1
    np.testing.assert_allclose(ref.truth("glossy"), 1.0, rtol=1e-2)
    # A 35 deg cap blocks at most 1 - cos^2(35 deg) of pi (axes uniform: some caps block nothing)
    occ = ref.truth("occluded") / np.pi
    assert np.all(occ <= 1.0 + 1e-3)  # the map's own discretisation of pi, as above
    assert np.all(occ >= 1 - np.sin(np.radians(35)) ** 2 - 1e-3)
    assert np.mean(occ) < 0.95  # the caps do shadow
    ambient = LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                       extra={"ambient": [4 * np.pi] * 3})
    assert ref.error("diffuse", ambient) < 5e-3
    assert ref.error("diffuse", LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))) == 1.0


def test_errors_grow_with_misplaced_energy_and_functions_agree() -> None:
    rng = np.random.default_rng(3)
    img = (rng.random((32, 64, 3)) ** 4).astype(np.float32)
    ref = ErrorReference(img)
    total = ref.truth("diffuse")
    good = _pixel_light(img, 5, 5)
    assert ref.error("diffuse", good) > 0.5  # one pixel cannot stand for the whole map
    assert diffuse_irradiance_error(img, good) == pytest.approx(ref.error("diffuse", good))
    assert occluded_irradiance_error(img, good) == pytest.approx(ref.error("occluded", good))
    assert glossy_error(img, good) == pytest.approx(ref.error("glossy", good))
    assert np.all(total > 0)


def test_degenerate_black_map_and_nan() -> None:
    black = np.zeros((16, 32, 3), np.float32)
    empty = LightSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    assert diffuse_irradiance_error(black, empty) == 0.0
    stray = LightSet([[0, 1, 0]], [[1.0, 1.0, 1.0]], [0.1])
    assert diffuse_irradiance_error(black, stray) > 0
    nan = black.copy()
    nan[3, 3] = np.nan
    assert diffuse_irradiance_error(nan, empty) == 0.0  # NaN is read as 0, never propagates
    assert relative_rmse(np.zeros(3), np.zeros(3)) == 0.0
