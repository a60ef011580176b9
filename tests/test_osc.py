"""OSC output (issue 44): python-osc's own UDP server as the receiver, the real service on the
simulator sending to it. Every documented address arrives, for every published set (or at the
configured rate), and the values are the probe's: the primary light's direction is /sh's on the
same frame, the SH /sh's in the three.js convention."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import aiohttp
import numpy as np
import pytest

from lightprobe.core.errors import InputError
from lightprobe.device.service.osc import ADDRESSES, OscSettings, parse_osc_target
from tests.service_harness import running_service, service_config

PROBE = "osctest0001"


def test_targets_are_udp_urls_and_bad_ones_name_their_parameter(tmp_path: Any) -> None:
    assert parse_osc_target("udp://127.0.0.1:9000") == ("127.0.0.1", 9000)
    assert parse_osc_target("udp://[::1]:8000") == ("::1", 8000)
    assert parse_osc_target("udp://studio-pc.local:7000") == ("studio-pc.local", 7000)
    for bad in ("tcp://x:1", "udp://x", "udp://x:0", "udp://x:70000", "udp://x:9/path", "x:9", ""):
        with pytest.raises(InputError) as e:
            parse_osc_target(bad, "--osc")
        assert e.value.param == "--osc"
    cfg = service_config(tmp_path)
    assert OscSettings.from_config(cfg) is None  # off by default
    s = OscSettings.from_config(cfg, ["udp://127.0.0.1:9000", "udp://10.0.0.2:8000"])
    assert s is not None
    assert s.targets == (("127.0.0.1", 9000), ("10.0.0.2", 8000))
    assert s.rate == 0.0
    with pytest.raises(InputError) as e:
        cfg.with_patch({"osc": {"targets": ["udp://nowhere"]}})
    assert e.value.param == "osc.targets"
    cfg2 = cfg.with_patch({"osc": {"targets": ["udp://127.0.0.1:9001"], "rate": 5.0}})
    assert OscSettings.from_config(cfg2) == OscSettings((("127.0.0.1", 9001),), 5.0)


class _Receiver:
    """python-osc's asyncio UDP server: every message with the frame it belongs to (the last
    ``frame`` message before it, as the probe sends ``frame`` first)."""

    def __init__(self) -> None:
        from pythonosc.dispatcher import Dispatcher

        self.by_frame: dict[int, dict[str, list[Any]]] = {}
        self.addresses: set[str] = set()
        self.frames: list[tuple[float, int]] = []
        self._frame: int | None = None
        self.dispatcher = Dispatcher()
        self.dispatcher.set_default_handler(self._on)

    def _on(self, address: str, *args: Any) -> None:
        prefix = f"/lightprobe/{PROBE}/"
        assert address.startswith(prefix), address
        name = address[len(prefix):]
        self.addresses.add(name)
        if name == "frame":
            self._frame = int(args[0])
            self.frames.append((time.monotonic(), self._frame))
            self.by_frame[self._frame] = {}
        if self._frame is not None:
            self.by_frame[self._frame][name] = list(args)

    async def __aenter__(self) -> tuple[_Receiver, int]:
        from pythonosc.osc_server import AsyncIOOSCUDPServer

        server = AsyncIOOSCUDPServer(("127.0.0.1", 0), self.dispatcher, asyncio.get_running_loop())
        self._transport, _ = await server.create_serve_endpoint()
        return self, self._transport.get_extra_info("sockname")[1]

    async def __aexit__(self, *exc: object) -> None:
        self._transport.close()


async def _sets_on_ws(ws: aiohttp.ClientWebSocketResponse, seconds: float) -> list[int]:
    frames, t0 = [], time.monotonic()
    while time.monotonic() - t0 < seconds:
        d = await ws.receive_json(timeout=10)
        frames.append(int(d["frame"]))
    return frames


@pytest.mark.timeout(180)
async def test_every_address_for_every_set_with_the_probes_values(tmp_path: Any) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 30.0, "light_count": 64})
    async with _Receiver() as (rx, port):
        settings = OscSettings((("127.0.0.1", port),), rate=0.0)
        async with running_service(cfg, probe_id=PROBE, osc=settings) as s, aiohttp.ClientSession() as c, \
                c.ws_connect(s.api + "/stream") as ws:
            await ws.receive_json(timeout=120)  # first lights
            await asyncio.sleep(0.3)
            n0 = len(rx.frames)
            published = await _sets_on_ws(ws, 3.0)
            await asyncio.sleep(0.2)
            sent = [f for _, f in rx.frames[n0:]]
            # the same frame on both sides: /sh (canonical and three.js) against what OSC sent for it
            for _ in range(20):
                async with c.get(s.api + "/sh", params={"convention": "canonical"}) as r:
                    sh = await r.json()
                async with c.get(s.api + "/sh", params={"convention": "threejs"}) as r:
                    sh3 = await r.json()
                await asyncio.sleep(0.1)
                if sh["frame"] == sh3["frame"] and sh["frame"] in rx.by_frame:
                    break
            async with c.get(s.api + "/status") as r:
                status = await r.json()
    # every documented address arrived
    assert rx.addresses == set(ADDRESSES), set(ADDRESSES) ^ rx.addresses
    # every published set (at the default rate): the frames the WebSocket saw, OSC sent too
    assert len(published) > 30
    window = [f for f in published if min(sent) <= f <= max(sent)]
    missed = set(window) - set(sent)
    assert len(window) > 30, (published, sent)
    print(f"OSC: {len(window) - len(missed)} of the {len(window)} sets the WebSocket saw")
    assert len(missed) <= 0.05 * len(window), (sorted(missed), len(window))
    assert status["osc"]["targets"][0]["errors"] == 0
    assert status["osc"]["sets_sent"] >= len(sent)
    # the values are the probe's, on the same frame
    msg = rx.by_frame[sh["frame"]]
    assert set(msg) >= set(ADDRESSES) - {"cct"}, set(msg)
    d_osc = np.array(msg["primary/direction"])
    d_sh = np.array(sh["primary_light"]["direction"])
    angle = np.degrees(np.arccos(np.clip(d_osc @ d_sh / np.linalg.norm(d_osc) / np.linalg.norm(d_sh), -1, 1)))
    assert angle <= 0.5, (d_osc, d_sh)
    np.testing.assert_allclose(msg["primary/rgb"], sh["primary_light"]["rgb"], rtol=1e-5)
    np.testing.assert_allclose(np.reshape(msg["sh/ambient"], (9, 3)), sh3["ambient_coefficients"], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(np.reshape(msg["sh/all"], (9, 3)), sh3["coefficients"], rtol=1e-5, atol=1e-7)
    assert msg["captured"][0] <= msg["timestamp"][0]
    assert abs(msg["timestamp"][0] - sh["timestamp"]) < 1e-3
    assert msg["unit"] == [sh["unit"]]
    assert len(msg["pose"]) == 12
    assert msg["stale"] == [0]
    assert max(msg["primary/color"]) == pytest.approx(1.0)
    assert msg["primary/intensity"][0] > 0
    assert msg["illuminance"][0] > 0


@pytest.mark.timeout(180)
async def test_a_configured_rate_caps_the_sets_sent(tmp_path: Any) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 30.0, "light_count": 64})
    async with _Receiver() as (rx, port):
        settings = OscSettings((("127.0.0.1", port), ("127.0.0.1", 9)), rate=5.0)  # port 9: nobody listens
        async with running_service(cfg, probe_id=PROBE, osc=settings) as s, aiohttp.ClientSession() as c, \
                c.ws_connect(s.api + "/stream") as ws:
            await ws.receive_json(timeout=120)
            await asyncio.sleep(0.5)
            t0, n0 = time.monotonic(), len(rx.frames)
            await asyncio.sleep(3.0)
            rate = (len(rx.frames) - n0) / (time.monotonic() - t0)
            async with c.get(s.api + "/lights") as r:
                assert r.status == 200  # a target that refuses costs the service nothing
    assert 3.5 <= rate <= 5.5, rate
