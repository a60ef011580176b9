"""Debevec-Malik response recovery (lightprobe.calibration.response, the one solver)."""

from __future__ import annotations

import numpy as np
import pytest

from lightprobe.calibration.response import fit_stack, pair_bins, response_from_stack, solve_debevec
from lightprobe.core.errors import InputError


def _stack(gamma: tuple[float, float, float], seed: int = 0) -> tuple[list[np.ndarray], list[float]]:
    rng = np.random.default_rng(seed)
    x = np.exp(rng.uniform(np.log(1e-3), np.log(1.0), (120, 160, 3)))
    times = [0.02, 0.08, 0.32, 1.28, 5.12]
    g = np.asarray(gamma)
    frames = [np.rint(255 * np.clip(x * t, 0, 1) ** (1 / g)).astype(np.uint8) for t in times]
    return frames, times


def test_recovers_a_known_response_up_to_scale() -> None:
    gamma = (2.0, 2.2, 2.6)
    frames, times = _stack(gamma)
    resp = solve_debevec(frames, times)
    assert resp.inverse.shape == (256, 3)
    assert np.all(np.diff(resp.inverse, axis=0) >= 0)
    z = np.arange(256) / 255.0
    for c, gc in enumerate(gamma):
        truth = z**gc
        sel = slice(20, 250)
        ratio = resp.inverse[sel, c] / truth[sel]
        # One free scale per channel (Debevec fixes g(128) = 0): the ratio must be flat
        assert np.std(np.log(ratio)) < 0.03, c


def test_deterministic_and_works_on_tiny_images() -> None:
    frames, times = _stack((2.2, 2.2, 2.2))
    small = [f[:6, :7] for f in frames]
    a = solve_debevec(small, times)
    b = solve_debevec(small, times)
    np.testing.assert_array_equal(a.inverse, b.inverse)
    assert np.isfinite(a.inverse).all()
    assert a.log_sigma is not None
    assert np.isfinite(a.log_sigma).all()
    assert pair_bins(small, times, 0).count.sum() <= 42 * (len(times) - 1)  # 42 pixels, 4 pairs


def test_needs_two_exposures_and_positive_times() -> None:
    frames, times = _stack((2.2, 2.2, 2.2))
    with pytest.raises(InputError, match="at least 2"):
        solve_debevec(frames[:1], times[:1])
    with pytest.raises(InputError, match="positive"):
        solve_debevec(frames[:2], [0.1, -1.0])


def test_nominal_exposure_labels_are_corrected_from_the_pictures() -> None:
    """Two middle labels off as a camera's are (1/15 s for 2^-4 s: 6.7%): the fit finds the
    effective exposures (up to the level and span it holds to the labels) and the response
    comes out as exact as with true labels; ``solve_debevec`` (a calibration's response, used
    later with the driver's exposures) keeps the labels."""
    gamma = (2.0, 2.2, 2.6)
    frames, true = _stack(gamma, seed=3)
    labels = list(true)
    labels[2], labels[3] = true[2] / 1.067, true[3] * 1.055
    fit = fit_stack(frames, labels)
    assert fit.refined.all()
    assert fit.rejected_correction == 1.0
    np.testing.assert_allclose(fit.labels_s, labels)
    lt = np.log(true)
    basis = np.stack([np.ones_like(lt), lt], axis=1)

    def off(exposures: np.ndarray) -> float:  # log error after the best level and span
        r = np.log(exposures) - lt
        return float(np.max(np.abs(r - basis @ np.linalg.lstsq(basis, r, rcond=None)[0])))

    assert off(np.asarray(labels)) > 0.03
    assert off(fit.exposures_s) < 0.004, np.log(fit.corrections)
    z = np.arange(256) / 255.0
    sel = slice(20, 250)
    flat = [float(np.std(np.log(fit.response.inverse[sel, c] / z[sel] ** gc))) for c, gc in enumerate(gamma)]
    held = solve_debevec(frames, labels)
    flat_held = [float(np.std(np.log(held.inverse[sel, c] / z[sel] ** gc))) for c, gc in enumerate(gamma)]
    assert max(flat) < 0.02, flat
    assert max(flat) < 0.5 * max(flat_held), (flat, flat_held)


def test_labels_that_do_not_belong_to_the_pictures_are_kept_and_flagged() -> None:
    """Times given in the wrong order ask for corrections beyond a factor 2: the fit keeps every
    label (and says how far off the pictures put them) rather than invent exposures."""
    frames, true = _stack((2.2, 2.2, 2.2), seed=5)
    labels = [true[1], true[0], true[3], true[2], true[4]]
    fit = fit_stack(frames, labels)
    assert fit.rejected_correction > 2.0
    assert not fit.refined.any()
    np.testing.assert_array_equal(fit.exposures_s, labels)


def test_a_stack_that_does_not_brighten_with_its_labels_is_refused() -> None:
    """Auto-exposure left on (the same picture at every label) or another stack's times: no
    response can be fitted, and the error says why rather than invent corrections."""
    frames, true = _stack((2.2, 2.2, 2.2), seed=9)
    mid = frames[len(frames) // 2]
    rng = np.random.default_rng(0)
    flat = [np.clip(mid.astype(int) + rng.integers(-1, 2, mid.shape), 0, 255).astype(np.uint8) for _ in frames]
    for stack in ([mid] * len(frames), flat, frames[::-1]):
        with pytest.raises(InputError, match="do not get brighter with exposure time") as e:
            fit_stack(stack, true)
        assert e.value.param == "times"
        with pytest.raises(InputError, match="do not get brighter with exposure time"):  # Robertson too
            response_from_stack(stack, true, method="robertson")
    fit_stack(frames, true)  # the real bracket passes


def test_white_and_black_frames_keep_their_labels() -> None:
    """A frame with next to nothing well exposed (white or black) has nothing to say about its
    exposure: its label stands; a stack of fewer than three informative frames, or a thumbnail,
    is not refined."""
    frames, true = _stack((2.2, 2.2, 2.2), seed=7)
    frames = [np.full_like(frames[0], 255), *frames, np.zeros_like(frames[0])]
    times = [true[-1] * 64, *true, true[0] / 64]
    fit = fit_stack(frames, times)
    assert not fit.refined[0]
    assert not fit.refined[-1]
    assert fit.refined[1:-1].all()
    assert fit.corrections[0] == 1.0
    assert fit.corrections[-1] == 1.0
    two = fit_stack(frames[:3], times[:3])
    assert not two.refined.any()
    thumb = fit_stack([f[:2, :2] for f in frames], times)  # 4 pixels say nothing about an exposure
    assert not thumb.refined.any()
    np.testing.assert_array_equal(thumb.exposures_s, times)


def test_scatter_core_is_the_typical_sample_spread_and_rms_holds_the_tails() -> None:
    """A bracket whose samples scatter log-normally (sigma 0.03) with one in twenty thrown far off
    (a leaf that moved, sigma 0.5): ``log_sigma_core`` finds the typical spread, ``log_sigma`` (the
    rms) the tails too; both survive the JSON round trip."""
    from lightprobe.calibration.response import code_scatter
    from lightprobe.core.calibration import Response

    rng = np.random.default_rng(5)
    x = np.exp(rng.uniform(np.log(2e-3), np.log(1.0), (200, 240, 3)))
    times = [0.25, 0.5, 1.0, 2.0, 4.0]
    frames = []
    for t in times:
        eps = rng.normal(0.0, 0.03, x.shape) + np.where(rng.random(x.shape) < 0.05, rng.normal(0.0, 0.5, x.shape), 0)
        frames.append(np.rint(255 * np.clip(x * t * np.exp(eps), 0, 1) ** (1 / 2.2)).astype(np.uint8))
    z = np.arange(256) / 255.0
    inverse = np.repeat((z**2.2)[:, None], 3, axis=1)
    rms, core = code_scatter(frames, times, inverse)
    mid = slice(60, 220)  # quantisation (2.2 / z per code / sqrt(12) <= 0.011 here) adds little
    q = 2.2 / np.arange(256)[mid, None] / np.sqrt(12)
    typical = np.sqrt(0.03**2 + q**2)
    # the 68% half-width of this mixture is ~1.15 sigma of its core (a tenth of the pairs hold an
    # outlier), the rms ~2.5 sigma; per code it is estimated from ~700 pixels
    ratio = core[mid] / typical
    assert ratio.min() > 0.85, ratio.min()
    assert ratio.max() < 1.6, ratio.max()  # the rms would be ~2.5
    assert np.median(ratio) < 1.3, np.median(ratio)
    assert np.all(rms[mid] > 1.5 * core[mid]), (rms[mid] / core[mid]).min()
    resp = Response("table", 8, inverse, "debevec", rms, core)
    back = Response.from_json(resp.to_json())
    np.testing.assert_allclose(back.log_sigma_core, core, atol=1e-6)
    np.testing.assert_allclose(back.normalised().log_sigma_core, core, atol=1e-6)
    bad = resp.to_json()
    bad["log_sigma_core"][0][5] = -1.0
    with pytest.raises(InputError, match="log_sigma_core"):
        Response.from_json(bad)
