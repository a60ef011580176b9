"""A fake V4L2 endpoint: a simulated UVC webcam behind the :class:`IoctlTransport` interface.

It stands where the kernel stands. It decodes the ioctl number (``_IOC`` fields) and the struct
*bytes* with its own offset tables, written from the kernel's videodev2.h independently of
``lightprobe.drivers.v4l2._structs`` (so a wrong ctypes layout is caught, for the LP64 and the ARM EABI
ILP32 layouts alike), keeps the device state a real driver keeps (format, buffers, queue,
streaming, controls), produces frames on a thread while streaming, and records every call in
``calls`` and every misuse in ``violations`` (the kernel would answer EINVAL/EBUSY; we also keep
a note of what was wrong so a test can say why).

The simulated camera: YUYV and MJPEG at 640x480 and 320x240; controls EXPOSURE_AUTO (menu,
default 3 = aperture priority as on most UVC webcams), EXPOSURE_ABSOLUTE (1..5000 x 100 us),
EXPOSURE_AUTO_PRIORITY (default 1) and GAIN (16..255, 16 = unity); a new exposure or gain lands
``latency_frames`` frames after the S_CTRL; the scene is a fixed linear radiance gradient seen
through a gamma-2.2 response. :class:`FakeV4L2Node` is the device across plugs: ``unplug()`` makes
the open transport fail with ENODEV semantics, ``replug()`` brings it back with controls reset to
their defaults (as UVC cameras do).

Used by tests and by ``open_camera("v4l2-fake")``; never touches a real device.
"""

from __future__ import annotations

import ctypes
import errno
import os
import struct
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.drivers.base import CameraDisconnected, CameraUnavailable
from lightprobe.drivers.v4l2._ioctl import IoctlError
from lightprobe.drivers.v4l2._structs import ABI64, V4L2Abi
from lightprobe.drivers.v4l2.camera import V4L2Camera

__all__ = ["FakeUVCCamera", "FakeV4L2Device", "FakeV4L2Node", "fake_uvc_calibration", "rgb_to_yuyv", "sim_scene"]

# ioctl nr -> name, and the kernel's struct size per ABI (bits) for that ioctl.
_NR = {0: "VIDIOC_QUERYCAP", 2: "VIDIOC_ENUM_FMT", 4: "VIDIOC_G_FMT", 5: "VIDIOC_S_FMT",
       8: "VIDIOC_REQBUFS", 9: "VIDIOC_QUERYBUF", 15: "VIDIOC_QBUF", 17: "VIDIOC_DQBUF",
       18: "VIDIOC_STREAMON", 19: "VIDIOC_STREAMOFF", 27: "VIDIOC_G_CTRL", 28: "VIDIOC_S_CTRL",
       36: "VIDIOC_QUERYCTRL", 74: "VIDIOC_ENUM_FRAMESIZES", 75: "VIDIOC_ENUM_FRAMEINTERVALS"}  # fmt: skip
_KERNEL_SIZE = {
    64: {"VIDIOC_QUERYCAP": 104, "VIDIOC_ENUM_FMT": 64, "VIDIOC_G_FMT": 208, "VIDIOC_S_FMT": 208,
         "VIDIOC_REQBUFS": 20, "VIDIOC_QUERYBUF": 88, "VIDIOC_QBUF": 88, "VIDIOC_DQBUF": 88,
         "VIDIOC_STREAMON": 4, "VIDIOC_STREAMOFF": 4, "VIDIOC_G_CTRL": 8, "VIDIOC_S_CTRL": 8,
         "VIDIOC_QUERYCTRL": 68, "VIDIOC_ENUM_FRAMESIZES": 44, "VIDIOC_ENUM_FRAMEINTERVALS": 52},
    32: {"VIDIOC_QUERYCAP": 104, "VIDIOC_ENUM_FMT": 64, "VIDIOC_G_FMT": 204, "VIDIOC_S_FMT": 204,
         "VIDIOC_REQBUFS": 20, "VIDIOC_QUERYBUF": 68, "VIDIOC_QBUF": 68, "VIDIOC_DQBUF": 68,
         "VIDIOC_STREAMON": 4, "VIDIOC_STREAMOFF": 4, "VIDIOC_G_CTRL": 8, "VIDIOC_S_CTRL": 8,
         "VIDIOC_QUERYCTRL": 68, "VIDIOC_ENUM_FRAMESIZES": 44, "VIDIOC_ENUM_FRAMEINTERVALS": 52},
}  # fmt: skip
# struct v4l2_buffer field offsets (videodev2.h) per ABI: LP64 pads before the 16-byte timeval.
_BUF: dict[int, dict[str, int]] = {
    64: {"index": 0, "type": 4, "bytesused": 8, "flags": 12, "field": 16, "sequence": 56,
         "memory": 60, "offset": 64, "length": 72},
    32: {"index": 0, "type": 4, "bytesused": 8, "flags": 12, "field": 16, "sequence": 44,
         "memory": 48, "offset": 52, "length": 56},
}  # fmt: skip
_TIMEVAL: dict[int, tuple[int, str]] = {64: (24, "<qq"), 32: (20, "<ii")}  # offset, tv_sec/tv_usec
_PIX = {64: 8, 32: 4}  # offset of fmt.pix inside struct v4l2_format

YUYV, MJPG = 0x56595559, 0x47504A4D
CID_EXPOSURE_AUTO, CID_EXPOSURE_ABSOLUTE, CID_EXPOSURE_AUTO_PRIORITY = 0x009A0901, 0x009A0902, 0x009A0903
CID_GAIN = 0x00980913


@dataclass
class _Ctrl:
    name: str
    type: int
    minimum: int
    maximum: int
    step: int
    default: int
    value: int = 0

    def __post_init__(self) -> None:
        self.value = self.default


def _default_controls() -> dict[int, _Ctrl]:
    return {
        CID_EXPOSURE_AUTO: _Ctrl("Auto Exposure", 3, 0, 3, 1, 3),
        CID_EXPOSURE_ABSOLUTE: _Ctrl("Exposure Time, Absolute", 1, 1, 5000, 1, 156),
        CID_EXPOSURE_AUTO_PRIORITY: _Ctrl("Exposure, Dynamic Framerate", 2, 0, 1, 1, 1),
        CID_GAIN: _Ctrl("Gain", 1, 16, 255, 1, 16),
    }


def sim_scene(width: int, height: int) -> np.ndarray:
    """The fake camera's linear radiance (H, W, 3) float32: a horizontal ramp 0.05..1 per s."""
    ramp = np.linspace(0.05, 1.0, width, dtype=np.float32)[None, :, None]
    tint = np.array([1.0, 0.8, 0.6], np.float32)[None, None, :]
    return np.broadcast_to(ramp * tint, (height, width, 3)).astype(np.float32) * 40.0


@dataclass
class _State:
    """What a driver keeps per open device."""

    fmt: tuple[int, int, int] = (640, 480, YUYV)
    buffers: list[bytearray] = field(default_factory=list)
    queued: list[int] = field(default_factory=list)
    done: list[tuple[int, int, float, int]] = field(default_factory=list)  # idx, seq, t, used
    streaming: bool = False
    sequence: int = -1
    # control changes in flight: (frame sequence at which it lands, exposure_100us, gain)
    pending: list[tuple[int, int, int]] = field(default_factory=list)
    sensor_exposure: int = 156
    sensor_gain: int = 16


class FakeV4L2Node:
    """The simulated webcam across plugs: ``open()`` gives a :class:`FakeV4L2Device` transport."""

    def __init__(self, path: str = "/dev/v4l/by-id/usb-Fake_UVC_Cam_0001-video-index0", *,
                 abi: V4L2Abi = ABI64, fps: float = 120.0, latency_frames: int = 3,
                 formats: tuple[int, ...] = (YUYV, MJPG)) -> None:  # fmt: skip
        self.path, self.abi, self.fps, self.latency_frames = path, abi, fps, latency_frames
        self.formats = formats
        self.plugged = True
        self.controls = _default_controls()
        self.open_count = 0
        self.devices: list[FakeV4L2Device] = []

    def open(self) -> FakeV4L2Device:
        if not self.plugged:
            raise CameraUnavailable(f"{self.path} does not exist (camera not attached?)", device=self.path)
        self.open_count += 1
        dev = FakeV4L2Device(self)
        self.devices.append(dev)
        return dev

    def unplug(self) -> None:
        self.plugged = False
        for d in self.devices:
            d.gone()

    def replug(self) -> None:
        """Come back with every control at its default (UVC controls reset on power-up)."""
        self.controls = _default_controls()
        self.plugged = True


class FakeV4L2Device:
    """One open file on the fake node; implements :class:`lightprobe.drivers.v4l2._ioctl.IoctlTransport`."""

    def __init__(self, node: FakeV4L2Node) -> None:
        self.node, self.path, self.abi = node, node.path, node.abi
        self._bits = node.abi.bits  # the "kernel" decodes with its own ABI, whatever we are told
        self.calls: list[tuple[str, bytes]] = []
        self.call_threads: list[int] = []  # thread ident per call: ioctls must stay off the loop
        self.violations: list[str] = []
        self.drop_frames = 0  # fault injection: the next N sensor frames find no buffer
        self._st = _State()
        self._rendered: dict[tuple[int, int, int, float, int], bytes] = {}
        self._lock = threading.RLock()
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        self._gone = False
        self._maps: list[memoryview] = []

    # ---- transport interface --------------------------------------------------------------------
    def fileno(self) -> int:
        return self._rfd

    def ioctl(self, request: int, arg: ctypes.Structure | ctypes.c_int) -> None:
        name, size = _NR.get(request & 0xFF, f"nr{request & 0xFF}"), (request >> 16) & 0x3FFF
        data = bytearray(bytes(arg))
        self.calls.append((name, bytes(data)))
        self.call_threads.append(threading.get_ident())
        if self._closed:
            raise IoctlError(name, errno.EBADF, device=self.path)
        if self._gone:
            raise CameraDisconnected(f"{self.path} went away during {name}", device=self.path)
        expect = _KERNEL_SIZE[self._bits].get(name)
        if (request >> 8) & 0xFF != ord("V") or expect is None or expect != size or len(data) != size:
            self.violations.append(f"{name}: ioctl size {size}, struct {len(data)}, kernel {expect}")
            raise IoctlError(name, errno.ENOTTY, device=self.path)
        with self._lock:
            getattr(self, "_" + name[7:].lower())(data)
        ctypes.memmove(ctypes.addressof(arg), bytes(data), len(data))

    def mmap(self, length: int, offset: int) -> memoryview:
        idx = offset // 0x100000
        if idx >= len(self._st.buffers) or length != len(self._st.buffers[idx]):
            self.violations.append(f"mmap of unknown buffer offset={offset} length={length}")
            raise IoctlError("mmap", errno.EINVAL, device=self.path)
        view = memoryview(self._st.buffers[idx])
        self._maps.append(view)
        return view

    def unmap(self, view: memoryview) -> None:
        view.release()

    def close(self) -> None:
        if self._closed:
            return
        self._stop_thread()
        self._closed = True
        os.close(self._rfd)
        os.close(self._wfd)
        if self in self.node.devices:
            self.node.devices.remove(self)

    def gone(self) -> None:
        """Unplugged: every later ioctl fails, poll wakes the reader (POLLERR)."""
        self._gone = True
        self._stop.set()
        if not self._closed:
            os.write(self._wfd, b"!")

    # ---- helpers --------------------------------------------------------------------------------
    def _bad(self, name: str, why: str, err: int = errno.EINVAL) -> None:
        self.violations.append(f"{name}: {why}")
        raise IoctlError(name, err, device=self.path)

    def called(self) -> list[str]:
        """Names of the ioctls issued so far, in order."""
        return [c[0] for c in self.calls]

    def _sizes(self) -> list[tuple[int, int, int]]:
        return [(w, h, f) for f in self.node.formats for (w, h) in ((640, 480), (320, 240))]

    # ---- ioctl handlers (names follow VIDIOC_*) -------------------------------------------------
    def _querycap(self, d: bytearray) -> None:
        d[:] = bytes(104)
        d[0:8], d[16:32], d[48:64] = b"uvcvideo", b"Fake UVC Camera\0", b"usb-0000:01:00.0"
        struct.pack_into("<IIII", d, 80, 0x060100, 0x84A00001, 0x04200001, 0)

    def _enum_fmt(self, d: bytearray) -> None:
        index, type_ = struct.unpack_from("<II", d, 0)
        names = {YUYV: b"YUYV 4:2:2", MJPG: b"Motion-JPEG"}
        fmts = [(f, names[f]) for f in self.node.formats]
        if type_ != 1 or index >= len(fmts):
            raise IoctlError("VIDIOC_ENUM_FMT", errno.EINVAL, device=self.path)
        d[12:44] = fmts[index][1].ljust(32, b"\0")
        struct.pack_into("<II", d, 8, 1 if fmts[index][0] == MJPG else 0, 0)
        struct.pack_into("<I", d, 44, fmts[index][0])

    def _enum_framesizes(self, d: bytearray) -> None:
        index, pixfmt = struct.unpack_from("<II", d, 0)
        sizes = [(w, h) for w, h, f in self._sizes() if f == pixfmt]
        if index >= len(sizes):
            raise IoctlError("VIDIOC_ENUM_FRAMESIZES", errno.EINVAL, device=self.path)
        struct.pack_into("<III", d, 8, 1, *sizes[index])

    def _enum_frameintervals(self, d: bytearray) -> None:
        index, pixfmt, w, h = struct.unpack_from("<IIII", d, 0)
        if index > 0 or (w, h, pixfmt) not in self._sizes():
            raise IoctlError("VIDIOC_ENUM_FRAMEINTERVALS", errno.EINVAL, device=self.path)
        struct.pack_into("<III", d, 16, 1, 1000, round(self.node.fps * 1000))

    def _g_fmt(self, d: bytearray) -> None:
        self._fill_fmt(d)

    def _fill_fmt(self, d: bytearray) -> None:
        w, h, f = self._st.fmt
        struct.pack_into("<IIIIII", d, _PIX[self._bits], w, h, f, 1, 2 * w if f == YUYV else 0, 2 * w * h)

    def _s_fmt(self, d: bytearray) -> None:
        if "VIDIOC_QUERYCAP" not in self.called():
            self.violations.append("VIDIOC_S_FMT before VIDIOC_QUERYCAP")
        if self._st.streaming or self._st.buffers:
            self._bad("VIDIOC_S_FMT", "format change with buffers allocated", errno.EBUSY)
        (type_,) = struct.unpack_from("<I", d, 0)
        w, h, f = struct.unpack_from("<III", d, _PIX[self._bits])
        if type_ != 1:
            self._bad("VIDIOC_S_FMT", f"buffer type {type_}")
        if (w, h, f) not in self._sizes():  # like a driver: fall back to what it has
            w, h, f = self._sizes()[0]
        self._st.fmt = (w, h, f)
        self._fill_fmt(d)

    def _reqbufs(self, d: bytearray) -> None:
        count, type_, memory = struct.unpack_from("<III", d, 0)
        if "VIDIOC_S_FMT" not in self.called():
            self.violations.append("VIDIOC_REQBUFS before VIDIOC_S_FMT")
        if type_ != 1 or memory != 1:
            self._bad("VIDIOC_REQBUFS", f"type {type_} memory {memory}")
        if self._st.streaming:
            self._bad("VIDIOC_REQBUFS", "while streaming", errno.EBUSY)
        w, h, _ = self._st.fmt
        count = min(count, 8)
        self._st.buffers = [bytearray(2 * w * h) for _ in range(count)]
        self._st.queued.clear()
        self._st.done.clear()
        struct.pack_into("<I", d, 0, count)

    def _buf_index(self, name: str, d: bytearray) -> int:
        b = _BUF[self._bits]
        index, type_ = struct.unpack_from("<II", d, 0)
        (memory,) = struct.unpack_from("<I", d, b["memory"])
        if type_ != 1 or memory != 1 or index >= len(self._st.buffers):
            self._bad(name, f"index {index} type {type_} memory {memory}")
        return int(index)

    def _querybuf(self, d: bytearray) -> None:
        i, b = self._buf_index("VIDIOC_QUERYBUF", d), _BUF[self._bits]
        struct.pack_into("<I", d, b["offset"], i * 0x100000)
        struct.pack_into("<I", d, b["length"], len(self._st.buffers[i]))
        struct.pack_into("<I", d, b["flags"], 1 | (2 if i in self._st.queued else 0))

    def _qbuf(self, d: bytearray) -> None:
        i = self._buf_index("VIDIOC_QBUF", d)
        if i in self._st.queued or any(x[0] == i for x in self._st.done):
            self._bad("VIDIOC_QBUF", f"buffer {i} is already queued")
        self._st.queued.append(i)

    def _dqbuf(self, d: bytearray) -> None:
        b = _BUF[self._bits]
        (type_,), (memory,) = struct.unpack_from("<I", d, 4), struct.unpack_from("<I", d, b["memory"])
        if type_ != 1 or memory != 1:
            self._bad("VIDIOC_DQBUF", f"type {type_} memory {memory}")
        if not self._st.streaming or not self._st.done:
            raise BlockingIOError(errno.EAGAIN, "no buffer ready")
        os.read(self._rfd, 1)
        i, seq, t, used = self._st.done.pop(0)
        struct.pack_into("<III", d, 0, i, 1, used)
        struct.pack_into("<II", d, b["flags"], 0x1 | 0x4 | 0x2000, 1)
        off, fmt = _TIMEVAL[self._bits]
        struct.pack_into(fmt, d, off, int(t), round((t - int(t)) * 1e6))
        struct.pack_into("<II", d, b["sequence"], seq, 1)
        struct.pack_into("<I", d, b["offset"], i * 0x100000)
        struct.pack_into("<I", d, b["length"], len(self._st.buffers[i]))

    def _streamon(self, d: bytearray) -> None:
        if struct.unpack_from("<i", d, 0)[0] != 1:
            self._bad("VIDIOC_STREAMON", "buffer type")
        if not self._st.queued:
            self._bad("VIDIOC_STREAMON", "no buffers queued")
        if not self._st.streaming:
            self._st.streaming = True
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="fake-v4l2", daemon=True)
            self._thread.start()

    def _streamoff(self, d: bytearray) -> None:
        self._st.streaming = False
        self._stop.set()
        self._st.queued.clear()
        while self._st.done:
            self._st.done.pop()
            os.read(self._rfd, 1)

    def _stop_thread(self) -> None:
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def _queryctrl(self, d: bytearray) -> None:
        (cid,) = struct.unpack_from("<I", d, 0)
        c = self.node.controls.get(cid)
        if c is None:
            raise IoctlError("VIDIOC_QUERYCTRL", errno.EINVAL, device=self.path)
        inactive = cid == CID_EXPOSURE_ABSOLUTE and self.node.controls[CID_EXPOSURE_AUTO].value != 1
        d[8:40] = c.name.encode().ljust(32, b"\0")
        struct.pack_into("<iiiiI", d, 40, c.minimum, c.maximum, c.step, c.default, 0x10 if inactive else 0)
        struct.pack_into("<I", d, 4, c.type)

    def _g_ctrl(self, d: bytearray) -> None:
        (cid,) = struct.unpack_from("<I", d, 0)
        if cid not in self.node.controls:
            raise IoctlError("VIDIOC_G_CTRL", errno.EINVAL, device=self.path)
        struct.pack_into("<i", d, 4, self.node.controls[cid].value)

    def _s_ctrl(self, d: bytearray) -> None:
        cid, value = struct.unpack_from("<Ii", d, 0)
        c = self.node.controls.get(cid)
        if c is None:
            raise IoctlError("VIDIOC_S_CTRL", errno.EINVAL, device=self.path)
        if not c.minimum <= value <= c.maximum:
            self._bad("VIDIOC_S_CTRL", f"{c.name}={value} out of range", errno.ERANGE)
        if cid == CID_EXPOSURE_ABSOLUTE and self.node.controls[CID_EXPOSURE_AUTO].value != 1:
            self.violations.append("EXPOSURE_ABSOLUTE set while auto exposure is on (ignored)")
            return
        c.value = value
        if cid in (CID_EXPOSURE_ABSOLUTE, CID_GAIN):
            land = self._st.sequence + self.node.latency_frames
            ctrls = self.node.controls
            self._st.pending.append((land, ctrls[CID_EXPOSURE_ABSOLUTE].value, ctrls[CID_GAIN].value))

    # ---- the sensor -----------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.node.fps
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))
            if self._stop.is_set():
                return
            with self._lock:
                if self._st.streaming:
                    self._sensor_frame()

    def _sensor_frame(self) -> None:
        st = self._st
        st.sequence += 1
        while st.pending and st.pending[0][0] <= st.sequence:
            _, st.sensor_exposure, st.sensor_gain = st.pending.pop(0)
        if self.drop_frames > 0 or not st.queued:
            self.drop_frames = max(0, self.drop_frames - 1)
            return  # no buffer: the frame is lost, the sequence number still advances
        i = st.queued.pop(0)
        used = self._render(st.buffers[i])
        st.done.append((i, st.sequence, time.monotonic(), used))
        os.write(self._wfd, b"\x01")

    def _render(self, out: bytearray) -> int:
        w, h, f = self._st.fmt
        ae = self.node.controls.get(CID_EXPOSURE_AUTO)
        auto = ae is None or ae.value != 1  # no controls at all: the camera runs its own AE
        exposure_s = 0.0156 if auto else self._st.sensor_exposure * 1e-4
        key = (w, h, f, exposure_s, self._st.sensor_gain)
        data = self._rendered.get(key)
        if data is None:  # the scene is static: a frame per (exposure, gain), as cheap as a kernel's copy
            lin = sim_scene(w, h) * (exposure_s * self._st.sensor_gain / 16.0)
            rgb = (255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2) + 0.5).astype(np.uint8)
            if f == MJPG:
                _ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
                data = jpg.tobytes()
            else:
                data = rgb_to_yuyv(rgb).tobytes()
            if len(self._rendered) >= 16:
                self._rendered.clear()
            self._rendered[key] = data
        out[: len(data)] = data
        return len(data)


def rgb_to_yuyv(rgb: np.ndarray) -> np.ndarray:
    """Pack (H, W, 3) uint8 RGB as YUYV 4:2:2 (H, W, 2): BT.601 limited range, as UVC webcams send
    it (Y0 U Y1 V per pixel pair, chroma averaged over the pair)."""
    f = rgb.astype(np.float64)
    r, g, b = f[..., 0], f[..., 1], f[..., 2]
    y = 16 + (65.738 * r + 129.057 * g + 25.064 * b) / 256
    cb = 128 + (-37.945 * r - 74.494 * g + 112.439 * b) / 256
    cr = 128 + (112.439 * r - 94.154 * g - 18.285 * b) / 256
    out = np.empty((*rgb.shape[:2], 2), np.uint8)
    out[..., 0] = np.clip(np.rint(y), 0, 255)
    out[:, 0::2, 1] = np.clip(np.rint((cb[:, 0::2] + cb[:, 1::2]) / 2), 0, 255)
    out[:, 1::2, 1] = np.clip(np.rint((cr[:, 0::2] + cr[:, 1::2]) / 2), 0, 255)
    return out


def fake_uvc_calibration(width: int = 640, height: int = 480) -> Calibration:
    """What a webcam module's vendor would ship for the fake camera: an equidistant 180-degree
    fisheye filling the frame's height, centred, and the gamma-2.2 response the fake applies
    (the YUYV round trip adds under a code of error). No photometric scale: unit ``relative``."""
    f = (min(width, height) / 2.0) / (np.pi / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    z = np.arange(256, dtype=np.float64) / 255.0
    inverse = z ** 2.2
    inverse[0] = 0.5 * inverse[1]  # strictly increasing
    # The calibration file's schema (CONVENTIONS.md), as the module's EEPROM would hold it
    return Calibration.from_json({
        "version": Calibration.VERSION,
        "source": "factory",
        "fisheye": {"model": "opencv-fisheye", "image_size": [width, height], "K": K.tolist(),
                    "D": [0.0, 0.0, 0.0, 0.0], "fov_deg": 180.0},
        "response": {"model": "table", "bits": 8, "method": "factory", "inverse": [inverse.tolist()] * 3},
        "pose": {"rotation": np.eye(3).tolist(), "position": [0.0, 0.0, 0.0]},
    })


class FakeUVCCamera(V4L2Camera):
    """The real V4L2 driver on a :class:`FakeV4L2Node`, with the module's factory calibration
    (:func:`fake_uvc_calibration`) as a real camera module with an EEPROM would carry."""

    def __init__(self, node: FakeV4L2Node | None = None) -> None:
        self.node = node or FakeV4L2Node()
        super().__init__(self.node.path, opener=self.node.open)

    def factory_calibration(self) -> Calibration:
        return fake_uvc_calibration()
