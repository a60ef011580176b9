"""UVC controls over the REAL pyusb code path, on the simulated device backend (lightprobe.sim.usb)."""

from __future__ import annotations

import struct

import pytest
import usb.core

from lightprobe.drivers.base import (
    CameraBusy,
    CameraDisconnected,
    CameraUnavailable,
    ControlNotSupported,
    Controls,
)
from lightprobe.drivers.discovery import open_camera
from lightprobe.drivers.uvc import (
    AE_MANUAL,
    CT_AE_MODE,
    CT_EXPOSURE_TIME_ABSOLUTE,
    UvcCamera,
    UvcControls,
    find_uvc_devices,
    parse_vc_descriptors,
    v4l2_controls_with_uvc_fallback,
)
from lightprobe.drivers.v4l2.camera import V4L2Camera
from lightprobe.sim.usb import (
    EXTENSION_GUID,
    SimUsbBackend,
    SimUvcDevice,
    SimUvcFrames,
    _vc_descriptors,
)
from lightprobe.sim.v4l2_fake import FakeV4L2Node


@pytest.fixture
def sim() -> tuple[SimUvcDevice, SimUsbBackend]:
    dev = SimUvcDevice()
    return dev, SimUsbBackend(dev, SimUvcDevice(vid=0x046D, pid=0x0825, serial="OTHER", address=6))


def _controls(backend: SimUsbBackend, vid: int = 0x1209) -> UvcControls:
    devs = find_uvc_devices(backend, vid=vid)
    assert len(devs) == 1
    c = UvcControls(devs[0])
    c.probe()
    return c


def test_parse_vc_descriptors() -> None:
    topo = parse_vc_descriptors(0, _vc_descriptors())
    assert topo.uvc_version == 0x0110
    assert topo.camera_terminal == 1
    assert topo.ct_supports(1)
    assert topo.ct_supports(3)
    assert not topo.ct_supports(2)
    assert topo.processing_unit == 2
    assert topo.processing_controls >> 9 & 1
    assert topo.extension_units == {3: EXTENSION_GUID}
    # malformed: a zero length must stop the walk, a truncated descriptor is ignored
    assert parse_vc_descriptors(0, b"\x00\x24\x02" + bytes(20)).camera_terminal is None
    assert parse_vc_descriptors(0, _vc_descriptors()[:20]).camera_terminal is None


def test_enumeration_through_pyusb(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    _, backend = sim
    devs = find_uvc_devices(backend)
    assert [(d.idVendor, d.idProduct) for d in devs] == [(0x1209, 0x0001), (0x046D, 0x0825)]
    assert devs[0].serial_number == "SIM0001"
    assert devs[0].product == "Simulated UVC Camera"
    assert find_uvc_devices(backend, vid=0x046D, pid=0x0001) == []


def test_set_get_round_trip_and_wire_format(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    dev, backend = sim
    c = _controls(backend)
    assert c.exposure_range == (1e-4, 0.5)
    assert c.gain_range == (1.0, 255 / 16)
    dev.log.clear()
    exp, gain = c.apply_all(0.0123, 2.0)
    assert (exp, gain) == (pytest.approx(0.0123), 2.0)
    assert c.ae_mode == AE_MANUAL
    assert dev.value(1, 0x04) == 123
    assert dev.value(2, 0x04) == 32
    sets = [e for e in dev.log if e[1] == 0x01]
    # AE mode first: SET_CUR 0x21/0x01, wValue = selector << 8, wIndex = terminal << 8 | interface 0
    assert sets[0] == (0x21, 0x01, CT_AE_MODE << 8, 0x0100, b"\x01")
    assert sets[1] == (0x21, 0x01, CT_EXPOSURE_TIME_ABSOLUTE << 8, 0x0100, struct.pack("<I", 123))
    assert sets[2] == (0x21, 0x01, 0x0400, 0x0200, struct.pack("<H", 32))
    assert all(e[0] == 0xA1 for e in dev.log if e[1] != 0x01)
    assert c.current() == (pytest.approx(0.0123), 2.0)
    c.close()


def test_stall_is_control_not_supported(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    _dev, backend = sim
    c = _controls(backend)
    with pytest.raises(ControlNotSupported, match="wrong state"):  # exposure while AE is automatic
        c.set(0.01, None)
    with pytest.raises(ControlNotSupported, match="invalid control"):
        c.get(1, 0x0B, 2)  # CT_ZOOM_ABSOLUTE: not on this camera
    with pytest.raises(ControlNotSupported, match="out of range"):
        c.set_cur(1, CT_AE_MODE, b"\x06")  # not a single supported mode bit
    with pytest.raises(ControlNotSupported) as ei:
        c.get(1, 0x0B, 2)
    assert isinstance(ei.value.__cause__, usb.core.USBError)
    assert ei.value.__cause__.errno == 32
    c.close()


def test_extension_unit_controls(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    dev, backend = sim
    c = _controls(backend)
    assert c.xu_get(3, 1) == struct.pack("<I", 0x1234)  # length from GET_LEN
    c.xu_set(3, 1, struct.pack("<I", 0xBEEF))
    assert c.xu_get(3, 1, 4) == struct.pack("<I", 0xBEEF)
    assert dev.value(3, 1) == 0xBEEF
    with pytest.raises(ControlNotSupported, match="extension unit 9"):
        c.xu_get(9, 1, 1)
    with pytest.raises(ControlNotSupported):
        c.xu_get(3, 7, 1)
    c.close()


def test_busy_when_uvcvideo_is_bound(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    dev, backend = sim
    dev.kernel_driver_bound = True
    c = UvcControls(find_uvc_devices(backend, vid=0x1209)[0])
    with pytest.raises(CameraBusy, match="uvcvideo"):
        c.probe()


def test_busy_claim_error_errno16(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    """A driver bound after our kernel-driver check: the claim itself fails with errno 16."""
    dev, backend = sim
    c = UvcControls(find_uvc_devices(backend, vid=0x1209)[0])
    orig = backend.is_kernel_driver_active
    backend.is_kernel_driver_active = lambda h, i: (setattr(dev, "kernel_driver_bound", True), False)[1]  # type: ignore[method-assign]
    try:
        with pytest.raises(CameraBusy):
            c.probe()
    finally:
        backend.is_kernel_driver_active = orig  # type: ignore[method-assign]


async def test_unplug_and_replug_reapplies_controls(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    dev, backend = sim
    cam = open_camera("uvc:1209:0001", usb_backend=backend, frame_source=SimUvcFrames(dev))
    assert isinstance(cam, UvcCamera)
    await cam.open()
    await cam.apply(Controls(exposure_s=0.02, gain=1.5))
    await cam.capture(1.0)
    dev.unplug()
    with pytest.raises(CameraDisconnected):
        await cam.capture(1.0)
    with pytest.raises(CameraDisconnected):
        await cam.apply(Controls(exposure_s=0.03))
    await cam.close()
    with pytest.raises(CameraUnavailable):
        await cam.open()
    dev.replug()
    assert dev.value(1, CT_AE_MODE) == 8  # firmware defaults after power-up
    dev.log.clear()
    await cam.open()
    try:
        sets = [e for e in dev.log if e[1] == 0x01]
        assert sets[0][2] == CT_AE_MODE << 8
        assert sets[0][4] == b"\x01"
        assert dev.value(1, 0x04) == 200
        assert dev.value(2, 0x04) == 24
    finally:
        await cam.close()


async def test_v4l2_node_without_exposure_falls_back_to_uvc(sim: tuple[SimUvcDevice, SimUsbBackend]) -> None:
    dev, backend = sim
    node = FakeV4L2Node(fps=60.0)
    node.controls = {}  # a node whose driver exposes no exposure controls
    find = lambda: find_uvc_devices(backend, 0x1209, 0x0001)[0]  # noqa: E731
    cam = V4L2Camera(node.path, opener=node.open, controls_factory=v4l2_controls_with_uvc_fallback(find))
    await cam.open()
    try:
        await cam.apply(Controls(exposure_s=0.004))
        assert dev.value(1, CT_AE_MODE) == AE_MANUAL
        assert dev.value(1, 0x04) == 40
        assert (await cam.capture(2.0)).data.shape == (480, 640, 3)
    finally:
        await cam.close()
    plain = V4L2Camera(node.path, opener=node.open)
    with pytest.raises(ControlNotSupported, match="EXPOSURE_ABSOLUTE"):
        await plain.open()


async def test_uvc_spec_for_absent_device(sim: tuple[SimUvcDevice, SimUsbBackend], tmp_path: object) -> None:
    dev, backend = sim
    cam = open_camera("uvc:dead:beef", usb_backend=backend, frame_source=SimUvcFrames(dev), by_id_dir=str(tmp_path))
    with pytest.raises(CameraUnavailable, match="no such USB camera"):
        await cam.open()
    with pytest.raises(CameraUnavailable, match="V4L2 node"):
        open_camera("uvc", usb_backend=backend, by_id_dir=str(tmp_path))
