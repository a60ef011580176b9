"""A real external mDNS client (avahi) sees the probe's advertisement and its TXT records.

The test makes its own network + mount namespace (``unshare -nm``, root): loopback up, private
/run/dbus and /run/avahi-daemon (tmpfs), a private system bus, ``avahi-daemon``; then the service's
zeroconf registration (``lightprobe.device.service.mdns.Advertiser`` on 127.0.0.1) runs in the same namespace
and ``avahi-browse -rtp _lightprobe._tcp`` must list it with its TXT; after the goodbye it must not.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = [pytest.mark.netns, pytest.mark.slow]

NEEDED = ("unshare", "ip", "dbus-daemon", "avahi-daemon", "avahi-browse", "mount")

HELPER = """
import asyncio, sys, pathlib
from lightprobe.device.service.mdns import Advertiser, MdnsInfo
work = pathlib.Path(sys.argv[1])
async def main():
    a = Advertiser(MdnsInfo("abcdef012345", "Netns probe", 8080, model="lightprobe-sim",
                            sampler="pharr", interfaces=["127.0.0.1"]))
    await a.start()
    (work / "registered").touch()
    for _ in range(300):
        if (work / "stop").exists():
            break
        await asyncio.sleep(0.05)
    await a.close()
    (work / "closed").touch()
asyncio.run(main())
"""

SCRIPT = r"""
set -u
W="$1"; PY="$2"
mount --make-rprivate /
mkdir -p /run/dbus /run/avahi-daemon
mount -t tmpfs tmpfs /run/dbus
mount -t tmpfs tmpfs /run/avahi-daemon
ip link set lo up
ip link set lo multicast on 2>/dev/null || true
dbus-daemon --system --fork --print-pid > "$W/dbus.pid"
avahi-daemon --no-drop-root --no-rlimits -D
for i in $(seq 50); do avahi-daemon -c && break; sleep 0.1; done
"$PY" "$W/helper.py" "$W" 2> "$W/helper.err" &
HELPER=$!
for i in $(seq 100); do [ -e "$W/registered" ] && break; sleep 0.1; done
timeout 10 avahi-browse -rtp _lightprobe._tcp > "$W/browse1.txt" 2> "$W/browse1.err"
touch "$W/stop"
wait $HELPER
sleep 0.5
timeout 10 avahi-browse -rtp _lightprobe._tcp > "$W/browse2.txt" 2> "$W/browse2.err"
avahi-daemon -k 2>/dev/null
kill "$(cat "$W/dbus.pid")" 2>/dev/null
exit 0
"""


def _skip_reason() -> str | None:
    if os.geteuid() != 0:
        return "needs root for unshare -n / mount namespaces"
    missing = [t for t in NEEDED if shutil.which(t) is None]
    if missing:
        return f"missing tools: {', '.join(missing)} (apt-get install avahi-daemon avahi-utils dbus iproute2)"
    r = subprocess.run(["unshare", "-nm", "true"], capture_output=True, timeout=10)
    if r.returncode != 0:
        return f"unshare -nm not permitted here: {r.stderr.decode().strip()}"
    return None


def test_avahi_browse_sees_service_and_txt(tmp_path: Path) -> None:
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    (tmp_path / "helper.py").write_text(HELPER)
    (tmp_path / "run.sh").write_text(SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run(["unshare", "-nm", "bash", str(tmp_path / "run.sh"), str(tmp_path), sys.executable],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=90)
    assert r.returncode == 0, r.stderr
    helper_err = (tmp_path / "helper.err").read_text()
    assert (tmp_path / "closed").exists(), helper_err
    lines = (tmp_path / "browse1.txt").read_text().splitlines()
    resolved = [ln.split(";") for ln in lines if ln.startswith("=")]
    assert resolved, f"avahi-browse saw nothing: {lines} {(tmp_path / 'browse1.err').read_text()}"
    rec = resolved[0]
    # =;iface;proto;name;type;domain;host;address;port;txt
    assert rec[3] == r"Netns\032probe"
    assert rec[4] == "_lightprobe._tcp"
    assert rec[5] == "local"
    assert rec[6] == "lightprobe-abcdef012345.local"
    assert rec[7] == "127.0.0.1"
    assert rec[8] == "8080"
    txt = dict(item.strip('"').split("=", 1) for item in rec[9].split('" "'))
    assert txt == {"txtvers": "1", "id": "abcdef012345", "path": "/api/v1", "version": "0.1.0",
                   "model": "lightprobe-sim", "name": "Netns probe", "sampler": "pharr"}
    # after the goodbye avahi drops it: absent, or its last event is a removal ("-")
    after = [ln for ln in (tmp_path / "browse2.txt").read_text().splitlines() if "Netns" in ln]
    assert not after or after[-1].startswith("-;"), after
