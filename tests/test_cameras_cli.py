"""``lightprobe cameras`` and lightprobe.drivers.discovery: listing, specs, auto choice, clear errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lightprobe.cli.cameras import main
from lightprobe.core.errors import InputError
from lightprobe.drivers.base import CameraUnavailable
from lightprobe.drivers.discovery import (
    NoCameraFound,
    find_v4l2_node_for_usb,
    list_cameras,
    open_camera,
    parse_spec,
    probe_v4l2,
    usb_ids_of_node,
)
from lightprobe.sim.usb import SimUsbBackend, SimUvcDevice
from lightprobe.sim.v4l2_fake import FakeV4L2Node

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    ("spec", "parsed"),
    [("sim", ("sim", "")), ("auto", ("auto", "")), ("v4l2:/dev/video0", ("v4l2", "/dev/video0")),
     ("libcamera", ("libcamera", "")), ("libcamera:1", ("libcamera", "1")), ("uvc", ("uvc", "")),
     ("uvc:046d:0825", ("uvc", "046d:0825"))],
)  # fmt: skip
def test_parse_spec_accepts(spec: str, parsed: tuple[str, str]) -> None:
    assert parse_spec(spec) == parsed


@pytest.mark.parametrize("spec", ["", "webcam", "v4l2:video0", "v4l2:dev/video0", "uvc:046d", "uvc:zz:01", "libcamera:x", "sim:1"])
def test_parse_spec_rejects_with_param(spec: str) -> None:
    with pytest.raises(InputError) as ei:
        parse_spec(spec)
    assert ei.value.param == "--camera"
    assert "--camera" in str(ei.value)


def test_list_here_says_no_hardware_and_offers_sim(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    out = capsys.readouterr().out
    if "no camera hardware found" not in out:
        pytest.skip("this machine has camera hardware")
    assert {line.split()[0] for line in out.splitlines()[-2:]} == {"sim", "v4l2-fake"}  # plugins last
    assert main(["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["hardware_found"] is False
    assert {c["spec"] for c in doc["cameras"]} == {"sim", "v4l2-fake"}


def test_check_missing_device_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    node = tmp_path / "video7"
    assert main(["--check", f"v4l2:{node}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert str(node) in err[0]
    assert "does not exist" in err[0]
    assert main(["--check", "webcam"]) == 2
    assert "--camera 'webcam'" in capsys.readouterr().err


def test_check_not_a_camera_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--check", "v4l2:/dev/null"]) == 2
    assert "not a V4L2 device" in capsys.readouterr().err


def test_check_fake_v4l2_camera_reports_a_frame(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--check", "v4l2-fake", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frame"]["shape"] == [480, 640, 3]
    assert doc["frame_metadata"] is False
    assert doc["exposure_range_s"] == [0.0001, 0.5]


def test_entry_point_exit_code_and_help() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "cameras", "--check", "v4l2:/dev/v4l/by-id/none"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=60, check=False)  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.startswith("lightprobe: error: --camera v4l2:/dev/v4l/by-id/none")
    h = subprocess.run([sys.executable, "-m", "lightprobe.cli", "cameras", "--help"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=60, check=False)  # fmt: skip
    assert h.returncode == 0
    assert "--check" in h.stdout
    assert "--json" in h.stdout


def test_auto_never_picks_the_simulator(tmp_path: Path) -> None:
    """No hardware: ``auto`` raises NoCameraFound (a CameraUnavailable) naming what it looked
    at, never a simulated camera; plugins are listed but not picked."""
    if list_cameras(by_id_dir=str(tmp_path), include_plugins=False):
        pytest.skip("this machine has camera hardware")
    with pytest.raises(NoCameraFound, match="no camera hardware found") as e:
        open_camera("auto", by_id_dir=str(tmp_path))
    assert isinstance(e.value, CameraUnavailable)
    kinds = {c.kind for c in list_cameras(by_id_dir=str(tmp_path))}
    assert {"sim", "v4l2-fake"} <= kinds  # the simulator's plugins, listed as such


def test_cameras_check_auto_without_hardware_exits_2(tmp_path: Path) -> None:
    if list_cameras(include_plugins=False):
        pytest.skip("this machine has camera hardware")
    r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "cameras", "--check", "auto"],
                       capture_output=True, text=True, cwd=ROOT, timeout=60, check=False)  # fmt: skip
    assert r.returncode == 2
    assert "no camera hardware found" in r.stderr


def test_probe_fake_node_and_list_uvc_devices() -> None:
    node = FakeV4L2Node()
    info = probe_v4l2(node.path, opener=node.open)
    assert info is not None
    assert info.status == "available"
    assert info.name == "Fake UVC Camera"
    assert info.capabilities["exposure_range_s"] == [0.0001, 0.5]
    assert "640x480 rgb8 120fps" in info.capabilities["modes"]
    node.unplug()
    gone = probe_v4l2(node.path, opener=node.open)
    assert gone is not None
    assert gone.status.startswith("unavailable")

    free, bound = SimUvcDevice(), SimUvcDevice(pid=2, address=7, kernel_driver_bound=True)
    cams = list_cameras(by_id_dir="/nonexistent", dev_glob="/nonexistent/video*",
                        usb_backend=SimUsbBackend(free, bound), include_libcamera=False)  # fmt: skip
    uvc = [c for c in cams if c.kind == "uvc"]
    assert [c.spec for c in uvc] == ["uvc:1209:0001", "uvc:1209:0002"]
    assert uvc[0].status == "available"
    assert uvc[0].capabilities["exposure_range_s"] == [0.0001, 0.5]
    assert "uvcvideo" in uvc[1].status
    assert {c.kind for c in cams[-2:]} == {"sim", "v4l2-fake"}  # the plugins come last


def _fake_sysfs(tmp_path: Path) -> tuple[Path, Path]:
    """/dev/v4l/by-id link -> dev/video3; sys/class/video4linux/video3/device -> a USB interface."""
    dev, by_id, sysfs = tmp_path / "dev", tmp_path / "by-id", tmp_path / "sys"
    dev.mkdir()
    by_id.mkdir()
    (dev / "video3").write_bytes(b"")
    (by_id / "usb-Acme_Cam_123-video-index0").symlink_to(dev / "video3")
    usbdev = sysfs / "devices" / "pci0000:00" / "usb1" / "1-1"
    (usbdev / "1-1:1.0").mkdir(parents=True)
    (usbdev / "idVendor").write_text("046d\n")
    (usbdev / "idProduct").write_text("0825\n")
    v4l = sysfs / "class" / "video4linux" / "video3"
    v4l.mkdir(parents=True)
    (v4l / "device").symlink_to(usbdev / "1-1:1.0")
    return by_id, sysfs


def test_sysfs_maps_node_to_usb_ids(tmp_path: Path) -> None:
    by_id, sysfs = _fake_sysfs(tmp_path)
    link = str(by_id / "usb-Acme_Cam_123-video-index0")
    assert usb_ids_of_node(link, str(sysfs)) == (0x046D, 0x0825)
    assert find_v4l2_node_for_usb(0x046D, 0x0825, by_id_dir=str(by_id), sys_root=str(sysfs)) == link
    assert find_v4l2_node_for_usb(0x046D, 0x0001, by_id_dir=str(by_id), sys_root=str(sysfs)) is None
    assert usb_ids_of_node("/dev/null", str(sysfs)) is None
    cam = open_camera("uvc:046d:0825", by_id_dir=str(by_id), sys_root=str(sysfs))
    assert type(cam).__name__ == "V4L2Camera"
    assert cam.name == link
    # a /dev/videoN spec is swapped for its stable by-id link
    assert open_camera(f"v4l2:{tmp_path / 'dev' / 'video3'}", by_id_dir=str(by_id)).name == link
