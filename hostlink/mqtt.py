"""Probes through an MQTT broker: one connection per broker for any number of probes.

A :class:`BrokerFeed` subscribes to ``<prefix>/+/status`` (retained: a host that connects late
learns every probe at once, and a dead probe's last will says ``offline``) and, once somebody
follows a probe's lights, to ``<prefix>/+/lights``. :class:`lightprobe.hostlink.discovery.Discovery` takes
its probes from feeds (``brokers=["mqtt://host"]``) and :class:`lightprobe.hostlink.stream.MergedStream`
follows them through the same feed, so a host merges a building's probes across subnets with
the same :class:`~lightprobe.hostlink.discovery.ProbeEvent` s and light sets as from mDNS + WebSocket.
Topics and payloads: :mod:`lightprobe.core.mqtt_topics`.

Lights over MQTT carry no Q2-Tree (an HTTP resource): ``MergedStream(method="auto")`` merges
MQTT-followed probes by index interpolation.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable
from typing import Any

from lightprobe.core.errors import InputError
from lightprobe.core.lightset import LightSet
from lightprobe.core.mqtt_topics import (
    DEFAULT_PREFIX,
    PASSWORD_ENV,
    parse_broker_url,
    parse_status,
    probe_of_topic,
)

__all__ = ["BrokerFeed"]

log = logging.getLogger(__name__)



class BrokerFeed:
    """Status of every probe on one broker, and the light sets of the probes followed.

    ``on_status(probe_id, status_or_None)`` is called (on the loop) for every status message
    (``None`` when a retained status is cleared); :meth:`follow` registers a callback for one
    probe's light sets. Reconnects with backoff; subscriptions are renewed on reconnect."""

    def __init__(self, url: str, *, prefix: str = DEFAULT_PREFIX, password: str | None = None,
                 on_status: Callable[[str, dict[str, Any] | None], None] | None = None,
                 backoff: tuple[float, float] = (0.25, 4.0), keepalive: int = 30,
                 ca_file: str | None = None) -> None:
        self.address = parse_broker_url(url, "broker")
        self.url = url
        self.prefix = prefix
        self.password = password if password is not None else os.environ.get(PASSWORD_ENV) or None
        self.on_status = on_status
        self.backoff, self.keepalive, self.ca_file = backoff, int(keepalive), ca_file
        self.connected = asyncio.Event()
        self.messages = 0
        self.bad_messages = 0
        self._lights: dict[str, Callable[[LightSet], None]] = {}
        self._client: Any = None
        self._subscribed_lights = False
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name=f"hostlink-mqtt-{self.address.host}")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None

    async def __aenter__(self) -> BrokerFeed:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ---- following lights -----------------------------------------------------------------------
    def follow(self, probe_id: str, callback: Callable[[LightSet], None]) -> None:
        self._lights[probe_id] = callback
        if self._client is not None and not self._subscribed_lights:
            asyncio.get_running_loop().create_task(self._subscribe_lights())

    def unfollow(self, probe_id: str, callback: Callable[[LightSet], None] | None = None) -> None:
        if callback is None or self._lights.get(probe_id) is callback:
            self._lights.pop(probe_id, None)

    async def _subscribe_lights(self) -> None:
        if self._client is None or self._subscribed_lights:
            return
        self._subscribed_lights = True
        with contextlib.suppress(Exception):
            await self._client.subscribe(f"{self.prefix}/+/lights", qos=0)

    # ---- the connection -------------------------------------------------------------------------
    async def _run(self) -> None:
        import aiomqtt

        a = self.address
        delay = self.backoff[0]
        tls = aiomqtt.TLSParameters(ca_certs=self.ca_file) if a.tls else None
        while True:
            try:
                async with aiomqtt.Client(a.host, a.port, username=a.username, password=self.password,
                                          keepalive=self.keepalive, tls_params=tls) as client:
                    self._client, self._subscribed_lights = client, False
                    await client.subscribe(f"{self.prefix}/+/status", qos=1)
                    if self._lights:
                        await self._subscribe_lights()
                    self.connected.set()
                    delay = self.backoff[0]
                    async for m in client.messages:
                        self._dispatch(str(m.topic), m.payload)
            except aiomqtt.MqttError as e:
                log.info("mqtt %s: %s (retrying in %.1f s)", a.url, e, delay)
            finally:
                self._client = None
                self.connected.clear()
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.backoff[1])

    def _dispatch(self, t: str, payload: Any) -> None:
        got = probe_of_topic(self.prefix, t)
        if got is None:
            return
        pid, name = got
        data = payload if isinstance(payload, bytes | bytearray) else str(payload or "").encode()
        self.messages += 1
        if name == "status":
            status = parse_status(bytes(data)) if data else None
            if data and status is None:
                self.bad_messages += 1
                return
            if self.on_status is not None:
                self.on_status(pid, status)
        elif name == "lights":
            cb = self._lights.get(pid)
            if cb is None or not data:
                return
            try:
                ls = LightSet.from_json(json.loads(data))
            except (ValueError, InputError, TypeError, KeyError) as e:
                self.bad_messages += 1
                log.info("mqtt %s: bad light set from %s: %s", self.address.url, pid, e)
                return
            cb(ls)
