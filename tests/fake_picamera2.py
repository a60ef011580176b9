"""A fake ``picamera2.Picamera2`` for tests (picamera2 only installs on a Raspberry Pi).

A mock at the edge of code we do not own: it mimics the parts of picamera2's API that
``lightprobe.drivers.libcamera`` uses (camera_controls, sensor_modes, camera_properties,
create_still_configuration, configure, start/stop/close, set_controls, capture_request ->
request.get_metadata / make_array / release, capture_metadata) and libcamera's behaviour that
matters: a control change lands ``latency`` frames after set_controls, exposure is quantised to
whole sensor lines (``line_us``), raw buffers are unpacked 16-bit containers in uint8 rows with
a stride, SensorBlackLevels on a 16-bit scale, and ``drop_next`` loses frames (timestamps jump).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from lightprobe.drivers.v4l2.convert import mosaic


class FakeRequest:
    def __init__(self, md: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        self.md, self.arrays, self.released = md, arrays, False

    def get_metadata(self) -> dict[str, Any]:
        return dict(self.md)

    def make_array(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def release(self) -> None:
        self.released = True


class FakePicamera2:
    """Sensor 'imx-fake': 640x480 SRGGB12 at 60 fps, lines of 20 us, black level 256 (12-bit)."""


    def __init__(self, camera_num: int = 0, *, fps: float = 100.0, latency: int = 4, line_us: int = 20) -> None:
        self.camera_num, self.fps, self.latency, self.line_us = camera_num, fps, latency, line_us
        self.camera_controls = {"ExposureTime": (20, 2_000_000, 10_000), "AnalogueGain": (1.0, 16.0, 1.0),
                                "FrameDurationLimits": (16_666, 10_000_000, 16_666)}  # fmt: skip
        self.sensor_modes = [{"size": (640, 480), "format": "SRGGB12_CSI2P", "unpacked": "SRGGB12",
                              "bit_depth": 12, "fps": 60.0}]  # fmt: skip
        self.camera_properties = {"Model": "imx-fake"}
        self.started = self.closed = False
        self._t0_ns = time.monotonic_ns()
        self.config: dict[str, Any] | None = None
        self.controls_log: list[dict[str, Any]] = []
        self.drop_next = 0
        self._frame = 0
        self._pending: list[tuple[int, dict[str, Any]]] = []
        self._state = {"ExposureTime": 10_000, "AnalogueGain": 1.0}
        self._lock = threading.Lock()

    def create_still_configuration(self, **kw: Any) -> dict[str, Any]:
        return dict(kw)

    def configure(self, config: dict[str, Any]) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        self.config = config
        self.set_controls(config.get("controls", {}))

    def start(self) -> None:
        self.started = True
        self._t0_ns = time.monotonic_ns()
        self._frame = -1

    def _now_frame(self) -> int:
        """Index of the frame the sensor is exposing now (frames run continuously)."""
        return (time.monotonic_ns() - self._t0_ns) * self.fps // 1_000_000_000

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        self.closed = True

    def set_controls(self, controls: dict[str, Any]) -> None:
        with self._lock:
            self.controls_log.append(dict(controls))
            self._pending.append((max(self._frame, self._now_frame()) + self.latency, dict(controls)))

    def capture_metadata(self) -> dict[str, Any]:
        return dict(self._state)

    def capture_request(self) -> FakeRequest:
        if not self.started:
            raise RuntimeError("camera not started")
        with self._lock:
            # frame k is exposed from t0 + k / fps (CLOCK_MONOTONIC) and complete one period later;
            # only the newest `buffers` complete frames are kept when the caller is slow
            buffers = int((self.config or {}).get("buffer_count", 4))
            complete = self._now_frame() - 1
            self._frame = max(self._frame + 1 + self.drop_next, complete - buffers + 1)
            self.drop_next = 0
            ts_ns = self._t0_ns + int(self._frame * 1e9 / self.fps)
        time.sleep(max(0.0, (ts_ns + 1e9 / self.fps - time.monotonic_ns()) * 1e-9))
        with self._lock:
            while self._pending and self._pending[0][0] <= self._frame:
                c = self._pending.pop(0)[1]
                self._state.update({k: c[k] for k in ("ExposureTime", "AnalogueGain") if k in c})
            exp_us = max(self.line_us, round(self._state["ExposureTime"] / self.line_us) * self.line_us)
            gain = self._state["AnalogueGain"]
            frame = self._frame
        md = {"ExposureTime": exp_us, "AnalogueGain": gain, "FrameDuration": 1e6 / self.fps,
              "SensorTimestamp": ts_ns, "SensorBlackLevels": (4096,) * 4, "FrameNumber": frame}  # fmt: skip
        return FakeRequest(md, self._arrays(exp_us * 1e-6 * gain))

    def _arrays(self, exposure: float) -> dict[str, np.ndarray]:
        h, w = 480, 640
        ramp = np.linspace(0.05, 1.0, w)[None, :, None] * np.array([1.0, 0.8, 0.6])[None, None, :]
        lin = np.clip(np.broadcast_to(ramp, (h, w, 3)) * 40.0 * exposure, 0, 1)
        raw = (256 + lin * (4095 - 256)).astype(np.uint16)
        mono = mosaic(raw, "RGGB").astype("<u2")
        stride = w * 2 + 64
        rows = np.zeros((h, stride), np.uint8)
        rows[:, : w * 2] = mono.view(np.uint8).reshape(h, w * 2)
        main = (255 * lin ** (1 / 2.2)).astype(np.uint8)[..., ::-1]  # BGR in memory, like RGB888
        return {"raw": rows, "main": np.ascontiguousarray(main)}
