"""MQTT publication (``[mqtt] url`` or ``lightprobe serve --mqtt URL``; off by default).

A building's probes reach hosts through a broker when one LAN and mDNS no longer do: each probe
keeps one connection to the broker (aiomqtt over paho) and publishes what hosts read over HTTP
(topics and payloads: :mod:`lightprobe.core.mqtt_topics`), each topic rate-limited (newest wins: a
frame that arrives inside a topic's interval is replaced by the next, nothing queues):

* ``status`` (retained, QoS 1) on connect, on a health change and every ``status_interval``;
  the connection's last will is the ``offline`` status, so a probe that dies (SIGKILL, power,
  network) is ``offline`` for everyone within 1.5 x ``keepalive`` (MQTT 3.1.1 §3.1.2.10);
* ``lights`` (retained) at most ``lights_rate`` per second: the very bytes of ``GET /lights``;
* ``sh`` at most ``sh_rate`` per second, computed only when published (0 = off);
* ``sensors`` at ``sensors_rate``: illuminance on a horizontal surface at the probe (lux once
  the probe is photometrically calibrated, else the map's relative unit), the correlated colour
  temperature of that light (McCamy 1992 from CIE xy, linear Rec. 709 primaries), the primary
  light's elevation and azimuth (CONVENTIONS.md angles, degrees) and the probe's health;
* Home Assistant MQTT discovery configs (retained) for those five sensors, one device per probe,
  so a smart home sees the probe with no code (republished when the unit changes).

A broker that is down or refuses costs nothing but retries (backoff ``0.5 .. 8 s``); the API
and the pipeline never wait on MQTT. A clean shutdown publishes ``offline`` itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from lightprobe.core.mqtt_topics import (
    offline_payload,
    topic,
)
from lightprobe.device.sensors import horizontal_illuminance, sensor_body
from lightprobe.device.service.home_assistant import ha_discovery
from lightprobe.device.service.mqtt_settings import MqttSettings

__all__ = ["MqttPublisher",]

log = logging.getLogger(__name__)


class Source(Protocol):
    """What a publisher reads: the service (:class:`ServiceSource`) or a simulated fleet."""

    probe_id: str
    hub: Any  # lightprobe.device.service.runner.FrameHub

    def status(self) -> dict[str, Any]: ...
    def unit(self) -> str: ...
    async def sh(self) -> bytes | None: ...
    async def sensors(self) -> dict[str, Any] | None: ...


def _dump(body: Any) -> bytes:
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()


# ---- the service as a source ----------------------------------------------------------------------
class ServiceSource:
    """The running service: its hub, status, SH (on demand) and sensor values."""

    def __init__(self, st: Any, url: str) -> None:
        self.st, self.url = st, url
        self.probe_id = st.probe_id
        self.hub = st.runner.hub

    def unit(self) -> str:
        r = self.st.runner.result
        return str(getattr(r, "unit", None) or "relative")

    def status(self) -> dict[str, Any]:
        st, cfg = self.st, self.st.config
        s = st.runner.status()
        return {"version": 1, "probe": self.probe_id, "state": "online", "name": cfg.get("probe", "name"),
                "model": st.model(), "sw_version": st.version,
                "sampler": cfg.get("pipeline", "sampler"), "health": s["health"], "url": self.url,
                "frames": s["frames"], "fps": s["fps"], "stale": s["stale"], "timestamp": time.time()}

    async def sh(self) -> bytes | None:
        from lightprobe.device.service.payloads import sh_payload

        return await sh_payload(self.st, "canonical")

    async def sensors(self) -> dict[str, Any] | None:
        r, lights = self.st.runner.result, self.st.runner.lights
        equirect = getattr(r, "equirect", None)
        if r is None or lights is None or equirect is None:
            return None
        rgb = await asyncio.to_thread(horizontal_illuminance, equirect)
        env = await self.st.runner.environment()
        prim = env.primary.direction if env is not None and env.primary is not None else None
        return sensor_body(rgb, self.unit(), prim, self.st.runner.status()["health"],
                           int(lights.frame), float(lights.timestamp), lights.captured)


# ---- the publisher --------------------------------------------------------------------------------
@dataclass
class _Counters:
    published: dict[str, int] = field(default_factory=dict)
    connects: int = 0
    last_error: str | None = None


class MqttPublisher:
    """Publish ``source`` to the broker in ``settings`` until :meth:`stop`; reconnects forever."""

    def __init__(self, source: Source, settings: MqttSettings, *,
                 backoff: tuple[float, float] = (0.5, 8.0)) -> None:
        self.source, self.settings, self.backoff = source, settings, backoff
        self.connected = False
        self.counters = _Counters()
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._client: Any = None

    def start(self) -> None:
        self._task = asyncio.create_task(self.run(), name=f"mqtt-{self.source.probe_id}")

    async def stop(self, within: float = 2.0) -> None:
        """Publish ``offline`` (retained) and disconnect; cancel if that takes ``within`` s."""
        self._stop.set()
        if self._task is None:
            return
        try:
            await asyncio.wait_for(asyncio.shield(self._task), within)
        except (TimeoutError, asyncio.CancelledError, Exception):
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task

    def stats(self) -> dict[str, Any]:
        return {"broker": self.settings.broker.url, "connected": self.connected,
                "connects": self.counters.connects, "published": dict(self.counters.published),
                "last_error": self.counters.last_error}

    def _t(self, name: str) -> str:
        return topic(self.settings.prefix, self.source.probe_id, name)

    async def _publish(self, name: str, payload: bytes, *, qos: int = 0, retain: bool = True,
                       raw_topic: str | None = None) -> None:
        await self._client.publish(raw_topic or self._t(name), payload, qos=qos, retain=retain)
        self.counters.published[name] = self.counters.published.get(name, 0) + 1

    async def run(self) -> None:
        import aiomqtt

        s = self.settings
        delay = self.backoff[0]
        will = aiomqtt.Will(self._t("status"), offline_payload(self.source.probe_id), qos=1, retain=True)
        tls = aiomqtt.TLSParameters(ca_certs=s.ca_file) if s.broker.tls else None
        while not self._stop.is_set():
            try:
                async with aiomqtt.Client(s.broker.host, s.broker.port, username=s.broker.username,
                                          password=s.password, identifier=f"lightprobe-{self.source.probe_id}",
                                          keepalive=s.keepalive, will=will, tls_params=tls,
                                          max_queued_outgoing_messages=256) as client:
                    self._client = client
                    self.connected = True
                    self.counters.connects += 1
                    delay = self.backoff[0]
                    log.info("mqtt: connected to %s", s.broker.url)
                    await self._session()
                    # stopping: say goodbye ourselves (the will is only for a lost connection)
                    await self._publish("status", offline_payload(self.source.probe_id), qos=1)
                    return
            except aiomqtt.MqttError as e:
                self.counters.last_error = str(e)
                if self.connected:
                    log.warning("mqtt: connection to %s lost: %s", s.broker.url, e)
                else:
                    log.info("mqtt: cannot connect to %s: %s (retrying in %.1f s)", s.broker.url, e, delay)
            finally:
                self.connected = False
                self._client = None
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), delay)
            delay = min(delay * 2, self.backoff[1])

    async def _session(self) -> None:
        """One connection's life: status + discovery, then the topic loops until stop."""
        src, s = self.source, self.settings
        status = src.status()
        await self._publish("status", _dump(status), qos=1)
        unit = src.unit()
        if s.discovery:
            await self._send_discovery(status, unit)
        loops = [asyncio.create_task(self._lights_loop()), asyncio.create_task(self._periodic(status, unit))]
        stop = asyncio.create_task(self._stop.wait())
        try:
            done, _ = await asyncio.wait([*loops, stop], return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not stop:
                    t.result()  # a loop failed (MqttError): reconnect
        finally:
            for t in (*loops, stop):
                t.cancel()
            for t in (*loops, stop):
                with contextlib.suppress(asyncio.CancelledError):
                    await t

    async def _send_discovery(self, status: dict[str, Any], unit: str) -> None:
        for t, body in ha_discovery(self.source.probe_id, status, unit, self.settings):
            await self._publish("discovery", _dump(body), qos=1, raw_topic=t)

    async def _lights_loop(self) -> None:
        hub = self.source.hub
        interval = 1.0 / self.settings.lights_rate
        seen = 0
        while True:
            await hub.wait_newer(seen)
            if hub.closed:
                return
            seen, payload = hub.version, hub.payload
            if payload is not None:
                await self._publish("lights", payload)
            await asyncio.sleep(interval)  # newest wins: later frames wait, then the newest goes

    async def _periodic(self, status: dict[str, Any], unit: str) -> None:
        """sensors, SH and status on their own clocks (one task: they are slow topics)."""
        s, src = self.settings, self.source
        now = time.monotonic()
        due: dict[str, float] = {"sensors": now, "status": now + s.status_interval}
        if s.sh_rate > 0:
            due["sh"] = now
        last_sh_version = -1
        health = status.get("health")
        jobs: dict[str, tuple[float, Callable[[], Awaitable[None]]]] = {}

        async def sensors() -> None:
            nonlocal unit, health
            body = await src.sensors()
            if body is not None:
                await self._publish("sensors", _dump(body))
            st = src.status()
            new_unit = src.unit()
            if s.discovery and new_unit != unit:
                unit = new_unit
                await self._send_discovery(st, unit)
            if st.get("health") != health:
                health = st.get("health")
                await self._publish("status", _dump(st), qos=1)

        async def sh() -> None:
            nonlocal last_sh_version
            if src.hub.version == last_sh_version:
                return
            body = await src.sh()
            if body is not None:
                last_sh_version = src.hub.version
                await self._publish("sh", body)

        async def status_() -> None:
            await self._publish("status", _dump(src.status()), qos=1)

        jobs["sensors"] = (1.0 / s.sensors_rate, sensors)
        jobs["status"] = (s.status_interval, status_)
        if "sh" in due:
            jobs["sh"] = (1.0 / s.sh_rate, sh)
        while True:
            name = min(due, key=due.__getitem__)
            await asyncio.sleep(max(0.0, due[name] - time.monotonic()))
            period, fn = jobs[name]
            await fn()
            due[name] = max(due[name] + period, time.monotonic())
