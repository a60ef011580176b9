"""A simulated UVC camera as a pyusb backend, so the real pyusb code path runs in tests.

:class:`SimUsbBackend` subclasses ``usb.backend.IBackend``: ``usb.core.find(backend=...)`` enumerates
its devices, reads their descriptors, opens them, claims interfaces and sends control transfers
through pyusb's own ``Device`` / ``_ResourceManager`` code exactly as with libusb. Each
:class:`SimUvcDevice` has a real UVC 1.1 descriptor set (IAD device, a VideoControl interface with
header, camera terminal, processing unit, extension unit and output terminal; a VideoStreaming
interface), string descriptors, and control state answering GET_CUR/MIN/MAX/RES/LEN/INFO/DEF and
SET_CUR like firmware does:

- camera terminal (id 1): CT_AE_MODE (1 byte; RES = bitmap of supported modes: manual 1,
  aperture priority 8; default 8) and CT_EXPOSURE_TIME_ABSOLUTE (4 bytes LE, 100 us units,
  1..5000, default 156; setting it while AE is automatic STALLs with "wrong state");
- processing unit (id 2): PU_GAIN (2 bytes, 16..255, default 16);
- extension unit (id 3, GUID ``EXTENSION_GUID``): selector 1 (4 bytes), selector 2 (1 byte);
- anything else STALLs (``USBError`` errno 32, as libusb reports LIBUSB_ERROR_PIPE) and sets the
  VC request error code control (selector 2 on entity 0) like the spec says.

Fault injection (real code, switchable per test): ``kernel_driver_bound=True`` makes the VC
interface look bound to uvcvideo (``is_kernel_driver_active`` True, claiming it fails with errno
16 / LIBUSB_ERROR_BUSY); ``unplug()`` makes every transfer fail with errno 19 (LIBUSB_ERROR_NO_DEVICE)
and hides the device from enumeration; ``replug()`` brings it back with controls at their defaults.

:class:`SimUvcFrames` is a frame source for ``lightprobe.drivers.uvc.UvcCamera``: it renders the fixed ramp
scene with the exposure and gain the device's sensor is using (a SET_CUR lands
``latency_frames`` frames later), because frames never travel over this control path.
Importing this module does nothing.
"""

from __future__ import annotations

import array
import asyncio
import struct
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import usb.backend
import usb.core

from lightprobe.drivers.base import Mode, PixelFormat
from lightprobe.sim.v4l2_fake import sim_scene

__all__ = ["EXTENSION_GUID", "SimUsbBackend", "SimUvcDevice", "SimUvcFrames"]

EXTENSION_GUID = bytes.fromhex("6c69676874707262652d73696d2d7875")  # "lightprbe-sim-xu"
SET_CUR, GET_CUR, GET_MIN, GET_MAX, GET_RES, GET_LEN, GET_INFO, GET_DEF = 0x01, 0x81, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87
CT_ID, PU_ID, XU_ID, OT_ID = 1, 2, 3, 4
VC_IF, VS_IF = 0, 1
# libusb error -> (errno, message) as pyusb's libusb1 backend raises them
_PIPE, _BUSY, _NODEV = (-9, 32, "Pipe error"), (-6, 16, "Resource busy"), (-4, 19, "No such device (it may have been disconnected)")


def _usb_error(kind: tuple[int, int, str]) -> usb.core.USBError:
    code, errno_, msg = kind
    return usb.core.USBError(f"[Errno {errno_}] {msg}", code, errno_)


@dataclass
class _Control:
    length: int
    minimum: int | None
    maximum: int | None
    res: int
    default: int
    cur: int = 0
    signed: bool = False

    def __post_init__(self) -> None:
        self.cur = self.default

    def encode(self, v: int) -> bytes:
        return int(v).to_bytes(self.length, "little", signed=self.signed)


def _default_controls() -> dict[tuple[int, int], _Control]:
    return {
        (CT_ID, 0x02): _Control(1, None, None, 0x09, 8),  # AE mode: RES is the supported-mode bitmap
        (CT_ID, 0x04): _Control(4, 1, 5000, 1, 156),  # exposure time absolute, 100 us
        (PU_ID, 0x04): _Control(2, 16, 255, 1, 16),  # gain
        (XU_ID, 0x01): _Control(4, 0, 0xFFFF, 1, 0x1234),
        (XU_ID, 0x02): _Control(1, 0, 3, 1, 0),
    }


def _vc_descriptors() -> bytes:
    """Class-specific VideoControl descriptors (UVC 1.1, section 3.7)."""
    ct = struct.pack("<BBBBHBBHHHB3s", 18, 0x24, 0x02, CT_ID, 0x0201, 0, 0, 0, 0, 0, 3, bytes([0x0A, 0, 0]))
    pu = struct.pack("<BBBBBHB2sBB", 12, 0x24, 0x05, PU_ID, CT_ID, 0, 2, bytes([0x00, 0x02]), 0, 0)
    xu = struct.pack("<BBBB16sBBBBBB", 26, 0x24, 0x06, XU_ID, EXTENSION_GUID, 2, 1, PU_ID, 1, 0x03, 0)
    ot = struct.pack("<BBBBHBBB", 9, 0x24, 0x03, OT_ID, 0x0101, 0, XU_ID, 0)
    body = ct + pu + xu + ot
    header = struct.pack("<BBBHHIBB", 13, 0x24, 0x01, 0x0110, 13 + len(body), 48_000_000, 1, VS_IF)
    return header + body


@dataclass
class SimUvcDevice:
    """One simulated UVC camera (state shared by every handle opened on it)."""

    vid: int = 0x1209
    pid: int = 0x0001
    serial: str = "SIM0001"
    product: str = "Simulated UVC Camera"
    manufacturer: str = "lightprobe sim"
    bus: int = 1
    address: int = 5
    kernel_driver_bound: bool = False
    latency_frames: int = 3
    plugged: bool = True
    controls: dict[tuple[int, int], _Control] = field(default_factory=_default_controls)
    claimed: set[int] = field(default_factory=set)
    error_code: int = 0
    log: list[tuple[int, int, int, int, bytes]] = field(default_factory=list)  # (type, req, wValue, wIndex, data)
    # sensor side: control changes in flight and the values the sensor uses now
    sequence: int = -1
    pending: list[tuple[int, int, int]] = field(default_factory=list)
    sensor: tuple[int, int] = (156, 16)

    def unplug(self) -> None:
        self.plugged = False
        self.claimed.clear()

    def replug(self) -> None:
        """Back on the bus with every control at its default (firmware power-up)."""
        self.controls = _default_controls()
        self.plugged, self.pending, self.sensor = True, [], (156, 16)

    def value(self, entity: int, selector: int) -> int:
        return self.controls[(entity, selector)].cur

    # ---- the sensor (driven by SimUvcFrames) ----------------------------------------------------
    def next_sensor_frame(self) -> tuple[int, float, float]:
        """Advance one frame; returns (sequence, exposure_s, gain) the sensor used for it."""
        self.sequence += 1
        while self.pending and self.pending[0][0] <= self.sequence:
            _, exp, gain = self.pending.pop(0)
            self.sensor = (exp, gain)
        auto = self.value(CT_ID, 0x02) != 1
        exp_s = 0.0156 if auto else self.sensor[0] * 1e-4
        return self.sequence, exp_s, self.sensor[1] / 16.0

    # ---- the control endpoint -------------------------------------------------------------------
    def control(self, bm: int, req: int, w_value: int, w_index: int, length: int, data: bytes) -> bytes:
        """Handle a class request to an interface; returns IN data. Raises USBError on STALL."""
        selector, entity, intf = w_value >> 8, w_index >> 8, w_index & 0xFF
        self.log.append((bm, req, w_value, w_index, bytes(data)))
        if intf != VC_IF or (bm & 0x60) != 0x20:
            return self._stall(7)
        if entity == 0 and selector == 0x02 and req == GET_CUR:  # VC_REQUEST_ERROR_CODE_CONTROL
            return bytes([self.error_code])
        c = self.controls.get((entity, selector))
        if c is None:
            return self._stall(5 if entity not in (CT_ID, PU_ID, XU_ID) else 6)
        if req == SET_CUR:
            return self._set(entity, selector, c, data)
        answers = {
            GET_CUR: c.encode(c.cur) if c.length else b"", GET_DEF: c.encode(c.default),
            GET_RES: c.encode(c.res), GET_LEN: struct.pack("<H", c.length),
            GET_INFO: bytes([0x03 | (0x04 if self._disabled(entity, selector) else 0)]),
        }  # fmt: skip
        if req in (GET_MIN, GET_MAX) and c.minimum is not None and c.maximum is not None:
            answers[req] = c.encode(c.minimum if req == GET_MIN else c.maximum)
        if req not in answers:
            return self._stall(7)
        self.error_code = 0
        return answers[req]

    def _disabled(self, entity: int, selector: int) -> bool:
        return (entity, selector) == (CT_ID, 0x04) and self.value(CT_ID, 0x02) != 1

    def _set(self, entity: int, selector: int, c: _Control, data: bytes) -> bytes:
        if len(data) != c.length:
            return self._stall(7)
        v = int.from_bytes(data, "little", signed=c.signed)
        if (entity, selector) == (CT_ID, 0x02):
            if v & c.res != v or bin(v).count("1") != 1:
                return self._stall(4)
        elif c.minimum is not None and c.maximum is not None and not c.minimum <= v <= c.maximum:
            return self._stall(4)
        if self._disabled(entity, selector):
            return self._stall(2)  # wrong state: exposure is automatic
        c.cur = v
        self.error_code = 0
        if (entity, selector) in ((CT_ID, 0x04), (PU_ID, 0x04)):
            land = self.sequence + self.latency_frames
            self.pending.append((land, self.value(CT_ID, 0x04), self.value(PU_ID, 0x04)))
        return b""

    def _stall(self, code: int) -> bytes:
        self.error_code = code
        raise _usb_error(_PIPE)

    def string(self, index: int) -> bytes:
        if index == 0:
            return bytes([4, 3]) + struct.pack("<H", 0x0409)
        s = {1: self.manufacturer, 2: self.product, 3: self.serial}.get(index)
        if s is None:
            raise _usb_error(_PIPE)
        enc = s.encode("utf-16-le")
        return bytes([2 + len(enc), 3]) + enc


class SimUsbBackend(usb.backend.IBackend):  # type: ignore[misc]
    """A pyusb backend whose bus holds :class:`SimUvcDevice` objects."""

    def __init__(self, *devices: SimUvcDevice) -> None:
        super().__init__()
        self.devices = list(devices)

    def enumerate_devices(self) -> Any:
        return [d for d in self.devices if d.plugged]

    def get_parent(self, dev: SimUvcDevice) -> None:
        return None

    def get_device_descriptor(self, dev: SimUvcDevice) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0xEF, bDeviceSubClass=2,
            bDeviceProtocol=1, bMaxPacketSize0=64, idVendor=dev.vid, idProduct=dev.pid,
            bcdDevice=0x0100, iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
            address=dev.address, bus=dev.bus, port_number=1, port_numbers=(1,), speed=3,
        )  # fmt: skip

    def get_configuration_descriptor(self, dev: SimUvcDevice, config: int) -> SimpleNamespace:
        if config != 0:
            raise IndexError(f"Invalid configuration index {config}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=0, bNumInterfaces=2, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0x80, bMaxPower=250, extra_descriptors=[],
        )  # fmt: skip

    def get_interface_descriptor(self, dev: SimUvcDevice, intf: int, alt: int, config: int) -> SimpleNamespace:
        if config != 0 or intf > 1 or alt != 0:
            raise IndexError(f"Invalid interface index {intf}/{alt}")
        vc = intf == VC_IF
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=intf, bAlternateSetting=0,
            bNumEndpoints=1 if vc else 0, bInterfaceClass=0x0E, bInterfaceSubClass=1 if vc else 2,
            bInterfaceProtocol=0, iInterface=0, extra_descriptors=list(_vc_descriptors()) if vc else [],
        )  # fmt: skip

    def get_endpoint_descriptor(self, dev: SimUvcDevice, ep: int, intf: int, alt: int, config: int) -> SimpleNamespace:
        if intf != VC_IF or ep != 0 or alt != 0 or config != 0:
            raise IndexError(f"Invalid endpoint index {ep}")
        return SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=0x83, bmAttributes=3,
                               wMaxPacketSize=16, bInterval=8, bRefresh=0, bSynchAddress=0,
                               extra_descriptors=[5, 0x25, 0x03, 16, 0])  # fmt: skip

    def open_device(self, dev: SimUvcDevice) -> SimUvcDevice:
        if not dev.plugged:
            raise _usb_error(_NODEV)
        return dev

    def close_device(self, dev_handle: SimUvcDevice) -> None:
        dev_handle.claimed.clear()

    def set_configuration(self, dev_handle: SimUvcDevice, config_value: int) -> None:
        self._alive(dev_handle)

    def get_configuration(self, dev_handle: SimUvcDevice) -> int:
        self._alive(dev_handle)
        return 1

    def set_interface_altsetting(self, dev_handle: SimUvcDevice, intf: int, altsetting: int) -> None:
        self._alive(dev_handle)

    def claim_interface(self, dev_handle: SimUvcDevice, intf: int) -> None:
        self._alive(dev_handle)
        if dev_handle.kernel_driver_bound:
            raise _usb_error(_BUSY)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle: SimUvcDevice, intf: int) -> None:
        dev_handle.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle: SimUvcDevice, intf: int) -> bool:
        self._alive(dev_handle)
        return dev_handle.kernel_driver_bound

    def detach_kernel_driver(self, dev_handle: SimUvcDevice, intf: int) -> None:
        dev_handle.kernel_driver_bound = False

    def attach_kernel_driver(self, dev_handle: SimUvcDevice, intf: int) -> None:
        dev_handle.kernel_driver_bound = True

    def ctrl_transfer(self, dev_handle: SimUvcDevice, bmRequestType: int, bRequest: int, wValue: int,
                      wIndex: int, data: array.array, timeout: int) -> int:  # type: ignore[type-arg]  # fmt: skip
        self._alive(dev_handle)
        length = len(data) * data.itemsize
        if bmRequestType == 0x80 and bRequest == 0x06 and wValue >> 8 == 3:  # GET_DESCRIPTOR(string)
            out = dev_handle.string(wValue & 0xFF)
        elif bmRequestType & 0x1F == 1:  # to an interface
            if (wIndex & 0xFF) not in dev_handle.claimed:
                raise _usb_error(_BUSY)
            out = dev_handle.control(bmRequestType, bRequest, wValue, wIndex, length,
                                     data.tobytes() if bmRequestType & 0x80 == 0 else b"")  # fmt: skip
        else:
            raise _usb_error(_PIPE)
        if bmRequestType & 0x80 == 0:
            return length
        n = min(length, len(out))
        data[:n] = array.array(data.typecode, out[:n])
        return n

    @staticmethod
    def _alive(dev: SimUvcDevice) -> None:
        if not dev.plugged:
            raise _usb_error(_NODEV)


class SimUvcFrames:
    """Frames for ``lightprobe.drivers.uvc.UvcCamera`` from a :class:`SimUvcDevice`'s sensor state.

    ``fps`` paces frames (``asyncio.sleep``); timestamps are CLOCK_MONOTONIC when a frame is
    complete (rendered), as the frame source protocol asks.
    The picture is the ramp of ``lightprobe.sim.v4l2_fake.sim_scene`` through a gamma-2.2 response.
    """

    def __init__(self, device: SimUvcDevice, *, width: int = 320, height: int = 240, fps: float = 120.0) -> None:
        self.device, self.fps = device, fps
        self.modes = (Mode(width, height, PixelFormat.RGB8, fps),)
        self.mode = self.modes[0]
        self._next_t = 0.0
        self.running = False

    async def start(self) -> None:
        self.running, self._next_t = True, time.monotonic()

    async def stop(self) -> None:
        self.running = False

    async def next_frame(self, timeout: float) -> tuple[np.ndarray, int, float]:  # noqa: ASYNC109 - the protocol's signature
        if not self.running:
            raise RuntimeError("frame source is stopped")
        self._next_t += 1.0 / self.fps
        delay = self._next_t - time.monotonic()
        if delay > timeout:
            await asyncio.sleep(timeout)
            raise TimeoutError
        await asyncio.sleep(max(0.0, delay))
        if not self.device.plugged:
            raise ConnectionError("device unplugged")
        seq, exp, gain = self.device.next_sensor_frame()
        lin = sim_scene(self.mode.width, self.mode.height) * (exp * gain)
        rgb = (255.0 * np.clip(lin, 0.0, 1.0) ** (1 / 2.2) + 0.5).astype(np.uint8)
        return rgb, seq, time.monotonic()
