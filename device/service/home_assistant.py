"""Home Assistant MQTT discovery: the configs (retained, one device per probe) that make a smart
home see a probe's five sensors (illuminance, colour temperature, primary light elevation and
azimuth, health) with no code. Keys are HA's documented MQTT sensor options (no abbreviations)."""

from __future__ import annotations

from typing import Any

from lightprobe.core.mqtt_topics import (
    topic,
)
from lightprobe.device.service.mqtt_settings import MqttSettings

__all__ = ["ha_discovery"]


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
