"""The probe service on a real aiohttp server on 127.0.0.1: API, WebSocket stream, auth, bad input,
faults. The real pipeline runs on the simulated camera (tests/service_harness.py); faults are the
simulator's own."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from service_harness import running_service, service_config, sim_factories

from lightprobe.core.sphere import equirect_integral
from lightprobe.device.service.config import load_config


async def _get_json(c: aiohttp.ClientSession, url: str, **kw: Any) -> tuple[int, Any]:
    async with c.get(url, **kw) as r:
        return r.status, await r.json(content_type=None)


async def test_lights_arrive_on_the_websocket_in_order(tmp_path: Path) -> None:
    async with running_service(service_config(tmp_path)) as s, aiohttp.ClientSession() as c, \
            c.ws_connect(s.api + "/stream") as ws:
        msg = await ws.receive(timeout=60.0)  # a hang guard: the first frame may build tables
        assert msg.type == aiohttp.WSMsgType.TEXT
        d = json.loads(msg.data)
        assert d["version"] == 1
        assert d["probe"] == "probetest0001"
        assert d["stale"] is False
        assert len(d["lights"]) == 64
        assert set(d["lights"][0]) >= {"direction", "rgb", "solid_angle"}
        # frames keep coming, in order
        frames = [d["frame"]]
        for _ in range(3):
            frames.append(json.loads((await ws.receive(timeout=30.0)).data)["frame"])
        assert frames == sorted(frames)
        assert len(set(frames)) == 4


async def test_read_endpoints(tmp_path: Path) -> None:
    import cv2

    from lightprobe.core.imageio import read_exr_header, read_hdr_image

    cfg = service_config(tmp_path, pipeline={"fps": 4.0, "light_count": 64})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        await _wait_frames(c, s.api, 2)
        code, st = await _get_json(c, s.api + "/status")
        assert code == 200
        assert st["health"] == "ok"
        assert st["camera"]["state"] == "running"
        cam = s.state.camera
        assert st["calibration_id"] == cam.truth_calibration().id  # the simulator's own calibration
        lo, hi = cam.capabilities.exposure_range
        assert st["exposures"]
        assert all(lo <= t <= hi for t in st["exposures"])
        assert set(st["timings"]) >= {"capture", "prepare", "fusion", "sampling", "total"}
        assert len(st["histogram"]) == 64
        assert sum(st["histogram"]) > 1000  # luminances of the image circle's pixels
        assert st["stale"] is False
        code, lights = await _get_json(c, s.api + "/lights")
        assert code == 200
        assert len(lights["lights"]) == 64
        # on demand: the requested method and count, energy equal to the map's integral
        for _ in range(20):  # the on-demand set and the EXR must come from the same frame
            code, od = await _get_json(c, s.api + "/lights", params={"method": "pharr", "count": "18"})
            async with c.get(s.api + "/probe.exr", headers=s.auth) as r:
                assert r.status == 200
                assert r.content_type == "image/x-exr"
                exr = await r.read()
            (tmp_path / "p.exr").write_bytes(exr)
            hdr = read_exr_header(tmp_path / "p.exr")
            if str(od["frame"]) == hdr["frame"]:
                break
        assert code == 200
        assert od["method"] == "pharr"
        assert len(od["lights"]) == 18
        assert str(od["frame"]) == hdr["frame"]
        assert {"unit", "probe", "timestamp", "calibration_id"} <= set(hdr)
        img = read_hdr_image(tmp_path / "p.exr")
        total = np.sum([li["rgb"] for li in od["lights"]], axis=0)
        np.testing.assert_allclose(total, equirect_integral(img), rtol=1e-5)
        async with c.get(s.api + "/probe.hdr", headers=s.auth) as r:
            (tmp_path / "p.hdr").write_bytes(await r.read())
        assert read_hdr_image(tmp_path / "p.hdr").shape == img.shape
        for view in ("fisheye", "equirect"):
            async with c.get(s.api + "/preview.jpg", params={"view": view}, headers=s.auth) as r:
                assert r.status == 200
                assert r.content_type == "image/jpeg"
                jpg = cv2.imdecode(np.frombuffer(await r.read(), np.uint8), cv2.IMREAD_COLOR)
                assert jpg is not None
                assert jpg.ndim == 3
        code, h = await _get_json(c, s.api + "/healthz")
        assert code == 200
        assert h["ok"] is True
        # the binary Q2-Tree for host-side merging (routes.q2tree, wired into the app)
        from lightprobe.core.q2wire import decode_q2tree

        async with c.get(s.api + "/q2tree", params={"count": "16"}) as r:
            assert r.status == 200
            assert r.content_type == "application/x-lightprobe-q2tree"
            tree = decode_q2tree(await r.read())
            frame = int(r.headers["X-Lightprobe-Frame"])
        assert 16 <= len(tree.uniq) <= 18  # each split adds 3 leaves to the 12 base faces
        assert frame >= 1
        assert np.all(tree.rgb >= 0)
        async with c.get(s.url + "/") as r:
            assert r.status == 200
            assert "text/html" in r.content_type
            assert "Access-Control-Allow-Origin" not in r.headers  # CORS off by default


async def _wait_frames(c: aiohttp.ClientSession, api: str, n: int, within: float = 60.0) -> dict[str, Any]:
    t_end = time.monotonic() + within
    while time.monotonic() < t_end:
        _, st = await _get_json(c, api + "/status")
        if st["frames"] >= n:
            return st  # type: ignore[no-any-return]
        await asyncio.sleep(0.05)
    raise AssertionError(f"fewer than {n} frames in {within} s")


BAD_REQUESTS: list[tuple[str, str, Any, dict[str, str] | None, int, str | None]] = [
    # (method, path, body, extra headers, status, param)
    ("GET", "/lights?count=abc", None, None, 400, "count"),
    ("GET", "/lights?count=0", None, None, 400, "count"),
    ("GET", "/lights?count=100000", None, None, 400, "count"),
    ("GET", "/lights?method=bogus", None, None, 400, "method"),
    ("GET", "/lights?colour=red", None, None, 400, "colour"),
    ("GET", "/preview.jpg?view=side", None, "auth", 400, "view"),
    ("GET", "/preview.jpg", None, None, 401, "Authorization"),  # a picture of the room
    ("GET", "/nothing/here", None, None, 404, "path"),
    ("GET", "/../../etc/passwd", None, None, 404, "path"),
    ("POST", "/status", b"{}", None, 405, None),  # routing before auth: no such operation
    ("POST", "/status", b"{}", "auth", 405, None),
    ("DELETE", "/config", None, None, 405, None),
    ("PUT", "/config", b'{"probe": {"name": "x"}}', {"Authorization": ""}, 401, "Authorization"),
    ("PUT", "/config", b'{"probe": {"name": "x"}}', {"Authorization": "Bearer nope"}, 403, "Authorization"),
    ("PUT", "/config", b"{not json", "auth", 400, "body"),
    ("PUT", "/config", b"[1, 2]", "auth", 400, "config"),
    ("PUT", "/config", b"[" * 60_000, "auth", 400, "body"),  # RecursionError in json
    ("PUT", "/config", b"\xff\xfe{}", "auth", 400, "body"),
    ("PUT", "/config", b'{"probe": {"name": "x"}}', {"Authorization": "auth", "Content-Type": "text/plain"}, 400,
     "Content-Type"),
    ("PUT", "/config", b'{"pipeline": {"fps": "fast"}}', "auth", 400, "pipeline.fps"),
    ("PUT", "/config", b'{"pipeline": {"fps": 1e9}}', "auth", 400, "pipeline.fps"),
    ("PUT", "/config", b'{"pipeline": {"light_count": true}}', "auth", 400, "pipeline.light_count"),
    ("PUT", "/config", b'{"pipeline": {"sampler": "magic"}}', "auth", 400, "pipeline.sampler"),
    ("PUT", "/config", b'{"pipeline": {"nside": 48}}', "auth", 400, "pipeline.nside"),
    ("PUT", "/config", b'{"probe": {"name": "\\u0000evil"}}', "auth", 400, "probe.name"),
    ("PUT", "/config", b'{"probe": {"colour": "red"}}', "auth", 400, "probe.colour"),
    ("PUT", "/config", ('{"probe": {"name": "' + "\u00e9" * 40 + '"}}').encode(), "auth", 400, "probe.name"),
    ("PUT", "/config", b'{"nope": {}}', "auth", 400, "nope"),
    ("PUT", "/config", b'{"probe": {"name": "ok"}, "pipeline": {"fps": -1}}', "auth", 400, "pipeline.fps"),
    ("PUT", "/config", b'{"probe": {"name": "' + b"x" * 200_000 + b'"}}', "auth", 413, "body"),
]


async def test_bad_input_gives_json_4xx_and_config_unchanged(tmp_path: Path) -> None:
    cfg = service_config(tmp_path)
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        await _wait_frames(c, s.api, 1)
        _, before = await _get_json(c, s.api + "/config")
        for method, path, body, headers, status, param in BAD_REQUESTS:
            h = dict(s.auth) if headers == "auth" else dict(headers or {})
            if h.get("Authorization") == "auth":
                h["Authorization"] = s.auth["Authorization"]
            h.setdefault("Content-Type", "application/json")
            url = (s.api + path) if not path.startswith("/..") else s.url + path
            async with c.request(method, url, data=body, headers=h) as r:
                assert r.status == status, (method, path, await r.text())
                assert r.content_type == "application/json", (method, path)
                err = await r.json()
                assert err["status"] == status
                assert err["error"]
                if param is not None:
                    assert err["param"] == param, (method, path, err)
        _, after = await _get_json(c, s.api + "/config")
        assert after == before
        assert not (tmp_path / "config.toml").exists()  # nothing was ever written
        code, h = await _get_json(c, s.api + "/healthz")
        assert code == 200
        assert h["ok"]


async def test_put_config_needs_token_persists_and_applies(tmp_path: Path) -> None:
    async with running_service(service_config(tmp_path)) as s, aiohttp.ClientSession() as c:
        await _wait_frames(c, s.api, 1)
        patch = {"probe": {"name": "Atrium east"}, "pipeline": {"light_count": 16, "sampler": "pharr"}}
        async with c.put(s.api + "/config", json=patch, headers=s.auth) as r:
            assert r.status == 200
            body = await r.json()
        assert body["saved"] is True
        assert body["config"]["probe"]["name"] == "Atrium east"
        on_disk = load_config(tmp_path / "config.toml")
        assert on_disk.get("probe", "name") == "Atrium east"
        assert on_disk.get("pipeline", "light_count") == 16
        # the pipeline is rebuilt: new frames carry the new count and method
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end:
            _, ls = await _get_json(c, s.api + "/lights")
            if len(ls["lights"]) == 16 and ls["method"] == "pharr":
                break
            await asyncio.sleep(0.05)
        else:
            raise AssertionError("light_count/sampler change did not reach the pipeline")
        _, st = await _get_json(c, s.api + "/status")
        assert st["probe"]["name"] == "Atrium east"
        assert st["light_count"] == 16


async def test_reads_can_require_token(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, service={"require_token_for_reads": True})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        code, err = await _get_json(c, s.api + "/status")
        assert code == 401
        assert err["param"] == "Authorization"
        code, _ = await _get_json(c, s.api + "/status", headers=s.auth)
        assert code == 200
        code, _ = await _get_json(c, s.api + "/healthz")  # health stays open for supervisors
        assert code in (200, 503)
        with pytest.raises(aiohttp.WSServerHandshakeError):
            await c.ws_connect(s.api + "/stream")
        async with c.ws_connect(s.api + "/stream", params={"access_token": s.token}) as ws:
            assert json.loads((await ws.receive(timeout=60)).data)["version"] == 1


async def test_cors_only_for_configured_origins(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, service={"cors_origins": ["http://host.example"]})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        async with c.get(s.api + "/healthz", headers={"Origin": "http://host.example"}) as r:
            assert r.headers.get("Access-Control-Allow-Origin") == "http://host.example"
        async with c.get(s.api + "/healthz", headers={"Origin": "http://evil.example"}) as r:
            assert "Access-Control-Allow-Origin" not in r.headers


def _raw_ws(port: int, rcvbuf: int = 8192) -> Any:
    """A WebSocket client on a plain socket with a tiny receive buffer: it reads only when told,
    so the server sees real TCP backpressure (aiohttp's client would buffer in its own memory)."""
    import socket as pysocket

    raw = pysocket.socket()
    raw.setsockopt(pysocket.SOL_SOCKET, pysocket.SO_RCVBUF, rcvbuf)
    raw.connect(("127.0.0.1", port))
    raw.sendall((f"GET /api/v1/stream HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                 "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                 "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += raw.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return raw


def _recv_exact(sock: Any, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed")
        buf += chunk
    return bytes(buf)


def _read_ws_text(sock: Any) -> str:
    """The next unmasked, unfragmented text frame from the server (RFC 6455 section 5.2); pings
    (the server's heartbeat) are answered with a masked pong."""
    import os as _os

    while True:
        b0, b1 = _recv_exact(sock, 2)
        n = b1 & 0x7F
        if n == 126:
            n = int.from_bytes(_recv_exact(sock, 2), "big")
        elif n == 127:
            n = int.from_bytes(_recv_exact(sock, 8), "big")
        data = _recv_exact(sock, n)
        opcode = b0 & 0x0F
        if opcode == 9:  # ping -> pong with the same payload (n < 126 for control frames)
            mask = _os.urandom(4)
            sock.sendall(bytes([0x8A, 0x80 | n]) + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(data)))
            continue
        assert opcode == 1, f"opcode {opcode}"
        return data.decode()


async def test_slow_reader_skips_frames(tmp_path: Path) -> None:
    """A client that stops reading for a while: the server's send waits on TCP backpressure
    (bounded socket buffers), and once the client drains the backlog it gets the newest frame,
    not every frame it missed, so frame numbers jump."""
    cfg = service_config(tmp_path, pipeline={"light_count": 1024}, service={"ws_send_timeout": 60.0})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        await _wait_frames(c, s.api, 1)
        raw = await asyncio.to_thread(_raw_ws, s.port)
        try:
            first = json.loads(await asyncio.to_thread(_read_ws_text, raw))["frame"]
            while (await _wait_frames(c, s.api, 1))["frame"] < first + 40:  # noqa: ASYNC110 - the client stalls
                await asyncio.sleep(0.2)
            frames = [first]
            while len(frames) < 60 and (len(frames) < 2 or np.diff(frames).max() <= 1):
                frames.append(json.loads(await asyncio.to_thread(_read_ws_text, raw))["frame"])
            _, st = await _get_json(c, s.api + "/status")
        finally:
            raw.close()
        gaps = np.diff(frames)
        assert gaps.min() >= 1
        assert gaps.max() > 1, frames
        assert st["websocket"]["frames_skipped"] > 0
        assert st["websocket"]["dropped"] == 0
        # the backlog it read first is bounded (socket buffers), not every frame it missed
        assert len(frames) < 40, frames


async def test_stalled_client_is_dropped_and_others_keep_streaming(tmp_path: Path) -> None:
    """A client that never reads: its sends block on a full socket and it is dropped after
    ws_send_timeout; memory is bounded by one payload in the slot plus the socket buffers."""

    cfg = service_config(tmp_path, service={"ws_send_timeout": 0.5}, pipeline={"light_count": 4096, "fps": 30.0})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        raw = await asyncio.to_thread(_raw_ws, s.port, 4096)
        try:
            async with c.ws_connect(s.api + "/stream") as ws:
                t_end = time.monotonic() + 60
                dropped = 0
                while time.monotonic() < t_end and dropped == 0:
                    msg = await ws.receive(timeout=30)  # the good client keeps getting frames
                    assert msg.type == aiohttp.WSMsgType.TEXT
                    dropped = s.state.ws_dropped
                assert dropped == 1
                assert len(s.state.websockets) == 1
        finally:
            raw.close()


async def test_camera_disconnect_turns_lights_stale_then_recovers(tmp_path: Path) -> None:
    """The simulator unplugs itself (its ``disconnect`` fault, 5 s): lights turn stale, the loop
    reconnects with backoff, and fresh lights follow once the camera is back."""
    async with running_service(service_config(tmp_path), backoff=(0.1, 0.4)) as s, \
            aiohttp.ClientSession() as c, c.ws_connect(s.api + "/stream") as ws:
        await _wait_frames(c, s.api, 2)
        s.state.camera.faults.inject("disconnect", duration_s=5.0)
        st = await _poll_status(c, s.api, lambda st: st["stale"], 30.0)
        assert st["camera"]["state"] == "reconnecting"
        assert st["health"] == "degraded"
        assert "CameraDisconnected" in st["camera"]["error"] or "CameraUnavailable" in st["camera"]["error"]
        code, ls = await _get_json(c, s.api + "/lights")
        assert code == 200
        assert ls["stale"] is True
        assert len(ls["lights"]) == 64
        code, _ = await _get_json(c, s.api + "/healthz")
        assert code in (200, 503)
        # the stream also says stale, then fresh again
        saw_stale = False
        while True:
            d = json.loads((await ws.receive(timeout=60)).data)
            saw_stale |= d["stale"]
            if saw_stale and not d["stale"]:
                break
        st = await _poll_status(c, s.api, lambda st: not st["stale"], 30.0)
        assert st["camera"]["state"] == "running"
        assert st["camera"]["reconnects"] >= 1


async def _poll_status(c: aiohttp.ClientSession, api: str, cond: Any, within: float) -> dict[str, Any]:
    t_end = time.monotonic() + within
    while True:
        _, st = await _get_json(c, api + "/status")
        if cond(st):
            return st  # type: ignore[no-any-return]
        if time.monotonic() > t_end:
            raise AssertionError(f"status never matched: {st}")
        await asyncio.sleep(0.05)


async def test_api_answers_while_the_pipeline_is_still_starting(tmp_path: Path) -> None:
    """The server listens before the camera and pipeline exist (imports, tables and the first
    burst happen behind it): /status says "starting", /healthz answers 503, and both the camera
    and the pipeline are made off the event loop. The camera factory is held back by the test
    (as importing a driver or the simulator would)."""
    import threading

    make_camera, make_pipeline = sim_factories(tmp_path)
    threads: list[str] = []
    release = threading.Event()

    def slow_camera() -> Any:
        threads.append(threading.current_thread().name)
        release.wait(30.0)
        return make_camera()

    async with running_service(service_config(tmp_path), slow_camera, make_pipeline) as s, \
            aiohttp.ClientSession() as c:
        code, st = await _get_json(c, s.api + "/status")
        assert code == 200
        assert st["health"] == "starting"
        assert st["camera"]["state"] == "starting"
        assert st["frames"] == 0
        code, hz = await _get_json(c, s.api + "/healthz")
        assert code == 503
        assert hz["ok"] is False
        assert s.state.camera is None
        release.set()
        async with c.ws_connect(s.api + "/stream") as ws:
            msg = await ws.receive(timeout=60.0)
        assert msg.type == aiohttp.WSMsgType.TEXT
        assert threads
        assert threads[0] != threading.main_thread().name


async def test_on_demand_lights_without_a_pipeline_serve_the_published_frame(tmp_path: Path) -> None:
    """With no pipeline (dropped for a rebuild after a camera change, or the camera reconnecting)
    on-demand sampling answers 200 from the published frame, marked stale like the published set
    (the last good state keeps serving; schemathesis' ST101 counts any 5xx as a server error)."""
    async with running_service(service_config(tmp_path)) as s, aiohttp.ClientSession() as c:
        await _wait_frames(c, s.api, 1)
        runner = s.state.runner
        await runner.stop()  # the loop and the pipeline gone: nothing but the published frame
        await runner._mark_stale()
        assert runner.pipeline is None
        frame = runner.result.frame
        code, ls = await _get_json(c, s.api + "/lights?method=q2tree&count=8")
        assert code == 200
        assert len(ls["lights"]) == 8
        assert ls["frame"] == frame
        assert ls["stale"] is True
