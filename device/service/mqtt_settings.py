"""The MQTT publication's settings (``[mqtt]`` in the config, ``lightprobe serve --mqtt URL``):
the broker, the topics' prefix, each topic's rate, Home Assistant discovery."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightprobe.core.errors import InputError
from lightprobe.core.mqtt_topics import (
    DEFAULT_PREFIX,
    PASSWORD_ENV,
    BrokerAddress,
    check_prefix,
    parse_broker_url,
)

__all__ = ["MqttSettings"]


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
