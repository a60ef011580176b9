"""The MQTT contract between probes and hosts: broker URLs, topics, status payloads.

Topics, under a prefix (default ``lightprobe``) and the probe id::

    lightprobe/<id>/status    retained, QoS 1: {"version": 1, "probe", "state": "online", "name",
                              "model", "sw_version", "sampler", "health", "url", "timestamp"};
                              the broker publishes the last will {"version": 1, "probe",
                              "state": "offline"} (retained) when the probe's connection dies,
                              and the probe publishes it itself on a clean shutdown
    lightprobe/<id>/lights    retained, QoS 0: the light-set JSON (CONVENTIONS.md), byte for
                              byte what GET /api/v1/lights and the WebSocket send
    lightprobe/<id>/sh        retained, QoS 0: the SH body of GET /api/v1/sh (canonical)
    lightprobe/<id>/sensors   retained, QoS 0: {"illuminance", "illuminance_unit", "cct",
                              "elevation", "azimuth", "health", "frame", "timestamp",
                              "captured"} (both wall-clock seconds, as in the light set)

and Home Assistant's MQTT discovery configs under ``homeassistant/<component>/lightprobe_<id>/
<object>/config`` (retained). Topic segments are the probe id ([A-Za-z0-9_-], so never a
wildcard or a separator).
"""

from __future__ import annotations

import json
import re
import urllib.parse
from dataclasses import dataclass
from typing import Any

from lightprobe.core.errors import InputError

__all__ = [
    "DEFAULT_PREFIX",
    "PASSWORD_ENV",
    "TOPICS",
    "BrokerAddress",
    "offline_payload",
    "parse_broker_url",
    "probe_of_topic",
    "topic",
]

DEFAULT_PREFIX = "lightprobe"
PASSWORD_ENV = "LIGHTPROBE_MQTT_PASSWORD"  # the broker password, for probes and hosts alike
TOPICS = ("status", "lights", "sh", "sensors")
_PREFIX_RE = re.compile(r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")


@dataclass(frozen=True)
class BrokerAddress:
    """Where the broker is: ``mqtt://[USER@]HOST[:PORT]`` (1883) or ``mqtts://`` (TLS, 8883).
    A password never goes in the URL (it would show in configs and logs): pass it apart."""

    host: str
    port: int
    tls: bool = False
    username: str | None = None

    @property
    def url(self) -> str:
        user = f"{urllib.parse.quote(self.username)}@" if self.username else ""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'mqtts' if self.tls else 'mqtt'}://{user}{host}:{self.port}"


def parse_broker_url(text: str, param: str = "--mqtt") -> BrokerAddress:
    """Parse a broker URL; :class:`InputError` naming ``param`` when it is not one."""
    s = str(text).strip()
    try:
        u = urllib.parse.urlsplit(s)
        port = u.port
    except ValueError as e:
        raise InputError(f"{param}: not a broker URL ({e}): {s[:80]!r}", param=param) from None
    if u.scheme not in ("mqtt", "mqtts") or not u.hostname:
        raise InputError(f"{param} must be mqtt://HOST[:PORT] or mqtts://HOST[:PORT], got {s[:80]!r}",
                         param=param)
    if u.password is not None:
        raise InputError(f"{param}: put the password in [mqtt] password_file or "
                         f"$LIGHTPROBE_MQTT_PASSWORD, not in the URL", param=param)
    if u.path not in ("", "/") or u.query or u.fragment:
        raise InputError(f"{param}: a broker URL has no path or query, got {s[:80]!r}", param=param)
    tls = u.scheme == "mqtts"
    return BrokerAddress(u.hostname, port or (8883 if tls else 1883), tls,
                         urllib.parse.unquote(u.username) if u.username else None)


def check_prefix(prefix: str, param: str = "mqtt.topic_prefix") -> str:
    if not _PREFIX_RE.match(prefix) or len(prefix) > 128:
        raise InputError(f"{param} must be topic levels of [A-Za-z0-9_-] separated by '/', "
                         f"got {prefix[:60]!r}", param=param)
    return prefix


def topic(prefix: str, probe_id: str, name: str) -> str:
    """``prefix/<id>/name`` for one of :data:`TOPICS`."""
    if name not in TOPICS:
        raise ValueError(f"unknown topic {name!r}")
    return f"{prefix}/{probe_id}/{name}"


def probe_of_topic(prefix: str, t: str) -> tuple[str, str] | None:
    """(probe id, topic name) of ``prefix/<id>/<name>``, or ``None`` for any other topic."""
    head = prefix + "/"
    if not t.startswith(head):
        return None
    parts = t[len(head):].split("/")
    if len(parts) != 2 or parts[1] not in TOPICS or not parts[0]:
        return None
    return parts[0], parts[1]


def offline_payload(probe_id: str) -> bytes:
    """The status a dead probe leaves behind (its last will)."""
    return json.dumps({"version": 1, "probe": probe_id, "state": "offline"},
                      separators=(",", ":")).encode()


def parse_status(payload: bytes) -> dict[str, Any] | None:
    """A status message as a dict, or ``None`` when it is not one (empty = retained status
    cleared, or foreign data on our topic)."""
    try:
        d = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(d, dict) or d.get("state") not in ("online", "offline"):
        return None
    return d
