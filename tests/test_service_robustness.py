"""Robustness of the service: a request fuzzer, a blocking-call detector, torn config writes."""

from __future__ import annotations

import asyncio
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from service_harness import running_service, service_config

from lightprobe.device.service.config import ServiceConfig, load_config

ROOT = Path(__file__).resolve().parent.parent

PATHS = ["/api/v1/status", "/api/v1/lights", "/api/v1/config", "/api/v1/healthz", "/api/v1/probe.exr",
         "/api/v1/preview.jpg", "/api/v1/probe.hdr", "/api/v1/stream", "/api/v1/openapi.json", "/",
         "/static/app.js", "/static/../device/service/auth.py", "/api/v1/%00", "/api/v2/status",
         "/api/v1/lights/../config", "/" + "a" * 3000, "/static/%2e%2e/%2e%2e/etc/passwd"]
KEYS = ["method", "count", "view", "access_token", "x", "", "count[]", "é"]
VALUES = ["q2tree", "pharr", "0", "-1", "4097", "1e9", "NaN", "null", "", "'", "\x00", "%ff", "256",
          "fisheye", "equirect", "x" * 500]


def _random_body(rng: random.Random) -> bytes:
    tables = ["service", "pipeline", "probe", "mdns", "bogus", ""]
    keys = ["fps", "sampler", "light_count", "name", "port", "interfaces", "enabled", "nside", "?"]
    vals: list[Any] = [None, True, -1, 0, 1, 2.5, 1e308, "q2tree", "x" * 70, [], ["a"], {"a": 1}, "é\u202e"]
    kind = rng.randrange(6)
    if kind == 0:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(200)))
    if kind == 1:
        return rng.choice([b"{", b"[", b"{\"a\":"]) * rng.randrange(1, 30000)  # deep nesting
    if kind == 2:
        return b"x" * rng.choice([10, 70_000, 200_000])
    obj: Any = {rng.choice(tables): {rng.choice(keys): rng.choice(vals) for _ in range(rng.randrange(3))}}
    if kind == 3:
        obj = rng.choice([[], 1, "s", None, obj])
    return json.dumps(obj).encode()


async def test_fuzz_1000_requests_then_healthy(tmp_path: Path) -> None:
    rng = random.Random(20261122)
    cfg = service_config(tmp_path, pipeline={"fps": 10.0})
    statuses: dict[int, int] = {}
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        async with c.ws_connect(s.api + "/stream") as ws:  # the first frame exists: no 503s
            await ws.receive(timeout=60)
        async with c.get(s.api + "/config") as r:
            before = await r.json()
        sem = asyncio.Semaphore(16)

        async def one(i: int) -> None:
            method = rng.choice(["GET", "GET", "PUT", "PUT", "POST", "DELETE", "HEAD", "OPTIONS", "PATCH"])
            path = rng.choice(PATHS)
            params = {rng.choice(KEYS): rng.choice(VALUES) for _ in range(rng.randrange(3))}
            headers = {}
            if rng.random() < 0.5:
                headers["Authorization"] = rng.choice(["Bearer " + s.token[:-1], "Bearer", "Basic abc", "Bearer x" * 50])
            if rng.random() < 0.7:
                headers["Content-Type"] = rng.choice(["application/json", "text/plain", "multipart/form-data"])
            body = _random_body(rng) if method in ("PUT", "POST", "PATCH") else None
            async with sem, c.request(method, s.url + path, params=params, data=body, headers=headers,
                                      timeout=aiohttp.ClientTimeout(total=10)) as r:
                await r.read()
                statuses[r.status] = statuses.get(r.status, 0) + 1
                assert r.status < 500, (method, path, params, r.status)
                if r.status >= 400 and method != "HEAD":
                    assert r.content_type == "application/json", (method, path, r.status)

        await asyncio.gather(*(one(i) for i in range(1000)))
        assert sum(statuses.values()) == 1000
        async with c.get(s.api + "/healthz") as r:
            assert r.status == 200
            assert (await r.json())["ok"] is True
        async with c.get(s.api + "/config") as r:
            assert await r.json() == before  # no fuzz request had the token
        async with c.ws_connect(s.api + "/stream") as ws:
            assert json.loads((await ws.receive(timeout=60)).data)["version"] == 1
    assert any(400 <= k < 500 for k in statuses)


ENDPOINTS = ("/probe.exr", "/probe.hdr", "/preview.jpg", "/preview.jpg?view=equirect",
             "/lights?count=4096&method=pharr", "/lights", "/status", "/config")


def _client_pass(api: str, port: int, rounds: int, token: str = "") -> None:
    """HTTP requests and a WebSocket reader from another thread, so that client work does not
    run on (and is not blamed on) the service's loop."""
    import urllib.request

    from test_service import _raw_ws, _read_ws_text

    raw = _raw_ws(port, rcvbuf=1 << 20)
    try:
        for _ in range(rounds):
            for path in ENDPOINTS:
                req = urllib.request.Request(api + path, headers={"Authorization": f"Bearer {token}"} if token else {})
                with urllib.request.urlopen(req, timeout=10) as r:
                    assert r.status == 200, path
                    r.read()
                _read_ws_text(raw)
    finally:
        raw.close()


# The whole-frame work of the API and the publication (image encodings, tone maps, JSON of a light
# set, on-demand sampling, the SH / primary-light estimate): each must run in a worker thread.
FRAME_WORK = (
    ("lightprobe.device.service.encode", "encode_jpeg"),
    ("lightprobe.device.service.encode", "encode_hdr"),
    ("lightprobe.core.imageio", "exr_bytes"),
    ("lightprobe.device.tonemap", "tone_map"),
    ("lightprobe.device.pipeline", "lights_on_demand"),
    ("lightprobe.device.service.runner", "_encode"),
    ("lightprobe.device.service.runner", "_lights_payload"),
    ("lightprobe.device.service.runner", "_environment"),
)


async def test_no_blocking_calls_on_the_event_loop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole-frame work (encoding, sampling, JSON of 4096 lights: ~90 ms) never runs on the
    event loop's thread: each such function is wrapped, wherever a module imported it, and every
    call made on the loop's thread is recorded with what ran it. (No timing: a call is on the
    loop or it is not.) The same for a light set's JSON (``LightSet.to_json``) of a set of 4096."""
    import importlib
    import sys
    import threading

    from lightprobe.core.lightset import LightSet

    loop_thread = threading.get_ident()
    on_loop: list[str] = []
    calls: dict[str, int] = {}

    def watched(name: str, fn: Any) -> Any:
        def wrapper(*a: Any, **kw: Any) -> Any:
            calls[name] = calls.get(name, 0) + 1
            if threading.get_ident() == loop_thread:
                on_loop.append(name)
            return fn(*a, **kw)
        return wrapper

    for mod_name, attr in FRAME_WORK:
        orig = getattr(importlib.import_module(mod_name), attr)
        w = watched(f"{mod_name}.{attr}", orig)
        for m in [m for k, m in list(sys.modules.items()) if k.startswith("lightprobe.") and m is not None]:
            if getattr(m, attr, None) is orig:
                monkeypatch.setattr(m, attr, w)
    orig_to_json = LightSet.to_json

    def to_json(self: LightSet) -> dict[str, Any]:
        if len(self) >= 1024 and threading.get_ident() == loop_thread:
            on_loop.append(f"LightSet.to_json of {len(self)} lights")
        return orig_to_json(self)

    monkeypatch.setattr(LightSet, "to_json", to_json)
    cfg = service_config(tmp_path, pipeline={"light_count": 4096})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        async with c.ws_connect(s.api + "/stream") as ws:
            await ws.receive(timeout=60)
        await asyncio.to_thread(_client_pass, s.api, s.port, 3, s.token)
    # the check saw the work it polices: every endpoint's encoder ran, and the stream's
    assert {"lightprobe.device.service.encode.encode_jpeg", "lightprobe.device.service.encode.encode_hdr",
            "lightprobe.core.imageio.exr_bytes", "lightprobe.device.pipeline.lights_on_demand",
            "lightprobe.device.service.runner._encode"} <= set(calls), calls
    assert on_loop == []


# ---- torn config writes ------------------------------------------------------------------------
WRITER = """
import sys
from lightprobe.device.service.config import ServiceConfig, save_config
a = ServiceConfig().with_patch({"probe": {"name": "A" * 60}, "pipeline": {"fps": 1.5}})
b = ServiceConfig().with_patch({"probe": {"name": "B" * 60}, "pipeline": {"fps": 2.5},
                                 "service": {"cors_origins": ["http://x.example"] * 30}})
save_config(b, sys.argv[1])  # an old config exists before the kills start
print("ready", flush=True)
i = 1
while True:
    save_config(a if i % 2 else b, sys.argv[1])
    i += 1
"""


def test_sigkill_during_config_writes_never_tears(tmp_path: Path) -> None:
    target = tmp_path / "config.toml"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    rng = random.Random(7)
    for _ in range(12):
        p = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], cwd=ROOT, env=env,
                             stdout=subprocess.PIPE, text=True)
        assert p.stdout is not None
        assert p.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.02, 0.25))
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        p.stdout.close()
        cfg = load_config(target)  # parses: never torn
        assert cfg.get("probe", "name") in ("A" * 60, "B" * 60)
        assert cfg.get("pipeline", "fps") == (1.5 if cfg.get("probe", "name")[0] == "A" else 2.5)
    leftovers = [f.name for f in tmp_path.iterdir() if f.name != "config.toml"]
    # a kill between mkstemp and rename can leave a dot-temp file, never a partial config.toml
    assert all(n.startswith(".config.toml.") and n.endswith(".tmp") for n in leftovers)


def test_config_roundtrip_and_validation(tmp_path: Path) -> None:
    cfg = ServiceConfig(path=tmp_path / "c.toml").with_patch(
        {"probe": {"name": 'Quote " and \\ and \u00e9'}, "mdns": {"interfaces": ["127.0.0.1"]},
         "pipeline": {"fps": 12}})
    from lightprobe.device.service.config import save_config

    save_config(cfg)
    back = load_config(tmp_path / "c.toml")
    assert back.data == cfg.data
    assert isinstance(back.get("pipeline", "fps"), float)
    (tmp_path / "bad.toml").write_text("[pipeline]\nfps = 'fast'\n")
    from lightprobe.core.errors import InputError

    with pytest.raises(InputError, match=r"pipeline\.fps") as ei:
        load_config(tmp_path / "bad.toml")
    assert ei.value.param == "pipeline.fps"
    (tmp_path / "torn.toml").write_text("[pipeline\nfps = ")
    with pytest.raises(InputError, match=r"torn\.toml"):
        load_config(tmp_path / "torn.toml")
