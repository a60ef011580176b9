"""Finding probes: mDNS/DNS-SD browsing of ``_lightprobe._tcp.local.`` plus manual addresses.

:class:`Discovery` runs python-zeroconf's ``AsyncServiceBrowser`` (handlers are synchronous:
they only schedule a resolve task on the loop). A probe is identified by the ``id`` in its TXT
record, never by its instance name or address (as Home Assistant does): when a known id shows up
under a new name, host or port the entry is updated in place ("moved"). A probe is forgotten on
its goodbye (TTL 0) or when its records expire in the cache (TTL timeout); python-zeroconf
reports both as ``Removed``. python-zeroconf keeps PTR records at least 1125 s
(``_DNS_PTR_MIN_TTL``), so a probe that crashed without a goodbye would linger ~19 min: a
liveness check (``liveness_s``, default 10 s) asks each mDNS probe's ``/api/v1/healthz`` and
forgets a probe after ``liveness_failures`` refused or timed-out connections in a row (a 503
"not progressing" is alive); such a probe is re-added when it answers again.

mDNS does not cross VLANs or routed networks: ``brokers`` lists MQTT brokers
(``mqtt://host[:port]``) whose probes' retained status messages list them (``source="mqtt"``,
``service_name`` = the broker URL; a probe is removed when its status turns ``offline``, which the
broker publishes as the probe's last will when its connection dies); ``mdns=False`` browses no
mDNS at all. ``manual`` lists ``host:port`` addresses that are
polled on ``GET /api/v1/status`` every ``manual_poll_s`` and listed while they answer (their id
comes from the status reply). ``interfaces`` restricts the mDNS sockets (e.g. ``["127.0.0.1"]``
in tests; default: all IPv4 interfaces).

Nothing happens at import or construction; ``start()`` opens sockets, ``close()`` cancels the
browser, then closes zeroconf (the order python-zeroconf asks for).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

from lightprobe.core.mdns_txt import DEFAULT_PATH, SERVICE_TYPE, parse_txt

if TYPE_CHECKING:
    from zeroconf import ServiceStateChange, Zeroconf
    from zeroconf.asyncio import AsyncServiceBrowser, AsyncZeroconf

__all__ = ["SERVICE_TYPE", "Discovery", "ProbeEvent", "ProbeInfo", "parse_address"]

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class ProbeInfo:
    """A probe on the network. ``id`` is the stable key (TXT ``id``); the rest may change."""

    id: str
    name: str
    host: str
    port: int
    path: str = "/api/v1"
    version: str = ""
    model: str = ""
    sampler: str = ""
    source: str = "mdns"  # "mdns", "manual" or "mqtt" (service_name is then the broker URL)
    service_name: str = ""
    seen: float = field(default=0.0, compare=False)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def api(self) -> str:
        return self.url + (self.path if self.path.startswith("/") else "/" + self.path)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("seen")
        d["url"] = self.url
        return d


@dataclass(frozen=True)
class ProbeEvent:
    """``kind`` is ``"added"``, ``"moved"`` (host/port/name changed), ``"updated"`` (TXT) or
    ``"removed"``; ``probe`` the new (or, for removed, the last) info."""

    kind: str
    probe: ProbeInfo


def _ipv4(text: str) -> str:
    import ipaddress

    from lightprobe.core.errors import InputError

    try:
        return str(ipaddress.IPv4Address(text.strip()))
    except ValueError:
        raise InputError(f"interface must be an IPv4 address, got {text[:60]!r}",
                         param="--interface") from None


def parse_address(text: str) -> tuple[str, int]:
    """``host:port`` (or ``http://host:port[/...]``, ``[v6]:port``) -> (host, port)."""
    from lightprobe.core.errors import InputError

    s = text.strip()
    if "://" in s:
        s = s.split("://", 1)[1]
    s = s.split("/", 1)[0]
    if s.startswith("["):
        host, _, rest = s[1:].partition("]")
        port_s = rest.lstrip(":")
    else:
        host, _, port_s = s.rpartition(":")
    try:
        port = int(port_s)
    except ValueError:
        port = -1
    if not host or not 0 < port < 65536:
        raise InputError(f"address must be HOST:PORT, got {text[:60]!r}", param="--address")
    return host, port


class Discovery:
    """Live set of probes (``probes``), updated by mDNS and by polling manual addresses.

    ``on_event`` (sync callable) is called with every :class:`ProbeEvent`; ``wait_for`` waits
    for a condition on the set. Use as ``async with Discovery(...) as d:``.
    """

    def __init__(self, *, interfaces: Sequence[str] | None = None, manual: Sequence[str] = (),
                 manual_poll_s: float = 5.0, resolve_timeout_s: float = 3.0,
                 on_event: Callable[[ProbeEvent], None] | None = None,
                 token: str | None = None, liveness_s: float | None = 10.0,
                 liveness_failures: int = 2, brokers: Sequence[str] = (), mdns: bool = True,
                 mqtt_prefix: str | None = None) -> None:
        from lightprobe.core.mqtt_topics import DEFAULT_PREFIX, check_prefix, parse_broker_url

        for b in brokers:
            parse_broker_url(b, "brokers")
        self.brokers = list(brokers)
        self.mdns = bool(mdns)
        self.mqtt_prefix = check_prefix(mqtt_prefix or DEFAULT_PREFIX, "mqtt_prefix")
        self.feeds: dict[str, Any] = {}  # broker URL -> lightprobe.hostlink.mqtt.BrokerFeed (after start)
        self.interfaces = [_ipv4(a) for a in interfaces] if interfaces else None
        self.manual = [parse_address(a) for a in manual]
        self.manual_poll_s = float(manual_poll_s)
        self.resolve_timeout_s = float(resolve_timeout_s)
        self.on_event = on_event
        self.token = token
        self.liveness_s, self.liveness_failures = liveness_s, max(1, int(liveness_failures))
        self.probes: dict[str, ProbeInfo] = {}
        self._lost: dict[str, ProbeInfo] = {}  # forgotten by the liveness check, still in mDNS
        self._failures: dict[str, int] = {}
        self._liveness: asyncio.Task[None] | None = None
        self._azc: AsyncZeroconf | None = None
        self._browser: AsyncServiceBrowser | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._gone: set[str] = set()  # service names removed since their last Added/Updated
        self._change: asyncio.Future[None] | None = None  # resolved (and replaced) on each change
        self._started = False
        self._poller: asyncio.Task[None] | None = None

    # ---- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        """Open the mDNS sockets and start browsing (and polling manual addresses)."""
        from zeroconf import InterfaceChoice, IPVersion
        from zeroconf.asyncio import AsyncServiceBrowser, AsyncZeroconf

        self._started = True
        if self.mdns:
            ifaces: Any = self.interfaces if self.interfaces else InterfaceChoice.All
            self._azc = AsyncZeroconf(interfaces=ifaces, ip_version=IPVersion.V4Only)
            self._browser = AsyncServiceBrowser(self._azc.zeroconf, [SERVICE_TYPE],
                                                handlers=[self._on_state_change])
        if self.brokers:
            from lightprobe.hostlink.mqtt import BrokerFeed

            for url in self.brokers:
                feed = self.feeds[url] = BrokerFeed(
                    url, prefix=self.mqtt_prefix,
                    on_status=lambda pid, st, url=url: self._on_broker_status(url, pid, st))  # type: ignore[misc]
                await feed.start()
        if self.manual:
            self._poller = asyncio.create_task(self._poll_manual(), name="hostlink-manual-poll")
        if self.liveness_s:
            self._liveness = asyncio.create_task(self._check_liveness(), name="hostlink-liveness")

    async def close(self) -> None:
        """Cancel the browser, the pending resolves and the poller, then close zeroconf."""
        if self._browser is not None:
            await self._browser.async_cancel()
            self._browser = None
        pending = [t for t in (*self._tasks, self._poller, self._liveness) if t is not None]
        for t in pending:
            t.cancel()
        for t in pending:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self._tasks.clear()
        self._poller = self._liveness = None
        for feed in self.feeds.values():
            await feed.close()
        self.feeds.clear()
        if self._azc is not None:
            await self._azc.async_close()
            self._azc = None

    async def __aenter__(self) -> Discovery:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ---- waiting --------------------------------------------------------------------------------
    async def wait_for(self, predicate: Callable[[dict[str, ProbeInfo]], bool],
                       within: float) -> dict[str, ProbeInfo]:
        """Wait until ``predicate(probes)`` holds; raises ``TimeoutError`` after ``within`` s.

        Waits on a plain future that every change resolves (no lock to re-acquire: Python
        3.11's ``wait_for`` around a ``Condition`` wait can swallow a cancellation and hang the
        canceller when changes arrive in a burst, seen here with 50 MQTT probes leaving at once)."""
        assert self._started, "start() first"
        async with asyncio.timeout(within):
            while not predicate(self.probes):
                await self._next_change()
        return dict(self.probes)

    def _next_change(self) -> asyncio.Future[None]:
        if self._change is None or self._change.done():
            self._change = asyncio.get_running_loop().create_future()
        return asyncio.shield(self._change)

    async def _emit(self, kind: str, probe: ProbeInfo) -> None:
        log.info("probe %s %s at %s (%s)", probe.id, kind, probe.url, probe.source)
        if self.on_event is not None:
            try:
                self.on_event(ProbeEvent(kind, probe))
            except Exception:
                log.exception("discovery: on_event handler failed")
        if self._change is not None and not self._change.done():
            self._change.set_result(None)

    async def _put(self, info: ProbeInfo) -> None:
        self._lost.pop(info.id, None)
        self._failures.pop(info.id, None)
        old = self.probes.get(info.id)
        self.probes[info.id] = info
        if old is None:
            await self._emit("added", info)
        elif (old.host, old.port, old.service_name) != (info.host, info.port, info.service_name):
            await self._emit("moved", info)
        elif old != info:
            await self._emit("updated", info)

    # ---- mDNS -----------------------------------------------------------------------------------
    def _on_state_change(self, zeroconf: Zeroconf, service_type: str, name: str,
                         state_change: ServiceStateChange) -> None:
        """Browser handler (sync, on the loop): only schedule work."""
        from zeroconf import ServiceStateChange

        if state_change is ServiceStateChange.Removed:
            self._gone.add(name)  # a resolve still in flight must not bring it back
            coro: Any = self._removed(name)
        else:
            self._gone.discard(name)
            coro = self._resolve(service_type, name)
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _resolve(self, service_type: str, name: str) -> None:
        from zeroconf.asyncio import AsyncServiceInfo

        assert self._azc is not None
        info = AsyncServiceInfo(service_type, name)
        if not await info.async_request(self._azc.zeroconf, int(self.resolve_timeout_s * 1000)):
            log.info("discovery: cannot resolve %s", name)
            return
        props = parse_txt(info.properties)
        if name in self._gone:
            return
        pid = props.get("id", "")
        addrs = info.parsed_addresses()
        if not pid or not addrs or info.port is None:
            log.info("discovery: %s has no id, address or port: ignored", name)
            return
        await self._put(ProbeInfo(
            id=pid, name=props.get("name") or name.removesuffix("." + service_type),
            host=addrs[0], port=int(info.port), path=props.get("path") or DEFAULT_PATH,
            version=props.get("version", ""), model=props.get("model", ""),
            sampler=props.get("sampler", ""), source="mdns", service_name=name,
            seen=time.monotonic()))

    async def _removed(self, name: str) -> None:
        for pid, p in list(self._lost.items()):
            if p.service_name == name:
                del self._lost[pid]
        for pid, p in list(self.probes.items()):
            if p.source == "mdns" and p.service_name == name:
                del self.probes[pid]
                await self._emit("removed", p)

    # ---- MQTT brokers ---------------------------------------------------------------------------
    def _on_broker_status(self, broker: str, pid: str, status: dict[str, Any] | None) -> None:
        """Feed handler (sync, on the loop): only schedule work."""
        task = asyncio.get_running_loop().create_task(self._broker_status(broker, pid, status))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _broker_status(self, broker: str, pid: str, status: dict[str, Any] | None) -> None:
        old = self.probes.get(pid)
        if status is None or status.get("state") != "online":
            if old is not None and old.source == "mqtt" and old.service_name == broker:
                del self.probes[pid]
                await self._emit("removed", old)
            return
        host, port = "", 0
        with contextlib.suppress(Exception):
            host, port = parse_address(str(status.get("url", "")))
        if old is not None and old.source != "mqtt":
            return  # the same probe is also on mDNS / manual: that entry wins (direct HTTP)
        await self._put(ProbeInfo(
            id=pid, name=str(status.get("name") or pid), host=host, port=port,
            version=str(status.get("sw_version", "")), model=str(status.get("model", "")),
            sampler=str(status.get("sampler", "")), source="mqtt", service_name=broker,
            seen=time.monotonic()))

    # ---- manual addresses -----------------------------------------------------------------------
    async def _poll_manual(self) -> None:
        from lightprobe.hostlink.client import ProbeClient, ProbeError

        while True:
            for host, port in self.manual:
                url = f"http://{host}:{port}"
                try:
                    async with ProbeClient(url, token=self.token, timeout=2.0) as c:
                        st = await c.status()
                    pr = st["probe"]
                    await self._put(ProbeInfo(
                        id=str(pr["id"]), name=str(pr.get("name", "")), host=host, port=port,
                        version=str(pr.get("version", "")), model=str(pr.get("model", "")),
                        sampler=str(st.get("sampler", "")), source="manual",
                        service_name=url, seen=time.monotonic()))
                except (ProbeError, KeyError, TypeError) as e:
                    log.debug("discovery: manual %s: %s", url, e)
                    for pid, p in list(self.probes.items()):
                        if p.source == "manual" and p.service_name == url:
                            del self.probes[pid]
                            await self._emit("removed", p)
            await asyncio.sleep(self.manual_poll_s)

    # ---- liveness (probes that vanished without a goodbye) --------------------------------------
    async def _check_liveness(self) -> None:
        import aiohttp

        assert self.liveness_s is not None
        timeout = aiohttp.ClientTimeout(total=min(2.0, self.liveness_s))
        async with aiohttp.ClientSession(timeout=timeout) as session:
            while True:
                await asyncio.sleep(self.liveness_s)
                checks = [p for p in self.probes.values() if p.source == "mdns"]
                checks += list(self._lost.values())
                alive = await asyncio.gather(*(_answers(session, p) for p in checks))
                for p, ok in zip(checks, alive, strict=True):
                    await self._liveness_result(p, ok)

    async def _liveness_result(self, p: ProbeInfo, ok: bool) -> None:
        if ok:
            self._failures.pop(p.id, None)
            if p.id in self._lost and p.id not in self.probes:
                await self._put(replace(self._lost[p.id], seen=time.monotonic()))
            return
        if self.probes.get(p.id) is not p:
            return
        n = self._failures[p.id] = self._failures.get(p.id, 0) + 1
        if n >= self.liveness_failures:
            del self.probes[p.id]
            self._lost[p.id] = p
            await self._emit("removed", p)

    def snapshot(self) -> list[ProbeInfo]:
        """The probes known now, sorted by name then id."""
        return sorted(self.probes.values(), key=lambda p: (p.name, p.id))



async def _answers(session: Any, p: ProbeInfo) -> bool:
    """True when the probe's HTTP server answers ``/healthz`` at all (any status)."""
    import aiohttp

    try:
        async with session.get(p.api + "/healthz") as r:
            await r.read()
            return True
    except (aiohttp.ClientError, TimeoutError, OSError):
        return False
