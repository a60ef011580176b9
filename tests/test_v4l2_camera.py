"""V4L2Camera against the fake ioctl endpoint (lightprobe.sim.v4l2_fake), and the real transport's errors.

The fake decodes ioctl numbers and struct bytes with its own kernel offset tables and records
every call, so these tests check call order, the bytes we send, streaming, drops, the settling
rule and replug handling, for the LP64 and the 32-bit ARM layouts.
"""

from __future__ import annotations

import asyncio
import errno
import os
import struct
import time

import pytest

from lightprobe.drivers.base import (
    CameraDisconnected,
    CameraUnavailable,
    ControlNotSupported,
    Controls,
    Mode,
    PixelFormat,
)
from lightprobe.drivers.discovery import open_with_retry
from lightprobe.drivers.v4l2._ioctl import DeviceTransport, IoctlError
from lightprobe.drivers.v4l2._structs import ABI32, ABI64, V4L2Abi
from lightprobe.drivers.v4l2.camera import V4L2Camera
from lightprobe.sim.v4l2_fake import (
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_EXPOSURE_AUTO_PRIORITY,
    MJPG,
    YUYV,
    FakeV4L2Node,
    sim_scene,
)

ABIS = [pytest.param(ABI64, id="lp64"), pytest.param(ABI32, id="arm32")]


def _ctrl_sets(dev: object) -> list[tuple[int, int]]:
    return [struct.unpack_from("<Ii", data, 0) for name, data in dev.calls if name == "VIDIOC_S_CTRL"]  # type: ignore[attr-defined]


async def _open(abi: V4L2Abi = ABI64, **kw: object) -> tuple[FakeV4L2Node, V4L2Camera]:
    node = FakeV4L2Node(abi=abi, fps=float(kw.pop("fps", 90.0)), **kw)  # type: ignore[arg-type]
    cam = V4L2Camera(node.path, opener=node.open)
    await cam.open()
    return node, cam


@pytest.mark.parametrize("abi", ABIS)
async def test_open_call_order_and_struct_bytes(abi: V4L2Abi) -> None:
    node, cam = await _open(abi)
    try:
        dev = node.devices[0]
        names = dev.called()
        assert dev.violations == []
        assert names[0] == "VIDIOC_QUERYCAP"
        i_fmt, i_req, i_on = names.index("VIDIOC_S_FMT"), names.index("VIDIOC_REQBUFS"), names.index("VIDIOC_STREAMON")
        assert i_fmt < i_req < names.index("VIDIOC_QUERYBUF") < names.index("VIDIOC_QBUF") < i_on
        assert names[i_req + 1 : i_on] == ["VIDIOC_QUERYBUF"] * 4 + ["VIDIOC_QBUF"] * 4
        # S_FMT bytes: type 1 at 0, pix at 8 (LP64) or 4 (ARM EABI): 640x480 YUYV, field NONE
        sfmt = dict(dev.calls)["VIDIOC_S_FMT"]
        pix = 8 if abi.bits == 64 else 4
        assert len(sfmt) == (208 if abi.bits == 64 else 204)
        assert struct.unpack_from("<I", sfmt, 0)[0] == 1
        assert struct.unpack_from("<IIII", sfmt, pix) == (640, 480, YUYV, 1)
        assert struct.unpack_from("<III", dict(dev.calls)["VIDIOC_REQBUFS"], 0) == (4, 1, 1)
        # controls: manual exposure first, then auto priority off, then exposure absolute
        sets = _ctrl_sets(dev)
        assert sets[0] == (CID_EXPOSURE_AUTO, 1)
        assert sets[1] == (CID_EXPOSURE_AUTO_PRIORITY, 0)
        assert [c for c, _ in sets].index(CID_EXPOSURE_ABSOLUTE) > 1
        assert names.index("VIDIOC_S_CTRL") < i_on
    finally:
        await cam.close()
    after = dev.called()[len(names) :]
    assert after[0] == "VIDIOC_STREAMOFF"
    assert after[-1] == "VIDIOC_REQBUFS"
    assert struct.unpack_from("<I", dev.calls[-1][1], 0)[0] == 0  # REQBUFS(0) frees the buffers
    assert dev.violations == []


async def test_a_wrong_struct_layout_is_caught() -> None:
    """The fake decodes by the kernel's sizes: 64-bit structs sent to a 32-bit kernel fail."""
    node = FakeV4L2Node(abi=ABI32)
    opened = []

    def open_with_wrong_layout() -> object:
        dev = node.open()
        dev.abi = ABI64  # as if our ctypes layout did not match the kernel's
        opened.append(dev)
        return dev

    cam = V4L2Camera(node.path, opener=open_with_wrong_layout)  # type: ignore[arg-type]
    with pytest.raises(IoctlError):
        await cam.open()
    assert any("VIDIOC_S_FMT: ioctl size 208, struct 208, kernel 204" in v for v in opened[0].violations)


async def test_ioctls_run_off_the_event_loop_thread() -> None:
    import threading

    node, cam = await _open()
    dev = node.devices[0]
    try:
        await cam.apply(Controls(exposure_s=0.02))
        for _ in range(3):
            await cam.capture(2.0)
    finally:
        await cam.close()
    assert len(dev.call_threads) == len(dev.calls) > 20
    assert threading.get_ident() not in dev.call_threads


@pytest.mark.parametrize("abi", ABIS)
async def test_stream_frames_decode_to_the_scene(abi: V4L2Abi) -> None:
    _node, cam = await _open(abi)
    try:
        f = await cam.capture(2.0)
        assert f.data.shape == (480, 640, 3)
        assert f.format is PixelFormat.RGB8
        expect = (255.0 * (sim_scene(640, 480) * 0.0156).clip(0, 1) ** (1 / 2.2))
        err = abs(f.data.astype(float) - expect)
        assert float(err.mean()) < 1.5  # YUYV 4:2:2 chroma subsampling + rounding
        assert f.meta.exposure_verified is False
        assert f.extra["pixelformat"] == "YUYV"
        seqs = [(await cam.capture(2.0)).meta.sequence for _ in range(4)]
        assert seqs == sorted(seqs)
        assert len(set(seqs)) == 4
        ts = f.meta.timestamp_s
        assert abs(ts - time.monotonic()) < 5.0  # CLOCK_MONOTONIC seconds
    finally:
        await cam.close()


async def test_mjpeg_only_camera_and_set_mode() -> None:
    node, cam = await _open(formats=(MJPG,))
    try:
        f = await cam.capture(2.0)
        assert f.extra["pixelformat"] == "MJPG"
        assert f.data.shape == (480, 640, 3)
        small = Mode(320, 240, PixelFormat.RGB8, 90.0)
        assert small in cam.capabilities.modes
        await cam.set_mode(small)
        g = await cam.capture(2.0)
        assert g.data.shape == (240, 320, 3)
        assert cam.mode == small
        with pytest.raises(ControlNotSupported):
            await cam.set_mode(Mode(1920, 1080))
        assert node.devices[0].violations == []
    finally:
        await cam.close()


async def test_dropped_frames_show_as_sequence_gaps() -> None:
    node, cam = await _open()
    try:
        a = await cam.capture(2.0)
        node.devices[0].drop_frames = 3
        seen = [await cam.capture(2.0) for _ in range(6)]
        gaps = sum(int(f.extra["dropped"]) for f in seen)  # type: ignore[call-overload]
        last = seen[-1].meta.sequence
        assert gaps == last - a.meta.sequence - 6
        assert gaps >= 3
        assert cam.dropped_frames >= 3
    finally:
        await cam.close()


async def test_new_exposure_reported_only_when_frames_show_it() -> None:
    node, cam = await _open()
    try:
        base = await cam.capture(2.0)
        old_level = float(base.data.mean())
        await cam.apply(Controls(exposure_s=0.05))
        assert _ctrl_sets(node.devices[0])[-1] == (CID_EXPOSURE_ABSOLUTE, 500)
        frames = [await cam.capture(2.0) for _ in range(20)]
        new = [f for f in frames if f.meta.exposure_s == pytest.approx(0.05)]
        old = [f for f in frames if f.meta.exposure_s == pytest.approx(0.0156)]
        assert new
        assert old
        assert len(new) + len(old) == 20
        switched = [f.meta.exposure_s == pytest.approx(0.05) for f in frames]
        assert switched == [False] * len(old) + [True] * len(new)  # once switched, it stays
        new_level = float(new[0].data.mean())
        assert new_level > old_level * 1.3  # the first frame reported as 0.05 s is bright
        assert all(abs(float(f.data.mean()) - new_level) < 1.0 for f in new)
        assert new[0].extra["settle_reason"] == "step"
    finally:
        await cam.close()


async def test_unplug_replug_reapplies_controls() -> None:
    node, cam = await _open()
    await cam.apply(Controls(exposure_s=0.03, gain=2.0))
    await cam.capture(2.0)
    node.unplug()
    with pytest.raises(CameraDisconnected):
        await cam.capture(2.0)
    await cam.close()
    await cam.close()
    with pytest.raises(CameraUnavailable):
        await cam.open()
    node.replug()
    assert node.controls[CID_EXPOSURE_AUTO].value == 3  # reset by the "firmware"
    await cam.open()
    try:
        sets = _ctrl_sets(node.devices[-1])
        assert sets[0] == (CID_EXPOSURE_AUTO, 1)
        assert node.controls[CID_EXPOSURE_AUTO].value == 1
        assert node.controls[CID_EXPOSURE_ABSOLUTE].value == 300
        assert node.controls[0x00980913].value == 32
        f = await cam.capture(2.0)
        assert f.meta.exposure_s == pytest.approx(0.03)
        assert f.meta.gain == pytest.approx(2.0)
    finally:
        await cam.close()


async def test_open_with_retry_waits_for_the_camera() -> None:
    node = FakeV4L2Node(fps=60.0)
    node.unplug()
    cam = V4L2Camera(node.path, opener=node.open)
    errors: list[float] = []
    loop = asyncio.get_running_loop()
    loop.call_later(0.25, node.replug)
    await open_with_retry(cam, initial_s=0.05, max_s=0.2, attempts=50, on_error=lambda e, d: errors.append(d))
    try:
        assert errors
        assert errors[:3] == [0.05, 0.1, 0.2][: len(errors[:3])]
        assert (await cam.capture(2.0)).data.shape == (480, 640, 3)
    finally:
        await cam.close()
    node.unplug()
    with pytest.raises(CameraUnavailable):
        await open_with_retry(cam, initial_s=0.01, attempts=2)


async def test_capture_timeout_when_no_frames() -> None:
    _node, cam = await _open(fps=2.0)
    try:
        from lightprobe.drivers.base import CaptureTimeout

        await cam.capture(3.0)
        with pytest.raises(CaptureTimeout):
            await cam.capture(0.05)
    finally:
        await cam.close()


# ---- the real transport ---------------------------------------------------------------------
def test_real_transport_missing_node(tmp_path: os.PathLike[str]) -> None:
    with pytest.raises(CameraUnavailable, match="does not exist"):
        DeviceTransport(os.path.join(tmp_path, "video9"))


async def test_real_transport_on_a_non_v4l2_file() -> None:
    t = DeviceTransport("/dev/null")
    try:
        from lightprobe.drivers.v4l2 import _structs as S

        with pytest.raises(IoctlError) as ei:
            t.ioctl(t.abi.VIDIOC_QUERYCAP, S.v4l2_capability())
        assert ei.value.errno == errno.ENOTTY
        assert "VIDIOC_QUERYCAP" in str(ei.value)
    finally:
        t.close()
        t.close()
    cam = V4L2Camera("/dev/null")
    with pytest.raises(CameraUnavailable, match="not a V4L2 device"):
        await cam.open()
    await cam.close()


HIL = os.environ.get("LIGHTPROBE_HIL_CAMERA", "")


@pytest.mark.hardware
@pytest.mark.skipif(not HIL.startswith("v4l2:"), reason="set LIGHTPROBE_HIL_CAMERA=v4l2:/dev/v4l/by-id/...")
async def test_hardware_v4l2_node_modes_and_controls() -> None:
    from lightprobe.drivers.v4l2.camera import enumerate_modes
    from lightprobe.drivers.v4l2.controls import V4L2Controls

    t = DeviceTransport(HIL.split(":", 1)[1])
    try:
        assert enumerate_modes(t)
        ctl = V4L2Controls(t)
        ctl.probe()
        lo, hi = ctl.exposure_range
        assert 0 < lo < hi
        exp, _ = ctl.apply_all(None, None)
        assert lo <= exp <= hi
    finally:
        t.close()
