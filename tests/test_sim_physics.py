"""Simulator physics: area-correct lights and render, sensor noise statistics, response curve."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.core.sphere import (
    directions_from_angles,
    equirect_integral,
    equirect_row_solid_angle,
)
from lightprobe.drivers.base import PixelFormat
from lightprobe.sim.lens import standard_lens
from lightprobe.sim.scene import DynamicLight, Scene, disc_energy, rasterize_disc
from lightprobe.sim.sensor import ResponseCurve, SensorModel, raw_levels


# ---- dynamic lights -----------------------------------------------------------------------------
def test_rasterised_disc_energy_matches_analytic() -> None:
    rng = np.random.default_rng(11)
    h = 512
    omega = equirect_row_solid_angle(h)
    cases = [(0.0, 0.0, 0.1), (np.pi, 1.0, 0.2), (0.002, 5.0, 0.5), (np.pi / 2, 0.0, 0.27),
             (np.pi / 2, 2 * np.pi - 1e-4, 3.0), (0.05, 1.0, 10.0), (1.0, 2.0, 40.0)]
    cases += [(float(np.arccos(rng.uniform(-1, 1))), float(rng.uniform(0, 2 * np.pi)),
               float(rng.choice([0.1, 0.27, 1.0, 3.0, 8.0]))) for _ in range(40)]
    for theta, phi, radius_deg in cases:
        a = np.deg2rad(radius_deg)
        rows, cols, frac = rasterize_disc(h, directions_from_angles(theta, phi), a)
        assert np.all((frac > 0) & (frac <= 1 + 1e-12))
        assert np.unique(rows * 2 * h + cols).size == rows.size
        got = float((frac * omega[rows]).sum())
        assert got == pytest.approx(float(disc_energy(a, [1.0])[0]), rel=5e-3), (theta, phi, radius_deg)


def test_scene_lights_energy_and_exposure_average() -> None:
    def blink(t: float) -> float:
        return 1.0 if (t % 0.02) < 0.01 else 0.0

    lights = [DynamicLight("a", np.deg2rad(2.0), (100.0, 50.0, 10.0), lambda t: (0.0, 1.0, 0.1)),
              DynamicLight("b", np.deg2rad(0.3), (1e4, 1e4, 1e4), lambda t: (1.0, -0.2, 0.3), blink)]
    base = np.full((256, 512, 3), 0.5, np.float32)
    base[3, 7, 1] = np.nan  # the clamping policy: NaN and negatives -> 0
    base[9, 9, 0] = -1.0
    scene = Scene(base, scale=2.0, lights=lights)
    assert scene.clamped_pixels == 2
    for t in (0.0, 0.015):
        assert scene.true_integral(t) == pytest.approx(scene.analytic_integral(t), rel=5e-3)
    # Averaged over a 20 ms exposure the blinking light has half its power
    avg = equirect_integral(scene.radiance_equirect(0.0, exposure_s=0.02))
    on, off = scene.analytic_integral(0.0), scene.analytic_integral(0.015)
    assert avg == pytest.approx(0.5 * (on + off), rel=5e-3)


# ---- lens render --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def vga_lens():  # type: ignore[no-untyped-def]
    return standard_lens(640, 480)


def test_render_of_uniform_map_is_uniform_inside_the_circle(vga_lens) -> None:  # type: ignore[no-untyped-def]
    img = vga_lens.render(np.full((512, 1024, 3), 2.0, np.float32))
    h, w = img.shape[:2]
    vv, uu = np.mgrid[0:h, 0:w]
    r = np.hypot(uu - 319.5, vv - 239.5)
    clean = r < vga_lens.clean_radius_px - 1.5
    np.testing.assert_allclose(img[clean], 2.0, rtol=1e-5)
    assert np.all(img[r > vga_lens.circle_radius_px + 1.5] == 0)  # the black lens frame
    ring = (r > vga_lens.clean_radius_px + 0.8) & (r < vga_lens.circle_radius_px - 0.8)
    assert ring.any()
    assert np.all(img[ring] < 0.1)


@pytest.mark.parametrize("name", ["lebombo_1k.hdr", "studio_small_03_1k.hdr", "rooitou_park_1k.hdr"])
def test_render_is_area_correct_over_the_visible_cap(vga_lens, name: str, envmap_paths: dict[str, Path]) -> None:  # type: ignore[no-untyped-def]
    from lightprobe.core.imageio import read_hdr_image

    eq = read_hdr_image(envmap_paths[name])
    eq[eq.shape[0] // 2 :] = 0  # keep the upper hemisphere (the lens sees 185 deg)
    img = vga_lens.render(eq)  # the housing ring lies below the horizon
    omega = vga_lens.pixel_solid_angle()
    got = (img.astype(np.float64) * omega[..., None]).sum(axis=(0, 1))
    np.testing.assert_allclose(got, equirect_integral(eq), rtol=0.01)


def test_render_is_area_correct_in_the_large_mode(envmap_paths: dict[str, Path]) -> None:
    from lightprobe.core.imageio import read_hdr_image

    lens = standard_lens(1280, 960)
    eq = read_hdr_image(envmap_paths["interior_blender.exr"])  # tiny 3e4 lamps: a hard case
    eq = np.clip(np.nan_to_num(eq), 0, None)
    eq[eq.shape[0] // 2 :] = 0
    got = (lens.render(eq).astype(np.float64) * lens.pixel_solid_angle()[..., None]).sum(axis=(0, 1))
    np.testing.assert_allclose(got, equirect_integral(eq), rtol=0.01)


def test_render_keeps_the_energy_of_a_small_sun(vga_lens) -> None:  # type: ignore[no-untyped-def]
    for theta_deg in (10.0, 50.0, 85.0):
        d = directions_from_angles(np.deg2rad(theta_deg), 1.0)
        scene = Scene(np.zeros((512, 1024, 3), np.float32),
                      lights=[DynamicLight("sun", np.deg2rad(0.27), (1.0, 1.0, 1.0), lambda t, d=d: d)])
        img = vga_lens.render(scene.radiance_equirect(0.0))
        got = float((img[..., 0].astype(np.float64) * vga_lens.pixel_solid_angle()).sum())
        assert got == pytest.approx(float(disc_energy(np.deg2rad(0.27), [1.0])[0]), rel=0.01)


@pytest.mark.parametrize("eq_height", [256, 512])
def test_every_equirect_pixel_of_the_upper_hemisphere_reaches_the_sensor_whole(vga_lens, eq_height: int) -> None:  # type: ignore[no-untyped-def]
    """A sun of one equirect pixel, anywhere above the horizon, keeps its energy: each column of
    the render matrix, weighted by the sensor pixels' solid angles, is the equirect pixel's exact
    solid angle. (Sampled from the sensor's side alone, the matrix lost 1% of a sun at 50 deg and
    all of some pixels near the zenith: ratio percentiles 0.1 / 99.9% were 0 and 2.1.)"""
    import scipy.sparse as sp

    m = vga_lens.render_matrix(eq_height)
    a = sp.csr_matrix((m.data, m.indices, m.indptr), shape=m.shape)
    got = (a.T @ vga_lens.pixel_solid_angle().ravel()).reshape(eq_height, 2 * eq_height)[: eq_height // 2]
    exact = equirect_row_solid_angle(eq_height)[: eq_height // 2, None]
    err = np.abs(got / exact - 1.0)
    assert np.percentile(err, 99.9) <= 0.005, np.percentile(err, [50, 99, 99.9])
    assert err.max() <= 0.025, err.max()


def test_pixel_solid_angle_matches_the_lens_jacobian(vga_lens) -> None:  # type: ignore[no-untyped-def]
    """Pixel solid angles: 1/f^2 on the axis; the upper hemisphere (1 on theta < 90 deg) sums to 2 pi."""
    up = np.zeros((512, 1024, 3), np.float32)
    up[:256] = 1.0
    omega = vga_lens.pixel_solid_angle()
    got = float((vga_lens.render(up, housing=False)[..., 0] * omega).sum())
    assert got == pytest.approx(2 * np.pi, rel=1e-3)
    assert omega[240, 320] == pytest.approx(1 / vga_lens.fisheye.K[0, 0] ** 2, rel=1e-3)
    # Between the optical axis and the rim, the solid angle per pixel follows eq. (J)
    assert np.all(np.diff(omega[240, 320:550]) < 0)


def test_render_matrix_arrays_apply_as_scipy_does() -> None:
    """The frame path's CSR loops (lightprobe.device.projection.sparse, no SciPy at run time) against SciPy on a random
    matrix with empty rows and columns: the product, the transpose and a combination of rows."""
    sp = pytest.importorskip("scipy.sparse")
    from lightprobe.device.projection.sparse import Csr

    rng = np.random.default_rng(7)
    a = sp.random(300, 500, density=0.02, random_state=8, format="csr", dtype=np.float32)
    a = (sp.diags((np.arange(300) != 5).astype(np.float32)) @ a).tocsr()  # row 5 empty
    a.eliminate_zeros()
    assert a.indptr[5] == a.indptr[6]
    m = Csr.from_scipy(a)
    x = rng.random((500, 3), dtype=np.float32) * 10
    np.testing.assert_allclose(m.matmul_rgb(x), a.astype(np.float64) @ x, rtol=1e-6, atol=1e-6)
    t = m.transpose()
    at = a.T.tocsr()
    assert t.shape == (500, 300)
    np.testing.assert_array_equal(t.indptr, at.indptr)
    np.testing.assert_array_equal(t.indices, at.indices)
    np.testing.assert_array_equal(t.data, at.data)
    rows, w = np.array([3, 3, 499, 17]), np.array([0.5, 1.5, 2.0, -1.0])
    np.testing.assert_allclose(t.rows_combination(rows, w), at[rows].T.astype(np.float64) @ w, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="matmul_rgb"):
        m.matmul_rgb(x[:10])


# ---- sensor -------------------------------------------------------------------------------------
@pytest.mark.parametrize(("mu", "fmt"), [(4.0, PixelFormat.RAW12), (40.0, PixelFormat.RAW12),
                                         (2500.0, PixelFormat.RAW12), (800.0, PixelFormat.RAW10)])
def test_noise_statistics_match_shot_plus_read_model(mu: float, fmt: PixelFormat) -> None:
    s = SensorModel()
    exposure = 0.01
    radiance = mu / (s.sensitivity * exposure)
    flat = np.full((200, 200, 3), radiance, np.float32)
    data = s.capture(flat, exposure, 1.0, fmt, np.random.default_rng(5)).astype(np.float64)
    black, white = raw_levels(fmt)
    k = (white - black) / s.full_well  # DN per electron
    # Black clipping at DN 0 is far below these levels (black >= 64 DN)
    assert data.mean() == pytest.approx(black + k * mu, abs=0.02 * k * mu + 0.05)
    var = k**2 * (mu + s.read_noise**2) + 1 / 12  # shot + read + quantisation
    assert data.var() == pytest.approx(var, rel=0.05)


def test_gain_saturation_and_degenerate_input() -> None:
    s = SensorModel()
    img = np.full((50, 50, 3), 1.0, np.float32)
    img[0, 0] = np.nan
    img[0, 1] = -5.0
    img[0, 2] = np.inf
    img[0, 3] = 1e30
    a = s.capture(img, 0.01, 1.0, PixelFormat.RAW12, None).astype(float)
    b = s.capture(img, 0.01, 4.0, PixelFormat.RAW12, None).astype(float)
    assert a[0, 0].tolist() == a[0, 1].tolist() == [256.0] * 3  # no light
    assert a[0, 2].tolist() == a[0, 3].tolist() == [4095.0] * 3  # saturated
    assert (b[10, 10] - 256) == pytest.approx(4 * (a[10, 10] - 256), abs=1)
    z = s.capture(img, 1.0, 16.0, PixelFormat.RGB8, np.random.default_rng(0))
    assert z.dtype == np.uint8
    assert z[10, 10].tolist() == [255] * 3
    assert z[0, 1].max() < 40


def test_response_curve_is_smooth_increasing_and_exactly_inverted() -> None:
    curve = ResponseCurve()
    x = np.repeat(np.geomspace(1e-7, 1.0, 20001)[:, None], 3, axis=1)
    y = curve.forward(x)
    assert np.all(np.diff(y, axis=0) > 0)
    np.testing.assert_allclose(curve.inverse(y), x, rtol=1e-9, atol=1e-15)
    # sRGB-like (mid grey 0.18 maps near 0.6), slightly different per channel, S-shaped shoulder
    assert np.all((y[np.searchsorted(x[:, 0], 0.18)] > 0.5) & (y[np.searchsorted(x[:, 0], 0.18)] < 0.7))
    assert np.ptp(curve.forward(np.full((1, 3), 0.18))) > 0.01
    slope = np.diff(y, axis=0) / np.diff(x, axis=0)
    assert np.all(slope[-1] < slope[len(slope) // 2])
    inverse = SensorModel().truth_inverse(PixelFormat.RGB8)
    assert inverse.shape == (256, 3)
    assert inverse[0].tolist() == [0, 0, 0]
    assert inverse[255].tolist() == [1.0, 1.0, 1.0]
    assert np.all(np.diff(inverse, axis=0) > 0)
    # The 8-bit code of x is the rounding of 255 f(x), implemented as a threshold search
    xs = np.random.default_rng(1).uniform(0, 1, (20000, 3))
    codes = SensorModel().digitise(xs * 6000.0, 1.0, PixelFormat.RGB8)
    np.testing.assert_array_equal(codes, np.rint(255 * curve.forward(xs)).astype(np.uint8))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=3, max_size=48),
       exposure=st.floats(1e-5, 1.0), gain=st.floats(1.0, 16.0),
       fmt=st.sampled_from([PixelFormat.RGB8, PixelFormat.RAW10, PixelFormat.RAW12]))
def test_sensor_never_fails_on_any_input(values: list[float], exposure: float, gain: float,
                                         fmt: PixelFormat) -> None:
    n = len(values) // 3 * 3
    img = np.asarray(values[:n], np.float32).reshape(-1, 1, 3)
    out = SensorModel().capture(img, exposure, gain, fmt, np.random.default_rng(0))
    white = 255 if fmt is PixelFormat.RGB8 else raw_levels(fmt)[1]
    assert out.shape == img.shape
    assert out.dtype == (np.uint8 if fmt is PixelFormat.RGB8 else np.uint16)
    assert int(out.max()) <= white
    # Non-finite or negative radiance is no light: at most read noise above black
    dark = ~np.isfinite(img) | (img <= 0)
    dark &= ~np.isposinf(img)
    x6 = 6 * 2.5 * gain / 6000  # six sigma of read noise, as normalised exposure
    if fmt is PixelFormat.RGB8:
        bound = 255 * float(ResponseCurve().forward(np.full((1, 3), x6)).max()) + 1
    else:
        black = raw_levels(fmt)[0]
        bound = black + x6 * (white - black) + 1
    assert np.all(out[dark].astype(float) <= bound)
