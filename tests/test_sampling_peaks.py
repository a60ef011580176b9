"""Peak detection (threshold + connected components on the sphere) and light-count choice."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.errors import InputError
from lightprobe.core.imageio import read_hdr_image
from lightprobe.core.sphere import (
    coarse_equirect,
    directions_from_angles,
    equirect_integral,
    equirect_row_solid_angle,
    luminance,
)
from lightprobe.device.sampling.metrics import ErrorReference
from lightprobe.device.sampling.peaks import choose_light_count, find_peaks
from lightprobe.device.sampling.q2tree import Q2TreeSampler
from lightprobe.sim.scene import rasterize_disc

H = 256
DISCS = [  # (theta deg, phi deg, radius deg, grey radiance): one plain, one across phi = 0,
    (60.0, 100.0, 3.0, 500.0),  # one over the zenith
    (115.0, 359.0, 5.0, 200.0),
    (1.5, 40.0, 4.0, 300.0),
]


def _disc_map(background: float = 0.1, discs: list[tuple[float, float, float, float]] = DISCS
              ) -> tuple[np.ndarray, list[np.ndarray], list[float]]:
    img = np.full((H, 2 * H, 3), background, np.float32)
    dirs, energies = [], []
    omega = equirect_row_solid_angle(H)
    for th, ph, r, radiance in discs:
        d = directions_from_angles(np.radians(th), np.radians(ph))
        rows, cols, frac = rasterize_disc(H, d, np.radians(r))
        img[rows, cols] += (frac * radiance).astype(np.float32)[:, None]
        dirs.append(d)
        energies.append(float(np.sum(frac * omega[rows]) * radiance))
    return img, dirs, energies


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_known_discs_are_found_with_their_energy_and_direction() -> None:
    img, dirs, energies = _disc_map()
    peaks = find_peaks(img)
    assert len(peaks) == 3  # the seam and the pole do not split a disc
    for d, e in zip(dirs, energies, strict=True):
        best = min(peaks, key=lambda p: _angle_deg(p.direction, d))
        assert _angle_deg(best.direction, d) < 0.2
        # the integral of the component: the disc plus the background under it
        grey = best.rgb.mean()
        assert abs(grey - e) / e < 0.02
        np.testing.assert_allclose(best.rgb, grey, rtol=1e-6)
        assert best.pixel_count > 10
        assert best.solid_angle > 0
    order = [p.energy_fraction for p in peaks]
    assert order == sorted(order, reverse=True)
    total = float(luminance(equirect_integral(img)))
    assert sum(order) == pytest.approx(sum(energies) / total, rel=0.02)
    json.dumps([p.to_json() for p in peaks])


def test_threshold_parameter_and_degenerate_maps() -> None:
    img, _, _ = _disc_map()
    assert len(find_peaks(img, threshold=350.0)) == 1  # only the 500-radiance disc is that bright
    assert find_peaks(np.zeros((64, 128, 3), np.float32)) == []
    assert find_peaks(np.full((64, 128, 3), 3.0, np.float32)) == []  # uniform: no peak
    nan_map = img.copy()
    nan_map[:10] = np.nan  # rows 0-9 cover theta < 7 deg: the whole zenith disc
    nan_map[100, 100] = -1e6
    assert len(find_peaks(nan_map)) == 2  # the zenith disc is gone with the NaN rows
    hot = np.full((64, 128, 3), 0.5, np.float32)
    hot[30, 70] = 1e9
    (p,) = find_peaks(hot)
    assert p.pixel_count == 1
    assert p.energy_fraction > 0.99
    with pytest.raises(InputError):
        find_peaks(np.ones((64, 64, 3), np.float32))


def test_studio_lamps(envmap_paths: dict[str, Path]) -> None:
    img = read_hdr_image(envmap_paths["studio_small_03_1k.hdr"])
    peaks = find_peaks(img)
    assert 1 <= len(peaks) <= 8
    # small bright lamps: the peaks hold most of the energy on a tiny part of the sphere
    assert sum(p.energy_fraction for p in peaks) > 0.6
    assert sum(p.solid_angle for p in peaks) < 0.01 * 4 * np.pi
    lum = luminance(img)
    h, w = lum.shape
    for p in peaks[:2]:
        theta = np.arccos(p.direction[1])
        phi = np.arctan2(p.direction[0], -p.direction[2]) % (2 * np.pi)
        r, c = int(theta / np.pi * h), int(phi / (2 * np.pi) * w)
        assert lum[r, c] > 0.01 * lum.max()  # the centroid lies on the lamp


def test_a_probe_hemisphere_has_the_peaks_of_its_sky(envmap_paths: dict[str, Path]) -> None:
    """A probe's map holds light in its upper half only: its peaks stand out against the mean of
    that half. Against the sphere's mean (half as bright) lebombo's open sky came out as seven
    peaks with 17% of the energy, where the whole map has none; the studio keeps its lamps."""
    for name, most in (("lebombo_1k.hdr", 0), ("studio_small_03_1k.hdr", 8)):
        img = read_hdr_image(envmap_paths[name])
        hemi = img.copy()
        hemi[img.shape[0] // 2:] = 0
        whole, upper = find_peaks(img), find_peaks(hemi)
        assert len(upper) <= max(most, len(whole)), (name, len(upper), len(whole))
        if most:
            assert sum(p.energy_fraction for p in upper) > 0.6, name
        assert find_peaks(hemi, threshold=0.0)  # an explicit threshold is taken as given


def _q2(img: np.ndarray):  # type: ignore[no-untyped-def]
    q2 = Q2TreeSampler(hysteresis=0.0)  # zero hysteresis: each count equals a fresh build
    return lambda c: q2.sample(img, c)


def test_choose_light_count_uses_fewer_lights_when_peaks_dominate() -> None:
    img, _, _ = _disc_map(background=0.02, discs=[(60.0, 100.0, 3.0, 2000.0)])
    count, peaks = choose_light_count(img, 256, 0.01, sample=_q2(img))
    assert len(peaks) == 1
    assert peaks[0].energy_fraction > 0.8
    assert count < 256
    exact = ErrorReference(img).error("diffuse", Q2TreeSampler().sample(img, count))
    assert exact <= 0.015  # the target, judged on a 64 x 128 reduction of the map
    # a tighter target needs more lights
    more, _ = choose_light_count(img, 256, 1e-4, sample=_q2(img))
    assert more > count


def test_choose_light_count_keeps_max_without_peaks() -> None:
    smooth = np.ones((128, 256, 3), np.float32)
    smooth *= (1.0 + np.linspace(0, 1, 128, dtype=np.float32))[:, None, None]
    assert choose_light_count(smooth, 200, 0.5, sample=_q2(smooth))[0] == 200
    assert choose_light_count(np.zeros((64, 128, 3), np.float32), 50, 0.1, sample=_q2(smooth)) == (50, [])
    with pytest.raises(InputError):
        choose_light_count(smooth, 0, 0.1, sample=_q2(smooth))


def test_q2tree_publishes_peaks_and_uses_error_target() -> None:
    img, _, _ = _disc_map(background=0.02, discs=[(60.0, 100.0, 3.0, 2000.0)])
    ls = Q2TreeSampler(error_target=0.01).sample(img, 256)
    assert len(ls) < 256
    assert len(ls.extra["peaks"]) == 1
    np.testing.assert_allclose(ls.total, equirect_integral(img), rtol=1e-9)
    json.dumps(ls.to_json())


def test_coarse_equirect_conserves_energy() -> None:
    img, _, _ = _disc_map()
    small = coarse_equirect(img, 64)
    assert small.shape == (64, 128, 3)
    np.testing.assert_allclose(equirect_integral(small), equirect_integral(img), rtol=1e-6)
