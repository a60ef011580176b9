"""MQTT publication (``[mqtt] url`` or ``lightprobe serve --mqtt URL``; off by default).

A building's probes reach hosts through a broker when one LAN and mDNS no longer do: each probe
keeps one connection to the broker (aiomqtt over paho) and publishes what hosts read over HTTP
(topics and payloads: :mod:`device.core.broker`), each topic rate-limited (newest wins: a
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
import math
import os
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from device.core.broker import (
    DEFAULT_PREFIX,
    PASSWORD_ENV,
    BrokerAddress,
    check_prefix,
    offline_payload,
    parse_broker_url,
    topic,
)
from device.core.errors import InputError

__all__ = ["MqttPublisher", "MqttSettings", "cct_mccamy", "ha_discovery", "horizontal_illuminance",
           "primary_angles"]

log = logging.getLogger(__name__)


# linear Rec. 709 / sRGB primaries, D65 white -> CIE XYZ
_RGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]])


def _planck_xy(t: float) -> tuple[float, float]:
    """CIE 1931 xy of the Planckian locus, Kim et al. 2002 cubic splines (1667 .. 25000 K)."""
    if t <= 4000:
        x = -0.2661239e9 / t ** 3 - 0.2343589e6 / t ** 2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t ** 3 + 2.1070379e6 / t ** 2 + 0.2226347e3 / t + 0.240390
    if t <= 2222:
        y = -1.1063814 * x ** 3 - 1.34811020 * x ** 2 + 2.18555832 * x - 0.20219683
    elif t <= 4000:
        y = -0.9549476 * x ** 3 - 1.37418593 * x ** 2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x ** 3 - 5.87338670 * x ** 2 + 3.75112997 * x - 0.37001483
    return x, y


def _uv(x: float, y: float) -> tuple[float, float]:
    d = -2 * x + 12 * y + 3
    return 4 * x / d, 6 * y / d


def cct_mccamy(rgb: np.ndarray | list[float]) -> float | None:
    """Correlated colour temperature (K) of linear Rec. 709 RGB by McCamy's cubic in CIE xy
    (C. S. McCamy, Color Res. Appl. 17(2), 1992; within a few K of the tabulated CCTs of D65, D50
    and A). ``None`` for black or non-finite input, outside 1667 .. 25000 K, or farther than
    Duv 0.05 from the Planckian locus (CIE 1960 uv; ANSI C78.377's limit for a CCT to mean
    anything: a saturated colour has no colour temperature)."""
    x_, y_, z_ = _RGB_TO_XYZ @ np.asarray(rgb, np.float64).reshape(3)
    s = x_ + y_ + z_
    if not np.isfinite(s) or s <= 0 or y_ <= 0:
        return None
    x, y = x_ / s, y_ / s
    if abs(0.1858 - y) < 1e-9:
        return None
    n = (x - 0.3320) / (0.1858 - y)
    t = 449.0 * n ** 3 + 3525.0 * n ** 2 + 6823.3 * n + 5520.33
    if not 1667.0 <= t <= 25000.0:
        return None
    u, v = _uv(x, y)
    up, vp = _uv(*_planck_xy(t))
    return float(t) if math.hypot(u - up, v - vp) <= 0.05 else None


def horizontal_illuminance(equirect: np.ndarray) -> np.ndarray:
    """(3,) RGB of ``int L cos(theta) dw`` over the upper hemisphere (the light on an upward
    surface at the probe; Y of it is illuminance in lux when the map is in nits). Exact row
    weights; a pixel with any non-finite channel counts as zero (as in the photometric
    calibration's ``upper_irradiance``, so Y is exactly what the lux meter was matched to)."""
    from calibration.photometric import upper_row_weights

    img = np.asarray(equirect)
    h, w = img.shape[:2]
    rows = upper_row_weights(h, w)
    top = int(np.count_nonzero(rows))
    band = img[:top].astype(np.float64)
    band = np.where(np.isfinite(band).all(axis=-1, keepdims=True), band, 0.0)
    return rows[:top] @ band.sum(axis=1)


def primary_angles(direction: np.ndarray | list[float] | None) -> tuple[float | None, float | None]:
    """(elevation above the horizon, azimuth) in degrees of a probe-frame direction, with
    CONVENTIONS.md's azimuth: d = (sin t sin p, cos t, -sin t cos p), p in [0, 360)."""
    if direction is None:
        return None, None
    d = np.asarray(direction, np.float64).reshape(3)
    d = d / max(float(np.linalg.norm(d)), 1e-300)
    elev = math.degrees(math.asin(float(np.clip(d[1], -1.0, 1.0))))
    az = math.degrees(math.atan2(float(d[0]), float(-d[2]))) % 360.0
    return round(elev, 3), round(az, 3)


# ---- settings -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MqttSettings:
    broker: BrokerAddress
    password: str | None = None
    keepalive: int = 10
    prefix: str = DEFAULT_PREFIX
    lights_rate: float = 10.0
    sh_rate: float = 1.0
    sensors_rate: float = 1.0
    status_interval: float = 30.0
    discovery: bool = True
    discovery_prefix: str = "homeassistant"
    ca_file: str | None = None

    @classmethod
    def from_config(cls, cfg: Any, url: str | None = None,
                    env: dict[str, str] | None = None) -> MqttSettings | None:
        """The ``[mqtt]`` table (``url`` overrides ``mqtt.url``); ``None`` when MQTT is off.
        The password comes from ``password_file`` or ``$LIGHTPROBE_MQTT_PASSWORD``."""
        env = dict(os.environ) if env is None else env
        text = url if url is not None else str(cfg.get("mqtt", "url"))
        if not text:
            return None
        broker = parse_broker_url(text, "--mqtt" if url is not None else "mqtt.url")
        user = str(cfg.get("mqtt", "username")) or None
        if user and broker.username and user != broker.username:
            raise InputError("mqtt.username and the user in the broker URL differ", param="mqtt.username")
        broker = BrokerAddress(broker.host, broker.port, broker.tls or bool(cfg.get("mqtt", "tls")),
                               broker.username or user)
        password = env.get(PASSWORD_ENV) or None
        pfile = str(cfg.get("mqtt", "password_file"))
        if pfile:
            try:
                password = Path(pfile).read_text(encoding="utf-8").strip()
            except (OSError, UnicodeDecodeError) as e:
                raise InputError(f"{pfile}: cannot read mqtt.password_file: {e}", param="mqtt.password_file") from e
        ca = str(cfg.get("mqtt", "ca_file")) or None
        if ca is not None and not Path(ca).is_file():
            raise InputError(f"{ca}: mqtt.ca_file does not exist", param="mqtt.ca_file")
        return cls(broker, password, int(cfg.get("mqtt", "keepalive")),
                   check_prefix(str(cfg.get("mqtt", "topic_prefix"))),
                   float(cfg.get("mqtt", "lights_rate")), float(cfg.get("mqtt", "sh_rate")),
                   float(cfg.get("mqtt", "sensors_rate")), float(cfg.get("mqtt", "status_interval")),
                   bool(cfg.get("mqtt", "discovery")),
                   check_prefix(str(cfg.get("mqtt", "discovery_prefix")), "mqtt.discovery_prefix"), ca)


class Source(Protocol):
    """What a publisher reads: the service (:class:`ServiceSource`) or a simulated fleet."""

    probe_id: str
    hub: Any  # device.service.runner.FrameHub

    def status(self) -> dict[str, Any]: ...
    def unit(self) -> str: ...
    async def sh(self) -> bytes | None: ...
    async def sensors(self) -> dict[str, Any] | None: ...


# ---- Home Assistant discovery ---------------------------------------------------------------------
def ha_discovery(probe_id: str, status: dict[str, Any], unit: str,
                 settings: MqttSettings) -> list[tuple[str, dict[str, Any]]]:
    """(topic, config) of the probe's Home Assistant MQTT discovery messages: illuminance,
    colour temperature, primary light elevation and azimuth, health. Keys are HA's documented
    MQTT sensor options (no abbreviations)."""
    node = f"lightprobe_{probe_id}"
    state = topic(settings.prefix, probe_id, "sensors")
    avail = topic(settings.prefix, probe_id, "status")
    device = {"identifiers": [node], "name": status.get("name") or f"lightprobe {probe_id}",
              "manufacturer": "lightprobe", "model": status.get("model") or "lightprobe",
              "sw_version": str(status.get("sw_version", ""))}
    if status.get("url"):
        device["configuration_url"] = str(status["url"])
    common = {"state_topic": state, "availability_topic": avail,
              "availability_template": "{{ value_json.state }}", "payload_available": "online",
              "payload_not_available": "offline", "device": device, "qos": 0,
              "origin": {"name": "lightprobe", "sw_version": str(status.get("sw_version", ""))}}
    lux = unit == "nit"
    sensors: list[tuple[str, dict[str, Any]]] = [
        ("illuminance", {"name": "Illuminance" if lux else "Relative illuminance",
                         "value_template": "{{ value_json.illuminance }}", "state_class": "measurement",
                         **({"device_class": "illuminance", "unit_of_measurement": "lx"} if lux
                            else {"icon": "mdi:brightness-5"}),
                         "suggested_display_precision": 1}),
        ("colour_temperature", {"name": "Colour temperature", "value_template": "{{ value_json.cct }}",
                                "unit_of_measurement": "K", "state_class": "measurement",
                                "icon": "mdi:thermometer-lines", "suggested_display_precision": 0}),
        ("light_elevation", {"name": "Primary light elevation", "value_template": "{{ value_json.elevation }}",
                             "unit_of_measurement": "°", "state_class": "measurement",
                             "icon": "mdi:angle-acute", "suggested_display_precision": 1}),
        ("light_azimuth", {"name": "Primary light azimuth", "value_template": "{{ value_json.azimuth }}",
                           "unit_of_measurement": "°", "state_class": "measurement",
                           "icon": "mdi:compass-outline", "suggested_display_precision": 1}),
        ("health", {"name": "Health", "value_template": "{{ value_json.health }}", "device_class": "enum",
                    "options": ["ok", "degraded", "starting"], "entity_category": "diagnostic"}),
    ]
    out = []
    for obj, cfg in sensors:
        body = {**cfg, **common, "unique_id": f"{node}_{obj}", "object_id": f"{node}_{obj}"}
        out.append((f"{settings.discovery_prefix}/sensor/{node}/{obj}/config", body))
    return out


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
                "model": cfg.get("probe", "model"), "sw_version": st.version,
                "sampler": cfg.get("pipeline", "sampler"), "health": s["health"], "url": self.url,
                "frames": s["frames"], "fps": s["fps"], "stale": s["stale"], "timestamp": time.time()}

    async def sh(self) -> bytes | None:
        from device.service.payloads import sh_payload

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
                           int(lights.frame), float(lights.timestamp))


def sensor_body(rgb: np.ndarray, unit: str, primary: Any, health: str, frame: int,
                timestamp: float) -> dict[str, Any]:
    """The ``sensors`` payload from the horizontal irradiance RGB and the primary direction."""
    from device.core.sphere import LUMINANCE_WEIGHTS

    e = float(np.asarray(rgb, np.float64) @ LUMINANCE_WEIGHTS)
    elev, az = primary_angles(primary)
    cct = cct_mccamy(rgb)
    return {"version": 1, "illuminance": round(e, 6) if math.isfinite(e) else None,
            "illuminance_unit": "lx" if unit == "nit" else unit,
            "cct": None if cct is None else round(cct, 1), "elevation": elev, "azimuth": az,
            "health": health, "frame": frame, "timestamp": timestamp}


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
