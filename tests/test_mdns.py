"""mDNS advertising with real python-zeroconf instances on 127.0.0.1 (no mocks): TXT records,
rename re-announcement, name conflicts, goodbyes."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import aiohttp
from service_harness import running_service, service_config
from waiting import HANG_S, hang_guard
from zeroconf import IPVersion, ServiceStateChange
from zeroconf.asyncio import AsyncServiceBrowser, AsyncServiceInfo, AsyncZeroconf

from lightprobe.device.service.mdns import (
    HTTP_TYPE,
    SERVICE_TYPE,
    Advertiser,
    MdnsInfo,
    stable_probe_id,
)

LOOPBACK = ["127.0.0.1"]


class Browser:
    """Collects add/remove events for our two service types (handlers are sync: record only)."""

    def __init__(self) -> None:
        self.events: list[tuple[str, str, str]] = []
        self.changed = asyncio.Event()

    async def __aenter__(self) -> Browser:
        self.azc = AsyncZeroconf(interfaces=LOOPBACK, ip_version=IPVersion.V4Only)
        self.browser = AsyncServiceBrowser(self.azc.zeroconf, [SERVICE_TYPE, HTTP_TYPE], handlers=[self._on])
        return self

    def _on(self, zeroconf: Any, service_type: str, name: str, state_change: ServiceStateChange) -> None:
        self.events.append((state_change.name, service_type, name))
        self.changed.set()

    async def wait_for(self, state: str, name_part: str, typ: str = SERVICE_TYPE, within: float = HANG_S) -> str:
        async def loop() -> str:
            while True:
                for st, t, n in self.events:
                    if st == state and t == typ and name_part in n:
                        return n
                self.changed.clear()
                await self.changed.wait()

        async with hang_guard(f"mDNS {state} of {name_part!r} ({typ})", within):
            return await loop()

    async def resolve(self, typ: str, name: str) -> AsyncServiceInfo:
        info = AsyncServiceInfo(typ, name)
        assert await info.async_request(self.azc.zeroconf, 3000)
        return info

    async def __aexit__(self, *exc: object) -> None:
        await self.browser.async_cancel()
        await self.azc.async_close()


async def test_browser_sees_both_services_with_txt_and_rename(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, mdns={"enabled": True, "interfaces": LOOPBACK},
                         probe={"name": "Lobby probe", "model": "lightprobe-sim"})
    async with Browser() as b, running_service(cfg, probe_id="a1b2c3d4e5f6") as s:
        for typ in (SERVICE_TYPE, HTTP_TYPE):
            name = await b.wait_for("Added", "Lobby probe", typ)
            info = await b.resolve(typ, name)
            assert info.port == s.port
            assert "127.0.0.1" in info.parsed_addresses()
            txt = info.text or b""
            first_key = txt[1:1 + txt[0]].split(b"=")[0]
            assert first_key == b"txtvers"  # txtvers first
            props = {k.decode(): (v or b"").decode() for k, v in info.properties.items()}
            assert props == {"txtvers": "1", "id": "a1b2c3d4e5f6", "path": "/api/v1", "version": "0.1.0",
                             "model": "lightprobe-sim", "name": "Lobby probe", "sampler": "q2tree"}
            assert len(txt) < 200
        # the installer renames the probe: the old instance says goodbye, the new one appears
        async with aiohttp.ClientSession() as c, \
                c.put(s.api + "/config", json={"probe": {"name": "Atrium"}}, headers=s.auth) as r:
            assert r.status == 200
        await b.wait_for("Removed", "Lobby probe")
        name = await b.wait_for("Added", "Atrium")
        info = await b.resolve(SERVICE_TYPE, name)
        assert info.properties[b"name"] == b"Atrium"
        assert s.state.advertiser.registered_names[0].startswith("Atrium.")


async def test_goodbye_on_shutdown(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, mdns={"enabled": True, "interfaces": LOOPBACK}, probe={"name": "Bye probe"})
    async with Browser() as b:
        async with running_service(cfg):
            await b.wait_for("Added", "Bye probe")
            await b.wait_for("Added", "Bye probe", HTTP_TYPE)
        await b.wait_for("Removed", "Bye probe")
        await b.wait_for("Removed", "Bye probe", HTTP_TYPE)


async def test_txt_model_names_the_camera_once_it_is_open(tmp_path: Path) -> None:
    """No model configured: the TXT record says the open camera's model and driver (re-announced
    when the camera opens), never a simulator that is not running."""
    cfg = service_config(tmp_path, mdns={"enabled": True, "interfaces": LOOPBACK}, probe={"name": "Cam probe"})
    async with Browser() as b, running_service(cfg) as s:
        name = await b.wait_for("Added", "Cam probe")
        deadline = asyncio.get_running_loop().time() + 30
        while True:
            info = await b.resolve(SERVICE_TYPE, name)
            model = (info.properties.get(b"model") or b"").decode()
            assert model in ("lightprobe", "lightprobe-sim (sim)"), model
            if model != "lightprobe" or asyncio.get_running_loop().time() > deadline:
                break
            await asyncio.sleep(0.3)
        assert s.state.runner.camera_info is not None
        assert model == "lightprobe-sim (sim)"


async def test_name_conflict_is_resolved_by_renaming() -> None:
    a = Advertiser(MdnsInfo("aaaaaaaaaaaa", "Same name", 8001, interfaces=LOOPBACK))
    b = Advertiser(MdnsInfo("bbbbbbbbbbbb", "Same name", 8002, interfaces=LOOPBACK))
    try:
        await b.open()  # b is on the network (its cache hears a's announcements)
        await a.start()
        await asyncio.sleep(0.5)
        await b.register()
        assert a.registered_names[0] == f"Same name.{SERVICE_TYPE}"
        assert b.registered_names[0] != a.registered_names[0]
        assert b.registered_names[0].startswith("Same name")
    finally:
        await b.close()
        await a.close()


async def test_address_change_is_reannounced() -> None:
    """When the host's addresses change the service is updated (poll period patched short)."""
    adv = Advertiser(MdnsInfo("cccccccccccc", "Moving probe", 8003, interfaces=LOOPBACK), address_poll_s=0.1)
    async with Browser() as b:
        try:
            await adv.start()
            name = await b.wait_for("Added", "Moving probe")
            import lightprobe.device.service.mdns as mdns

            orig = mdns.current_addresses
            mdns.current_addresses = lambda interfaces: ["127.0.0.1", "127.0.0.2"]
            try:
                await b.wait_for("Updated", "Moving probe")
            finally:
                mdns.current_addresses = orig
            info = await b.resolve(SERVICE_TYPE, name)
            assert set(info.parsed_addresses()) == {"127.0.0.1", "127.0.0.2"}
        finally:
            await adv.close()


def test_stable_probe_id(tmp_path: Path) -> None:
    mid = tmp_path / "machine-id"
    mid.write_text("0123456789abcdef0123456789abcdef\n")
    a, b = stable_probe_id(mid), stable_probe_id(mid)
    assert a == b
    assert len(a) == 12
    assert "0123456789" not in a
    mid.write_text("fedcba9876543210fedcba9876543210\n")
    assert stable_probe_id(mid) != a
    # no machine-id: from the MAC, still stable
    assert stable_probe_id(tmp_path / "missing") == stable_probe_id(tmp_path / "missing")
