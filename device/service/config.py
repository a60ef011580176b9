"""Service configuration: a TOML file of flat tables, with defaults, validation and atomic writes.

The file has seven tables (every key optional; missing keys take the defaults below)::

    [service]   host, port, require_token_for_reads, public_images, allowed_hosts, cors_origins,
                client_max_size, ws_send_timeout, max_connections, max_connections_per_peer,
                header_timeout, body_timeout, keepalive_timeout
    [pipeline]  fps, sampler, light_count, max_exposures, equirect_height, nside
    [probe]     name, id, model
    [mdns]      enabled, interfaces
    [mqtt]      url, username, password_file, tls, ca_file, keepalive, topic_prefix, lights_rate,
                sh_rate, sensors_rate, status_interval, discovery, discovery_prefix
    [osc]       targets, rate
    [view]      mesh

Reading uses :mod:`tomllib`; writing is our own small serialiser for flat tables of strings,
numbers, booleans and lists of strings, done atomically (temp file in the same folder, fsync,
rename, fsync of the folder) so a crash at any instant leaves the old or the new file, never a torn
one. Validation raises :class:`lightprobe.core.errors.InputError` naming the ``table.key`` at fault.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightprobe.core.errors import InputError
from lightprobe.core.fsutil import atomic_write
from lightprobe.device.sampling.registry import SAMPLERS as REGISTRY

__all__ = [
    "SAMPLERS",
    "ServiceConfig",
    "dump_toml",
    "load_config",
    "save_config",
    "validate_patch",
]

# Sampler names the pipeline understands: the registry's (CONVENTIONS.md `lightprobe sample --method`)
SAMPLERS = tuple(REGISTRY)

# (type, default, validator description, check) per key; check returns True when valid.
_Spec = tuple[type, Any, str, Any]
_NAME_RE = re.compile(r"^[^\x00-\x1f\x7f.][^\x00-\x1f\x7f]{0,62}$")


class in_range:  # lower case: it reads as a predicate in SCHEMA
    """``lo <= v <= hi``, with its bounds readable (the OpenAPI schema is generated from them)."""

    def __init__(self, lo: float, hi: float) -> None:
        self.lo, self.hi = lo, hi

    def __call__(self, v: float) -> bool:
        return self.lo <= v <= self.hi


_LABEL = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)$")


def _is_host(v: str) -> bool:
    """An IP address or a DNS name (RFC 1123 labels); whether it resolves is checked where it
    is used (PUT /config resolves it, ``serve`` names it if it does not)."""
    import ipaddress

    with contextlib.suppress(ValueError):
        ipaddress.ip_address(v)
        return True
    name = v[:-1] if v.endswith(".") else v
    return 0 < len(name) <= 253 and all(_LABEL.match(p) for p in name.split("."))


SCHEMA: dict[str, dict[str, _Spec]] = {
    "service": {
        "host": (str, "127.0.0.1", "an IP address or a host name", _is_host),
        "port": (int, 8080, "an integer in [0, 65535]", in_range(0, 65535)),
        "require_token_for_reads": (bool, False, "true or false", None),
        "public_images": (bool, False, "true or false (camera images and maps readable without the token)", None),
        "allowed_hosts": (list, [], "a list of host names the probe answers to besides its own",
                          lambda v: len(v) <= 32 and all(isinstance(s, str) and _is_host(s) for s in v)),
        "cors_origins": (list, [], "a list of origin strings (empty = CORS off)",
                         lambda v: all(isinstance(s, str) and len(s) < 256 for s in v) and len(v) <= 32),
        "client_max_size": (int, 64 * 1024, "an integer in [1024, 16777216] bytes", in_range(1024, 1 << 24)),
        "ws_send_timeout": (float, 5.0, "seconds in [0.1, 60]", in_range(0.1, 60.0)),
        "max_connections": (int, 512, "an integer in [16, 65536] (capped below the fd limit)", in_range(16, 65536)),
        "max_connections_per_peer": (int, 64, "an integer in [1, 65536]", in_range(1, 65536)),
        "header_timeout": (float, 10.0, "seconds in [0.5, 300]", in_range(0.5, 300.0)),
        "body_timeout": (float, 30.0, "seconds in [0.5, 600]", in_range(0.5, 600.0)),
        "keepalive_timeout": (float, 15.0, "seconds in [1, 3600]", in_range(1.0, 3600.0)),
    },
    "pipeline": {
        "fps": (float, 30.0, "light sets per second at most, in [0.1, 60] (the camera paces below it)",
                in_range(0.1, 60.0)),
        "sampler": (str, "q2tree", "one of " + ", ".join(SAMPLERS), lambda v: v in SAMPLERS),
        "light_count": (int, 256, "an integer in [1, 4096]", in_range(1, 4096)),
        "max_exposures": (int, 8, "an integer in [1, 16]", in_range(1, 16)),
        # map sizes a small board holds (tables, rolling estimate, samplers), measured on the
        # simulator 2026-12-02: 256 / 64 -> ~310 MB RSS (peak ~380); 512 / 128 -> ~480 MB (peak
        # ~810 while the table is built); 1024 / 256 -> ~880 MB (peak 2.4 GB): refused
        "equirect_height": (int, 256, "an integer in [16, 512]", in_range(16, 512)),
        "nside": (int, 64, "a power of two in [1, 128]", lambda v: 1 <= v <= 128 and v & (v - 1) == 0),
    },
    "probe": {
        "name": (str, "", "up to 63 bytes of UTF-8 without control characters, not starting with '.'",
                 lambda v: v == "" or (bool(_NAME_RE.match(v)) and len(v.encode("utf-8")) <= 63)),
        "id": (str, "", "up to 32 characters [A-Za-z0-9_-] (empty = from machine-id)",
               lambda v: re.fullmatch(r"[A-Za-z0-9_-]{0,32}", v) is not None),
        "model": (str, "", "up to 63 printable characters (empty = the open camera's model and driver)",
                  lambda v: len(v) <= 63 and v.isprintable()),
    },
    "mdns": {
        "enabled": (bool, True, "true or false", None),
        "interfaces": (list, [], "a list of interface addresses (empty = all)",
                       lambda v: all(isinstance(s, str) and 0 < len(s) < 64 for s in v) and len(v) <= 16),
    },
    # publication to an MQTT broker (lightprobe.device.service.mqtt); off while url is empty
    "mqtt": {
        "url": (str, "", "mqtt://[USER@]HOST[:PORT] or mqtts://... (empty = off; no password in it)",
                lambda v: v == "" or _is_broker(v)),
        "username": (str, "", "a user name (or put it in the URL)", lambda v: len(v) <= 128 and v.isprintable()),
        "password_file": (str, "", "a file holding the broker password (or $LIGHTPROBE_MQTT_PASSWORD)",
                          lambda v: len(v) <= 4096 and v.isprintable()),
        "tls": (bool, False, "true or false (mqtts:// implies true)", None),
        "ca_file": (str, "", "a CA bundle for TLS (empty = the system's)", lambda v: len(v) <= 4096 and v.isprintable()),
        "keepalive": (int, 10, "seconds in [2, 3600] (the broker declares a silent probe offline "
                               "after 1.5 x this)", in_range(2, 3600)),
        "topic_prefix": (str, "lightprobe", "topic levels of [A-Za-z0-9_-] separated by '/'", lambda v: _is_prefix(v)),
        "lights_rate": (float, 10.0, "light sets per second at most, in [0.1, 60]", in_range(0.1, 60.0)),
        "sh_rate": (float, 1.0, "SH bodies per second at most, in [0, 30] (0 = off)", in_range(0.0, 30.0)),
        "sensors_rate": (float, 1.0, "sensor updates per second, in [0.02, 10]", in_range(0.02, 10.0)),
        "status_interval": (float, 30.0, "seconds between status refreshes, in [1, 3600]", in_range(1.0, 3600.0)),
        "discovery": (bool, True, "true or false (Home Assistant MQTT discovery configs)", None),
        "discovery_prefix": (str, "homeassistant", "topic levels of [A-Za-z0-9_-] separated by '/'",
                             lambda v: _is_prefix(v)),
    },
    # OSC to hosts (lightprobe.device.service.osc); off while targets is empty
    "osc": {
        "targets": (list, [], "a list of udp://HOST:PORT (empty = off)",
                    lambda v: len(v) <= 16 and all(isinstance(u, str) and _is_osc_target(u) for u in v)),
        "rate": (float, 0.0, "light sets per second at most, in [0, 120] (0 = every set)", in_range(0.0, 120.0)),
    },
    # recordings of the camera's frames (POST /api/v1/recordings; lightprobe.device.service.recordings)
    "recordings": {
        "max_seconds": (float, 60.0, "longest recording, seconds, in [1, 3600]", in_range(1.0, 3600.0)),
        "max_mb": (float, 512.0, "largest recording, MB, in [1, 65536]", in_range(1.0, 65536.0)),
        "keep_mb": (float, 2048.0, "MB all recordings may take in the state dir, in [1, 1048576]; a "
                    "recording that would not fit is refused (507)", in_range(1.0, 1048576.0)),
    },
    "view": {
        "mesh": (str, "", "an OBJ file /view shows beside its spheres (empty = a torus knot)",
                 lambda v: len(v) <= 4096 and v.isprintable()),
    },
}


def _is_broker(v: str) -> bool:
    from lightprobe.core.mqtt_topics import parse_broker_url

    try:
        parse_broker_url(v, "mqtt.url")
    except InputError:
        return False
    return True


def _is_osc_target(v: str) -> bool:
    from lightprobe.device.service.osc import parse_osc_target

    try:
        parse_osc_target(v)
    except InputError:
        return False
    return True


def _is_prefix(v: str) -> bool:
    from lightprobe.core.mqtt_topics import check_prefix

    try:
        check_prefix(v)
    except InputError:
        return False
    return True

# Keys that take effect only after a restart (the listening socket, the mDNS sockets, the map
# geometry). A PUT saves them and reports them pending; the running service keeps the values it
# started with until it restarts.
RESTART_KEYS = {("service", "host"), ("service", "port"), ("service", "client_max_size"),
                ("service", "max_connections"), ("service", "max_connections_per_peer"),
                ("service", "header_timeout"), ("service", "body_timeout"), ("service", "keepalive_timeout"),
                ("mdns", "enabled"), ("mdns", "interfaces"), ("pipeline", "equirect_height"),
                ("pipeline", "nside"), ("pipeline", "max_exposures"), ("view", "mesh")} \
    | {("mqtt", k) for k in SCHEMA["mqtt"]} | {("osc", k) for k in SCHEMA["osc"]}


def _defaults() -> dict[str, dict[str, Any]]:
    return {t: {k: copy.deepcopy(spec[1]) for k, spec in keys.items()} for t, keys in SCHEMA.items()}


@dataclass
class ServiceConfig:
    """The validated configuration: ``data[table][key]``. Use ``get`` / ``with_patch``."""

    data: dict[str, dict[str, Any]] = field(default_factory=_defaults)
    path: Path | None = None

    def get(self, table: str, key: str) -> Any:
        return self.data[table][key]

    def to_json(self) -> dict[str, dict[str, Any]]:
        return copy.deepcopy(self.data)

    def with_patch(self, patch: Any) -> ServiceConfig:
        """A new config with ``patch`` (a partial ``{table: {key: value}}``) validated and merged."""
        clean = validate_patch(patch)
        data = copy.deepcopy(self.data)
        for t, kv in clean.items():
            data[t].update(kv)
        return ServiceConfig(data, self.path)

    def running(self, current: ServiceConfig) -> ServiceConfig:
        """This (saved) config as the running service applies it: the restart-only keys keep
        ``current``'s values."""
        data = copy.deepcopy(self.data)
        for t, k in RESTART_KEYS:
            data[t][k] = copy.deepcopy(current.data[t][k])
        return ServiceConfig(data, self.path)

    def pending(self, running: ServiceConfig) -> dict[str, dict[str, Any]]:
        """The restart-only keys whose saved value differs from the running one."""
        out: dict[str, dict[str, Any]] = {}
        for t, k in sorted(RESTART_KEYS):
            if self.data[t][k] != running.data[t][k]:
                out.setdefault(t, {})[k] = copy.deepcopy(self.data[t][k])
        return out


def _coerce(table: str, key: str, value: Any) -> Any:
    """Check one value against the schema; return it in its canonical type."""
    typ, _default, desc, check = SCHEMA[table][key]
    param = f"{table}.{key}"
    if typ is int and isinstance(value, float) and value.is_integer():  # JSON's 256.0 is the integer 256
        value = int(value)
    ok_type = isinstance(value, typ) and not (typ is int and isinstance(value, bool))
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok_type = float(value), True
    if not ok_type:
        raise InputError(f"{param} must be {desc}, got {type(value).__name__}", param=param)
    for text in ([value] if typ is str else (value if typ is list else [])):
        try:
            str(text).encode("utf-8")
        except UnicodeEncodeError:
            raise InputError(f"{param} must be valid UTF-8 text (no lone surrogates)", param=param) from None
    if typ is float and not math.isfinite(value):
        raise InputError(f"{param} must be {desc}, got {value!r}", param=param)
    if check is not None and not check(value):
        shown = repr(value) if len(repr(value)) < 80 else repr(value)[:77] + "..."
        raise InputError(f"{param} must be {desc}, got {shown}", param=param)
    return list(value) if typ is list else value


def validate_patch(patch: Any) -> dict[str, dict[str, Any]]:
    """Validate a partial config ``{table: {key: value}}``; unknown tables/keys are errors."""
    if not isinstance(patch, dict):
        raise InputError("config must be a JSON object of tables", param="config")
    out: dict[str, dict[str, Any]] = {}
    for table, kv in patch.items():
        if table not in SCHEMA:
            raise InputError(f"unknown config table {str(table)[:40]!r}", param=str(table)[:40])
        if not isinstance(kv, dict):
            raise InputError(f"config table {table!r} must be an object", param=table)
        for key, value in kv.items():
            if key not in SCHEMA[table]:
                raise InputError(f"unknown config key {table}.{str(key)[:40]}", param=f"{table}.{str(key)[:40]}")
            out.setdefault(table, {})[key] = _coerce(table, key, value)
    return out


def load_config(path: str | os.PathLike[str] | None) -> ServiceConfig:
    """Read a TOML config (missing file = defaults). Raises InputError naming the file or key."""
    if path is None:
        return ServiceConfig()
    p = Path(path)
    if not p.exists():
        return ServiceConfig(path=p)
    try:
        text = p.read_text(encoding="utf-8")
        raw = tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"{p}: cannot read config: {e}", param=str(p)) from e
    if not text.strip():  # a truncated write or a mistake, not "use the defaults"
        raise InputError(f"{p}: config file is empty (delete it to start from the defaults)", param=str(p))
    try:
        return ServiceConfig(path=p).with_patch(raw)
    except InputError as e:
        raise InputError(f"{p}: {e}", param=e.param) from e


# ---- TOML writing ---------------------------------------------------------------------------------
def _toml_str(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(data: dict[str, dict[str, Any]]) -> str:
    """Serialise flat tables ``{table: {key: scalar | list}}`` to TOML text."""
    lines = ["# lightprobe service configuration (written by the service; comments are not kept)"]
    for table, kv in data.items():
        lines.append(f"\n[{table}]")
        for key, value in kv.items():
            lines.append(f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (``lightprobe.core.fsutil.atomic_write``)."""
    atomic_write(path, text.encode("utf-8"))


def save_config(cfg: ServiceConfig, path: str | os.PathLike[str] | None = None) -> None:
    """Write ``cfg`` atomically to ``path`` (default ``cfg.path``); blocking (call off the loop)."""
    target = Path(path) if path is not None else cfg.path
    if target is None:
        raise InputError("no config file to write to (start with --config FILE)", param="config")
    atomic_write_text(target, dump_toml(cfg.data))
