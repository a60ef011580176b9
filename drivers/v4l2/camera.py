"""V4L2Camera: a ``lightprobe.drivers.base.Camera`` over a V4L2 capture node (USB/UVC webcams, CSI bridges).

Lifecycle on ``open()`` (the kernel requires this order): QUERYCAP (must be a streaming capture
device) -> ENUM_FMT / ENUM_FRAMESIZES / ENUM_FRAMEINTERVALS (modes) -> S_FMT -> controls (auto
exposure manual first, see ``controls.py``) -> REQBUFS -> QUERYBUF + mmap -> QBUF all ->
STREAMON. ``close()`` is STREAMOFF, unmap, REQBUFS(0), close. Every ioctl runs in a worker thread;
the event loop only waits on the fd with ``loop.add_reader`` (the node is non-blocking, so
DQBUF answers EAGAIN when no buffer is ready).

Frames: timestamps are the buffer's CLOCK_MONOTONIC time when ``flags & 0xE000 == 0x2000``
(otherwise the dequeue time, marked ``extra["timestamp_source"] = "dequeue"``), turned into the
protocol's start of exposure: a start-of-exposure stamp (``V4L2_BUF_FLAG_TSTAMP_SRC_SOE``, as
uvcvideo gives) as it is, an end-of-frame or dequeue stamp less the exposure and one frame
time of readout (``extra["timestamp_source"]`` says which: "soe", "eof", "dequeue"); a jump in the
buffer sequence counts dropped frames (``extra["dropped"]``, running total in ``dropped_frames``).
V4L2 has no per-frame exposure: ``exposure_verified`` is always False and a frame reports a new
exposure only once :class:`lightprobe.drivers.v4l2.settle.SettleTracker` says it has settled (frame-count
latency, then a brightness-step check); until then it reports the previous exposure.

Replug: open by ``/dev/v4l/by-id/...``; after :class:`CameraDisconnected`, ``close()`` then
``open()`` again re-applies every control (UVC resets them on power-up), auto exposure first.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from lightprobe.drivers.base import (
    Camera,
    CameraError,
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

from . import _structs as S
from ._ioctl import DeviceTransport, IoctlError, IoctlTransport
from .controls import ControlBackend, V4L2Controls
from .convert import SUPPORTED_FORMATS, CorruptFrame, buffer_to_rgb
from .settle import SettleTracker, frame_level

__all__ = ["V4L2Camera", "enumerate_modes"]

log = logging.getLogger(__name__)
# When several pixel formats offer the same size, take the first of these (uncompressed first).
_PREFERENCE = [S.V4L2_PIX_FMT_YUYV, S.V4L2_PIX_FMT_GREY, S.V4L2_PIX_FMT_RGB24, S.V4L2_PIX_FMT_MJPEG]


def _mode_format(pixfmt: int) -> PixelFormat | None:
    if pixfmt in S.BAYER_FORMATS:
        bits = S.BAYER_FORMATS[pixfmt][1]
        return {10: PixelFormat.RAW10, 12: PixelFormat.RAW12, 16: PixelFormat.RAW16}.get(bits)
    return PixelFormat.RGB8 if pixfmt in SUPPORTED_FORMATS else None


def enumerate_modes(t: IoctlTransport) -> dict[Mode, int]:
    """Modes the node offers (discrete frame sizes) -> the V4L2 pixel format that gives each.

    8-bit Bayer is skipped (``PixelFormat`` has no 8-bit raw); so are formats we cannot convert.
    """
    found: dict[tuple[int, int, PixelFormat], list[tuple[int, float]]] = {}
    for i in range(64):
        fd = S.v4l2_fmtdesc(index=i, type=S.V4L2_BUF_TYPE_VIDEO_CAPTURE)
        if not _enum(t, t.abi.VIDIOC_ENUM_FMT, fd):
            break
        pf = _mode_format(fd.pixelformat)
        if pf is None:
            continue
        for j in range(256):
            fs = S.v4l2_frmsizeenum(index=j, pixel_format=fd.pixelformat)
            if not _enum(t, t.abi.VIDIOC_ENUM_FRAMESIZES, fs) or fs.type != S.V4L2_FRMSIZE_TYPE_DISCRETE:
                break
            w, h = fs.discrete.width, fs.discrete.height
            found.setdefault((w, h, pf), []).append((fd.pixelformat, _max_fps(t, fd.pixelformat, w, h)))
    modes: dict[Mode, int] = {}
    for (w, h, pf), offers in found.items():
        offers.sort(key=lambda o: _PREFERENCE.index(o[0]) if o[0] in _PREFERENCE else len(_PREFERENCE))
        modes[Mode(w, h, pf, offers[0][1])] = offers[0][0]
    return modes


def _enum(t: IoctlTransport, request: int, arg: Any) -> bool:
    try:
        t.ioctl(request, arg)
    except IoctlError as e:
        if e.errno == errno.EINVAL:  # the end of the list
            return False
        raise
    return True


def _max_fps(t: IoctlTransport, pixfmt: int, w: int, h: int) -> float:
    best = 0.0
    for k in range(64):
        fi = S.v4l2_frmivalenum(index=k, pixel_format=pixfmt, width=w, height=h)
        if not _enum(t, t.abi.VIDIOC_ENUM_FRAMEINTERVALS, fi):
            break
        if fi.type == S.V4L2_FRMIVAL_TYPE_DISCRETE and fi.discrete.numerator:
            best = max(best, fi.discrete.denominator / fi.discrete.numerator)
        else:  # stepwise/continuous: the minimum interval is the first fract
            best = max(best, fi.discrete.denominator / max(fi.discrete.numerator, 1))
            break
    return best or 30.0


class V4L2Camera(Camera):
    """A V4L2 capture node as a :class:`lightprobe.drivers.base.Camera`.

    Parameters
    ----------
    path : the node, preferably ``/dev/v4l/by-id/...`` (stable across replugs).
    opener : makes the transport; default ``DeviceTransport(path)`` (tests pass a fake node's
        ``open``).
    controls_factory : builds the control backend from the open transport; default
        :class:`V4L2Controls`. ``lightprobe.drivers.uvc`` passes one that falls back to UVC over USB.
    buffer_count : mmap buffers (>= 2).
    sensor_latency_frames : frames between S_CTRL and the sensor using it; the reported
        ``control_latency_frames`` adds the buffers that may already hold older frames.
    mode : the mode to stream at first; default the largest RGB8 mode.
    """

    driver = "v4l2"

    def __init__(self, path: str, *, opener: Callable[[], IoctlTransport] | None = None,
                 controls_factory: Callable[[IoctlTransport], ControlBackend] | None = None,
                 buffer_count: int = 4, sensor_latency_frames: int = 3, mode: Mode | None = None) -> None:  # fmt: skip
        self.name = path
        self.path = path
        self._opener = opener or (lambda: DeviceTransport(path))
        self._controls_factory = controls_factory or V4L2Controls
        self.buffer_count = max(2, buffer_count)
        self.sensor_latency = sensor_latency_frames
        self._want_mode = mode
        self._t: IoctlTransport | None = None
        self._ctl: ControlBackend | None = None
        self._caps: Capabilities | None = None
        self._modes: dict[Mode, int] = {}
        self._mode: Mode | None = None
        self._fmt: tuple[int, int, int, int] = (0, 0, 0, 0)  # w, h, fourcc, bytesperline
        self._maps: list[memoryview] = []
        self._streaming = False
        self._desired: tuple[float | None, float | None] = (None, None)
        self._tracker: SettleTracker | None = None
        self._last_seq: int | None = None
        self.dropped_frames = 0
        self.card = ""

    # ---- Camera protocol ------------------------------------------------------------------------
    @property
    def capabilities(self) -> Capabilities:
        return self._opened(self._caps)

    @property
    def mode(self) -> Mode:
        return self._opened(self._mode)

    async def open(self) -> None:
        if self._t is not None:
            return
        await asyncio.to_thread(self._open_sync)

    async def close(self) -> None:
        if self._t is None:
            return
        await asyncio.to_thread(self._close_sync)

    async def set_mode(self, mode: Mode) -> None:
        if mode not in self._modes:
            raise ControlNotSupported(f"mode {mode} is not one of {self.name}'s modes", device=self.name)
        if mode == self._mode:
            return
        await asyncio.to_thread(self._restream, mode)

    async def apply(self, controls: Controls) -> None:
        self.check_controls(controls)
        ctl, tracker = self._require(), self._tracker
        assert tracker is not None
        exp, gain = await asyncio.to_thread(ctl.set, controls.exposure_s, controls.gain)
        self._desired = (exp if controls.exposure_s is not None else self._desired[0],
                         gain if controls.gain is not None else self._desired[1])  # fmt: skip
        tracker.request(exp, gain)

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        self._require()
        deadline = time.monotonic() + timeout
        while True:
            got = await asyncio.to_thread(self._grab)
            if got is not None:
                return self._frame(*got)
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not await self._wait_readable(remaining):
                raise CaptureTimeout(f"{self.name}: no frame within {timeout:.3g} s", device=self.name)

    # ---- open / close (worker thread) -----------------------------------------------------------
    def _open_sync(self) -> None:
        t = self._opener()
        try:
            self._t = t
            self._querycap(t)
            self._modes = enumerate_modes(t)
            self._check_modes()
            mode = self._want_mode if self._want_mode in self._modes else self._default_mode()
            self._set_format(mode)
            ctl = self._controls_factory(t)
            ctl.probe()
            exp, gain = ctl.apply_all(*self._desired)  # manual first; re-applied on every (re)open
            self._ctl = ctl
            self._caps = Capabilities(
                exposure_range=ctl.exposure_range, gain_range=ctl.gain_range,
                modes=tuple(self._modes), has_frame_metadata=False,
                control_latency_frames=self.sensor_latency + self.buffer_count,
                model=self.card, serial=self.path.rsplit("/", 1)[-1],
                exposure_step_s=float(getattr(ctl, "exposure_step_s", 0.0)),
            )  # fmt: skip
            gamma = 1.0 if mode.format.is_raw else 1 / 2.2
            self._tracker = SettleTracker(self._caps.control_latency_frames, exposure_s=exp, gain=gain, gamma=gamma)
            self._last_seq = None
            self._start_stream()
            log.info("opened %s (%s) %dx%d %s", self.name, self.card, mode.width, mode.height,
                     S.fourcc_str(self._fmt[2]))  # fmt: skip
        except BaseException:
            self._close_sync()
            raise

    def _check_modes(self) -> None:
        if not self._modes:
            raise CameraUnavailable(f"{self.name} offers no pixel format we can use", device=self.name)

    def _querycap(self, t: IoctlTransport) -> None:
        cap = S.v4l2_capability()
        try:
            t.ioctl(t.abi.VIDIOC_QUERYCAP, cap)
        except IoctlError as e:
            if e.errno not in (errno.ENOTTY, errno.EINVAL):
                raise
            raise CameraUnavailable(f"{self.name} is not a V4L2 device ({e})", device=self.name) from e
        caps = cap.device_caps if cap.capabilities & S.V4L2_CAP_DEVICE_CAPS else cap.capabilities
        self.card = bytes(cap.card).split(b"\0", 1)[0].decode("utf-8", "replace")
        if not caps & S.V4L2_CAP_VIDEO_CAPTURE or not caps & S.V4L2_CAP_STREAMING:
            raise CameraUnavailable(
                f"{self.name} ({self.card}) is not a streaming capture node (caps 0x{caps:08x}); "
                "use the '-video-index0' node", device=self.name,
            )  # fmt: skip

    def _default_mode(self) -> Mode:
        rgb = [m for m in self._modes if m.format is PixelFormat.RGB8] or list(self._modes)
        return max(rgb, key=lambda m: (m.width * m.height, m.max_fps))

    def _set_format(self, mode: Mode) -> None:
        t = self._t
        assert t is not None
        f = t.abi.format(type=S.V4L2_BUF_TYPE_VIDEO_CAPTURE)
        pix = f.fmt.pix
        pix.width, pix.height, pix.pixelformat = mode.width, mode.height, self._modes[mode]
        pix.field = S.V4L2_FIELD_NONE
        t.ioctl(t.abi.VIDIOC_S_FMT, f)
        got = (pix.width, pix.height, pix.pixelformat)
        if got != (mode.width, mode.height, self._modes[mode]):
            raise CameraError(f"{self.name}: driver set {got} instead of {mode}", device=self.name)
        self._fmt = (pix.width, pix.height, pix.pixelformat, pix.bytesperline)
        self._mode = mode

    def _start_stream(self) -> None:
        t = self._t
        assert t is not None
        req = S.v4l2_requestbuffers(count=self.buffer_count, type=S.V4L2_BUF_TYPE_VIDEO_CAPTURE,
                                    memory=S.V4L2_MEMORY_MMAP)  # fmt: skip
        t.ioctl(t.abi.VIDIOC_REQBUFS, req)
        if req.count < 2:
            raise CameraError(f"{self.name}: driver granted {req.count} buffers", device=self.name)
        for i in range(req.count):
            b = self._buffer(i)
            t.ioctl(t.abi.VIDIOC_QUERYBUF, b)
            self._maps.append(t.mmap(b.length, b.m.offset))
        for i in range(req.count):
            t.ioctl(t.abi.VIDIOC_QBUF, self._buffer(i))
        t.ioctl(t.abi.VIDIOC_STREAMON, S.ctypes.c_int(S.V4L2_BUF_TYPE_VIDEO_CAPTURE))
        self._streaming = True

    def _stop_stream(self) -> None:
        t = self._t
        if t is None:
            return
        try:
            if self._streaming:
                t.ioctl(t.abi.VIDIOC_STREAMOFF, S.ctypes.c_int(S.V4L2_BUF_TYPE_VIDEO_CAPTURE))
        except CameraError as e:  # gone already: nothing to stop
            log.debug("STREAMOFF on %s: %s", self.name, e)
        self._streaming = False
        for m in self._maps:
            t.unmap(m)
        had_buffers, self._maps = bool(self._maps), []
        if had_buffers:
            try:
                t.ioctl(t.abi.VIDIOC_REQBUFS, S.v4l2_requestbuffers(
                    count=0, type=S.V4L2_BUF_TYPE_VIDEO_CAPTURE, memory=S.V4L2_MEMORY_MMAP))  # fmt: skip
            except CameraError as e:
                log.debug("REQBUFS(0) on %s: %s", self.name, e)

    def _restream(self, mode: Mode) -> None:
        self._stop_stream()
        self._set_format(mode)
        self._start_stream()
        if self._tracker is not None:
            self._tracker.gamma = 1.0 if mode.format.is_raw else 1 / 2.2

    def _close_sync(self) -> None:
        t = self._t
        if t is None:
            return
        try:
            self._stop_stream()
        finally:
            self._t, self._ctl, self._caps = None, None, None
            t.close()

    # ---- streaming (worker thread) --------------------------------------------------------------
    def _require(self) -> ControlBackend:
        if self._t is None or self._ctl is None:
            raise CameraUnavailable(f"{self.name} is not open", device=self.name)
        return self._ctl

    def _buffer(self, index: int = 0) -> Any:
        t = self._t
        assert t is not None
        return t.abi.buffer(index=index, type=S.V4L2_BUF_TYPE_VIDEO_CAPTURE, memory=S.V4L2_MEMORY_MMAP)

    def _grab(self) -> tuple[np.ndarray, int, float | None, int] | None:
        """DQBUF (non-blocking), convert, QBUF. None when no buffer is ready."""
        t = self._t
        if t is None:
            raise CameraUnavailable(f"{self.name} is not open", device=self.name)
        while True:
            b = self._buffer()
            try:
                t.ioctl(t.abi.VIDIOC_DQBUF, b)
            except BlockingIOError:
                return None
            try:
                rgb = self._convert(b)
            except CorruptFrame as e:
                log.warning("%s: dropped frame %d: %s", self.name, b.sequence, e)
                self.dropped_frames += 1
                continue
            finally:
                t.ioctl(t.abi.VIDIOC_QBUF, self._buffer(b.index))
            monotonic = (b.flags & S.V4L2_BUF_FLAG_TIMESTAMP_MASK) == S.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC
            ts = b.timestamp.tv_sec + b.timestamp.tv_usec * 1e-6 if monotonic else None
            return rgb, int(b.sequence), ts, int(b.flags)

    def _convert(self, b: Any) -> np.ndarray:
        if b.flags & S.V4L2_BUF_FLAG_ERROR:
            raise CorruptFrame("driver flagged the buffer")
        w, h, pixfmt, bpl = self._fmt
        return buffer_to_rgb(self._maps[b.index][: b.bytesused], pixfmt, w, h, bpl)

    async def _wait_readable(self, wait_s: float) -> bool:
        t = self._t
        if t is None:
            raise CameraUnavailable(f"{self.name} is not open", device=self.name)
        loop = asyncio.get_running_loop()
        ready: asyncio.Future[None] = loop.create_future()
        fd = t.fileno()

        def wake() -> None:
            if not ready.done():
                ready.set_result(None)

        loop.add_reader(fd, wake)
        try:
            await asyncio.wait_for(ready, wait_s)
        except TimeoutError:
            return False
        finally:
            loop.remove_reader(fd)
        return True

    def _frame(self, rgb: np.ndarray, seq: int, ts: float | None, flags: int) -> Frame:
        extra: dict[str, object] = {"pixelformat": S.fourcc_str(self._fmt[2])}
        if ts is None:  # not a monotonic buffer timestamp: use the dequeue time
            ts, extra["timestamp_source"] = time.monotonic(), "dequeue"
        elif flags & S.V4L2_BUF_FLAG_TSTAMP_SRC_MASK == S.V4L2_BUF_FLAG_TSTAMP_SRC_SOE:
            extra["timestamp_source"] = "soe"
        else:
            extra["timestamp_source"] = "eof"
        gap = 0 if self._last_seq is None else max(0, seq - self._last_seq - 1)
        self._last_seq = seq
        self.dropped_frames += gap
        extra["dropped"] = gap
        fmt = self.mode.format
        white = float((1 << fmt.bit_depth) - 1)
        assert self._tracker is not None
        d = self._tracker.observe(seq, frame_level(rgb, white))
        extra["settled"], extra["settle_reason"] = d.settled, d.reason
        if d.reason == "timeout":
            log.warning("%s: exposure %.6g s accepted without a brightness step", self.name, d.exposure_s)
        if extra["timestamp_source"] != "soe":  # the frame ended (or was dequeued) then: its
            # exposure started the exposure and one frame's readout before (the protocol's stamp)
            ts -= d.exposure_s + 1.0 / max(self.mode.max_fps, 1e-3)
        meta = FrameMetadata(exposure_s=d.exposure_s, gain=d.gain, timestamp_s=ts, sequence=seq,
                             exposure_verified=False)  # fmt: skip
        return Frame(data=rgb, meta=meta, format=fmt, white_level=white, extra=extra)

