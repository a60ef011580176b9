"""Conventions shared by every stage: directions, equirect solid angles, HEALPix NESTED, EXR I/O."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lightprobe.core import healpix as H
from lightprobe.core import sphere as S
from lightprobe.core.errors import InputError
from lightprobe.core.imageio import read_exr_header, read_hdr_image, write_exr


def test_direction_convention_matches_conventions_md():
    d = S.directions_from_angles(np.array([0.0, np.pi / 2, np.pi / 2]), np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(d, [[0, 1, 0], [0, 0, -1], [1, 0, 0]], atol=1e-15)


@given(st.floats(0, np.pi), st.floats(0, 2 * np.pi - 1e-9))
def test_angles_roundtrip(theta, phi):
    t, p = S.angles_from_directions(S.directions_from_angles(theta, phi))
    assert t == pytest.approx(theta, abs=1e-7)
    if 1e-6 < theta < np.pi - 1e-6:
        assert np.angle(np.exp(1j * (p - phi))) == pytest.approx(0, abs=1e-7)


@pytest.mark.parametrize("h", [1, 3, 90, 512])
def test_equirect_solid_angle_sums_to_4pi(h):
    assert S.equirect_solid_angle(h).sum() == pytest.approx(4 * np.pi, rel=1e-12)
    assert S.equirect_solid_angle(h, 4 * h).sum() == pytest.approx(4 * np.pi, rel=1e-12)


def test_equirect_integral_of_constant_is_4pi_float64_even_for_float32_input():
    img = np.full((512, 1024, 3), 1e-3, np.float32)
    np.testing.assert_allclose(S.equirect_integral(img), 4e-3 * np.pi, rtol=1e-6)


@pytest.mark.parametrize("nside", [1, 2, 16, 64, 512])
def test_healpix_matches_healpy_reference(nside):
    hp = pytest.importorskip("healpy")
    p = np.arange(H.npix(nside)) if nside <= 64 else np.random.default_rng(0).integers(0, H.npix(nside), 50000)
    theta, phi = H.pix2ang_nest(nside, p)
    t2, p2 = hp.pix2ang(nside, p, nest=True)
    np.testing.assert_allclose(theta, t2, atol=1e-9)
    assert np.abs(np.angle(np.exp(1j * (phi - p2)))).max() < 1e-9
    rng = np.random.default_rng(nside)
    t = np.arccos(rng.uniform(-1, 1, 200000))
    f = rng.uniform(0, 2 * np.pi, 200000)
    np.testing.assert_array_equal(H.ang2pix_nest(nside, t, f), hp.ang2pix(nside, t, f, nest=True))


def test_healpix_children_are_contiguous_and_inside_parent():
    parent = H.vec2pix_nest(8, H.pix2vec_nest(16, np.arange(H.npix(16))))
    np.testing.assert_array_equal(parent, np.arange(H.npix(16)) // 4)


def test_healpix_poles_and_seam():
    for nside in (1, 64):
        assert H.ang2pix_nest(nside, 0.0, 0.0) < 4 * nside * nside
        assert H.ang2pix_nest(nside, np.pi, 0.0) >= 8 * nside * nside
        assert H.ang2pix_nest(nside, 1.0, 2 * np.pi) == H.ang2pix_nest(nside, 1.0, 0.0)


def test_exr_roundtrip_with_metadata(tmp_path):
    img = np.random.default_rng(0).random((7, 14, 3)).astype(np.float32) * 1e4
    write_exr(tmp_path / "m.exr", img, {"unit": "relative", "probe": "abc"})
    np.testing.assert_array_equal(read_hdr_image(tmp_path / "m.exr"), img)
    assert read_exr_header(tmp_path / "m.exr")["unit"] == "relative"


def test_reads_shared_maps(envmap_paths):
    for p in envmap_paths.values():
        img = read_hdr_image(p)
        assert img.shape == (512, 1024, 3)
        assert img.dtype == np.float32


def test_bad_image_names_the_file(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(InputError, match=r"bad\.exr"):
        read_hdr_image(bad)
    with pytest.raises(InputError, match=r"missing\.hdr"):
        read_hdr_image(tmp_path / "missing.hdr")


@pytest.mark.parametrize(("height", "nside"), [(90, 16), (256, 64), (512, 64), (16, 64)])
def test_equirect_to_healpix_conserves_energy_exactly(height, nside):
    rng = np.random.default_rng(height)
    img = (rng.random((height, 2 * height, 3)) ** 8 * 1e3).astype(np.float32)
    img[height // 3, height // 2] = 1e6  # a sun in one pixel
    hp = H.equirect_to_healpix(img, nside)
    assert hp.shape == (H.npix(nside), 3)
    assert hp.dtype == np.float32
    total = hp.astype(np.float64).sum(axis=0) * H.pixel_solid_angle(nside)
    if height >= 90:  # fine enough that no HEALPix pixel is a hole: exact
        np.testing.assert_allclose(total, S.equirect_integral(img), rtol=1e-6)
    back = H.healpix_to_equirect(hp, 64)
    np.testing.assert_allclose(S.equirect_integral(back), total, rtol=1e-6)


def test_equirect_to_healpix_constant_map_stays_near_constant():
    hp = H.equirect_to_healpix(np.ones((256, 512, 3), np.float32), 64)
    assert np.all(np.isfinite(hp))
    assert abs(hp.mean() - 1) < 1e-6
    assert hp.std() < 0.03  # boundary quantisation texture, documented


def test_healpix_sun_lands_in_its_pixel():
    img = np.zeros((256, 512, 3), np.float32)
    img[40, 100] = 1.0
    hp = H.equirect_to_healpix(img, 16)
    theta = np.pi * 40.5 / 256
    phi = 2 * np.pi * 100.5 / 512
    assert np.argmax(hp[:, 0]) == H.ang2pix_nest(16, theta, phi)
