"""UVC camera controls over USB (pyusb), and a camera that pairs them with a frame source.

UVC 1.1 class requests on the VideoControl (VC) interface (NOTES.md): SET_CUR is bmRequestType
0x21 / bRequest 0x01, GET_* are 0xA1 with GET_CUR 0x81, MIN 0x82, MAX 0x83, RES 0x84, LEN 0x85,
INFO 0x86, DEF 0x87; ``wValue = selector << 8``; ``wIndex = entity id << 8 | VC interface number``.
The camera terminal id, the processing unit id and the extension units come from the VC
interface's class-specific descriptors (:func:`parse_vc_descriptors`).

Controls: CT_AE_MODE (0x02, 1 byte: 1 manual, 2 auto, 4 shutter priority, 8 aperture priority),
CT_EXPOSURE_TIME_ABSOLUTE (0x04, 4 bytes LE, 100 us units), PU_GAIN (0x04, 2 bytes), and raw
GET/SET_CUR on any extension unit selector. Errors: a STALL (``USBError`` errno 32) is
:class:`ControlNotSupported` (with the device's request error code when it gives one); errno 16 is
:class:`CameraBusy` (uvcvideo holds the interface); errno 19 is :class:`CameraDisconnected`.

Scope. While uvcvideo is bound to a camera, the kernel owns its VC interface and these requests
fail with EBUSY: on a normal unit exposure goes through V4L2 (uvcvideo maps V4L2 control ids to
these same CT/PU requests). :class:`UvcControls` is for devices *not* bound to uvcvideo, and is
what :func:`v4l2_controls_with_uvc_fallback` tries when a V4L2 node lacks the exposure controls.
:class:`UvcCamera` composes the controls with a :class:`FrameSource`; frames never travel over
this path, so on hardware the frame source is a separate capture path, and in tests it is
``lightprobe.sim.usb.SimUvcFrames`` (simulated frames rendered from the simulated device's sensor state).
Importing this module does nothing (pyusb is imported, no device is touched).
"""

from __future__ import annotations

import asyncio
import errno
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import usb.core
import usb.util

from lightprobe.drivers.base import (
    Camera,
    CameraBusy,
    CameraDisconnected,
    CameraError,
    CameraUnavailable,
    Capabilities,
    CaptureTimeout,
    ControlNotSupported,
    Controls,
    Frame,
    FrameMetadata,
    Mode,
)
from lightprobe.drivers.v4l2.controls import (
    EXPOSURE_UNIT_S,
    ControlBackend,
    ControlInfo,
    ControlRanges,
    V4L2Controls,
)
from lightprobe.drivers.v4l2.settle import SettleTracker, frame_level

__all__ = [
    "FrameSource",
    "UvcCamera",
    "UvcControls",
    "VcTopology",
    "find_uvc_devices",
    "parse_vc_descriptors",
    "v4l2_controls_with_uvc_fallback",
]

log = logging.getLogger(__name__)

SET_CUR, GET_CUR, GET_MIN, GET_MAX, GET_RES, GET_LEN, GET_INFO, GET_DEF = 0x01, 0x81, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87
RT_SET, RT_GET = 0x21, 0xA1  # class request to an interface, OUT / IN
CT_AE_MODE, CT_EXPOSURE_TIME_ABSOLUTE, PU_GAIN = 0x02, 0x04, 0x04
AE_MANUAL, AE_AUTO, AE_SHUTTER_PRIORITY, AE_APERTURE_PRIORITY = 1, 2, 4, 8
VC_REQUEST_ERROR_CODE_CONTROL = 0x02
CC_VIDEO, SC_VIDEOCONTROL = 0x0E, 0x01
_ERROR_CODES = {1: "not ready", 2: "wrong state", 3: "power", 4: "out of range", 5: "invalid unit",
                6: "invalid control", 7: "invalid request", 8: "invalid value within range"}  # fmt: skip


@dataclass
class VcTopology:
    """What the VC interface's class-specific descriptors say (UVC 1.1 section 3.7.2)."""

    interface: int
    camera_terminal: int | None = None
    camera_controls: int = 0  # bmControls bitmap of the camera terminal
    processing_unit: int | None = None
    processing_controls: int = 0
    extension_units: dict[int, bytes] = field(default_factory=dict)  # unit id -> GUID
    uvc_version: int = 0

    def ct_supports(self, bit: int) -> bool:
        return bool(self.camera_controls >> bit & 1)


def parse_vc_descriptors(interface: int, extra: bytes | list[int]) -> VcTopology:
    """Walk the CS_INTERFACE (0x24) descriptors: header, camera terminal, processing and
    extension units. Malformed lengths stop the walk (never loop)."""
    data, topo, i = bytes(extra), VcTopology(interface), 0
    while i + 3 <= len(data):
        length, dtype, sub = data[i], data[i + 1], data[i + 2]
        if length < 3 or i + length > len(data):
            break
        d = data[i : i + length]
        if dtype == 0x24 and sub == 0x01 and length >= 5:
            topo.uvc_version = int.from_bytes(d[3:5], "little")
        elif dtype == 0x24 and sub == 0x02 and length >= 8 and int.from_bytes(d[4:6], "little") == 0x0201:
            topo.camera_terminal = d[3]
            if length >= 15:
                n = d[14]
                topo.camera_controls = int.from_bytes(d[15 : 15 + n], "little")
        elif dtype == 0x24 and sub == 0x05 and length >= 8:
            topo.processing_unit, n = d[3], d[7]
            topo.processing_controls = int.from_bytes(d[8 : 8 + n], "little")
        elif dtype == 0x24 and sub == 0x06 and length >= 20:
            topo.extension_units[d[3]] = bytes(d[4:20])
        i += length
    return topo


def find_uvc_devices(backend: Any = None, vid: int | None = None, pid: int | None = None) -> list[usb.core.Device]:
    """USB devices with a UVC VideoControl interface (optionally one VID:PID)."""
    found = []
    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.NoBackendError:
        return []
    for dev in devices:
        if (vid is not None and dev.idVendor != vid) or (pid is not None and dev.idProduct != pid):
            continue
        try:
            if _vc_interface(dev) is not None:
                found.append(dev)
        except (usb.core.USBError, ValueError) as e:
            log.debug("skipping %04x:%04x: %s", dev.idVendor, dev.idProduct, e)
    return found


def _vc_interface(dev: usb.core.Device) -> Any:
    for intf in dev[0]:  # the first (usually only) configuration
        if intf.bInterfaceClass == CC_VIDEO and intf.bInterfaceSubClass == SC_VIDEOCONTROL:
            return intf
    return None


class UvcControls(ControlRanges):
    """Exposure/gain (and extension-unit) controls of one UVC device over pyusb.

    Implements :class:`lightprobe.drivers.v4l2.controls.ControlBackend`. Gain factor = raw / GET_DEF.
    """

    def __init__(self, device: usb.core.Device, *, timeout_ms: int = 500) -> None:
        self.dev = device
        self.name = f"uvc:{device.idVendor:04x}:{device.idProduct:04x}"
        self.timeout_ms = timeout_ms
        self.topo: VcTopology | None = None
        self.exposure: ControlInfo | None = None
        self.gain: ControlInfo | None = None

    # ---- transfers ------------------------------------------------------------------------------
    def _windex(self, entity: int) -> int:
        assert self.topo is not None
        return (entity << 8) | self.topo.interface

    def _transfer(self, what: str, fn: Callable[[], Any]) -> Any:
        try:
            return fn()
        except usb.core.USBTimeoutError as e:
            raise CameraError(f"{self.name}: {what} timed out", device=self.name) from e
        except usb.core.USBError as e:
            raise self._map(what, e) from e

    def _map(self, what: str, e: usb.core.USBError) -> CameraError:
        code = e.errno
        if code == errno.EPIPE:
            why = self._request_error()
            return ControlNotSupported(f"{self.name}: {what} not supported (STALL{why})", device=self.name)
        if code == errno.EBUSY:
            return CameraBusy(
                f"{self.name}: the VideoControl interface is claimed by a kernel driver (uvcvideo); "
                "use the V4L2 backend (--camera v4l2:/dev/v4l/by-id/...) or unbind uvcvideo",
                device=self.name,
            )
        if code in (errno.ENODEV, errno.ENOENT, errno.ESHUTDOWN):
            return CameraDisconnected(f"{self.name} was disconnected during {what}", device=self.name)
        if code in (errno.EACCES, errno.EPERM):
            return CameraUnavailable(f"{self.name}: no permission (install the udev rule)", device=self.name)
        return CameraError(f"{self.name}: {what} failed: {e}", device=self.name)

    def _request_error(self) -> str:
        """The VC request error code after a STALL (UVC 1.1 4.2.1.2), if the device gives one."""
        try:
            code = self.dev.ctrl_transfer(RT_GET, GET_CUR, VC_REQUEST_ERROR_CODE_CONTROL << 8,
                                          self._windex(0), 1, self.timeout_ms)  # fmt: skip
            return f": {_ERROR_CODES.get(code[0], f'code {code[0]}')}" if len(code) else ""
        except usb.core.USBError:
            return ""

    def get(self, entity: int, selector: int, length: int, request: int = GET_CUR) -> bytes:
        """A GET_* request; returns the bytes the device sent."""
        what = f"GET 0x{request:02x} entity {entity} selector 0x{selector:02x}"
        out = self._transfer(what, lambda: self.dev.ctrl_transfer(
            RT_GET, request, selector << 8, self._windex(entity), length, self.timeout_ms))  # fmt: skip
        return bytes(out)

    def set_cur(self, entity: int, selector: int, data: bytes) -> None:
        what = f"SET_CUR entity {entity} selector 0x{selector:02x}"
        self._transfer(what, lambda: self.dev.ctrl_transfer(
            RT_SET, SET_CUR, selector << 8, self._windex(entity), data, self.timeout_ms))  # fmt: skip

    def get_int(self, entity: int, selector: int, length: int, request: int = GET_CUR) -> int:
        return int.from_bytes(self.get(entity, selector, length, request), "little")

    def xu_get(self, unit: int, selector: int, length: int | None = None) -> bytes:
        """GET_CUR on an extension-unit control (length from GET_LEN when not given)."""
        self._check_xu(unit)
        n = length if length is not None else self.get_int(unit, selector, 2, GET_LEN)
        return self.get(unit, selector, n)

    def xu_set(self, unit: int, selector: int, data: bytes) -> None:
        self._check_xu(unit)
        self.set_cur(unit, selector, data)

    def _check_xu(self, unit: int) -> None:
        if self.topo is None:
            self.open()
        assert self.topo is not None
        if unit not in self.topo.extension_units:
            raise ControlNotSupported(f"{self.name} has no extension unit {unit}", device=self.name)

    # ---- lifecycle ------------------------------------------------------------------------------
    def open(self) -> None:
        """Find the VC interface and its topology; claim it (CameraBusy if uvcvideo holds it)."""
        intf = self._transfer("reading descriptors", lambda: _vc_interface(self.dev))
        if intf is None:
            raise CameraUnavailable(f"{self.name} has no UVC VideoControl interface", device=self.name)
        self.topo = parse_vc_descriptors(intf.bInterfaceNumber, intf.extra_descriptors)
        n = self.topo.interface
        if self._transfer("kernel driver check", lambda: self.dev.is_kernel_driver_active(n)):
            raise self._map("claim", usb.core.USBError("busy", -6, errno.EBUSY))
        self._transfer("claim", lambda: usb.util.claim_interface(self.dev, n))

    def close(self) -> None:
        try:
            usb.util.dispose_resources(self.dev)
        except usb.core.USBError as e:  # unplugged: nothing to release
            log.debug("%s: dispose: %s", self.name, e)

    def _range(self, entity: int, selector: int, length: int, name: str) -> ControlInfo:
        lo, hi = (self.get_int(entity, selector, length, r) for r in (GET_MIN, GET_MAX))
        res, default = (self.get_int(entity, selector, length, r) for r in (GET_RES, GET_DEF))
        return ControlInfo(selector, name, lo, hi, max(res, 1), default)

    # ---- ControlBackend -------------------------------------------------------------------------
    def probe(self) -> None:
        self.open()
        topo = self.topo
        assert topo is not None
        if topo.camera_terminal is None or not topo.ct_supports(3):
            raise ControlNotSupported(f"{self.name}: camera terminal has no exposure time control", device=self.name)
        self.exposure = self._range(topo.camera_terminal, CT_EXPOSURE_TIME_ABSOLUTE, 4, "exposure")
        self.gain = None
        if topo.processing_unit is not None and topo.processing_controls >> 9 & 1:
            self.gain = self._range(topo.processing_unit, PU_GAIN, 2, "gain")


    @property
    def ae_mode(self) -> int:
        assert self.topo is not None
        assert self.topo.camera_terminal is not None
        return self.get_int(self.topo.camera_terminal, CT_AE_MODE, 1)

    def set_ae_mode(self, mode: int) -> None:
        assert self.topo is not None
        assert self.topo.camera_terminal is not None
        self.set_cur(self.topo.camera_terminal, CT_AE_MODE, bytes([mode]))

    def current(self) -> tuple[float, float]:
        topo = self.topo
        assert topo is not None
        assert topo.camera_terminal is not None
        exp = self.get_int(topo.camera_terminal, CT_EXPOSURE_TIME_ABSOLUTE, 4) * EXPOSURE_UNIT_S
        gain = 1.0
        if self.gain is not None and topo.processing_unit is not None:
            gain = self.get_int(topo.processing_unit, PU_GAIN, 2) / self._unity()
        return exp, gain

    def apply_all(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        self.set_ae_mode(AE_MANUAL)  # first: exposure time is disabled while AE is automatic
        cur_exp, cur_gain = self.current()
        return self.set(cur_exp if exposure_s is None else exposure_s, cur_gain if gain is None else gain)

    def set(self, exposure_s: float | None, gain: float | None) -> tuple[float, float]:
        topo = self.topo
        assert topo is not None
        assert topo.camera_terminal is not None
        assert self.exposure is not None
        exp, g = self.current()
        if exposure_s is not None:
            raw = _clamp(exposure_s / EXPOSURE_UNIT_S, self.exposure)
            self.set_cur(topo.camera_terminal, CT_EXPOSURE_TIME_ABSOLUTE, raw.to_bytes(4, "little"))
            exp = raw * EXPOSURE_UNIT_S
        if gain is not None and self.gain is not None and topo.processing_unit is not None:
            raw = _clamp(gain * self._unity(), self.gain)
            self.set_cur(topo.processing_unit, PU_GAIN, raw.to_bytes(2, "little"))
            g = raw / self._unity()
        return exp, g


def _clamp(value: float, info: ControlInfo) -> int:
    raw = info.minimum + round((value - info.minimum) / info.step) * info.step
    return int(min(max(raw, info.minimum), info.maximum))


def v4l2_controls_with_uvc_fallback(find_usb: Callable[[], usb.core.Device | None]) -> Callable[[Any], ControlBackend]:
    """A ``controls_factory`` for V4L2Camera: V4L2 control ids, else UVC requests over USB.

    ``find_usb`` returns the USB device behind the node (or None). The fallback only helps when
    the VC interface is free; with uvcvideo bound it raises CameraBusy, naming the reason.
    """

    def factory(transport: Any) -> ControlBackend:
        v4l2 = V4L2Controls(transport)
        try:
            v4l2.probe()
        except ControlNotSupported as e:
            dev = find_usb()
            if dev is None:
                raise
            log.info("%s: %s; using UVC requests over USB", transport.path, e)
            uvc = UvcControls(dev)
            uvc.probe()
            return uvc
        return v4l2

    return factory


class FrameSource(Protocol):
    """Where a :class:`UvcCamera` gets pixels: (rgb uint8 (H, W, 3), sequence, CLOCK_MONOTONIC
    seconds when the frame was complete); the camera turns the last into the protocol's start of
    exposure (less the exposure and one frame time of readout)."""

    modes: tuple[Mode, ...]
    mode: Mode

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def next_frame(self, timeout: float) -> tuple[np.ndarray, int, float]: ...  # noqa: ASYNC109


class UvcCamera(Camera):
    """UVC controls over USB + a separate frame source (see the module docstring for when).

    ``opener`` returns the USB device (called on every open, so a replugged device is found
    again and every control is re-applied, AE mode first). Frames have no exposure metadata:
    ``exposure_verified=False`` and the same settling rule as V4L2.
    """

    driver = "uvc"

    def __init__(self, opener: Callable[[], usb.core.Device | None], frames: FrameSource, *,
                 name: str = "uvc", latency_frames: int = 5) -> None:  # fmt: skip
        self.name, self._opener, self._frames = name, opener, frames
        self.latency_frames = latency_frames
        self._ctl: UvcControls | None = None
        self._caps: Capabilities | None = None
        self._tracker: SettleTracker | None = None
        self._desired: tuple[float | None, float | None] = (None, None)
        self._last_seq: int | None = None

    @property
    def capabilities(self) -> Capabilities:
        return self._opened(self._caps)

    @property
    def mode(self) -> Mode:
        return self._frames.mode

    async def open(self) -> None:
        if self._ctl is not None:
            return
        dev = await asyncio.to_thread(self._opener)
        if dev is None:
            raise CameraUnavailable(f"{self.name}: no such USB camera attached", device=self.name)
        ctl = UvcControls(dev)
        try:
            await asyncio.to_thread(ctl.probe)
            exp, gain = await asyncio.to_thread(ctl.apply_all, *self._desired)
        except BaseException:
            ctl.close()
            raise
        self._ctl = ctl
        self._caps = Capabilities(ctl.exposure_range, ctl.gain_range, self._frames.modes, False,
                                  self.latency_frames, model=ctl.name, serial=str(dev.serial_number or ""),
                                  exposure_step_s=float(getattr(ctl, "exposure_step_s", 0.0)))  # fmt: skip
        self._tracker = SettleTracker(self.latency_frames, exposure_s=exp, gain=gain, gamma=1 / 2.2)
        await self._frames.start()

    async def close(self) -> None:
        ctl, self._ctl = self._ctl, None
        if ctl is None:
            return
        await self._frames.stop()
        await asyncio.to_thread(ctl.close)

    async def set_mode(self, mode: Mode) -> None:
        if mode not in self._frames.modes:
            raise ControlNotSupported(f"mode {mode} is not one of {self.name}'s modes", device=self.name)

    async def apply(self, controls: Controls) -> None:
        self.check_controls(controls)
        ctl, tracker = self._require()
        exp, gain = await asyncio.to_thread(ctl.set, controls.exposure_s, controls.gain)
        self._desired = (exp if controls.exposure_s is not None else self._desired[0],
                         gain if controls.gain is not None else self._desired[1])  # fmt: skip
        tracker.request(exp, gain)

    async def capture(self, timeout: float = 1.0) -> Frame:  # noqa: ASYNC109 - the protocol's signature
        _, tracker = self._require()
        try:
            rgb, seq, ts = await self._frames.next_frame(timeout)
        except TimeoutError as e:
            raise CaptureTimeout(f"{self.name}: no frame within {timeout:.3g} s", device=self.name) from e
        except ConnectionError as e:
            raise CameraDisconnected(f"{self.name} was disconnected", device=self.name) from e
        gap = 0 if self._last_seq is None else max(0, seq - self._last_seq - 1)
        self._last_seq = seq
        d = tracker.observe(seq, frame_level(rgb, 255.0))
        ts -= d.exposure_s + 1.0 / max(self._frames.mode.max_fps, 1e-3)  # end of frame -> start of exposure
        meta = FrameMetadata(d.exposure_s, d.gain, ts, seq, exposure_verified=False)
        extra: dict[str, object] = {"dropped": gap, "settled": d.settled, "settle_reason": d.reason}
        return Frame(rgb, meta, self._frames.mode.format, extra=extra)

    def _require(self) -> tuple[UvcControls, SettleTracker]:
        if self._ctl is None or self._tracker is None:
            raise CameraUnavailable(f"{self.name} is not open", device=self.name)
        return self._ctl, self._tracker

