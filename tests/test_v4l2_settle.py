"""The settling rule for cameras without per-frame exposure metadata (lightprobe.drivers.v4l2.settle)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightprobe.drivers.v4l2.settle import SettleTracker, frame_level


def _level(exposure: float, gamma: float = 1.0, k: float = 10.0) -> float:
    return min(1.0, (k * exposure) ** gamma)


def test_no_request_is_steady() -> None:
    t = SettleTracker(3, exposure_s=0.01)
    d = t.observe(0, 0.3)
    assert d.settled
    assert d.exposure_s == 0.01
    assert d.reason == "steady"
    t.request(0.01, 1.0)  # same values: nothing pending
    assert not t.pending


@pytest.mark.parametrize("gamma", [1.0, 1 / 2.2])
@pytest.mark.parametrize("land_after", [3, 5, 8])
def test_switches_only_after_the_step_shows_and_holds(gamma: float, land_after: int) -> None:
    t = SettleTracker(3, exposure_s=0.01, gamma=gamma)
    seq = 0
    for _ in range(4):
        t.observe(seq, _level(0.01, gamma))
        seq += 1
    t.request(0.04, 1.0)
    req_seq = seq
    reported = []
    for _ in range(20):
        true_exp = 0.04 if seq >= req_seq + land_after else 0.01
        if seq == req_seq + land_after:  # a rolling shutter: one half-changed frame first
            lvl = 0.5 * (_level(0.01, gamma) + _level(0.04, gamma))
        else:
            lvl = _level(true_exp, gamma)
        d = t.observe(seq, lvl)
        reported.append((seq, d.exposure_s, true_exp))
        seq += 1
    # never reports the new exposure for a frame taken with the old one or half-changed
    for s, rep, true in reported:
        if rep == 0.04:
            assert true == 0.04
            assert s > req_seq + land_after
    first_new = next(s for s, rep, _ in reported if rep == 0.04)
    assert first_new == req_seq + land_after + 2  # two full frames at the new level after the half one


def test_timeout_when_the_scene_does_not_follow() -> None:
    t = SettleTracker(2, exposure_s=0.01, timeout_frames=6)
    t.observe(0, 0.3)
    t.request(0.04, 1.0)
    reasons = [t.observe(s, 0.3).reason for s in range(1, 9)]
    assert "timeout" in reasons
    assert reasons.index("timeout") == 5
    assert t.exposure_s == 0.04


def test_unobservable_baseline_settles_on_frame_count() -> None:
    t = SettleTracker(3, exposure_s=0.01)
    t.observe(0, 1.0)  # clipped: no brightness information
    t.request(0.02, 1.0)
    decisions = [t.observe(s, 1.0) for s in range(1, 6)]
    assert [d.settled for d in decisions] == [False, False, True, True, True]
    assert decisions[2].reason == "unobservable"


def test_small_change_needs_no_step_and_drops_count_as_frames() -> None:
    t = SettleTracker(4, exposure_s=0.01)
    t.observe(10, 0.3)
    t.request(0.0102, 1.0)
    d = t.observe(15, 0.3)  # 4 frames dropped in between: latency already passed
    assert d.settled
    assert d.reason == "no-step-needed"


def test_frame_level_degenerate_inputs() -> None:
    assert frame_level(np.zeros((0, 0, 3)), 255.0) == 0.0
    assert frame_level(np.full((8, 8, 3), np.nan), 255.0) == 0.0
    img = np.zeros((64, 64, 3), np.uint8)
    img[0, 0] = 255  # a single hot pixel barely moves the level
    assert frame_level(img, 255.0) < 0.01
    assert math.isclose(frame_level(np.full((64, 64, 3), 4095, np.uint16), 4095.0), 1.0)
