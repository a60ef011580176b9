"""``lightprobe serve`` / ``lightprobe token`` as processes: startup output, token file, sd_notify
(READY, WATCHDOG, STOPPING) over an abstract socket, SIGTERM -> exit within 3 s with WebSockets
closed. The real ``lightprobe serve`` on the simulator (tests/service_harness.py run as a script:
``lightprobe.cli.serve.main`` with the session's table cache linked into the state dir)."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import aiohttp

ROOT = Path(__file__).resolve().parent.parent
SERVE = Path(__file__).resolve().parent / "service_harness.py"


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "STATE_DIRECTORY")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests")])
    env.update(extra)
    return env


def start_serve(state: Path, *args: str, env: dict[str, str] | None = None) -> tuple[subprocess.Popen[str], str, str]:
    """Start the service on a free port; return (process, base url, token) from its stdout."""
    p = subprocess.Popen([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(state),
                          "--log-format", "json", *args], cwd=ROOT, env=env or _env(),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout is not None
    url = token = ""
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end and not token:
        line = p.stdout.readline()
        if not line:
            raise AssertionError(f"serve exited: {p.wait(5)} {p.stderr.read() if p.stderr else ''}")
        if m := re.search(r"dashboard (http://\S+)", line):
            url = m.group(1).rstrip("/")
        if m := re.search(r"API token (\S+)", line):
            token = m.group(1)
    assert url
    assert token
    return p, url, token


def _notify_socket() -> tuple[socket.socket, str]:
    name = f"lightprobe-test-{os.getpid()}-{time.monotonic_ns()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(0.2)
    return s, "@" + name


def _drain(s: socket.socket, until: float, stop: Any = None) -> list[str]:
    """Datagrams until ``until`` (a hang guard) or until ``stop(messages)`` holds."""
    msgs: list[str] = []
    while time.monotonic() < until and not (stop is not None and stop(msgs)):
        try:
            msgs.extend(s.recv(4096).decode().split("\n"))
        except TimeoutError:
            continue
    return msgs


async def test_serve_notify_token_and_sigterm(tmp_path: Path) -> None:
    ns, addr = _notify_socket()
    state = tmp_path / "state"
    p, url, token = start_serve(state, env=_env(NOTIFY_SOCKET=addr, WATCHDOG_USEC="400000"))
    try:
        # token file: created at first start, mode 0600, same as printed
        tok_file = state / "token"
        assert stat.S_IMODE(tok_file.stat().st_mode) == 0o600
        assert tok_file.read_text().strip() == token
        # WATCHDOG=1 every 0.2 s once frames flow (after the first burst): wait for three of them
        msgs = _drain(ns, time.monotonic() + 60, stop=lambda m: m.count("WATCHDOG=1") >= 3)
        assert "READY=1" in msgs
        assert msgs.index("READY=1") < msgs.index("WATCHDOG=1")
        assert msgs.count("WATCHDOG=1") >= 3
        async with aiohttp.ClientSession() as c:
            async with c.get(url + "/api/v1/status") as r:
                st = await r.json()
            assert st["frames"] > 0
            assert st["camera"]["state"] == "running"
            assert st["threading_layer"] in ("omp", "tbb")  # never workqueue (lightprobe.device.threads)
            assert st["camera"]["driver"] == "sim"
            assert st["probe"]["model"] == "lightprobe-sim (sim)"
            async with c.ws_connect(url + "/api/v1/stream") as ws:
                await ws.receive(timeout=30)
                p.send_signal(signal.SIGTERM)
                closed_code = None
                while True:
                    msg = await ws.receive(timeout=3)
                    if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
                        closed_code = ws.close_code
                        break
                rc = p.wait(10)  # a hang guard; the 3 s stop budget is shown by `lightprobe bench service`
        assert rc == 0
        assert closed_code == 1001
        assert "STOPPING=1" in _drain(ns, time.monotonic() + 5, stop=lambda m: "STOPPING=1" in m)
        # structured logs: every stderr line is a JSON object
        assert p.stderr is not None
        lines = [ln for ln in p.stderr.read().splitlines() if ln.strip()]
        assert lines
        assert all(isinstance(json.loads(ln), dict) for ln in lines)
        assert any(json.loads(ln)["msg"].startswith("stopped in") for ln in lines)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(5)
        ns.close()
    # lightprobe token prints the same token
    out = await asyncio.to_thread(
        subprocess.run, [sys.executable, "-m", "lightprobe.cli", "token", "--state-dir", str(state)],
        cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=30)
    assert out.returncode == 0
    assert out.stdout.strip() == token


def test_token_command_creates_0600(tmp_path: Path) -> None:
    run: Any = lambda *a: subprocess.run([sys.executable, "-m", "lightprobe.cli", "token", *a], cwd=ROOT,  # noqa: E731
                                         env=_env(), capture_output=True, text=True, timeout=30)
    r = run("--state-dir", str(tmp_path / "s"), "--no-create")
    assert r.returncode == 1
    r1, r2 = run("--state-dir", str(tmp_path / "s")), run("--state-dir", str(tmp_path / "s"))
    assert r1.returncode == 0
    assert r1.stdout == r2.stdout
    assert len(r1.stdout.strip()) >= 40
    assert stat.S_IMODE((tmp_path / "s" / "token").stat().st_mode) == 0o600


def test_serve_bad_arguments_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[pipeline]\nlight_count = -5\n")
    r = subprocess.run([sys.executable, str(SERVE), "--config", str(bad), "--state-dir", str(tmp_path)],
                       cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    assert "pipeline.light_count" in r.stderr
    assert "bad.toml" in r.stderr
    r = subprocess.run([sys.executable, str(SERVE), "--port", "99999"], cwd=ROOT, env=_env(),
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    assert "--port" in r.stderr


async def test_serve_auto_without_hardware_stays_up_and_serves_no_lights(tmp_path: Path) -> None:
    """``--camera auto`` never falls back to the simulator: with no camera hardware the service
    answers, says why in /status, keeps retrying and serves no lights at all."""
    from lightprobe.drivers.discovery import list_cameras

    if list_cameras(include_plugins=False):
        import pytest

        pytest.skip("this machine has camera hardware")
    p, url, token = start_serve(tmp_path / "state", "--camera", "auto")
    try:
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as c:
            while True:  # the first attempt runs in the background after the API listens
                async with c.get(url + "/api/v1/status") as r:
                    assert r.status == 200
                    st = await r.json()
                if st["camera"]["error"]:
                    break
                await asyncio.sleep(0.1)
            assert "no camera hardware found" in st["camera"]["error"]
            assert st["camera"]["state"] == "reconnecting"
            assert st["frames"] == 0
            # no camera is open: nothing says simulator (mDNS and the dashboard read this model)
            assert "sim" not in st["probe"]["model"], st["probe"]
            assert st["probe"]["model"] == "lightprobe"
            assert st["camera"]["model"] is None
            assert st["camera"]["driver"] is None
            assert st["threading_layer"] in ("omp", "tbb")
            while st["camera"]["reconnects"] < 2:  # it keeps retrying (a camera may be plugged in)
                await asyncio.sleep(0.2)
                async with c.get(url + "/api/v1/status") as r:
                    st = await r.json()
            for path in ("/api/v1/lights", "/api/v1/probe.exr", "/api/v1/q2tree"):
                async with c.get(url + path) as r:
                    assert r.status == 503, path
            async with c.get(url + "/api/v1/healthz") as r:
                assert r.status == 503
        assert p.poll() is None  # still serving
    finally:
        p.send_signal(signal.SIGTERM)
        assert p.wait(10) == 0
