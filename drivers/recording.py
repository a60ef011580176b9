"""Recordings: a camera's frames saved as the driver delivered them, and read back.

A recording is what a unit's camera gave its pipeline, frame by frame, with everything the
pipeline needs to run on it again (:mod:`lightprobe.drivers.replay`): each frame's pixels as the
driver protocol delivered them (RGB8 or the demosaiced RAW codes, never a tone-mapped picture),
its metadata (exposure and gain the sensor used, the sensor timestamp, the sequence number, when
it was delivered, the controls last requested), and in the header the camera's capabilities and
mode, the calibration in use and the two clocks' offset. A recording is an image of the room:
private like ``probe.exr`` (the API serves it with the token only).

File format, version 1 (little-endian; ``.lprec``)::

    magic      8 bytes   b"LPREC\\r\\n\\x1a" (a text-mode transfer or a truncated first line shows)
    version    u32       1
    length     u32       header bytes
    header     JSON      {"format": "lightprobe-recording", "version": 1, "kind": "stream" | "bracket",
                          "created", "source", "camera": {capabilities}, "mode": {...},
                          "calibration": {...} | null, "clock": {"wall_minus_monotonic_s"}, ...}
    crc        u32       CRC-32 of the header bytes
    then one record per frame, appended as it comes (never rewritten):
    tag        4 bytes   b"FRME"
    meta_len   u32
    data_len   u64
    crc        u32       CRC-32 of meta + data
    meta       JSON      {"sequence", "exposure_s", "gain", "timestamp_s", "exposure_verified",
                          "format", "shape", "dtype", "black_level", "white_level",
                          "delivered_s", "requested": [exposure_s, gain] | null,
                          "lost_before": frames the recorder could not write before this one,
                          "wall_minus_monotonic_s": the clocks' offset the unit used,
                          "extra": {...}}
    data       bytes     the pixels, C order, ``dtype`` little-endian, ``shape`` (H, W, 3)

``kind`` says how a replay serves the frames: ``stream`` in the order recorded (a camera's
frames: the pipeline asked for these exposures and got these frames), ``bracket`` by request (a
set of photographs, each stored once: a frame at the exposure nearest the one requested,
:mod:`lightprobe.drivers.replay`). Each record is written whole with one ``write`` and flushed,
so a recording cut by a crash or a full disk reads up to its last whole frame
(:attr:`RecordingReader.truncated` says so). A changed byte fails the frame's CRC; a version
other than 1 is refused; both errors name the file (:class:`lightprobe.core.errors.InputError`:
exit 2 on the command line).

:class:`RecordingCamera` wraps any camera and appends what it delivers to a
:class:`RecordingWriter`: the caller's thread takes the frame's CRC as it arrives (0.2 ms for a
VGA frame, while the pipeline has just read its pixels and they are in the cache; a frame time
later, in another thread, the same CRC cost twice that) and queues it; the writer's own thread
writes it (one ``writev``). ``lightprobe bench replay``: 0.94-0.98 ms of CPU a frame in all
while the service runs at 30 fps.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import queue
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError
from lightprobe.drivers.base import (
    Camera,
    Capabilities,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
    PixelFormat,
    clock_offset,
)

__all__ = [
    "MAGIC",
    "VERSION",
    "RecordedFrame",
    "RecordingCamera",
    "RecordingReader",
    "RecordingWriter",
    "capabilities_from_json",
    "capabilities_to_json",
    "frame_record",
]

log = logging.getLogger(__name__)

MAGIC = b"LPREC\r\n\x1a"
VERSION = 1
_TAG = b"FRME"
_REC = struct.Struct("<4sIQI")  # tag, meta length, data length, crc
_HEAD = struct.Struct("<II")  # version, header length
_DTYPES = {"uint8": np.uint8, "uint16": np.uint16}


# ---- capabilities and modes as JSON ---------------------------------------------------------------
def _mode_to_json(m: Mode) -> dict[str, Any]:
    return {"width": m.width, "height": m.height, "format": m.format.value, "max_fps": m.max_fps}


def _mode_from_json(d: dict[str, Any]) -> Mode:
    return Mode(int(d["width"]), int(d["height"]), PixelFormat(d["format"]), float(d["max_fps"]))


def capabilities_to_json(c: Capabilities) -> dict[str, Any]:
    d = asdict(c)
    d["modes"] = [_mode_to_json(m) for m in c.modes]
    return d


def capabilities_from_json(d: dict[str, Any]) -> Capabilities:
    return Capabilities(exposure_range=(float(d["exposure_range"][0]), float(d["exposure_range"][1])),
                        gain_range=(float(d["gain_range"][0]), float(d["gain_range"][1])),
                        modes=tuple(_mode_from_json(m) for m in d["modes"]),
                        has_frame_metadata=bool(d["has_frame_metadata"]),
                        control_latency_frames=int(d["control_latency_frames"]),
                        model=str(d.get("model", "")), serial=str(d.get("serial", "")),
                        exposure_step_s=float(d.get("exposure_step_s", 0.0)))


def _json_safe(extra: dict[str, object]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in extra.items():
        if isinstance(v, (str, int, float, bool)) or v is None:
            out[str(k)] = v
    return out


def frame_record(frame: Frame, *, delivered_s: float, requested: Controls | None = None,
                 lost_before: int = 0) -> tuple[bytes, np.ndarray]:
    """The meta JSON of one frame and its pixels (C order), as :class:`RecordingWriter` writes them."""
    data = np.ascontiguousarray(frame.data)
    if data.dtype.name not in _DTYPES or data.ndim != 3 or data.shape[2] != 3:
        raise ValueError(f"a recording holds (H, W, 3) uint8 / uint16 frames, not {data.dtype} {data.shape}")
    m = frame.meta
    meta = {"sequence": int(m.sequence), "exposure_s": float(m.exposure_s), "gain": float(m.gain),
            "timestamp_s": float(m.timestamp_s), "exposure_verified": bool(m.exposure_verified),
            "format": frame.format.value, "shape": list(data.shape), "dtype": data.dtype.name,
            "black_level": float(frame.black_level), "white_level": float(frame.white_level),
            "delivered_s": float(delivered_s),
            "requested": None if requested is None else [requested.exposure_s, requested.gain],
            "lost_before": int(lost_before), "wall_minus_monotonic_s": clock_offset(),
            "extra": _json_safe(frame.extra)}
    return json.dumps(meta, separators=(",", ":")).encode(), data


# ---- writing --------------------------------------------------------------------------------------
class RecordingWriter:
    """Appends frames to a new recording file from a thread of its own.

    ``header``: the header's fields beyond ``format`` and ``version`` (``kind``, ``camera``,
    ``mode``, ``calibration``, ``source``...). ``max_bytes`` / ``max_seconds`` (of delivered
    frames) end it: :attr:`full` turns True and later frames are not written. At most ``queue``
    frames wait for the disk; beyond, a frame is lost and the next written one says how many
    (``lost_before``): a replay of it is then not the run it recorded, and :attr:`lost` counts them.
    """

    def __init__(self, path: str | os.PathLike[str], header: dict[str, Any], *, max_bytes: int = 2 << 30,
                 max_seconds: float = 600.0, queue_frames: int = 16) -> None:
        self.path = Path(path)
        self.max_bytes, self.max_seconds = int(max_bytes), float(max_seconds)
        head = {"format": "lightprobe-recording", "version": VERSION,
                "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                "clock": {"wall_minus_monotonic_s": clock_offset()}, **header}
        body = json.dumps(head, separators=(",", ":")).encode()
        self._f = open(self.path, "xb", buffering=0)  # noqa: SIM115 - closed by close() / the writer thread
        self._fd = self._f.fileno()
        first = MAGIC + _HEAD.pack(VERSION, len(body)) + body + struct.pack("<I", zlib.crc32(body))
        os.write(self._fd, first)
        self.bytes = len(first)
        self.frames = 0
        self.lost = 0
        self._lost_pending = 0
        self.full = False
        self.error: str | None = None
        self.cpu_s = 0.0  # CPU seconds the recording cost: queueing on the caller's thread, CRC and write on its own
        self._first_delivered: float | None = None
        self._last_delivered = 0.0
        self._q: queue.Queue[tuple[bytes, np.ndarray, int] | None] = queue.Queue(maxsize=max(1, queue_frames))
        self._thread = threading.Thread(target=self._run, name="lightprobe-recorder", daemon=True)
        self._thread.start()

    @property
    def seconds(self) -> float:
        """Seconds of delivered frames written so far."""
        return self._last_delivered - self._first_delivered if self._first_delivered is not None else 0.0

    def append(self, frame: Frame, *, delivered_s: float, requested: Controls | None = None) -> bool:
        """Queue one frame (non-blocking); False once the recording is full, closed or failed."""
        if self.full or self.error is not None or self._f.closed:
            return False
        c0 = time.thread_time()
        try:
            return self._append(frame, delivered_s, requested)
        finally:
            self.cpu_s += time.thread_time() - c0

    def _append(self, frame: Frame, delivered_s: float, requested: Controls | None) -> bool:
        if self._first_delivered is None:
            self._first_delivered = delivered_s
        self._last_delivered = delivered_s
        if delivered_s - self._first_delivered > self.max_seconds:
            self.full = True
            return False
        meta, data = frame_record(frame, delivered_s=delivered_s, requested=requested,
                                  lost_before=self._lost_pending)
        if self.bytes + _REC.size + len(meta) + data.nbytes > self.max_bytes:
            self.full = True
            return False
        # the CRC now, while the frame's pixels are in the cache (the pipeline has just read them)
        crc = zlib.crc32(memoryview(data).cast("B"), zlib.crc32(meta))  # type: ignore[arg-type]
        try:
            self._q.put_nowait((meta, data, crc))
        except queue.Full:
            self._lost_pending += 1
            self.lost += 1
            return True
        self._lost_pending = 0
        self.bytes += _REC.size + len(meta) + data.nbytes
        self.frames += 1
        return True

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            meta, data, crc = item
            if self.error is not None:
                continue
            c0 = time.thread_time()
            self._write(meta, data, crc)
            self.cpu_s += time.thread_time() - c0

    def _write(self, meta: bytes, data: np.ndarray, crc: int) -> None:
        """One record: its header, metadata and pixels, flushed (a crash leaves whole frames and
        at most one partial one after them)."""
        view = memoryview(data).cast("B")  # type: ignore[arg-type]  # an ndarray is a buffer
        head = _REC.pack(_TAG, len(meta), len(view), crc) + meta
        try:  # one system call per record, straight from the frame's memory (no buffer between)
            n = os.writev(self._fd, [head, view])
            while n < len(head) + len(view):  # a short write (a signal, a full pipe): the rest
                rest = (head + bytes(view))[n:]
                n += os.write(self._fd, rest)
        except OSError as e:
            self.error = f"{self.path}: {e.strerror or e}"
            self.full = True
            log.exception("recording stopped: %s", self.error)

    def close(self) -> None:
        """Write what is queued, sync and close (safe to call twice)."""
        if self._f.closed:
            return
        self._q.put(None)
        self._thread.join()
        try:
            os.fsync(self._fd)
        except OSError as e:  # pragma: no cover - a full disk at the very end
            self.error = self.error or f"{self.path}: {e.strerror or e}"
        self._f.close()

    def status(self) -> dict[str, Any]:
        return {"path": str(self.path), "frames": self.frames, "bytes": self.bytes, "seconds": self.seconds,
                "lost_frames": self.lost, "full": self.full, "error": self.error,
                "cpu_ms_per_frame": 1e3 * self.cpu_s / self.frames if self.frames else None}


# ---- reading --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecordedFrame:
    """Where one frame's record is in the file, and its metadata."""

    index: int
    offset: int  # of the meta JSON
    meta_len: int
    data_len: int
    crc: int
    meta: dict[str, Any]


class RecordingReader:
    """A recording's header and frame index (the pixels are read on demand, each frame's CRC
    checked as it is read; :meth:`verify` checks them all).

    Raises InputError naming the file for anything that is not a version-1 recording. A file
    cut inside a frame is read up to its last whole frame: :attr:`truncated` is True and the
    warning says how many bytes were left over."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            self._f = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        except OSError as e:
            raise InputError(f"{self.path}: cannot read the recording: {e.strerror or e}", param="recording") from e
        try:
            self.header = self._read_header()
            self.frames: list[RecordedFrame] = []
            self.truncated = False
            self.leftover_bytes = 0
            self._index()
        except BaseException:
            self._f.close()
            raise

    def _fail(self, what: str) -> InputError:
        return InputError(f"{self.path}: {what}", param="recording")

    def _read_header(self) -> dict[str, Any]:
        f = self._f
        magic = f.read(len(MAGIC))
        if magic != MAGIC:
            raise self._fail("not a lightprobe recording (no LPREC signature)")
        head = f.read(_HEAD.size)
        if len(head) < _HEAD.size:
            raise self._fail("truncated inside its header")
        version, length = _HEAD.unpack(head)
        if version != VERSION:
            raise self._fail(f"recording format version {version} is not supported (this lightprobe reads {VERSION})")
        body, crc = f.read(length), f.read(4)
        if len(body) < length or len(crc) < 4:
            raise self._fail("truncated inside its header")
        if zlib.crc32(body) != struct.unpack("<I", crc)[0]:
            raise self._fail("the header fails its checksum (the file was changed or damaged)")
        try:
            header = json.loads(body)
        except ValueError as e:
            raise self._fail(f"the header is not JSON ({e})") from e
        if header.get("format") != "lightprobe-recording" or header.get("kind") not in ("stream", "bracket"):
            raise self._fail("the header does not describe a lightprobe recording")
        return dict(header)

    def _index(self) -> None:
        f = self._f
        size = os.fstat(f.fileno()).st_size
        pos = f.tell()
        while pos < size:
            head = f.read(_REC.size)
            if len(head) < _REC.size:
                self._cut(size - pos)
                return
            tag, mlen, dlen, crc = _REC.unpack(head)
            if tag != _TAG:
                raise self._fail(f"frame {len(self.frames)}: bad record tag {tag!r} at byte {pos}")
            if pos + _REC.size + mlen + dlen > size:
                self._cut(size - pos)
                return
            try:
                meta = json.loads(f.read(mlen))
            except ValueError as e:
                raise self._fail(f"frame {len(self.frames)}: metadata is not JSON ({e})") from e
            self.frames.append(RecordedFrame(len(self.frames), pos + _REC.size, mlen, dlen, crc, meta))
            pos += _REC.size + mlen + dlen
            f.seek(pos)

    def _cut(self, leftover: int) -> None:
        self.truncated, self.leftover_bytes = True, leftover
        log.warning("%s: truncated inside frame %d: replaying its %d whole frames (%d bytes of a partial "
                    "frame ignored)", self.path, len(self.frames), len(self.frames), leftover)

    def read(self, i: int) -> Frame:
        """Frame ``i`` (its CRC checked: InputError naming the file and frame when it fails)."""
        rec = self.frames[i]
        self._f.seek(rec.offset)
        # a writable buffer: the pixels are the consumer's, as a driver's frames are (and numba
        # compiles a read-only array as another type: another kernel, another rounding)
        raw = bytearray(rec.meta_len + rec.data_len)
        if self._f.readinto(raw) != len(raw) or zlib.crc32(raw) != rec.crc:
            raise self._fail(f"frame {i} fails its checksum (the file was changed or damaged)")
        m = rec.meta
        shape = tuple(int(x) for x in m["shape"])
        data = np.frombuffer(raw, _DTYPES[m["dtype"]], offset=rec.meta_len).reshape(shape)
        meta = FrameMetadata(exposure_s=float(m["exposure_s"]), gain=float(m["gain"]),
                             timestamp_s=float(m["timestamp_s"]), sequence=int(m["sequence"]),
                             exposure_verified=bool(m["exposure_verified"]))
        extra = dict(m.get("extra") or {})
        extra["recording_frame"] = i
        return Frame(data, meta, PixelFormat(m["format"]), black_level=float(m["black_level"]),
                     white_level=float(m["white_level"]), extra=extra)

    def verify(self) -> None:
        """Check every frame's CRC (InputError naming the first that fails)."""
        for i, rec in enumerate(self.frames):
            self._f.seek(rec.offset)
            crc = 0
            left = rec.meta_len + rec.data_len
            while left:
                chunk = self._f.read(min(left, 1 << 22))
                if not chunk:
                    raise self._fail(f"frame {i} is cut short")
                crc = zlib.crc32(chunk, crc)
                left -= len(chunk)
            if crc != rec.crc:
                raise self._fail(f"frame {i} fails its checksum (the file was changed or damaged)")

    def __iter__(self) -> Iterator[Frame]:
        return (self.read(i) for i in range(len(self.frames)))

    @property
    def capabilities(self) -> Capabilities:
        return capabilities_from_json(self.header["camera"])

    @property
    def mode(self) -> Mode:
        return _mode_from_json(self.header["mode"])

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---- the recording camera -------------------------------------------------------------------------
class RecordingCamera(Camera):
    """``camera`` with every frame it delivers appended to :attr:`writer` while one is set
    (:meth:`start`; pass-through otherwise). Everything else is the wrapped camera's."""

    def __init__(self, camera: Camera) -> None:
        self.inner = camera
        self.name = camera.name
        self.driver = camera.driver
        self.writer: RecordingWriter | None = None
        self.calibration_json: dict[str, Any] | None = None  # the pipeline's (lightprobe.device.bootstrap)
        self._requested: Controls | None = None
        self._make_writer: Any = None
        self._on_done: Any = None

    def start(self, writer: RecordingWriter) -> None:
        """Record from the next frame into ``writer`` (the caller closes it: :meth:`stop`)."""
        self.writer = writer

    def arm(self, make_writer: Any, on_done: Any) -> None:
        """Record from the next frame into ``make_writer(self)`` (called then: the camera is open
        and its capabilities known); once the writer is full or failed it is detached and
        handed to ``on_done(writer)`` (which closes it)."""
        self._make_writer, self._on_done = make_writer, on_done

    def stop(self) -> RecordingWriter | None:
        """Stop recording (the writer is closed); returns it."""
        w, self.writer = self.writer, None
        if w is not None:
            w.close()
        return w

    def header(self, **fields: Any) -> dict[str, Any]:
        """The header fields of a recording of this camera (opened): capabilities and mode."""
        return {"kind": "stream", "source": self.name, "camera": capabilities_to_json(self.inner.capabilities),
                "mode": _mode_to_json(self.inner.mode), **fields}

    async def open(self) -> None:
        await self.inner.open()

    async def close(self) -> None:
        await self.inner.close()

    @property
    def capabilities(self) -> Capabilities:
        return self.inner.capabilities

    @property
    def mode(self) -> Mode:
        return self.inner.mode

    async def set_mode(self, mode: Mode) -> None:
        await self.inner.set_mode(mode)

    async def apply(self, controls: Controls) -> None:
        await self.inner.apply(controls)
        self._requested = controls

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        frame = await self.inner.capture(timeout)
        if self._make_writer is not None and self.writer is None:
            make, self._make_writer = self._make_writer, None
            self.writer = make(self)
        w = self.writer
        if w is not None and not w.append(frame, delivered_s=time.monotonic(), requested=self._requested) \
                and self._on_done is not None:
            self.writer = None
            done, self._on_done = self._on_done, None
            done(w)
        return frame

    async def drain(self) -> int:
        return await self.inner.drain()

    def factory_calibration(self) -> Any:
        return self.inner.factory_calibration()

    def present_board(self, board: Any) -> bool:
        return self.inner.present_board(board)

    def __getattr__(self, name: str) -> Any:  # the simulator's truth and the like, for tests and tools
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)
