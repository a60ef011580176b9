"""lightprobe.drivers.libcamera: control conversion, per-request metadata matching, raw frames.

picamera2 cannot be installed off a Raspberry Pi, so the camera runs against
tests/fake_picamera2.py (a mock at the edge of code we do not own).
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from fake_picamera2 import FakePicamera2

from lightprobe.drivers.base import CameraUnavailable, Controls, Mode, PixelFormat
from lightprobe.drivers.libcamera import (
    Picamera2Camera,
    RequestState,
    SequenceCounter,
    matches_request,
    raw_to_rgb,
    to_controls,
)
from lightprobe.drivers.v4l2.convert import mosaic


def test_to_controls_units() -> None:
    assert to_controls(0.0123456, 2) == {"ExposureTime": 12346, "AnalogueGain": 2.0}
    assert to_controls(1e-9, None) == {"ExposureTime": 1}
    assert to_controls(None, None) == {}


def test_matches_request_needs_values_and_a_later_timestamp() -> None:
    req = RequestState(exposure_us=10_000, gain=2.0, sent_ns=1_000)
    good = {"ExposureTime": 9_990, "AnalogueGain": 2.01, "SensorTimestamp": 2_000}
    assert matches_request(good, req)
    assert not matches_request({**good, "SensorTimestamp": 999}, req)  # exposed before the request
    assert not matches_request({**good, "ExposureTime": 5_000}, req)  # stale exposure
    assert not matches_request({**good, "AnalogueGain": 1.0}, req)
    assert not matches_request({"ExposureTime": 10_000}, req)  # metadata incomplete
    assert matches_request({"ExposureTime": 5}, None)
    assert not matches_request({}, None)


def test_sequence_counter_counts_drops_from_timestamps() -> None:
    c = SequenceCounter()
    d_us = 16_666.7
    ts = [0, 16_666_700, 33_333_400, 83_333_500, 100_000_200]
    assert [c.next(t, d_us) for t in ts] == [0, 1, 2, 5, 6]
    assert SequenceCounter().next(5, None) == 0


def test_raw_to_rgb_unpacked_with_stride() -> None:
    rgb = np.zeros((8, 10, 3), np.uint16)
    rgb[...] = (3000, 2000, 1000)
    m = mosaic(rgb, "BGGR").astype("<u2")
    rows = np.zeros((8, 10 * 2 + 12), np.uint8)
    rows[:, :20] = m.view(np.uint8).reshape(8, 20)
    out, bits = raw_to_rgb(rows, 10, 8, "SBGGR12")
    assert bits == 12
    assert out.dtype == np.uint16
    assert out.shape == (8, 10, 3)
    assert (np.abs(out[2:-2, 2:-2].astype(int) - (3000, 2000, 1000)) <= 1).all()
    with pytest.raises(ValueError, match="unpacked"):
        raw_to_rgb(rows, 10, 8, "SBGGR12_CSI2P")


def test_missing_picamera2_is_a_clear_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import fails like off a Pi

    async def run() -> None:
        await Picamera2Camera().open()

    import asyncio

    with pytest.raises(CameraUnavailable, match=r"lightprobe\[pi\]"):
        asyncio.run(run())


async def test_configuration_ae_awb_off_wide_frame_duration_raw_stream() -> None:
    fakes: list[FakePicamera2] = []
    cam = Picamera2Camera(factory=lambda n: fakes.append(FakePicamera2(n)) or fakes[-1], max_exposure_s=2.0)
    await cam.open()
    try:
        cfg = fakes[0].config
        assert cfg is not None
        ctrls = cfg["controls"]
        assert ctrls["AeEnable"] is False
        assert ctrls["AwbEnable"] is False
        lo, hi = ctrls["FrameDurationLimits"]
        assert hi >= 2_000_000
        assert lo <= 1e6 / 60 + 1
        assert cfg["raw"] == {"size": (640, 480), "format": "SRGGB12"}
        assert cfg["buffer_count"] >= 2
        assert cam.mode == Mode(640, 480, PixelFormat.RAW12, 60.0)
        caps = cam.capabilities
        assert caps.has_frame_metadata
        assert caps.exposure_range == (2e-5, 2.0)
        f = await cam.capture(2.0)
        assert f.format is PixelFormat.RAW12
        assert f.data.dtype == np.uint16
        assert f.black_level == 256.0
        assert f.white_level == 4095.0
        assert f.meta.exposure_verified
        assert f.meta.exposure_s == pytest.approx(0.01)
    finally:
        await cam.close()
    assert fakes[0].closed
    assert not fakes[0].started


async def test_burst_never_gets_a_stale_exposure() -> None:
    fake = FakePicamera2(latency=5)
    cam = Picamera2Camera(factory=lambda n: fake)
    await cam.open()
    try:
        await cam.capture(2.0)
        history = []
        for target in (0.004, 0.01, 0.004):  # A -> B -> A: timestamps tell the two A's apart
            await cam.apply(Controls(exposure_s=target, gain=1.0))
            for _ in range(12):
                f = await cam.capture(2.0)
                history.append((target, f))
                if f.extra["matches_request"]:
                    break
            assert f.extra["matches_request"]
            assert f.meta.exposure_s == pytest.approx(target)
        for target, f in history:
            if f.extra["matches_request"]:
                assert f.meta.exposure_s == pytest.approx(target, abs=20e-6)
        stale = [f for _, f in history if not f.extra["matches_request"]]
        assert len(stale) >= 3  # latency 5: the first frames after each apply are rejected
        assert all(f.meta.exposure_verified for _, f in history)
    finally:
        await cam.close()


async def test_dropped_requests_show_as_sequence_gaps_and_rgb_mode() -> None:
    fake = FakePicamera2()
    cam = Picamera2Camera(factory=lambda n: fake, raw=False)
    await cam.open()
    try:
        assert cam.mode.format is PixelFormat.RGB8
        a = await cam.capture(2.0)
        fake.drop_next = 2
        b = await cam.capture(2.0)
        gap = b.meta.sequence - a.meta.sequence
        assert gap >= 3  # 2 dropped here (+ any the sensor dropped while we were slow)
        assert gap == round((b.meta.timestamp_s - a.meta.timestamp_s) * fake.fps)
        assert a.data.dtype == np.uint8
        assert a.data.shape == (480, 640, 3)
        assert a.data[240, 600, 0] > a.data[240, 600, 2]  # red-tinted scene: RGB, not BGR
    finally:
        await cam.close()
