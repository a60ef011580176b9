"""``--camera replay:FILE``: a recording (:mod:`lightprobe.drivers.recording`) played back as a camera.

The camera protocol exactly, from what was recorded:

- **capabilities, mode, calibration** are the recorded camera's (``factory_calibration()`` is the
  calibration the recorded run used; :mod:`lightprobe.device.bootstrap` gives it precedence over
  a state directory's, so a replay on a desk runs as the unit ran);
- **a ``stream`` recording** delivers its frames in the order recorded, with their metadata as
  recorded (exposure, gain, sensor timestamp, sequence: the gaps of frames the unit's queue
  dropped stay gaps). Requests are checked against the recorded capabilities and otherwise change
  nothing, as on the unit, where the frames that came were these: the pipeline's requests on a
  replay are the recorded run's, since it sees the same frames (deterministic: the same recording
  gives the same light sets, bit for bit). A frame's ``captured`` is when the recorded unit
  exposed it (the header's clock offset, ``extra["wall_minus_monotonic_s"]``);
- **a ``bracket`` recording** (photographs, each stored once) answers each frame with the
  photograph whose exposure is nearest (in stops) the one in effect: a request lands
  ``control_latency_frames`` after it was made, as on a sensor, and the frame's metadata carries
  the photograph's own exposure and gain (verified), so a pipeline that asked for 1/90 s and got
  the 1/60 s photograph merges it as 1/60 s. A bracket has no clock of its own: frame ``i`` is
  stamped ``i / 30`` s (deterministic), while its mode's frame rate is the one its longest
  photograph allows (so a planner may ask for it);
- **pacing**: ``pace=True`` (``serve``'s default) delivers a stream's frames at the recorded
  delivery times (a bracket at its mode's frame rate), ``pace=False`` (``run-pipeline``'s) as fast
  as the consumer asks; ``speed`` scales the pace. ``loop=True`` starts again at the end
  (sequence numbers and timestamps continue past the last frame); otherwise the end raises
  :class:`RecordingEnded` (a :class:`lightprobe.drivers.base.CameraUnavailable`: a service marks
  its lights stale and says why, ``run-pipeline`` stops).

A recording that fails its checks (a frame's CRC, an unknown version) is refused at ``open()``
with an InputError naming the file: the service reports it and keeps serving its last state.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from typing import Any

from lightprobe.drivers.base import (
    Camera,
    CameraUnavailable,
    Capabilities,
    ControlNotSupported,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
)
from lightprobe.drivers.recording import RecordingReader

__all__ = ["BRACKET_FPS", "RecordingEnded", "ReplayCamera"]

BRACKET_FPS = 30.0  # a bracket's frames are stamped this far apart (module docstring)


class RecordingEnded(CameraUnavailable):
    """A replay without ``loop`` delivered its last frame."""


class ReplayCamera(Camera):
    """A recording as a camera (module docstring)."""

    driver = "replay"

    def __init__(self, path: str | os.PathLike[str], *, pace: bool = True, loop: bool = False,
                 speed: float = 1.0, verify: bool = True) -> None:
        if not str(path):
            from lightprobe.core.errors import InputError

            raise InputError("--camera replay:FILE needs a recording file", param="--camera")
        self.path = str(path)
        self.name = f"replay:{self.path}"
        self.pace, self.loop, self.speed, self.verify = bool(pace), bool(loop), float(speed), bool(verify)
        self._reader: RecordingReader | None = None
        self._caps: Capabilities | None = None
        self._mode: Mode | None = None
        self._next = 0  # the next frame index (stream) / frame number (bracket)
        self._loops = 0
        self._t0: float | None = None  # CLOCK_MONOTONIC the pace counts from
        self._pending: list[tuple[int, Controls]] = []  # bracket: (landing frame, controls)
        self._exposure: float | None = None
        self._gain: float | None = None
        self.ended = False

    # ---- lifecycle ------------------------------------------------------------------------------
    async def open(self) -> None:
        if self._reader is not None:
            return
        reader = await asyncio.to_thread(RecordingReader, self.path)
        if not reader.frames:
            reader.close()
            raise CameraUnavailable(f"{self.path}: the recording holds no whole frame", device=self.name)
        if self.verify:
            try:
                await asyncio.to_thread(reader.verify)
            except BaseException:
                reader.close()
                raise
        self._reader = reader
        self._caps = reader.capabilities
        self._mode = reader.mode
        self._t0 = None

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def reader(self) -> RecordingReader:
        return self._opened(self._reader)

    @property
    def kind(self) -> str:
        return str(self.reader.header["kind"])

    @property
    def capabilities(self) -> Capabilities:
        return self._opened(self._caps)

    @property
    def mode(self) -> Mode:
        return self._opened(self._mode)

    async def set_mode(self, mode: Mode) -> None:
        if mode not in self.capabilities.modes:
            raise ControlNotSupported(f"mode {mode} is not one of the recorded camera's", device=self.name)
        self._mode = mode

    async def apply(self, controls: Controls) -> None:
        self.check_controls(controls)
        if self._reader is not None and self.kind == "bracket":
            self._pending.append((self._next + self.capabilities.control_latency_frames, controls))

    def factory_calibration(self) -> Any:
        from lightprobe.core.calibration import Calibration

        cal = self.reader.header.get("calibration") if self._reader is not None else _header_calibration(self.path)
        return Calibration.from_json(cal) if cal else None

    # ---- frames ---------------------------------------------------------------------------------
    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        reader = self.reader
        if self.kind == "bracket":
            return await self._bracket_frame(reader)
        n = len(reader.frames)
        if self._next >= n:
            if not self.loop:
                self.ended = True
                raise RecordingEnded(f"{self.path}: the recording ended after {n} frames", device=self.name)
            self._next, self._loops = 0, self._loops + 1
        i = self._next
        self._next += 1
        rec = reader.frames[i]
        if self.pace:
            first, last = reader.frames[0].meta["delivered_s"], reader.frames[-1].meta["delivered_s"]
            span = (last - first) + _frame_period(reader)
            await self._pace(rec.meta["delivered_s"] - first + self._loops * span, timeout)
        frame = await asyncio.to_thread(reader.read, i)
        extra = frame.extra
        offset = rec.meta.get("wall_minus_monotonic_s", reader.header.get("clock", {}).get("wall_minus_monotonic_s"))
        if offset is not None:
            extra["wall_minus_monotonic_s"] = float(offset)
        if self._loops:  # sequence and time go on past the end
            first, last = reader.frames[0], reader.frames[-1]
            seq_span = int(last.meta["sequence"]) - int(first.meta["sequence"]) + 1
            t_span = float(last.meta["timestamp_s"]) - float(first.meta["timestamp_s"]) + _frame_period(reader)
            m = frame.meta
            frame = Frame(frame.data, FrameMetadata(m.exposure_s, m.gain, m.timestamp_s + self._loops * t_span,
                                                    m.sequence + self._loops * seq_span, m.exposure_verified),
                          frame.format, frame.black_level, frame.white_level, extra)
        return frame

    async def _bracket_frame(self, reader: RecordingReader) -> Frame:
        k = self._next
        still = []
        for eff, c in self._pending:
            if eff <= k:
                self._exposure = c.exposure_s if c.exposure_s is not None else self._exposure
                self._gain = c.gain if c.gain is not None else self._gain
            else:
                still.append((eff, c))
        self._pending = still
        want = self._exposure if self._exposure is not None else self.capabilities.exposure_range[0]
        g = self._gain if self._gain is not None else 1.0
        i = min(range(len(reader.frames)), key=lambda j: (
            abs(math.log(float(reader.frames[j].meta["exposure_s"]) * float(reader.frames[j].meta["gain"])
                         / (want * g))), j))
        self._next += 1
        t = k / BRACKET_FPS
        if self.pace:
            await self._pace(t, 1e9)
        photo = await asyncio.to_thread(reader.read, i)
        meta = FrameMetadata(exposure_s=photo.meta.exposure_s, gain=photo.meta.gain, timestamp_s=t, sequence=k)
        return Frame(photo.data, meta, photo.format, photo.black_level, photo.white_level,
                     {**photo.extra, "photo": i})

    async def _pace(self, at_s: float, wait_s: float) -> None:
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now - at_s / self.speed
        delay = self._t0 + at_s / self.speed - now
        if delay > 0:
            await asyncio.sleep(min(delay, max(wait_s, 0.0) + 1.0))


def _frame_period(reader: RecordingReader) -> float:
    return 1.0 / max(reader.mode.max_fps, 1e-3)


def _header_calibration(path: str) -> Any:
    with RecordingReader(path) as r:
        return r.header.get("calibration")
