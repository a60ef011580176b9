"""Debevec-Malik response recovery (calibration.response, the one solver)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.response import pair_bins, solve_debevec
from device.core.errors import InputError


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
