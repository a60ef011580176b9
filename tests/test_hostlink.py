"""hostlink against real probe services on 127.0.0.1 (real aiohttp servers, real python-zeroconf on
loopback, the real pipeline on the simulator, tests/service_harness.py): discovery of three probes,
a merged stream that survives one probe going away, the client's reads and typed errors, the
WebSocket subscription's stale marking and reconnect, manual addresses, moved probes, and
``lightprobe discover``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from aiohttp import web
from service_harness import RunningService, free_port, service_config, sim_factories
from waiting import HANG_S, discovered, hang_guard

from lightprobe.core.q2wire import decode_q2tree
from lightprobe.device.service.routes import q2tree as q2tree_api
from lightprobe.hostlink import (
    Discovery,
    MergedStream,
    ProbeAuthError,
    ProbeClient,
    ProbeProtocolError,
    ProbeRequestError,
    ProbeUnavailable,
)

LOOPBACK = ["127.0.0.1"]
ROOT = Path(__file__).resolve().parents[1]


@contextlib.asynccontextmanager
async def probe(tmp_path: Path, pid: str, name: str, *, port: int | None = None, mdns: bool = True,
                fps: float = 5.0, **tables: dict[str, Any]) -> AsyncIterator[RunningService]:
    """A real service (create_app + the q2tree route) on 127.0.0.1 advertising ``pid``."""
    from lightprobe.device.service.app import create_app

    d = tmp_path / pid
    d.mkdir(exist_ok=True)
    tables = {"mdns": {"enabled": mdns, "interfaces": LOOPBACK}, "probe": {"name": name, "id": pid},
              **tables}
    tables["pipeline"] = {"fps": fps, "light_count": 64, **tables.get("pipeline", {})}
    cfg = service_config(d, **tables)
    make_camera, make_pipeline = sim_factories(d, pid)
    port = port or free_port()
    token = "test-token-0123456789"
    app = create_app(cfg, make_camera, make_pipeline, token=token, probe_id=pid, port=port,
                     backoff=(0.1, 0.5))
    q2tree_api.add_routes(app)  # idempotent: create_app wires it already
    runner = web.AppRunner(app, shutdown_timeout=0.5, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    url = f"http://127.0.0.1:{port}"
    try:
        yield RunningService(url, url + "/api/v1", token, app, runner, port)
    finally:
        await stop(runner)


async def stop(runner: web.AppRunner) -> None:
    """Stop a service gracefully (WS close 1001, mDNS goodbye); a second call does nothing."""
    if runner.server is not None:
        await runner.cleanup()


async def _first_frame(client: ProbeClient, within: float = 60.0) -> None:
    deadline = time.monotonic() + within
    while True:
        try:
            await client.lights()
        except ProbeUnavailable:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)
        else:
            return


@pytest.mark.slow
async def test_three_probes_discovered_merged_and_one_stopped(tmp_path: Path) -> None:
    ids = ["probe0000a1", "probe0000b2", "probe0000c3"]
    async with contextlib.AsyncExitStack() as stack:
        services = {}
        for pid, name in zip(ids, ["North", "East", "South"], strict=True):
            services[pid] = await stack.enter_async_context(probe(tmp_path, pid, name))
        disc = await stack.enter_async_context(Discovery(interfaces=LOOPBACK))
        found = await discovered(disc, lambda p: set(ids) <= set(p), "the three probes discovered")
        for pid in ids:
            assert found[pid].port == services[pid].port
            assert found[pid].host == "127.0.0.1"
            assert found[pid].sampler == "q2tree"
        # (other test sessions on this machine may advertise probes on loopback too)
        # (stale_after: a probe is dropped for its stream's end here, not for a slow frame on a
        # loaded machine)
        stream = await stack.enter_async_context(MergedStream(disc, count=64, ids=ids, stale_after=HANG_S))
        updates = stream.updates(idle=HANG_S)
        async with hang_guard("a merge of all three probes"):
            merged = await anext(updates)
            while sorted(merged.extra["merged_from"]) != ids:
                merged = await anext(updates)
        assert len(merged) == 64
        assert merged.extra["merge"] == "q2tree"
        assert merged.extra["dropped"] == []
        np.testing.assert_allclose(merged.extra["weights"], [1 / 3] * 3)
        # one probe goes away: goodbye -> discovery forgets it; the merge continues from the rest
        victim = ids[1]
        stopped = services.pop(victim)
        await stop(stopped.runner)
        last_with_two = None
        async with hang_guard("a merge of the two probes left"):
            while last_with_two is None:
                m = await anext(updates)
                if sorted(m.extra["merged_from"]) == [ids[0], ids[2]]:
                    last_with_two = m
        assert len(last_with_two) == 64
        await discovered(disc, lambda p: victim not in p, "the stopped probe's goodbye")
        assert set(disc.probes) & set(ids) == {ids[0], ids[2]}
        # and it keeps streaming fresh merges of the two
        async with hang_guard("fresh merges of the two probes"):
            for _ in range(4):
                m = await anext(updates)
                assert victim not in m.extra["merged_from"]
                assert len(m.extra["merged_from"]) == 2
        await updates.aclose()



async def test_client_reads_status_lights_map_and_q2tree(tmp_path: Path) -> None:
    async with probe(tmp_path, "probe0000d4", "Desk", mdns=False, fps=2.0) as s, \
            ProbeClient(s.url, token=s.token) as c:
        await _first_frame(c)
        async with ProbeClient(s.url) as anonymous:  # the map is a picture of the room: token only
            with pytest.raises(ProbeAuthError):
                await anonymous.hdr_map()
            assert len(await anonymous.lights()) == 64  # lighting data is open to the LAN
        st = await c.status()
        assert st["probe"]["id"] == "probe0000d4"
        ls = await c.lights()
        assert len(ls) == 64
        assert ls.probe == "probe0000d4"
        od = await c.lights(method="pharr", count=18)
        assert len(od) == 18
        # the tree the probe serves is the tree of the map it serves (same frame)
        for _ in range(10):
            (img, _), tree = await asyncio.gather(c.hdr_map(), c.q2tree(64))
            frame_hdr = s.app[q2tree_api.STATE].runner.result.frame
            if tree.meta["frame"] == frame_hdr:
                break
        assert img.shape == (256, 512, 3)  # the service's equirect_height
        assert tree.meta["probe"] == "probe0000d4"
        assert tree.meta["stale"] is False
        assert 64 <= len(tree) <= 66
        from lightprobe.core.sphere import equirect_integral

        np.testing.assert_allclose(tree.total, equirect_integral(img), rtol=1e-6)
        local = decode_q2tree(q2tree_api.q2tree_bytes(type("R", (), {"equirect": img})(), 64))
        assert np.array_equal(local.uniq, tree.uniq)
        np.testing.assert_allclose(local.rgb, tree.rgb, rtol=1e-6)
        # cached per frame: a second request gets the same bytes
        async with aiohttp.ClientSession() as sess, sess.get(s.api + "/q2tree") as r:
            assert r.status == 200
            assert r.content_type == q2tree_api.CONTENT_TYPE
            assert len(await r.read()) <= 8 * 1024


async def test_client_errors_are_typed(tmp_path: Path) -> None:
    async with ProbeClient(f"http://127.0.0.1:{free_port()}", timeout=2.0) as c:
        with pytest.raises(ProbeUnavailable):
            await c.status()
    async with probe(tmp_path, "probe0000e5", "Locked", mdns=False,
                     service={"require_token_for_reads": True}) as s:
        async with ProbeClient(s.url) as c:
            with pytest.raises(ProbeAuthError):
                await c.status()
        async with ProbeClient(s.url, token="wrong-token") as c:
            with pytest.raises(ProbeAuthError):
                await c.lights()
        async with ProbeClient(s.api, token=s.token) as c:
            await _first_frame(c)
            with pytest.raises(ProbeRequestError, match="count"):
                await c.lights(count=0)
            with pytest.raises(ProbeRequestError, match="count"):
                await c.q2tree(count=10**6)
    # something that is not a probe answers on the port
    app = web.Application()

    async def junk(request: web.Request) -> web.Response:
        return web.Response(body=b"LPQ2 not really", content_type="text/plain")

    app.router.add_get("/api/v1/{tail:.*}", junk)
    runner = web.AppRunner(app)
    await runner.setup()
    port = free_port()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    try:
        async with ProbeClient(f"http://127.0.0.1:{port}") as c:
            for call in (c.status(), c.lights(), c.q2tree(), c.hdr_map()):
                with pytest.raises(ProbeProtocolError):
                    await call
    finally:
        await runner.cleanup()


async def test_subscription_marks_dropout_stale_then_reconnects(tmp_path: Path) -> None:
    port = free_port()
    async with ProbeClient(f"http://127.0.0.1:{port}", backoff_initial=0.05, backoff_max=0.4) as c:
        it = c.subscribe()
        async with probe(tmp_path, "probe0000f6", "Blinky", port=port, mdns=False, fps=20.0) as s:
            first = await asyncio.wait_for(anext(it), 60.0)
            assert first.stale is False
            assert first.probe == "probe0000f6"
            await stop(s.runner)
            async with hang_guard("the stopped probe's stream marked stale"):
                dropped = await anext(it)
                while not dropped.stale:  # frames already in flight
                    dropped = await anext(it)
            assert dropped.frame >= first.frame
            assert c.connected is False
        nxt = asyncio.ensure_future(anext(it))
        # keeps trying while the probe is away (backing off 0.05, 0.1, 0.2, 0.4 s ...)
        while c.reconnects < 3:  # noqa: ASYNC110 - polling the client's own counter
            await asyncio.sleep(0.05)
        assert not nxt.done()
        async with probe(tmp_path, "probe0000f6", "Blinky", port=port, mdns=False, fps=20.0):
            back = await asyncio.wait_for(nxt, 60.0)
            assert back.stale is False
            assert c.connected is True
        await it.aclose()


async def test_manual_addresses_and_moved_probes(tmp_path: Path) -> None:
    async with probe(tmp_path, "probe0000g7", "Behind VLAN", mdns=False) as s:
        events: list[tuple[str, str]] = []
        async with Discovery(interfaces=LOOPBACK, manual=[f"127.0.0.1:{s.port}"], manual_poll_s=0.2,
                             on_event=lambda e: events.append((e.kind, e.probe.id))
                             if e.probe.id.startswith("probe0000g7") else None) as d:
            found = await discovered(d, lambda p: "probe0000g7" in p, "the manual address polled")
            assert found["probe0000g7"].source == "manual"
            assert found["probe0000g7"].name == "Behind VLAN"
            await stop(s.runner)
            await discovered(d, lambda p: "probe0000g7" not in p, "the stopped manual probe dropped")
            assert events == [("added", "probe0000g7"), ("removed", "probe0000g7")]
    # a probe that comes back on another port under another name keeps its id
    async with Discovery(interfaces=LOOPBACK) as d:
        async with probe(tmp_path, "probe0000h8", "Old name") as s1:
            first = (await discovered(d, lambda p: "probe0000h8" in p, "the probe on mDNS"))["probe0000h8"]
            assert first.port == s1.port
        async with probe(tmp_path, "probe0000h8", "New name") as s2:
            now = await discovered(d, lambda p: "probe0000h8" in p and p["probe0000h8"].port == s2.port,
                                   "the probe back on another port")
            assert now["probe0000h8"].name == "New name"
            assert [p.id for p in d.snapshot()].count("probe0000h8") == 1


async def test_discover_cli_lists_a_running_probe(tmp_path: Path) -> None:
    async with probe(tmp_path, "probe0000i9", "CLI probe") as s:
        cmd = [sys.executable, "-m", "lightprobe.cli", "discover", "--timeout", "2", "--json"]
        proc = await asyncio.create_subprocess_exec(*cmd, cwd=ROOT, stdout=subprocess.PIPE,
                                                    stderr=subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 30)
        assert proc.returncode == 0, err.decode()
        listed = {p["id"]: p for p in json.loads(out)["probes"]}
        assert "probe0000i9" in listed, (out.decode(), err.decode())
        p = listed["probe0000i9"]
        assert p["port"] == s.port
        assert p["name"] == "CLI probe"
        assert p["url"] == f"http://{p['host']}:{s.port}"


def test_discover_cli_bad_arguments_exit_2() -> None:
    for args in (["--timeout", "-1"], ["--address", "nonsense"], ["--interface", "eth0"],
                 ["--bogus"]):
        r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "discover", *args], cwd=ROOT,
                           capture_output=True, text=True, timeout=30)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.strip()


@pytest.mark.slow
async def test_crashed_probe_without_goodbye_is_forgotten_and_comes_back(tmp_path: Path) -> None:
    """``lightprobe serve`` (the simulator) in a subprocess, killed with SIGKILL: no goodbye, its
    PTR record stays cached for >= 1125 s, so the liveness check must forget it; restarted on
    the same port it is listed again."""
    from lightprobe.device.service.config import dump_toml

    cfg = tmp_path / "config.toml"
    cfg.write_text(dump_toml({"mdns": {"enabled": True, "interfaces": LOOPBACK},
                              "probe": {"id": "crashprobe01", "name": "Crashy"},
                              "pipeline": {"fps": 5.0, "light_count": 16}}))
    port = free_port()
    cmd = [sys.executable, str(ROOT / "tests" / "service_harness.py"), "--config", str(cfg),
           "--state-dir", str(tmp_path / "state"), "--port", str(port), "--log-format", "text"]

    async def start() -> asyncio.subprocess.Process:
        proc = await asyncio.create_subprocess_exec(*cmd, cwd=ROOT, stdout=subprocess.PIPE,
                                                    stderr=subprocess.DEVNULL)
        assert proc.stdout is not None
        line = await asyncio.wait_for(proc.stdout.readline(), 30)
        assert b"dashboard" in line
        return proc

    events: list[str] = []
    proc = await start()
    try:
        async with Discovery(interfaces=LOOPBACK, liveness_s=0.3, liveness_failures=2,
                             on_event=lambda e: events.append(e.kind)
                             if e.probe.id == "crashprobe01" else None) as d:
            await discovered(d, lambda p: "crashprobe01" in p, "the probe on mDNS")
            proc.kill()
            await proc.wait()
            await discovered(d, lambda p: "crashprobe01" not in p, "the killed probe dropped by its liveness check")
            assert events == ["added", "removed"]
            proc = await start()
            back = await discovered(d, lambda p: "crashprobe01" in p, "the restarted probe")
            assert back["crashprobe01"].port == port
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_url_list_stream_merges_pharr_probes_by_index(tmp_path: Path) -> None:
    pipeline = {"sampler": "pharr"}
    async with probe(tmp_path, "probe0000j1", "P1", mdns=False, pipeline=pipeline) as a, \
            probe(tmp_path, "probe0000k2", "P2", mdns=False, pipeline=pipeline) as b, \
            MergedStream([a.url, b.url], count=64, target=[0.0, 0.0, 1.0]) as stream:
        updates = stream.updates(idle=60.0)
        m = await anext(updates)
        while len(m.extra["merged_from"]) < 2:
            m = await anext(updates)
        assert m.extra["merge"] == "index"
        assert sorted(m.extra["merged_from"]) == ["probe0000j1", "probe0000k2"]
        assert len(m) == 64
        assert m.pose["position"] == [0.0, 0.0, 1.0]
        np.testing.assert_allclose(np.linalg.norm(m.directions, axis=1), 1.0, atol=1e-9)
        async with ProbeClient(a.url) as c:
            with pytest.raises(ProbeRequestError, match="bogus"):
                await c._get("/q2tree", {"bogus": "1"})
        await updates.aclose()


def test_importing_hostlink_is_cheap() -> None:
    code = ("import sys, lightprobe.hostlink as hostlink, lightprobe.hostlink.discovery; "
            "heavy = {'numpy', 'zeroconf', 'aiohttp'} & set(sys.modules); "
            "assert not heavy, heavy; print(len(hostlink.__all__))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout) >= 15


async def test_a_probe_that_refuses_us_is_listed_as_dropped(tmp_path: Path) -> None:
    async with probe(tmp_path, "probe0000l3", "Open", mdns=False) as a, \
            probe(tmp_path, "probe0000m4", "Locked", mdns=False,
                  service={"require_token_for_reads": True}) as b, \
            MergedStream([a.url, b.url], count=32, stale_after=0.5) as stream:
        updates = stream.updates(idle=60.0)
        m = await anext(updates)
        while not m.extra["dropped"]:
            m = await anext(updates)
        assert m.extra["merged_from"] == ["probe0000l3"]
        assert m.extra["dropped"] == [b.url]
        assert len(m) == 32
        await updates.aclose()
