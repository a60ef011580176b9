"""A live merged light stream over several probes (Nikodym et al. 2013, §4).

:class:`MergedStream` follows every probe given (URLs) or found by a :class:`Discovery`: one task
per probe subscribes to its WebSocket stream and, for Q2-Tree probes, fetches the probe's tree
(``GET /q2tree``) for each new frame. :meth:`MergedStream.updates` yields the merge of the
newest data (newest wins: a slow consumer skips states, nothing queues). A probe whose stream
dropped (its last set is ``stale``), whose tree cannot be fetched, or that sent nothing for
``stale_after`` seconds drops out of the merge, which continues from the rest and lists it in
``extra["dropped"]``; a probe that discovery forgets (goodbye, TTL) is removed altogether.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Callable, Collection, Sequence
from typing import Any

import aiohttp
import numpy as np

from device.core.lightset import LightSet
from hostlink.client import ProbeClient, ProbeError
from hostlink.discovery import Discovery, ProbeInfo
from hostlink.merge import MergeError, ProbeInput, merge_probes

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
    :func:`hostlink.merge.merge_q2trees`.
    """

    def __init__(self, source: Discovery | Sequence[str], *, count: int = 256,
                 method: str = "auto", target: Sequence[float] | None = None,
                 token: str | None = None, stale_after: float = 3.0,
                 backoff: tuple[float, float] = (0.25, 4.0), ids: Collection[str] | None = None,
                 **q2: Any) -> None:
        if method not in ("auto", "q2tree", "index"):
            raise MergeError(f"method must be 'auto', 'q2tree' or 'index', got {method!r}")
        self.source = source
        self.count, self.method = int(count), method
        self.target = None if target is None else np.asarray(target, np.float64).reshape(3)
        self.token, self.stale_after, self.backoff = token, float(stale_after), backoff
        self.q2 = q2
        self.ids = None if ids is None else frozenset(ids)
        self._follows: dict[str, _Follow] = {}
        self._session: aiohttp.ClientSession | None = None
        self._cond: asyncio.Condition | None = None
        self._version = 0
        self._watch: asyncio.Task[None] | None = None

    # ---- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        self._session = aiohttp.ClientSession()
        self._cond = asyncio.Condition()
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
                if seen.get(pid) is None or (seen[pid].host, seen[pid].port) != (info.host, info.port):
                    self._unfollow(pid)
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
            f = self._follows.get(key)
            if f is None or f.task is not asyncio.current_task():
                return
            f.data = ProbeInput(ls.probe or key, ls, tree, ls.pose)
            f.received = time.monotonic()
            await self._notify()

    async def _notify(self) -> None:
        assert self._cond is not None
        async with self._cond:
            self._version += 1
            self._cond.notify_all()

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

    def _newer(self, seen: int) -> Callable[[], bool]:
        return lambda: self._version > seen

    def merge_now(self) -> LightSet:
        """The merge of the newest data (raises :class:`MergeError` if no probe is usable)."""
        return merge_probes(self._inputs(), self.count, method=self.method, target=self.target,
                            **self.q2)

    async def updates(self, idle: float | None = None) -> AsyncIterator[LightSet]:
        """Merged light sets, one per change of the inputs (newest wins). With ``idle``, that
        many seconds without any change ends the iteration with ``TimeoutError``."""
        assert self._cond is not None, "start() first"
        seen = 0
        while True:
            async with self._cond:
                await asyncio.wait_for(self._cond.wait_for(self._newer(seen)), idle)
                seen = self._version
            try:
                merged = await asyncio.to_thread(self.merge_now)
            except MergeError as e:
                log.info("merge: %s", e)
                continue
            yield merged
