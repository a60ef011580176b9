"""The mDNS / DNS-SD contract between probes and hosts (the MQTT one is :mod:`.mqtt_topics`).

A probe advertises ``<name>._lightprobe._tcp.local.`` (and ``_http._tcp`` for browsers) with
these TXT keys, ``txtvers`` first::

    txtvers  "1"
    id       the probe's stable id (12 hex digits): the key hosts follow a probe by
    path     the API's base path ("/api/v1")
    version  the probe's software version
    model    the camera model (at most 40 characters)
    name     the installer-set name (at most 63 characters, the DNS label limit)
    sampler  the light-set sampler in use

The advertiser is :mod:`lightprobe.device.service.mdns`; the browser
:mod:`lightprobe.hostlink.discovery`.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["DEFAULT_PATH", "HTTP_TYPE", "SERVICE_TYPE", "TXT_VERSION", "parse_txt", "txt_records"]

SERVICE_TYPE = "_lightprobe._tcp.local."
HTTP_TYPE = "_http._tcp.local."
TXT_VERSION = "1"
DEFAULT_PATH = "/api/v1"


def txt_records(*, probe_id: str, name: str, path: str, version: str, model: str, sampler: str) -> dict[str, str]:
    """TXT key/values in order, ``txtvers`` first (dicts keep insertion order)."""
    return {"txtvers": TXT_VERSION, "id": probe_id, "path": path, "version": version,
            "model": model[:40], "name": name[:63], "sampler": sampler}


def parse_txt(properties: Mapping[bytes, bytes | None] | None) -> dict[str, str]:
    """A resolved service's TXT properties as text (undecodable bytes replaced, a key without a
    value as ``""``)."""
    return {k.decode("utf-8", "replace"): (v or b"").decode("utf-8", "replace")
            for k, v in (properties or {}).items()}
