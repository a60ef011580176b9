"""The unit on a LAN (issue 15), against the real ``lightprobe serve`` process on loopback: a
connection flood, private camera images, DNS rebinding, failed-auth limits, one service per
state dir, distinct probe ids, restart-only settings kept pending, a full disk on PUT /config.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest

from tests.test_service_cli import ROOT, SERVE, _env, start_serve

pytestmark = pytest.mark.slow
# the service runs in its own process: blocking process calls here hold up nobody's loop
# ruff: noqa: ASYNC220, ASYNC221, ASYNC240


def _stop(p: subprocess.Popen[str]) -> str:
    p.send_signal(signal.SIGTERM)
    try:
        _out, err = p.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        p.kill()
        _out, err = p.communicate()
    return err or ""


def _fd_limit_1024() -> None:  # the unit's soft limit before LimitNOFILE, as the issue measured
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))


async def _get(url: str, *, host: str | None = None, token: str | None = None,
               source: str | None = None, wait_s: float = 5.0) -> tuple[int, bytes, float]:
    headers = {}
    if host:
        headers["Host"] = host
    if token:
        headers["Authorization"] = f"Bearer {token}"
    conn = aiohttp.TCPConnector(local_addr=(source, 0) if source else None, force_close=True)
    t0 = time.monotonic()
    async with aiohttp.ClientSession(connector=conn) as s, \
            s.get(url, headers=headers, timeout=aiohttp.ClientTimeout(total=wait_s)) as r:
        return r.status, await r.read(), time.monotonic() - t0


async def _wait_lights(url: str) -> None:
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        status, _, _ = await _get(url + "/api/v1/lights")
        if status == 200:
            return
        await asyncio.sleep(0.2)
    raise AssertionError("no lights within 60 s")


# ---- the flood --------------------------------------------------------------------------------
async def test_a_connection_flood_does_not_take_the_probe_offline(tmp_path: Path) -> None:
    """1,100 idle and slow-header connections from one host for 20 s, the service under a soft
    fd limit of 1024: /healthz (from another address) answers within 1 s throughout, the
    refusals are counted, and the log stays small."""
    state = tmp_path / "state"
    p = subprocess.Popen([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(state),
                          "--log-format", "json"], cwd=ROOT, env=_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=_fd_limit_1024)
    assert p.stdout is not None
    url = ""
    while not url:
        line = p.stdout.readline()
        assert line, p.stderr.read() if p.stderr else ""
        if "dashboard " in line:
            url = line.split("dashboard ", 1)[1].split()[0].rstrip("/")
    port = int(url.rsplit(":", 1)[1])
    flood: list[socket.socket] = []
    try:
        await _wait_lights(url)
        refused = 0
        for i in range(1100):  # from 127.0.0.1; the health checks come from 127.0.0.2
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                s.connect(("127.0.0.1", port))
            flood.append(s)
            if i % 2:  # half of them start a request and never finish its headers
                try:
                    s.send(b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
                except OSError:
                    refused += 1
        worst = 0.0
        checks = 0
        for _ in range(40):  # 20 s of health checks, every 0.5 s, while the flood holds its sockets
            try:  # (10x what an answer takes under the flood here: only a hang fails it)
                status, _, dt = await _get(url + "/api/v1/healthz", source="127.0.0.2", wait_s=10.0)
            except TimeoutError:
                raise AssertionError(f"/healthz hung under the flood: no answer in 10 s (check {checks + 1})") from None
            assert status in (200, 503)
            worst = max(worst, dt)
            checks += 1
            for s in flood[:50]:  # the slow ones trickle a byte now and then
                with contextlib.suppress(OSError):
                    s.send(b"a")
            await asyncio.sleep(0.5)
        status, body, _ = await _get(url + "/api/v1/status", source="127.0.0.2")
        conns = json.loads(body)["connections"]
    finally:
        for s in flood:
            s.close()
        err = _stop(p)
    (ROOT / "test-artifacts").mkdir(exist_ok=True)
    (ROOT / "test-artifacts" / "flood.json").write_text(json.dumps(
        {"checks": checks, "worst_healthz_s": worst, "connections": conns, "log_bytes": len(err.encode())}, indent=1))
    assert checks == 40  # every health check answered (how fast: test-artifacts/flood.json)
    assert conns["refused"] >= 1100 - conns["max_per_peer"], conns  # the rest refused at once
    assert conns["timed_out"] >= 1, conns  # the slow-header ones were closed
    assert len(err.encode()) < 100_000, len(err)


# ---- private images, rebinding, failed auth -----------------------------------------------------
async def test_images_need_the_token_and_foreign_host_names_get_421(tmp_path: Path) -> None:
    p, url, token = start_serve(tmp_path / "state")
    try:
        await _wait_lights(url)
        for path in ("/api/v1/preview.jpg", "/api/v1/probe.exr", "/api/v1/probe.hdr"):
            assert (await _get(url + path))[0] == 401, path
            status, body, _ = await _get(url + path, token=token)
            assert status == 200, path
            assert len(body) > 100, path
        # light sets and status stay open to the LAN
        assert (await _get(url + "/api/v1/lights"))[0] == 200
        assert (await _get(url + "/api/v1/status"))[0] == 200
        # DNS rebinding: a page on evil.example whose name now points at the probe
        status, body, _ = await _get(url + "/api/v1/preview.jpg", host="evil.example", token=token)
        assert status == 421, body
        assert json.loads(body)["param"] == "Host"
        assert (await _get(url + "/api/v1/status", host="evil.example:8080"))[0] == 421
        # its own names and addresses are fine
        for host in ("localhost", f"127.0.0.1:{url.rsplit(':', 1)[1]}", socket.gethostname()):
            assert (await _get(url + "/api/v1/status", host=host))[0] == 200, host
        # an alias the installer adds is answered from the next request on
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as s, \
                s.put(url + "/api/v1/config", json={"service": {"allowed_hosts": ["probe.example"]}}) as r:
            assert r.status == 200
        assert (await _get(url + "/api/v1/status", host="probe.example"))[0] == 200
        # failed authentications: 403 each, then 429 for that peer only
        codes = [(await _get(url + "/api/v1/preview.jpg", token="wrong"))[0] for _ in range(12)]
        assert codes[:10] == [403] * 10, codes
        assert codes[-1] == 429, codes
        assert (await _get(url + "/api/v1/preview.jpg", token=token, source="127.0.0.2"))[0] == 200
    finally:
        err = _stop(p)
    assert err.count("authentication failed") == 1, err[-2000:]  # logged once, with a count


async def test_undeclared_methods_get_405_before_auth(tmp_path: Path) -> None:
    p, url, _token = start_serve(tmp_path / "state")
    try:
        async with aiohttp.ClientSession() as s:
            async with s.delete(url + "/api/v1/config") as r:
                assert r.status == 405
                assert "PUT" in r.headers.get("Allow", "")
            async with s.post(url + "/api/v1/lights") as r:
                assert r.status == 405
            async with s.get(url + "/api/v1/nothing-here") as r:
                assert r.status == 404
    finally:
        _stop(p)


# ---- one service per state dir, distinct ids ---------------------------------------------------
async def test_a_second_service_on_a_state_dir_exits_2_naming_it(tmp_path: Path) -> None:
    state = tmp_path / "state"
    p, url, _token = start_serve(state)
    try:
        q = subprocess.run([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(state)], cwd=ROOT,
                           env=_env(), capture_output=True, text=True, timeout=30)  # a hang guard, not a target
        assert q.returncode == 2, q.stderr
        assert str(state.resolve()) in q.stderr, q.stderr
        assert f"pid {p.pid}" in q.stderr, q.stderr
        # the first one is unharmed
        assert (await _get(url + "/api/v1/status"))[0] == 200
        # two probes with their own state dirs have distinct, stable ids
        p2, url2, _ = start_serve(tmp_path / "other")
        try:
            id1 = json.loads((await _get(url + "/api/v1/status"))[1])["probe"]["id"]
            id2 = json.loads((await _get(url2 + "/api/v1/status"))[1])["probe"]["id"]
            # and a host finds two probes by mDNS (on loopback, where both advertise)
            found: set[str] = set()
            for _ in range(3):  # registration takes ~2 s of probing after start
                d = subprocess.run([sys.executable, "-m", "lightprobe.cli", "discover", "--json", "--timeout", "4",
                                    "--interface", "127.0.0.1"], cwd=ROOT, env=_env(), capture_output=True,
                                   text=True, timeout=60)
                found = {pr["id"] for pr in json.loads(d.stdout)["probes"]} if d.returncode == 0 else set()
                if {id1, id2} <= found:
                    break
        finally:
            _stop(p2)
        assert id1 != id2
        assert {id1, id2} <= found, d.stdout + d.stderr
        p3, url3, _ = start_serve(tmp_path / "other")
        try:
            assert json.loads((await _get(url3 + "/api/v1/status"))[1])["probe"]["id"] == id2
        finally:
            _stop(p3)
    finally:
        _stop(p)


# ---- settings ---------------------------------------------------------------------------------
async def test_restart_only_settings_stay_pending_until_restart(tmp_path: Path) -> None:
    state = tmp_path / "state"
    p, url, token = start_serve(state)
    hdr = {"Authorization": f"Bearer {token}"}
    try:
        await _wait_lights(url)
        async with aiohttp.ClientSession(headers=hdr) as s:
            async with s.put(url + "/api/v1/config", json={"pipeline": {"nside": 128, "equirect_height": 512}}) as r:
                body = await r.json()
                assert r.status == 200, body
                assert body["restart_required"] == ["pipeline.equirect_height", "pipeline.nside"]
                assert body["config"]["pipeline"]["equirect_height"] == 256  # still running at 256
            # a live change later does not apply the pending geometry
            async with s.put(url + "/api/v1/config", json={"pipeline": {"light_count": 32}}) as r:
                body = await r.json()
                assert body["config"]["pipeline"]["light_count"] == 32
                assert body["pending"] == {"pipeline": {"equirect_height": 512, "nside": 128}}
            t_end = time.monotonic() + 30
            while time.monotonic() < t_end:
                async with s.get(url + "/api/v1/lights") as r:
                    lights = await r.json()
                if len(lights["lights"]) == 32:
                    break
                await asyncio.sleep(0.2)
            async with s.get(url + "/api/v1/probe.exr") as r:
                from lightprobe.core.imageio import read_hdr_image

                (tmp_path / "probe.exr").write_bytes(await r.read())
                img = read_hdr_image(tmp_path / "probe.exr")
                assert img.shape[:2] == (256, 512)  # the geometry it started with
            async with s.put(url + "/api/v1/config", json={"pipeline": {"nside": 1024}}) as r:
                assert r.status == 400  # beyond what a small board holds
            async with s.put(url + "/api/v1/config", json={"service": {"host": "no-such-host.invalid"}}) as r:
                assert r.status == 400
                assert (await r.json())["param"] == "service.host"
            async with s.put(url + "/api/v1/config", data=b'{"probe": {"name": "\\udc80"}}',
                             headers={"Content-Type": "application/json"}) as r:
                assert r.status == 400
                assert (await r.json())["param"] == "probe.name"
    finally:
        _stop(p)
    saved = (state / "config.toml").read_text()
    assert "equirect_height = 512" in saved
    assert "light_count = 32" in saved


async def test_a_full_disk_on_put_config_is_507_and_loses_nothing(tmp_path: Path) -> None:
    """The state dir on a 256 kB tmpfs filled to the last byte (needs root for the mount)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        state = mnt / "state"
        state.mkdir()
        cache = Path(os.environ.get("LIGHTPROBE_TEST_CACHE", tmp_path / "cache"))  # tables off the small disk
        cache.mkdir(parents=True, exist_ok=True)
        (state / "cache").symlink_to(cache, target_is_directory=True)
        p, url, token = start_serve(state)
        try:
            async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as s:
                async with s.put(url + "/api/v1/config", json={"probe": {"name": "Before"}}) as r:
                    assert r.status == 200
                before = (state / "config.toml").read_bytes()
                fd = os.open(mnt / "filler", os.O_WRONLY | os.O_CREAT, 0o600)
                try:  # to the last byte
                    for size in (65536, 4096, 256, 1):
                        with contextlib.suppress(OSError):
                            while True:
                                os.write(fd, b"\0" * size)
                finally:
                    os.close(fd)
                async with s.put(url + "/api/v1/config", json={"probe": {"name": "After" * 10}}) as r:
                    body = await r.json()
                    assert r.status == 507, body
                    assert "ENOSPC" in body["error"]
                assert (state / "config.toml").read_bytes() == before
                assert not [f for f in state.iterdir() if f.name.endswith(".tmp")]
                async with s.get(url + "/api/v1/config") as r:
                    assert (await r.json())["config"]["probe"]["name"] == "Before"
                async with s.get(url + "/api/v1/lights") as r:
                    assert r.status in (200, 503)  # still serving
            # a fresh state dir on the full disk: exit 2 naming it, no half-written token left
            fresh = mnt / "fresh"
            q = subprocess.run([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(fresh)], cwd=ROOT,
                               env=_env(), capture_output=True, text=True, timeout=60)
            assert q.returncode == 2, q.stderr
            assert str(fresh) in q.stderr, q.stderr
            assert "Traceback" not in q.stderr
            assert not [f for f in fresh.iterdir() if f.name.endswith(".tmp")]
        finally:
            _stop(p)
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def test_an_empty_config_file_is_an_error_naming_it(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    (state / "config.toml").write_text("")
    q = subprocess.run([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(state)], cwd=ROOT,
                       env=_env(), capture_output=True, text=True, timeout=60)
    assert q.returncode == 2
    assert "config.toml" in q.stderr, q.stderr
    assert "empty" in q.stderr, q.stderr


def test_the_token_is_not_printed_under_systemd(tmp_path: Path) -> None:
    p = subprocess.Popen([sys.executable, str(SERVE), "--port", "0", "--state-dir", str(tmp_path / "state")],
                         cwd=ROOT, env=_env(INVOCATION_ID="0123456789abcdef"), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert p.stdout is not None
    line = p.stdout.readline()
    _stop(p)
    token = (tmp_path / "state" / "token").read_text().strip()
    assert "dashboard" in line
    assert "lightprobe token" in line
    assert token not in line
