"""systemd/lightprobe.service: verify cleanly and keep the hardening exposure <= 2.5."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "lightprobe.service"

pytestmark = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                reason="systemd-analyze not installed (apt-get install systemd)")


def _keys() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", ";", "[")):
            k, v = line.split("=", 1)
            out.setdefault(k.strip(), []).append(v.strip())
    return out


def test_verify_has_no_output(tmp_path: Path) -> None:
    r = subprocess.run(["systemd-analyze", "verify", str(UNIT)], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "", r.stderr  # unknown keys only warn: any output is a failure


def test_security_exposure_at_most_2_5(tmp_path: Path) -> None:
    r = subprocess.run(["systemd-analyze", "security", "--offline=yes", "--no-pager", str(UNIT)],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", r.stdout)
    assert m, r.stdout[-500:] + r.stderr
    assert float(m.group(1)) <= 2.5, r.stdout[-3000:]


def test_required_settings() -> None:
    k = _keys()
    assert k["Type"] == ["notify"]
    assert k["NotifyAccess"] == ["main"]
    assert "WatchdogSec" in k
    assert k["DynamicUser"] == ["yes"]
    assert k["StateDirectory"] == ["lightprobe"]
    assert k["ConfigurationDirectory"] == ["lightprobe"]
    assert set(k["SupplementaryGroups"][0].split()) == {"video", "dialout"}
    assert k["DevicePolicy"] == ["closed"]
    allowed = {v.split()[0] for v in k["DeviceAllow"]}
    assert {"char-video4linux", "char-ttyUSB", "char-ttyACM", "char-usb_device"} <= allowed
    assert any(a.startswith("/dev/dma_heap/") for a in allowed)
    assert "PrivateDevices" not in k  # it would hide the cameras
    assert k["ProtectSystem"] == ["strict"]
    assert k["NoNewPrivileges"] == ["yes"]
    assert set(k["RestrictAddressFamilies"][0].split()) == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}
    assert "@system-service" in k["SystemCallFilter"]
    assert "lightprobe serve" in k["ExecStart"][0]
    # numba's kernel cache must be writable under ProtectSystem=strict: the state directory
    env = dict(v.split("=", 1) for v in k["Environment"])
    assert env["NUMBA_CACHE_DIR"].startswith("%S/" + k["StateDirectory"][0] + "/"), env
