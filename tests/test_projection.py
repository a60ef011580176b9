"""Projection: fisheye radiance -> polar / equirect / HEALPix maps, area-correct and energy-true.

A QVGA lens with vignetting, a photometric scale and an image circle clipped by the sensor's top
and bottom edges keeps the table build short; the end-to-end energy acceptance against the
simulator (VGA, six shared maps) is in ``test_projection_energy.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from lightprobe.core.calibration import Calibration, FisheyeModel, Photometric, Vignetting
from lightprobe.core.errors import InputError
from lightprobe.core.healpix import npix, pix2vec_nest, vec2pix_nest
from lightprobe.core.sphere import CAMERA_TO_PROBE, directions_from_angles
from lightprobe.device.projection import (
    Projector,
    fisheye_pixel_directions,
    fisheye_pixel_solid_angles,
    fisheye_valid_mask,
    spherical_triangle_solid_angle,
)

W, H = 320, 240
F = 76.0
D = np.array([0.01, -0.004, 0.0, 0.0])
SCALE = 2.0
MAPS = ("polar", "equirect", "healpix")


def _calibration(vignetting: bool = True) -> Calibration:
    K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])
    fe = FisheyeModel((W, H), K, D, fov_deg=185.0)
    vig = Vignetting(((W - 1) / 2, (H - 1) / 2), 118.0, (-0.25, -0.1, 0.0)) if vignetting else None
    return Calibration(fisheye=fe, vignetting=vig, photometric=Photometric(SCALE, "relative"))


@pytest.fixture(scope="module")
def proj() -> Projector:
    return Projector(_calibration(), equirect_height=128, nside=32)


def _measured(p: Projector, radiance: np.ndarray) -> np.ndarray:
    """The fused image a camera with this calibration reports for a true sensor-plane radiance."""
    cal = p.calibration
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    v = cal.vignetting.factor(uu, vv) if cal.vignetting is not None else 1.0
    return (radiance * (v / SCALE)[..., None]).astype(np.float32)


def _energy(p: Projector, maps, name: str) -> np.ndarray:
    """Integral of radiance x solid angle of one map (float64 per channel)."""
    img = getattr(maps, name).reshape(-1, 3).astype(np.float64)
    cov = p._tables[name].coverage.astype(np.float64)  # partly seen pixels hold the seen mean
    if name == "equirect":  # the lower-hemisphere policy already blended coverage in
        cov = np.where(np.isin(np.arange(cov.size) // (2 * p.equirect_height), p._fill_rows),
                       1.0, cov)
    return (p.solid_angle(name)[:, None] * cov[:, None] * img).sum(axis=0)


def _jacobian(theta: np.ndarray) -> np.ndarray:
    """Solid angle per px^2 of the KB4 lens, analytic: sin t / (t_d t_d'(t)) / f^2."""
    t2 = theta * theta
    td = theta * (1 + t2 * (D[0] + t2 * D[1]))
    tdp = 1 + t2 * (3 * D[0] + t2 * 5 * D[1])
    return np.sin(theta) / (td * tdp) / F**2


def _theta_of(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    rd = np.hypot(u - (W - 1) / 2, v - (H - 1) / 2) / F
    t = rd.copy()
    for _ in range(30):  # Newton on t (1 + k1 t^2 + k2 t^4) = rd
        t2 = t * t
        t -= (t * (1 + t2 * (D[0] + t2 * D[1])) - rd) / (1 + t2 * (3 * D[0] + t2 * 5 * D[1]))
    return t


def _lamp(u0: float, v0: float, diameter: float, level: float, n: int = 32
          ) -> tuple[np.ndarray, float]:
    """A uniform disc rendered in the sensor plane (box-filtered pixels) and its exact energy."""
    img = np.zeros((H, W, 3), np.float32)
    r = diameter / 2
    off = (np.arange(n) + 0.5) / n - 0.5
    energy = 0.0
    for iv in range(int(np.floor(v0 - r)) - 1, int(np.ceil(v0 + r)) + 2):
        for iu in range(int(np.floor(u0 - r)) - 1, int(np.ceil(u0 + r)) + 2):
            su = iu + off[None, :]
            sv = iv + off[:, None]
            inside = np.hypot(su - u0, sv - v0) <= r
            img[iv, iu] = level * inside.mean()
            energy += level * (_jacobian(_theta_of(su, sv)) * inside).sum() / n**2
    return img, energy


def _pixel_of(d_probe: np.ndarray, p: Projector) -> np.ndarray:
    return p.calibration.fisheye.project(np.asarray(d_probe) @ CAMERA_TO_PROBE)


# -- pure helpers ---------------------------------------------------------------------------------
def test_octant_triangle_is_an_eighth_of_the_sphere() -> None:
    e = np.eye(3)
    assert spherical_triangle_solid_angle(e[0], e[1], e[2]) == pytest.approx(np.pi / 2, rel=1e-12)
    assert spherical_triangle_solid_angle(e[0], e[0], e[2]) == pytest.approx(0.0, abs=1e-15)


def test_pixel_solid_angles_match_the_lens_jacobian() -> None:
    fe = _calibration().fisheye
    omega = fisheye_pixel_solid_angles(fe, subdiv=4)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    jac = _jacobian(np.maximum(_theta_of(uu, vv), 1e-9))
    inner = fisheye_valid_mask(fe, 5.0)
    rel = omega[inner] / jac[inner] - 1
    assert np.max(np.abs(rel)) < 2e-3  # the Jacobian is a point value, omega the footprint
    # Pixel centres: image centre -> zenith, image right -> +x, image down -> -z (CAMERA_TO_PROBE)
    d = fisheye_pixel_directions(fe)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    assert d[120, 160, 1] > 0.9999
    assert d[120, 300, 0] > 0.9
    assert d[230, 160, 2] < -0.9
    # The hemisphere theta <= 90 deg holds 2 pi sr (staircase edge ~ a pixel ring)
    hemi = _theta_of(uu, vv) <= np.pi / 2
    assert omega[hemi].sum() == pytest.approx(2 * np.pi, rel=0.02)


def test_tables_are_balanced_and_the_polar_map_is_covered(proj: Projector) -> None:
    for name in MAPS:
        assert proj.balance_residual(name) < 1e-3
    cov = proj.coverage_polar
    assert cov.shape == (90, 360)
    assert cov.dtype == np.float32
    assert np.all(cov[:80] == 1.0)
    # The image circle is clipped by the sensor's bottom/top edge at theta ~90.5 deg around
    # azimuths 0 and 180 deg; to the sides the lens sees to 92 deg (fov / 2 - ring margin)
    eq = proj.coverage_equirect  # row 64 covers theta 90 .. 91.4 deg
    assert eq[64, 0] < 0.6
    assert eq[64, 128] < 0.6
    assert eq[64, 64] == 1.0
    assert eq[66, 64] == 0.0
    assert np.all((proj.coverage_healpix >= 0) & (proj.coverage_healpix <= 1))


# -- (2) constant radiance -----------------------------------------------------------------------
def test_constant_radiance_gives_constant_maps(proj: Projector) -> None:
    level = 3.5
    maps = proj.project(_measured(proj, np.full((H, W, 3), level, np.float32)))
    assert maps.polar.shape == (90, 360, 3)
    assert maps.equirect.shape == (128, 256, 3)
    assert maps.healpix.shape == (npix(32), 3)
    assert maps.nside == 32
    for name, cov in (("polar", maps.coverage_polar), ("healpix", maps.coverage_healpix),
                      ("equirect", maps.coverage_equirect)):
        img = getattr(maps, name).reshape(-1, 3)
        seen = cov.ravel() >= 1.0
        np.testing.assert_allclose(img[seen], level, rtol=2e-5)
        if name != "equirect":  # mean radiance of the seen part where partly covered
            np.testing.assert_allclose(img[cov.ravel() > 0], level, rtol=2e-5)
    # Integral = L x covered solid angle = L x the lens's valid solid angle
    lens_omega = (proj.pixel_solid_angle * proj.lens_mask).sum()
    for name in ("healpix", "equirect"):
        np.testing.assert_allclose(_energy(proj, maps, name), level * lens_omega, rtol=1e-4)


# -- (1) a lamp three pixels wide keeps its energy ------------------------------------------------
@pytest.mark.parametrize(("theta_deg", "phi_deg"), [(0.3, 10.0), (20.0, 90.0), (47.0, 200.0),
                                                    (84.0, 300.0), (89.0, 90.0), (90.4, 45.0)])
def test_lamp_three_pixels_wide_keeps_its_energy(proj: Projector, theta_deg: float,
                                                 phi_deg: float) -> None:
    d = directions_from_angles(np.deg2rad(theta_deg), np.deg2rad(phi_deg))
    u0, v0 = _pixel_of(d, proj) + np.array([0.23, -0.17])  # not centred on a pixel
    radiance, energy = _lamp(u0, v0, 3.0, 1000.0)  # inside the valid circle (92 deg) throughout
    maps = proj.project(_measured(proj, radiance))
    names = MAPS if theta_deg < 88 else ("equirect", "healpix")
    for name in names:
        e = _energy(proj, maps, name)
        np.testing.assert_allclose(e, energy, rtol=0.01, err_msg=name)


# -- (3) directions ------------------------------------------------------------------------------
def test_image_axes_map_to_the_documented_azimuths(proj: Projector) -> None:
    cx, cy = (W - 1) / 2, (H - 1) / 2
    img = np.zeros((H, W, 3), np.float32)
    img[round(cy) + 40, round(cx)] = 1.0  # below the centre: azimuth 0 (the front mark)
    p0 = proj.project_polar(img)[..., 0]
    r, c = np.unravel_index(np.argmax(p0), p0.shape)
    assert c in (0, 359)
    assert 20 < r < 45
    img[:] = 0
    img[round(cy), round(cx) + 40] = 1.0  # right of the centre: azimuth 90 deg
    p1 = proj.project_polar(img)[..., 0]
    r, c = np.unravel_index(np.argmax(p1), p1.shape)
    assert c in (89, 90)
    assert 20 < r < 45


@pytest.mark.parametrize(("theta_deg", "phi_deg"), [(12.5, 33.5), (45.5, 180.5), (70.5, 260.5),
                                                    (85.5, 5.5)])
def test_spot_lands_at_its_direction(proj: Projector, theta_deg: float, phi_deg: float) -> None:
    d = directions_from_angles(np.deg2rad(theta_deg), np.deg2rad(phi_deg))
    u, v = _pixel_of(d, proj)
    radiance, _ = _lamp(u, v, 1.2, 50.0)
    maps = proj.project(_measured(proj, radiance))
    # Energy centroids point at d (a wrong frame or azimuth convention is off by tens of degrees)
    pol = maps.polar[..., 1].astype(np.float64)
    theta = np.deg2rad(np.arange(90) + 0.5)[:, None]
    phi = np.deg2rad(np.arange(360) + 0.5)[None, :]
    w = pol * proj.solid_angle("polar").reshape(90, 360)
    cen_p = (directions_from_angles(theta, phi) * w[..., None]).sum(axis=(0, 1))
    hp = maps.healpix[:, 1].astype(np.float64)
    cen_h = (pix2vec_nest(32, np.arange(npix(32))) * hp[:, None]).sum(axis=0)
    for cen, tol in ((cen_p, 0.5), (cen_h, 1.0)):  # polar pixels 1 deg, HEALPix ~1.8 deg
        cen /= np.linalg.norm(cen)
        assert np.degrees(np.arccos(np.clip(cen @ d, -1, 1))) < tol
    # The brightest HEALPix pixel contains d or touches its pixel
    best = pix2vec_nest(32, int(np.argmax(hp)))
    assert np.degrees(np.arccos(np.clip(best @ d, -1, 1))) < 2.0
    assert np.argmax(hp) == vec2pix_nest(32, d) or hp[vec2pix_nest(32, d)] > 0


# -- (4) invalid pixels ------------------------------------------------------------------------------
def test_nan_inf_and_masked_pixels_do_not_leak(proj: Projector) -> None:
    rng = np.random.default_rng(7)
    level = 2.0
    img = _measured(proj, np.full((H, W, 3), level, np.float32))
    img[rng.random((H, W)) < 0.02] = np.nan
    img[rng.random((H, W)) < 0.01] = np.inf
    valid = np.ones((H, W), bool)
    valid[100:120, 150:170] = False
    img[100:120, 150:170] = 1e6  # a masked blob must not appear
    maps = proj.project(img, valid)
    invalid = ndimage.binary_dilation(~valid | ~np.isfinite(img).all(axis=2),
                                      structure=np.ones((3, 3), bool), iterations=2)
    for name, cov in (("polar", maps.coverage_polar), ("healpix", maps.coverage_healpix)):
        out = getattr(maps, name).reshape(-1, 3)
        assert np.isfinite(out).all()
        seen = cov.ravel() > 0
        # Renormalised over the valid contributions ...
        zero = out[:, 0] == 0
        np.testing.assert_allclose(out[seen & ~zero], level, rtol=1e-5)
        # ... and 0 only where every contributor is invalid (near an invalid fisheye pixel)
        dirs = (directions_from_angles(np.deg2rad(np.arange(90) + 0.5)[:, None],
                                       np.deg2rad(np.arange(360) + 0.5)[None, :]).reshape(-1, 3)
                if name == "polar" else pix2vec_nest(32, np.arange(npix(32))))
        uv = np.rint(_pixel_of(dirs[seen & zero], proj)).astype(int)
        assert invalid[uv[:, 1], uv[:, 0]].all()
    assert np.isfinite(maps.equirect).all()
    assert maps.equirect.max() < 2 * level


def test_all_black_and_a_single_hot_pixel(proj: Projector) -> None:
    zero = proj.project(np.zeros((H, W, 3), np.float32))
    for name in MAPS:
        assert not np.any(getattr(zero, name))
    img = np.zeros((H, W, 3), np.float32)
    img[60, 200] = 3.0e38  # full scale float32: must not overflow to inf
    hot = proj.project(img)
    for name in MAPS:
        assert np.isfinite(getattr(hot, name)).all()
    img[60, 200] = 1e4
    hot = proj.project(img)
    g = proj.pixel_gain.reshape(H, W)[60, 200]
    expect = 1e4 * g * proj.pixel_solid_angle[60, 200]
    for name in ("equirect", "healpix", "polar"):
        np.testing.assert_allclose(_energy(proj, hot, name), expect, rtol=1e-3, err_msg=name)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), exponent=st.floats(-6, 6))
def test_energy_is_conserved_for_any_image(proj: Projector, seed: int, exponent: float) -> None:
    rng = np.random.default_rng(seed)
    img = (rng.random((H, W, 3)) ** 4 * 10.0**exponent).astype(np.float32)
    maps = proj.project(img)
    expect = ((proj.pixel_gain * proj.pixel_solid_angle.ravel())[:, None]
              * img.reshape(-1, 3).astype(np.float64)).sum(axis=0)
    for name in ("equirect", "healpix"):
        np.testing.assert_allclose(_energy(proj, maps, name), expect, rtol=2e-4)


# -- lower hemisphere policies --------------------------------------------------------------------
@pytest.mark.parametrize("lower", ["zero", "mirror", "mean-horizon"])
def test_lower_hemisphere_policies(lower: str) -> None:
    cal = _calibration(vignetting=False)
    p = Projector(cal, polar_height=10, equirect_height=64, nside=8, lower=lower,
                  ground_albedo=0.25)
    theta = np.pi * (np.arange(64) + 0.5) / 64
    ramp = np.zeros((H, W, 3), np.float32)
    ramp[:] = np.arange(H, dtype=np.float32)[:, None, None] / SCALE + 1  # varies with elevation
    eq = p.project_equirect(ramp)
    below = theta > np.deg2rad(95)
    assert np.isfinite(eq).all()
    if lower == "zero":
        assert not np.any(eq[below])
    elif lower == "mirror":
        rows = np.flatnonzero(below)
        np.testing.assert_allclose(eq[rows], 0.25 * eq[63 - rows], rtol=1e-6)
    else:
        band = p._horizon_rows
        mean = eq[band].reshape(-1, 3).mean(axis=0)
        np.testing.assert_allclose(eq[below], np.broadcast_to(mean, eq[below].shape), rtol=1e-5)
        assert np.ptp(eq[below]) < 1e-4 * eq[below].max()


# -- bad input -----------------------------------------------------------------------------------
def test_bad_input_raises_input_error(proj: Projector) -> None:
    with pytest.raises(InputError, match="shape"):
        proj.project(np.zeros((H, W + 1, 3), np.float32))
    with pytest.raises(InputError, match="valid"):
        proj.project(np.zeros((H, W, 3), np.float32), np.ones((H, 3), bool))
    with pytest.raises(InputError, match="fisheye"):
        Projector(Calibration())
    with pytest.raises(InputError, match="lower"):
        Projector(_calibration(), lower="sky")
    with pytest.raises(InputError, match="nside"):
        Projector(_calibration(), nside=48)


def test_tables_are_memoised_per_calibration_and_read_only(proj: Projector) -> None:
    again = Projector(_calibration(), equirect_height=128, nside=32)
    assert again._tables is proj._tables
    fresh = Projector(_calibration(), equirect_height=128, nside=32, cache=False)
    assert fresh._tables is not proj._tables
    np.testing.assert_array_equal(fresh._tables["healpix"].data, proj._tables["healpix"].data)
    with pytest.raises(ValueError, match="read-only"):
        proj.coverage_polar[0, 0] = 0.5


@pytest.mark.parametrize("lower", ["zero", "mean-horizon"])
def test_a_lens_narrower_than_the_hemisphere(lower: str) -> None:
    cal = _calibration()
    fe = cal.fisheye
    narrow = cal.with_(fisheye=FisheyeModel(fe.image_size, fe.K, fe.D, fov_deg=160.0))
    p = Projector(narrow, polar_height=18, equirect_height=36, nside=8, lower=lower)
    cov = p.coverage_polar  # rows of 5 deg; the lens sees to 79.5 deg
    assert np.all(cov[:15] == 1.0)
    assert np.all(cov[16] < 0.01)  # pixel corners just past 80 deg
    assert np.all(cov[17:] == 0.0)
    level = 1.5
    maps = p.project(_measured(p, np.full((H, W, 3), level, np.float32)))
    for name in MAPS:
        assert np.isfinite(getattr(maps, name)).all()
    np.testing.assert_allclose(maps.polar[cov > 0], level, rtol=1e-5)
    assert not np.any(maps.polar[cov == 0])
    if lower == "mean-horizon":  # the unseen band, the horizon and the ground take the mean
        np.testing.assert_allclose(maps.equirect, level, rtol=1e-5)


def test_disk_cache_restores_identical_tables(tmp_path):  # type: ignore[no-untyped-def]
    """A restart loads the tables from the state dir instead of rebuilding them."""
    from lightprobe.device.projection import Projector
    from lightprobe.device.projection.diskcache import cache_path

    cal = _calibration()
    first = Projector(cal, equirect_height=32, nside=8, cache=False, cache_dir=tmp_path)
    files = list(tmp_path.glob("projection-*.npz"))
    assert len(files) == 1
    again = Projector(cal, equirect_height=32, nside=8, cache=False, cache_dir=tmp_path)
    img = np.random.default_rng(1).random((*first.lens_mask.shape, 3)).astype(np.float32)
    a, b = first.project(img), again.project(img)
    for name in ("polar", "equirect", "healpix"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    # A damaged cache file is ignored and rebuilt, never used
    files[0].write_bytes(b"garbage")
    third = Projector(cal, equirect_height=32, nside=8, cache=False, cache_dir=tmp_path)
    np.testing.assert_array_equal(third.project(img).healpix, a.healpix)
    assert cache_path(tmp_path, ("x",)) != files[0]


def test_the_table_builds_sparse_assembly_matches_scipy() -> None:
    """The build assembles its CSR itself (a service that builds tables imports no scipy):
    duplicates summed, columns sorted, rows added, as scipy.sparse does it."""
    import scipy.sparse as sp

    from lightprobe.device.projection.tables import _add_rows, _assemble_csr, _Coo

    rng = np.random.default_rng(5)
    n, m = 40, 300
    parts, rows, cols, vals = [], [], [], []
    for lo in range(0, m, 60):  # parts over disjoint, increasing column ranges
        k = 500
        r = rng.integers(0, n - 5, k)  # the last rows stay empty
        c = rng.integers(lo, lo + 60, k)
        v = rng.random(k)
        parts.append(_Coo.summed(r, c, v, m))
        rows.append(r), cols.append(c), vals.append(v)
    ref = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, m))
    ref.sum_duplicates()
    W = _assemble_csr(parts, n, m)
    assert not parts  # consumed
    np.testing.assert_array_equal(W.indptr, ref.indptr)
    np.testing.assert_array_equal(W.indices, ref.indices)
    np.testing.assert_allclose(W.data, ref.data, rtol=1e-14)
    er = np.repeat(np.arange(n - 5, n), 3)
    ec, ev = rng.integers(0, m, er.size), rng.random(er.size)
    W2 = _add_rows(W, _Coo.summed(er, ec, ev, m))
    ref2 = (ref + sp.csr_matrix((ev, (er, ec)), shape=(n, m))).tocsr()
    ref2.sum_duplicates()
    np.testing.assert_array_equal(W2.indptr, ref2.indptr)
    np.testing.assert_array_equal(W2.indices, ref2.indices)
    np.testing.assert_allclose(W2.data, ref2.data, rtol=1e-14)


def test_sample_sharing_splits_a_regions_variance_exactly() -> None:
    """``sample_sharing``: output pixels that read the same fisheye pixels. Over a region holding
    every reader of its fisheye pixels, ``sum_j var(L_j) k_j`` is the region's variance exactly
    (independent unit-variance inputs); one reader per input gives 1; two equal readers 2."""
    from lightprobe.device.projection import sample_sharing

    rng = np.random.default_rng(5)
    n_out, n_in = 40, 25
    dense = rng.random((n_out, n_in)) * (rng.random((n_out, n_in)) < 0.2)
    dense[np.arange(n_out), rng.integers(0, n_in, n_out)] += 0.5  # every row reads something
    indptr = np.concatenate([[0], np.cumsum((dense > 0).sum(1))])
    indices = np.nonzero(dense)[1]
    k = sample_sharing(indptr, indices, dense[dense > 0], n_out)
    a = dense / dense.sum(1, keepdims=True)
    region_var = float((a.sum(0) ** 2).sum())  # var(sum_j L_j), L = a x, var x_i = 1
    assert np.isclose(float(((a**2).sum(1) * k).sum()), region_var, rtol=1e-12)
    assert np.all(k >= 1 - 1e-12)
    # the caller's row of each entry and row sums (the pipeline has them): the same answer
    row_of = np.repeat(np.arange(n_out), np.diff(indptr))
    assert np.allclose(sample_sharing(indptr, indices, dense[dense > 0], n_out, row_of, dense.sum(1)), k, rtol=1e-12)
    eye = np.arange(6)
    assert np.allclose(sample_sharing(np.arange(7), eye, np.ones(6), 6), 1.0)
    pairs = np.array([0, 2, 4, 6])  # rows 0 and 1 read inputs 0 and 1; row 2 alone reads 2 and 3
    assert np.allclose(sample_sharing(pairs, np.array([0, 1, 0, 1, 2, 3]), np.ones(6), 3), [2.0, 2.0, 1.0])
