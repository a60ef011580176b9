"""mDNS / DNS-SD advertising with python-zeroconf (``AsyncZeroconf``).

Two services point at the same port: ``_lightprobe._tcp.local.`` (host applications) and
``_http._tcp.local.`` (the installer dashboard). TXT records, ``txtvers`` first, stay well under
200 bytes: ``txtvers=1``, ``id`` (stable: from /etc/machine-id, else the MAC; overridable),
``path=/api/v1``, ``version``, ``model``, ``name`` (installer-set), ``sampler``.

Name conflicts are resolved by python-zeroconf (``allow_name_change``: "name (2)"); a change of
the probe's name re-registers under the new instance name; a change of the host's addresses is
re-announced (polled every ``address_poll_s``); ``close()`` sends goodbyes (TTL 0) and closes the
sockets. ``interfaces`` restricts the sockets (tests use ``["127.0.0.1"]``).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import ipaddress
import logging
import socket
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from lightprobe.core import mdns_txt
from lightprobe.core.mdns_txt import HTTP_TYPE, SERVICE_TYPE

if TYPE_CHECKING:
    from zeroconf import ServiceInfo
    from zeroconf.asyncio import AsyncZeroconf

__all__ = ["HTTP_TYPE", "SERVICE_TYPE", "Advertiser", "MdnsInfo", "camera_identity", "stable_probe_id", "txt_records"]

log = logging.getLogger(__name__)



def stable_probe_id(machine_id_path: str | Path = "/etc/machine-id", identity: str = "") -> str:
    """12 hex digits that stay the same across restarts: a hash of the machine-id (never the raw
    id, which systemd asks not to expose), else of the primary MAC address, and of ``identity``,
    what tells this probe from another on the same machine (:func:`camera_identity`)."""
    try:
        mid = Path(machine_id_path).read_text(encoding="ascii").strip()
    except OSError:
        mid = ""
    if not mid:
        mid = f"mac:{uuid.getnode():012x}"
    key = "lightprobe:" + mid + (f"|{identity}" if identity else "")
    return hashlib.sha256(key.encode()).hexdigest()[:12]


def camera_identity(camera_spec: str, state_dir: Path) -> str:
    """What makes a probe unique on its machine, stable across restarts: a camera spec that
    names one device by a stable path (``v4l2:/dev/v4l/by-id/...``, ``uvc:VID:PID:SERIAL``), else
    the state directory (two services on one machine cannot share one: it is locked), which is
    the simulator's identity and that of a unit's only camera."""
    spec = camera_spec.strip()
    if spec.startswith("v4l2:/dev/v4l/by-id/") or spec.startswith("v4l2:/dev/v4l/by-path/"):
        return spec
    if spec.startswith("uvc:") and spec.count(":") >= 3:  # uvc:VID:PID:SERIAL
        return spec
    return f"state:{state_dir.resolve()}"


@dataclass
class MdnsInfo:
    """What is advertised. ``name`` is the installer-set name (the DNS-SD instance name)."""

    probe_id: str
    name: str
    port: int
    version: str = "0.1.0"
    model: str = "lightprobe"
    sampler: str = "q2tree"
    path: str = "/api/v1"
    interfaces: list[str] = field(default_factory=list)

    @property
    def instance(self) -> str:
        return (self.name or f"lightprobe-{self.probe_id[:6]}")[:63]


def txt_records(info: MdnsInfo) -> dict[str, str]:
    """TXT key/values in order, ``txtvers`` first (:mod:`lightprobe.core.mdns_txt`)."""
    return mdns_txt.txt_records(probe_id=info.probe_id, name=info.name, path=info.path, version=info.version,
                                model=info.model, sampler=info.sampler)


def current_addresses(interfaces: list[str]) -> list[str]:
    """IPv4 addresses to advertise: the configured interface addresses, else every up IPv4
    address except loopback (loopback only when there is nothing else)."""
    explicit = []
    for s in interfaces:
        with contextlib.suppress(ValueError):
            explicit.append(str(ipaddress.IPv4Address(s)))
    if explicit:
        return sorted(set(explicit))
    import ifaddr

    found: set[str] = set()
    for adapter in ifaddr.get_adapters():
        for ip in adapter.ips:
            if isinstance(ip.ip, str):
                found.add(ip.ip)
    public = sorted(a for a in found if not a.startswith("127."))
    return public or sorted(found) or ["127.0.0.1"]


class Advertiser:
    """Registers, updates and withdraws the two services. All methods are coroutines on the loop."""

    def __init__(self, info: MdnsInfo, *, address_poll_s: float = 10.0) -> None:
        self.info = info
        self.address_poll_s = address_poll_s
        self._azc: AsyncZeroconf | None = None
        self._registered: list[ServiceInfo] = []
        self._addresses: list[str] = []
        self._watch: asyncio.Task[None] | None = None
        self._lock = asyncio.Lock()
        self.registered_names: list[str] = []

    def _service_infos(self) -> list[ServiceInfo]:
        from zeroconf import ServiceInfo

        server = f"lightprobe-{self.info.probe_id[:12]}.local."
        props = txt_records(self.info)
        infos = []
        for typ in (SERVICE_TYPE, HTTP_TYPE):
            infos.append(ServiceInfo(
                typ, f"{self.info.instance}.{typ}", port=self.info.port, properties=props,
                server=server, addresses=[socket.inet_aton(a) for a in self._addresses]))
        return infos

    async def start(self) -> None:
        """Open the mDNS sockets and register both services (resolving name conflicts)."""
        await self.open()
        await self.register()

    async def open(self) -> None:
        """Open the mDNS sockets (from then on the cache follows the network)."""
        from zeroconf import IPVersion
        from zeroconf.asyncio import AsyncZeroconf

        ifaces: list[str] | object = self.info.interfaces
        if not self.info.interfaces:
            from zeroconf import InterfaceChoice
            ifaces = InterfaceChoice.All
        self._addresses = await asyncio.to_thread(current_addresses, self.info.interfaces)
        self._azc = AsyncZeroconf(interfaces=ifaces, ip_version=IPVersion.V4Only)  # type: ignore[arg-type]

    async def register(self) -> None:
        """Register both services and start following address changes."""
        await self._register()
        self._watch = asyncio.create_task(self._watch_addresses(), name="mdns-address-watch")

    async def _register(self) -> None:
        azc = self._azc
        assert azc is not None
        self._registered = []
        for si in self._service_infos():
            await (await azc.async_register_service(si, allow_name_change=True))
            self._registered.append(si)
        self.registered_names = [si.name for si in self._registered]
        log.info("mdns: advertised %s on %s", self.registered_names, self._addresses)

    async def _unregister(self) -> None:
        azc = self._azc
        assert azc is not None
        for si in self._registered:
            with contextlib.suppress(Exception):
                await (await azc.async_unregister_service(si))
        self._registered = []

    async def update(self, *, name: str | None = None, sampler: str | None = None,
                     model: str | None = None) -> None:
        """Re-announce after a change. A new name re-registers under the new instance name."""
        async with self._lock:
            renamed = name is not None and name != self.info.name
            if name is not None:
                self.info.name = name
            if sampler is not None:
                self.info.sampler = sampler
            if model is not None:
                self.info.model = model
            if self._azc is None:
                return
            if renamed:
                await self._unregister()
                await self._register()
            else:
                await self._update_all()

    async def _update_all(self) -> None:
        azc = self._azc
        assert azc is not None
        new = self._service_infos()
        for old, si in zip(self._registered, new, strict=True):
            si.name = old.name  # keep a conflict-resolved name
            await (await azc.async_update_service(si))
        self._registered = new

    async def _watch_addresses(self) -> None:
        while True:
            await asyncio.sleep(self.address_poll_s)
            try:
                addrs = await asyncio.to_thread(current_addresses, self.info.interfaces)
                if addrs != self._addresses:
                    log.info("mdns: addresses changed %s -> %s, re-announcing", self._addresses, addrs)
                    async with self._lock:
                        self._addresses = addrs
                        await self._update_all()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("mdns: address watch failed")

    async def close(self) -> None:
        """Goodbye packets for both services, then close the sockets."""
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
        if self._azc is not None:
            async with self._lock:
                await self._unregister()
            await self._azc.async_close()
            self._azc = None
