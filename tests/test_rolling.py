"""The rolling HDR estimate (device/hdr/rolling.py) on a synthetic camera: every output pixel sees
16 fisheye pixels with equal weights, a linear 8-bit response, Poisson-like noise. What is
asserted is what the live pipeline relies on: a static scene fuses to its radiance from any
exposures that measure it, a change is in the fused map in the frame that shows it (never
averaged with what was there), a sun smaller than an output pixel keeps its energy, a pixel
saturated in every exposure holds its highest lower bound, and the float32-stored running sums
do not drift from a fresh sum."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from lightprobe.device.hdr.fusion import FusionSettings, packed_lut
from lightprobe.device.hdr.rolling import RollingMerge, _resum, frame_to_map, lut_bounds

K = 16  # fisheye samples per output pixel
LINEAR = np.repeat(np.linspace(0.0, 1.0, 256)[:, None], 3, axis=1)


def _table(pixels: int) -> tuple[SimpleNamespace, np.ndarray, np.ndarray]:
    indptr = np.arange(0, (pixels + 1) * K, K, dtype=np.int64)
    indices = np.arange(pixels * K, dtype=np.int64)
    data = np.full(pixels * K, 1.0 / K, np.float32)
    return SimpleNamespace(indptr=indptr, indices=indices, data=data), data.copy(), np.ones(pixels, np.float64)


def _lut(t: float) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    lut = packed_lut(LINEAR, t, 1.0, black=0.0, sat=255.0, settings=FusionSettings())
    return lut, lut_bounds(lut)


def _codes(radiance: np.ndarray, t: float, rng: np.random.Generator) -> np.ndarray:
    """(pixels * K, 3) uint8 of per-sample radiance (pixels * K, 3) at exposure t (full scale 1)."""
    signal = radiance * t
    electrons = rng.poisson(np.clip(signal, 0, 2.0) * 4000.0) / 4000.0  # ~4000 e- full well
    return np.clip(np.round(electrons * 255.0), 0, 255).astype(np.uint8)


def _run(merge: RollingMerge, table, geo_n, gain, radiance: np.ndarray, exposures: list[float],
         frames: int, rng: np.random.Generator, start: int = 0) -> np.ndarray:
    fused = None
    for f in range(start, start + frames):
        t = exposures[f % len(exposures)]
        lut, bounds = _lut(t)
        fused = merge.update((t, 1.0), f, table, geo_n, gain, _codes(radiance, t, rng), lut, bounds)
    assert fused is not None
    return fused.copy()


def _scene(pixels: int, rng: np.random.Generator) -> np.ndarray:
    """Per-pixel radiance over four decades (grey), constant over each footprint."""
    level = np.logspace(-1, 2.9, pixels)  # the top within the shortest exposure's range
    rng.shuffle(level)
    return np.repeat(np.repeat(level[:, None], 3, axis=1), K, axis=0)


EXPOSURES = [1.0 / 1024, 1.0 / 128, 1.0 / 16, 1.0 / 2]


def test_a_static_scene_fuses_to_its_radiance_over_four_decades() -> None:
    rng = np.random.default_rng(1)
    pixels = 400
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels)
    fused = _run(merge, table, geo_n, gain, radiance, EXPOSURES, 40, rng)
    truth = radiance[::K]
    rel = np.abs(fused - truth) / truth
    assert np.median(rel) < 0.01, np.median(rel)
    assert rel.max() < 0.08, rel.max()  # the dimmest pixels: ~13 codes in the longest exposure
    assert not merge.bounded.any()


def test_a_change_is_in_the_fused_map_in_the_frame_that_shows_it() -> None:
    rng = np.random.default_rng(2)
    pixels = 400
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels)
    _run(merge, table, geo_n, gain, radiance, EXPOSURES, 40, rng)
    lit = radiance.copy()
    on = np.zeros(pixels, bool)
    on[:100] = True
    lit[np.repeat(on, K)] *= 4.0  # a lamp adds three times what was there
    # one frame of the shortest exposure: every pixel it measures well shows the new value now
    fused = _run(merge, table, geo_n, gain, lit, EXPOSURES[:1], 1, rng, start=40)
    truth = lit[::K]
    measured = (truth[:, 0] * EXPOSURES[0] > 0.05) & (truth[:, 0] * EXPOSURES[0] < 0.9)  # well exposed
    rel = np.abs(fused - truth) / truth
    assert (on & measured).sum() > 20
    assert np.median(rel[on & measured]) < 0.03, np.median(rel[on & measured])
    assert rel[on & measured].max() < 0.1, rel[on & measured].max()  # none averaged with the old value
    # and the lamp switched off again, shown by the next longest exposure
    fused = _run(merge, table, geo_n, gain, radiance, EXPOSURES[1:2], 1, rng, start=41)
    truth = radiance[::K]
    measured = (truth[:, 0] * EXPOSURES[1] > 0.05) & (truth[:, 0] * EXPOSURES[1] < 0.9)
    rel = np.abs(fused - truth) / truth
    assert np.median(rel[on & measured]) < 0.03, np.median(rel[on & measured])


def test_the_unchanged_scene_is_not_flagged_as_changed() -> None:
    rng = np.random.default_rng(3)
    pixels = 400
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels)
    _run(merge, table, geo_n, gain, radiance, EXPOSURES, 40, rng)
    flagged = 0
    for f in range(40, 80):
        _run(merge, table, geo_n, gain, radiance, EXPOSURES, 1, rng, start=f)
        flagged += int(merge.changed.sum())
    assert flagged / (40 * pixels) < 0.002, flagged


def test_a_sun_smaller_than_an_output_pixel_keeps_its_energy() -> None:
    """One sample in 16 is 1e5 times the sky around it: the long exposures see it saturated
    (censored, only a lower bound), the shortest measures it with the sky too dark to weigh."""
    rng = np.random.default_rng(4)
    pixels = 50
    radiance = np.full((pixels * K, 3), 0.5)
    radiance[::K] = 5e4  # the first sample of every footprint
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels)
    fused = _run(merge, table, geo_n, gain, radiance, [1.0 / 65536, 1.0 / 1024, 1.0 / 16, 1.0], 40, rng)
    truth = radiance.reshape(pixels, K, 3).mean(axis=1)
    rel = np.abs(fused - truth) / truth
    assert np.median(rel) < 0.02, np.median(rel)
    assert rel.max() < 0.06, rel.max()


def test_a_pixel_saturated_in_every_exposure_holds_its_lower_bound() -> None:
    rng = np.random.default_rng(5)
    pixels = 20
    radiance = np.full((pixels * K, 3), 0.5)
    radiance[: 10 * K] = 1e7  # beyond the shortest exposure
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels)
    fused = _run(merge, table, geo_n, gain, radiance, EXPOSURES, 12, rng)
    assert merge.bounded[:10].all()
    assert not merge.bounded[10:].any()
    _lut_table, (_dark, top) = _lut(EXPOSURES[0])
    # at least what the shortest exposure reads at saturation, never zero or the sky
    assert np.all(fused[:10] >= 0.99 * top), (fused[:10, 0], top)
    assert np.allclose(fused[10:], 0.5, rtol=0.05)


def test_running_sums_do_not_drift_from_a_fresh_sum() -> None:
    rng = np.random.default_rng(6)
    pixels = 300
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    merge = RollingMerge(pixels, resum_every=10_000)  # no periodic rebuild in this run
    _run(merge, table, geo_n, gain, radiance, EXPOSURES, 250, rng)
    num, den = merge.num.copy(), merge.den.copy()
    _resum(merge.m, merge.p, len(merge.keys), merge.num, merge.den)
    assert (den > 0).all()
    np.testing.assert_allclose(num / den, merge.num / merge.den, rtol=1e-5)


@pytest.mark.parametrize("t", EXPOSURES)
def test_frame_to_map_is_the_merge_of_one_frame(t: float) -> None:
    """The standalone per-frame map and the merge's first frame agree where the frame measures."""
    rng = np.random.default_rng(7)
    pixels = 200
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    codes = _codes(radiance, t, rng)
    lut, bounds = _lut(t)
    fm = frame_to_map(table, geo_n, gain, codes, lut, bounds, pixels)
    merge = RollingMerge(pixels)
    fused = merge.update((t, 1.0), 0, table, geo_n, gain, codes, lut, bounds)
    ok = np.isfinite(fm.var) & (fm.sat == 0) & (fm.dark == 0)
    assert ok.sum() > 50
    np.testing.assert_allclose(fused[ok], fm.m[ok], rtol=1e-5)
    # censored pixels report their lower bound, measured ones none
    assert np.all(fm.lower[fm.sat > 0] > 0)
    assert np.all(fm.lower[fm.sat == 0] == 0)


def test_by_response_fuses_the_slots_by_the_response_weights() -> None:
    """A measured (JPEG) response: the slots are fused by the footprint's mean of its samples'
    LUT weights (h(z) / sigma_core(z)^2), as the offline fusion weighs exposures, while the
    change test keeps the precisions (which hold the black floor). Brute force: each frame's
    map (frame_to_map) and the weights read off the LUT at the codes, averaged here."""
    rng = np.random.default_rng(8)
    pixels = 300
    radiance = _scene(pixels, rng)
    table, geo_n, gain = _table(pixels)
    z = np.arange(256, dtype=np.float64)
    sigma = np.repeat((0.01 + 0.05 * np.exp(-z / 20.0) + 0.04 * (z / 255.0) ** 8)[:, None], 3, axis=1)
    core = 0.6 * sigma
    exposures = [1.0 / 256, 1.0 / 32]

    def lut(t: float) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        lt = packed_lut(LINEAR, t, 1.0, black=0.0, sat=255.0, settings=FusionSettings(), log_sigma=sigma,
                        log_sigma_core=core, black_floor=True)
        return lt, lut_bounds(lt)

    frames = [(t, _codes(radiance, t, rng)) for t in exposures]
    fused = {}
    for by in (True, False):
        merge = RollingMerge(pixels, by_response=by, decay=0.0)
        for f, (t, codes) in enumerate(frames):
            out = merge.update((t, 1.0), f, table, geo_n, gain, codes, *lut(t))
        assert not merge.changed.any()
        fused[by] = out.copy()
    num = np.zeros((pixels, 3))
    den = np.zeros((pixels, 3))
    for t, codes in frames:
        lt, bounds = lut(t)
        fm = frame_to_map(table, geo_n, gain, codes, lt, bounds, pixels)
        w = lt[codes.astype(np.int64), np.arange(3)[None, :], 1].astype(np.float64)  # (samples, 3)
        w = np.where(lt[codes.astype(np.int64), np.arange(3)[None, :], 3] > 0, 0.0, w)
        wmean = w.reshape(pixels, K, 3).mean(axis=1)
        use = np.isfinite(fm.var) & (fm.sat == 0)
        num += np.where(use, wmean * fm.m, 0.0)
        den += np.where(use, wmean, 0.0)
    both = den > 0
    assert both.mean() > 0.5
    expect = num[both] / den[both]
    np.testing.assert_allclose(fused[True][both], expect, rtol=2e-5)
    # and it is not what the precisions give (the test would not see a merge that ignored it)
    assert np.abs(fused[False][both] / expect - 1.0).max() > 1e-3

    # over a long run with changes, the weights' running sums hold what a fresh sum gives
    merge = RollingMerge(pixels, by_response=True, resum_every=10_000)
    for f in range(200):
        t = exposures[f % 2]
        scene = radiance * (1.0 if (f // 37) % 2 == 0 else 1.5)  # a change every 37 frames
        merge.update((t, 1.0), f, table, geo_n, gain, _codes(scene, t, rng), *lut(t))
    numw, denw = merge.numw.copy(), merge.denw.copy()
    _resum(merge.m, merge.p, len(merge.keys), merge.num, merge.den, merge.w, merge.numw, merge.denw)
    ok = merge.denw > 0
    assert ok.mean() > 0.5
    np.testing.assert_allclose(numw[ok] / denw[ok], merge.numw[ok] / merge.denw[ok], rtol=1e-5)
    np.testing.assert_allclose(denw, merge.denw, rtol=1e-4, atol=1e-6 * merge.denw.max())
