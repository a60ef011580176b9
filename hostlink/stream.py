"""A live merged light stream over several probes (Nikodym et al. 2013, §4).

:class:`MergedStream` follows every probe given (URLs) or found by a :class:`Discovery`: one task
per probe subscribes to its WebSocket stream and, for Q2-Tree probes, fetches the probe's tree
(``GET /q2tree``) for each new frame. :meth:`MergedStream.updates` yields the merge of the
newest data (newest wins: a slow consumer skips states, nothing queues). A probe whose stream
dropped (its last set is ``stale``), whose tree cannot be fetched, or that sent nothing for
``stale_after`` seconds drops out of the merge, which continues from the rest and lists it in
``extra["dropped"]``; a probe that discovery forgets (goodbye, TTL) is removed altogether.

Probes found on an MQTT broker (``source="mqtt://host"``, or a :class:`Discovery` with
``brokers``) are followed through the broker instead: one connection per broker for all of them
(:class:`lightprobe.hostlink.mqtt.BrokerFeed`), the same light sets, no HTTP to the probe; their status
turning ``offline`` (the probe's last will) removes them.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Collection, Sequence
from typing import Any

import aiohttp
import numpy as np

from lightprobe.core.lightset import LightSet
from lightprobe.hostlink.client import ProbeClient, ProbeError
from lightprobe.hostlink.discovery import Discovery, ProbeInfo
from lightprobe.hostlink.merge import MergeError, ProbeInput, merge_probes

__all__ = ["MergedStream"]

log = logging.getLogger(__name__)


@dataclasses.dataclass
class _Follow:
    url: str
    task: asyncio.Task[None]
    data: ProbeInput
    received: float = 0.0
    started: float = dataclasses.field(default_factory=time.monotonic)


class MergedStream:
    """Merge the live lights of several probes for ``target`` (3,) in room coordinates.

    ``source`` is a started :class:`Discovery` (probes come and go with it) or a list of probe
    URLs. ``method`` is ``"auto"`` (Q2-Tree merging for probes that publish ``q2tree`` lights,
    index interpolation otherwise), ``"q2tree"`` or ``"index"``; ``count`` the merged light
    count (and the tree size fetched from each probe). ``ids`` restricts a discovery source to
    those probe ids (default: every probe discovered). ``q2`` passes options to
    :func:`lightprobe.hostlink.merge.merge_q2trees`.
    """

    def __init__(self, source: Discovery | Sequence[str] | str, *, count: int = 256,
                 method: str = "auto", target: Sequence[float] | None = None,
                 token: str | None = None, stale_after: float = 3.0,
                 backoff: tuple[float, float] = (0.25, 4.0), ids: Collection[str] | None = None,
                 **q2: Any) -> None:
        if method not in ("auto", "q2tree", "index"):
            raise MergeError(f"method must be 'auto', 'q2tree' or 'index', got {method!r}")
        self._own: Discovery | None = None
        if isinstance(source, str):
            if not source.startswith(("mqtt://", "mqtts://")):
                raise MergeError(f"a single source must be a broker URL (mqtt://host), got {source[:60]!r}; "
                                 "pass probe URLs as a list")
            source = self._own = Discovery(mdns=False, brokers=[source], liveness_s=None)
        self.source = source
        self.count, self.method = int(count), method
        self.target = None if target is None else np.asarray(target, np.float64).reshape(3)
        self.token, self.stale_after, self.backoff = token, float(stale_after), backoff
        self.q2 = q2
        self.ids = None if ids is None else frozenset(ids)
        self._follows: dict[str, _Follow] = {}
        self._session: aiohttp.ClientSession | None = None
        self._change: asyncio.Future[None] | None = None  # resolved (and replaced) on each change
        self._started = False
        self._version = 0
        self._watch: asyncio.Task[None] | None = None

    # ---- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        self._session = aiohttp.ClientSession()
        self._started = True
        if self._own is not None:
            await self._own.start()
        if isinstance(self.source, Discovery):
            self._watch = asyncio.create_task(self._watch_discovery(self.source),
                                              name="hostlink-merge-watch")
        else:
            for url in self.source:
                self._follow(url, url)

    async def close(self) -> None:
        tasks = [f.task for f in self._follows.values()]
        if self._watch is not None:
            tasks.append(self._watch)
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self._follows.clear()
        if self._session is not None:
            await self._session.close()
            self._session = None
        if self._own is not None:
            await self._own.close()

    async def __aenter__(self) -> MergedStream:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def probes(self) -> list[str]:
        """Ids (or URLs, before the first message) of the probes followed now."""
        return sorted(self._follows)

    # ---- following probes -----------------------------------------------------------------------
    async def _watch_discovery(self, disc: Discovery) -> None:
        """Mirror the discovery set: follow new or moved probes, forget removed ones."""
        seen: dict[str, ProbeInfo] = {}
        while True:
            now = {k: v for k, v in disc.probes.items() if self.ids is None or k in self.ids}
            for pid, info in now.items():
                old = seen.get(pid)
                if old is None or (old.host, old.port, old.source, old.service_name) != (
                        info.host, info.port, info.source, info.service_name):
                    self._unfollow(pid)
                    feed = disc.feeds.get(info.service_name) if info.source == "mqtt" else None
                    if feed is not None:
                        self._follow_feed(pid, feed)
                    else:
                        self._follow(pid, info.url)
            for pid in set(seen) - set(now):
                self._unfollow(pid)
                await self._notify()
            seen = now

            def changed(p: dict[str, ProbeInfo], before: dict[str, ProbeInfo] = seen) -> bool:
                return p != before

            with contextlib.suppress(TimeoutError):
                await disc.wait_for(changed, within=1.0)

    def _follow(self, key: str, url: str) -> None:
        data = ProbeInput(key)
        task = asyncio.create_task(self._run(key, url), name=f"hostlink-follow-{key}")
        self._follows[key] = _Follow(url, task, data)

    def _follow_feed(self, key: str, feed: Any) -> None:
        data = ProbeInput(key)
        task = asyncio.create_task(self._consume_feed(key, feed), name=f"hostlink-follow-mqtt-{key}")
        self._follows[key] = _Follow(feed.url, task, data)

    async def _consume_feed(self, key: str, feed: Any) -> None:
        """A probe's light sets from the broker (newest wins: a slot of one, no queue)."""
        slot: list[LightSet] = []
        ready = asyncio.Event()

        def got(ls: LightSet) -> None:
            slot[:] = [ls]
            ready.set()

        feed.follow(key, got)
        try:
            while True:
                await ready.wait()
                ready.clear()
                if not await self._store(key, slot.pop(), None):
                    return
        finally:
            feed.unfollow(key, got)

    def latest(self) -> dict[str, LightSet]:
        """The newest light set of each followed probe (what the next merge uses)."""
        return {k: f.data.lights for k, f in self._follows.items() if f.data.lights is not None}

    def _unfollow(self, key: str) -> None:
        f = self._follows.pop(key, None)
        if f is not None:
            f.task.cancel()

    async def _run(self, key: str, url: str) -> None:
        try:
            await self._consume(key, url)
        except ProbeError as e:  # e.g. a wrong token: retrying cannot help
            log.warning("%s: stopped following: %s", url, e)

    async def _consume(self, key: str, url: str) -> None:
        client = ProbeClient(url, token=self.token, session=self._session,
                             backoff_initial=self.backoff[0], backoff_max=self.backoff[1])
        async for ls in client.subscribe():
            tree = None
            wants_tree = self.method == "q2tree" or (self.method == "auto" and ls.method == "q2tree")
            if wants_tree and not ls.stale:
                try:
                    tree = await client.q2tree(self.count)
                except ProbeError as e:
                    log.info("%s: no tree this frame: %s", url, e)
                    ls = dataclasses.replace(ls, stale=True)
            if not await self._store(key, ls, tree):
                return

    async def _store(self, key: str, ls: LightSet, tree: Any) -> bool:
        """Keep a probe's newest data and wake the merge; False when this task no longer
        follows ``key`` (unfollowed or replaced), so it should end."""
        f = self._follows.get(key)
        if f is None or f.task is not asyncio.current_task():
            return False
        f.data = ProbeInput(ls.probe or key, ls, tree, ls.pose)
        f.received = time.monotonic()
        await self._notify()
        return True

    async def _notify(self) -> None:
        self._version += 1
        if self._change is not None and not self._change.done():
            self._change.set_result(None)

    def _next_change(self) -> asyncio.Future[None]:
        """A plain future, not a Condition (see :meth:`Discovery.wait_for`: the same Python
        3.11 hang when a wait with a timeout is cancelled during a burst of changes)."""
        if self._change is None or self._change.done():
            self._change = asyncio.get_running_loop().create_future()
        return asyncio.shield(self._change)

    # ---- merging --------------------------------------------------------------------------------
    def _inputs(self) -> list[ProbeInput]:
        now = time.monotonic()
        out = []
        for f in self._follows.values():
            d = f.data
            if d.lights is None:
                if now - f.started > self.stale_after:
                    out.append(d)  # silent for too long: listed as dropped
                continue  # just started: not part of the merge yet
            if now - f.received > self.stale_after and not d.lights.stale:
                d = dataclasses.replace(d, lights=dataclasses.replace(d.lights, stale=True))
            out.append(d)
        return out

    def merge_now(self) -> LightSet:
        """The merge of the newest data (raises :class:`MergeError` if no probe is usable)."""
        return merge_probes(self._inputs(), self.count, method=self.method, target=self.target,
                            **self.q2)

    async def updates(self, idle: float | None = None) -> AsyncIterator[LightSet]:
        """Merged light sets, one per change of the inputs (newest wins). With ``idle``, that
        many seconds without any change ends the iteration with ``TimeoutError``."""
        assert self._started, "start() first"
        seen = 0
        while True:
            async with asyncio.timeout(idle):
                while self._version <= seen:
                    await self._next_change()
            seen = self._version
            try:
                merged = await asyncio.to_thread(self.merge_now)
            except MergeError as e:
                log.info("merge: %s", e)
                continue
            yield merged
