"""Raspberry Pi cameras through libcamera's picamera2 (optional extra ``pi``, import-guarded).

``pip install lightprobe[pi]`` on a Pi (the ``libcamera`` bindings come from the OS; off a Pi
``import picamera2`` fails, and :class:`Picamera2Camera` then raises CameraUnavailable with
that hint). Importing this module never imports picamera2.

What it does (NOTES.md): AE and AWB off (fixed ``ColourGains``), ``ExposureTime`` in integer
microseconds and ``AnalogueGain``; ``FrameDurationLimits`` wide enough for the longest exposure
(otherwise the sensor silently caps the exposure at the frame time); a raw stream (unpacked
``S????NN`` format) for linear HDR, demosaiced to RGB uint16 with ``Frame.black_level`` taken
from ``SensorBlackLevels`` (libcamera reports them on a 16-bit scale). A control change lands
"about num_buffers + 3 frames" later, not guaranteed, so every frame is matched against the last
request by its own metadata (:func:`matches_request`): ``ExposureTime`` and ``AnalogueGain`` equal
to the request within the sensor's quantisation, and ``SensorTimestamp`` after the request was
sent (so an A -> B -> A sequence cannot pass a stale A frame). ``exposure_verified`` is True
whenever the exposure comes from the frame's metadata; the frame also says whether it matches
the latest request (``extra["matches_request"]``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lightprobe.drivers.base import (
    Camera,
    CameraBusy,
    CameraUnavailable,
    Capabilities,
    CaptureTimeout,
    ControlNotSupported,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
    PixelFormat,
)
from lightprobe.drivers.v4l2.convert import bayer_to_rgb

__all__ = ["Picamera2Camera", "RequestState", "SequenceCounter", "matches_request", "raw_to_rgb", "to_controls"]

log = logging.getLogger(__name__)
_RAW_BY_BITS = {10: PixelFormat.RAW10, 12: PixelFormat.RAW12, 16: PixelFormat.RAW16}


def to_controls(exposure_s: float | None, gain: float | None) -> dict[str, Any]:
    """libcamera control values: ExposureTime is integer microseconds (>= 1)."""
    out: dict[str, Any] = {}
    if exposure_s is not None:
        out["ExposureTime"] = max(1, round(exposure_s * 1e6))
    if gain is not None:
        out["AnalogueGain"] = float(gain)
    return out


@dataclass(frozen=True)
class RequestState:
    """The latest control request: what was asked, and when (CLOCK_MONOTONIC ns)."""

    exposure_us: int
    gain: float
    sent_ns: int


def matches_request(md: Mapping[str, Any], req: RequestState | None, *, rel_tol: float = 0.02,
                    abs_tol_us: int = 100, gain_tol: float = 0.03) -> bool:  # fmt: skip
    """True when a frame's metadata shows the latest request landed.

    Sensors quantise exposure to whole lines (tens of us) and gain to register steps, so the
    comparison has a tolerance; the sensor timestamp must be after the request was sent.
    """
    if req is None:
        return "ExposureTime" in md
    exp, gain, ts = md.get("ExposureTime"), md.get("AnalogueGain"), md.get("SensorTimestamp")
    if exp is None or gain is None or ts is None:
        return False
    exp_ok = abs(int(exp) - req.exposure_us) <= max(abs_tol_us, rel_tol * req.exposure_us)
    gain_ok = abs(float(gain) - req.gain) <= gain_tol * max(req.gain, 1.0)
    return exp_ok and gain_ok and int(ts) >= req.sent_ns


class SequenceCounter:
    """Frame sequence numbers from SensorTimestamp: gaps of k frame durations = k - 1 dropped."""

    def __init__(self) -> None:
        self.sequence = -1
        self._last_ns: int | None = None

    def next(self, timestamp_ns: int, frame_duration_us: float | None) -> int:
        if self._last_ns is None or not frame_duration_us:
            step = 1
        else:
            step = max(1, round((timestamp_ns - self._last_ns) / (frame_duration_us * 1e3)))
        self._last_ns = timestamp_ns
        self.sequence += step
        return self.sequence


def raw_to_rgb(arr: np.ndarray, width: int, height: int, fmt: str) -> tuple[np.ndarray, int]:
    """An unpacked raw buffer (``SRGGB12`` etc.) to demosaiced (H, W, 3) uint16 and its bit depth.

    picamera2 hands raw planes as uint8 rows of ``stride`` bytes; 16-bit containers are viewed
    little-endian. Packed ``*_CSI2P`` formats are refused (ask for the unpacked format).
    """
    if fmt.endswith("_CSI2P") or len(fmt) < 7 or fmt[0] != "S":
        raise ValueError(f"raw format {fmt!r} is not an unpacked Bayer format")
    pattern, bits = fmt[1:5], int(fmt[5:])
    a = np.asarray(arr)
    if a.dtype == np.uint8 and bits > 8:
        a = np.ascontiguousarray(a[:height]).view("<u2")
    mosaic_img = np.ascontiguousarray(a[:height, :width]).astype(np.uint16 if bits > 8 else np.uint8)
    return bayer_to_rgb(mosaic_img, pattern), bits


def _import_picamera2() -> Callable[[int], Any]:
    try:
        from picamera2 import Picamera2  # type: ignore[import-not-found]
    except ImportError as e:
        raise CameraUnavailable(
            "libcamera backend needs picamera2 on a Raspberry Pi: pip install 'lightprobe[pi]' "
            f"(import failed: {e})", device="libcamera",
        ) from e  # fmt: skip
    return Picamera2  # type: ignore[no-any-return]


class Picamera2Camera(Camera):
    """A libcamera camera through picamera2.

    Parameters
    ----------
    camera_num : libcamera camera index.
    factory : builds the Picamera2 object (tests pass a fake); default imports picamera2.
    raw : stream raw (linear) frames; False streams processed RGB8.
    buffer_count : request buffers (>= 2).
    max_exposure_s : the longest exposure to allow (sets FrameDurationLimits' upper bound).
    """

    name = "libcamera"
    driver = "libcamera"

    def __init__(self, camera_num: int = 0, *, factory: Callable[[int], Any] | None = None,
                 raw: bool = True, buffer_count: int = 4, max_exposure_s: float = 1.0) -> None:  # fmt: skip
        self.camera_num, self._factory, self.raw = camera_num, factory, raw
        self.buffer_count, self.max_exposure_s = max(2, buffer_count), max_exposure_s
        self._cam: Any = None
        self._caps: Capabilities | None = None
        self._mode: Mode | None = None
        self._sensor_modes: dict[Mode, dict[str, Any]] = {}
        self._req: RequestState | None = None
        self._seq = SequenceCounter()

    @property
    def capabilities(self) -> Capabilities:
        if self._caps is None:
            raise CameraUnavailable("libcamera camera is not open", device=self.name)
        return self._caps

    @property
    def mode(self) -> Mode:
        if self._mode is None:
            raise CameraUnavailable("libcamera camera is not open", device=self.name)
        return self._mode

    async def open(self) -> None:
        if self._cam is not None:
            return
        factory = self._factory or _import_picamera2()
        try:
            cam = await asyncio.to_thread(factory, self.camera_num)
        except (RuntimeError, IndexError) as e:
            msg = str(e)
            kind = CameraBusy if "busy" in msg.lower() or "acquire" in msg.lower() else CameraUnavailable
            raise kind(f"libcamera camera {self.camera_num}: {msg}", device=self.name) from e
        self._cam = cam
        try:
            self._caps = self._read_capabilities(cam)
            mode = next((m for m in self._caps.modes if m.format.is_raw == self.raw), self._caps.modes[0])
            await asyncio.to_thread(self._configure, mode)
        except BaseException:
            await self.close()
            raise

    def _read_capabilities(self, cam: Any) -> Capabilities:
        ctrls = cam.camera_controls
        if "ExposureTime" not in ctrls:
            raise ControlNotSupported("camera has no ExposureTime control", device=self.name)
        emin, emax, _ = ctrls["ExposureTime"]
        gmin, gmax, _ = ctrls.get("AnalogueGain", (1.0, 1.0, None))
        modes: list[Mode] = []
        self._sensor_modes = {}
        for sm in sorted(cam.sensor_modes, key=lambda s: -s["size"][0] * s["size"][1]):
            (w, h), fps = sm["size"], float(sm.get("fps", 30.0))
            raw_fmt = _RAW_BY_BITS.get(int(sm.get("bit_depth", 0)))
            for fmt in (raw_fmt, PixelFormat.RGB8):
                m = Mode(w, h, fmt, fps) if fmt is not None else None
                if m is not None and m not in self._sensor_modes:
                    self._sensor_modes[m] = sm
                    modes.append(m)
        if not modes:
            raise CameraUnavailable("libcamera reports no sensor modes", device=self.name)
        props = getattr(cam, "camera_properties", {}) or {}
        return Capabilities(
            exposure_range=(max(emin, 1) / 1e6, min(emax / 1e6, self.max_exposure_s)),
            gain_range=(float(gmin), float(gmax)), modes=tuple(modes), has_frame_metadata=True,
            control_latency_frames=self.buffer_count + 3, model=str(props.get("Model", "")),
            exposure_step_s=1e-6,  # ExposureTime is whole microseconds (the line time rounds further)
        )  # fmt: skip

    def _configure(self, mode: Mode) -> None:
        cam, sm = self._cam, self._sensor_modes[mode]
        if getattr(cam, "started", False):
            cam.stop()
        lo_us = int(1e6 / max(mode.max_fps, 1e-3))
        hi_us = int(max(self.max_exposure_s * 1e6 + 10_000, lo_us))  # wide: long exposures fit
        controls: dict[str, Any] = {"AeEnable": False, "AwbEnable": False, "ColourGains": (1.0, 1.0),
                                    "FrameDurationLimits": (lo_us, hi_us)}  # fmt: skip
        if self._req is not None:
            controls.update(ExposureTime=self._req.exposure_us, AnalogueGain=self._req.gain)
        kw: dict[str, Any] = {"main": {"size": mode.size, "format": "RGB888"},
                              "buffer_count": self.buffer_count, "controls": controls}  # fmt: skip
        if mode.format.is_raw:
            kw["raw"] = {"size": mode.size, "format": str(sm["unpacked"])}
        cam.configure(cam.create_still_configuration(**kw))
        cam.start()
        self._mode = mode

    async def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is None:
            return
        try:
            await asyncio.to_thread(cam.stop)
        finally:
            await asyncio.to_thread(cam.close)

    async def set_mode(self, mode: Mode) -> None:
        if mode not in self._sensor_modes:
            raise ControlNotSupported(f"mode {mode} is not one of the camera's modes", device=self.name)
        self._require()
        await asyncio.to_thread(self._configure, mode)

    async def apply(self, controls: Controls) -> None:
        self.check_controls(controls)
        cam = self._require()
        prev = self._req
        exp_us = to_controls(controls.exposure_s, None).get("ExposureTime", prev.exposure_us if prev else None)
        gain = controls.gain if controls.gain is not None else (prev.gain if prev else 1.0)
        if exp_us is None:
            exp_us = int(cam.capture_metadata().get("ExposureTime", 10_000))
        req = RequestState(int(exp_us), float(gain), time.monotonic_ns())
        await asyncio.to_thread(cam.set_controls, {"ExposureTime": req.exposure_us, "AnalogueGain": req.gain})
        self._req = req

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        cam = self._require()
        try:
            request = await asyncio.wait_for(asyncio.to_thread(cam.capture_request), timeout)
        except TimeoutError as e:
            raise CaptureTimeout(f"libcamera: no frame within {timeout:.3g} s", device=self.name) from e
        try:
            md = dict(request.get_metadata())
            arr = request.make_array("raw" if self.mode.format.is_raw else "main")
        finally:
            request.release()
        return self._frame(md, arr)

    def _frame(self, md: Mapping[str, Any], arr: np.ndarray) -> Frame:
        mode = self.mode
        ts_ns = int(md.get("SensorTimestamp", time.monotonic_ns()))
        seq = self._seq.next(ts_ns, md.get("FrameDuration"))
        verified = "ExposureTime" in md
        exp_s = md["ExposureTime"] / 1e6 if verified else (self._req.exposure_us / 1e6 if self._req else float("nan"))
        gain = float(md.get("AnalogueGain", self._req.gain if self._req else 1.0))
        extra: dict[str, object] = {"matches_request": matches_request(md, self._req)}
        if self._req is not None:
            extra["requested_exposure_s"] = self._req.exposure_us / 1e6
        meta = FrameMetadata(exp_s, gain, ts_ns * 1e-9, seq, exposure_verified=verified)
        if mode.format.is_raw:
            fmt = str(self._sensor_modes[mode]["unpacked"])
            rgb, bits = raw_to_rgb(arr, mode.width, mode.height, fmt)
            levels = md.get("SensorBlackLevels")
            black = float(np.mean(levels)) / (1 << (16 - bits)) if levels else 0.0
            return Frame(rgb, meta, mode.format, black_level=black, white_level=float((1 << bits) - 1), extra=extra)
        rgb = np.ascontiguousarray(np.asarray(arr)[: mode.height, : mode.width, 2::-1])  # BGR in memory
        return Frame(rgb, meta, PixelFormat.RGB8, extra=extra)

    def _require(self) -> Any:
        if self._cam is None:
            raise CameraUnavailable("libcamera camera is not open", device=self.name)
        return self._cam
