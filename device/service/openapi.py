"""The API contract served at ``/api/v1/openapi.json``: ``static/openapi.json`` (paths, prose,
light-set schema) completed here so that it cannot drift from the code:

- the ``Config`` and ``ConfigPatch`` schemas are generated from :data:`lightprobe.device.service.config.SCHEMA`
  (every table and key with its type, range, enum or pattern; no other key accepted);
- every operation documents the statuses the middlewares can answer: 400 for bad input where it
  takes any, 401 / 403 / 429 where a token may be needed (writes; camera images and maps unless
  ``service.public_images``; every read when ``service.require_token_for_reads``), 421 for a
  foreign Host, 405 for another method on the path, 413 / 408 for bodies, 503 where the data
  comes from the camera, 507 where the call saves to the state dir.
"""

from __future__ import annotations

import copy
import functools
import json
from pathlib import Path
from typing import Any

from lightprobe.device.service.config import SCHEMA, in_range

__all__ = ["config_schema", "document"]

_ERR = {"$ref": "#/components/responses/Error"}
_CAMERA_PATHS = {"/lights", "/probe.exr", "/probe.hdr", "/preview.jpg", "/q2tree", "/calibration/live/frame.jpg"}
_PRIVATE = {"/preview.jpg", "/probe.exr", "/probe.hdr", "/calibration/live/frame.jpg", "/recordings",
            "/recordings/{id}"}
_SAVES = {("/config", "put"), ("/calibration/live/commit", "post")}


def _key_schema(table: str, key: str) -> dict[str, Any]:
    typ, default, desc, _check = SCHEMA[table][key]
    s: dict[str, Any] = {"description": desc, "default": default}
    if typ is bool:
        s["type"] = "boolean"
    elif typ is int:
        s["type"] = "integer"
    elif typ is float:
        s["type"] = "number"
    elif typ is str:
        s["type"] = "string"
    elif typ is list:
        s.update({"type": "array", "items": {"type": "string", "minLength": 1, "maxLength": 63}})
    if isinstance(_check, in_range):  # the validator's own bounds: one source
        s["minimum"], s["maximum"] = _check.lo, _check.hi
    if (table, key) == ("pipeline", "nside"):  # the powers of two the validator accepts
        s["enum"] = [1 << k for k in range(16) if _check(1 << k)]
    if (table, key) == ("pipeline", "sampler"):
        from lightprobe.device.service.config import SAMPLERS

        s["enum"] = list(SAMPLERS)
    if (table, key) == ("probe", "id"):
        s["pattern"] = "^[A-Za-z0-9_-]{0,32}$"
    if (table, key) == ("probe", "name"):
        s.update({"maxLength": 63, "pattern": "^([^\\u0000-\\u001f\\u007f.][^\\u0000-\\u001f\\u007f]{0,62})?$"})
    if (table, key) == ("probe", "model"):
        s.update({"maxLength": 63, "pattern": "^[\\u0020-\\u007e]*$"})
    if (table, key) == ("service", "host"):
        s.update({"anyOf": [{"format": "ipv4"}, {"format": "ipv6"}, {"const": "localhost"}],
                  "description": desc + " (an address of this machine, or localhost; a name that "
                  "does not resolve is refused with 400)"})
    if (table, key) == ("service", "allowed_hosts"):
        s["items"] = {"type": "string", "format": "hostname"}
        s["maxItems"] = 32
    if (table, key) == ("service", "cors_origins"):
        s["items"] = {"type": "string", "maxLength": 255}
        s["maxItems"] = 32
    if (table, key) == ("mdns", "interfaces"):
        s["maxItems"] = 16
    return s


def config_schema(partial: bool) -> dict[str, Any]:
    """The config's JSON schema; ``partial``: the PUT body (any subset of tables and keys)."""
    tables: dict[str, Any] = {}
    for table, keys in SCHEMA.items():
        props = {k: _key_schema(table, k) for k in keys}
        t: dict[str, Any] = {"type": "object", "properties": props, "additionalProperties": False}
        if not partial:
            t["required"] = list(keys)
        tables[table] = t
    out: dict[str, Any] = {"type": "object", "properties": tables, "additionalProperties": False}
    if not partial:
        out["required"] = list(SCHEMA)
    return out


def _num(lo: float, hi: float, default: float | None, integer: bool = False, **kw: Any) -> dict[str, Any]:
    return {"type": "integer" if integer else "number", "minimum": lo, "maximum": hi,
            **({"default": default} if default is not None else {}), **kw}


def _calibration_start_schema() -> dict[str, Any]:
    """``POST /calibration/live``: what ``routes.calibration.parse_start`` accepts, exactly."""
    return {
        "type": "object", "required": ["board"], "additionalProperties": False,
        "properties": {
            "board": {"type": "object", "required": ["cols", "rows"],
                      "properties": {"cols": _num(2, 64, None, True, description="inner corners"),
                                     "rows": _num(2, 64, None, True, description="inner corners"),
                                     "square": _num(1e-6, 1e4, 1.0, description="square size (any unit)")}},
            "targets": {"type": "object",
                        "properties": {"min_views": _num(3, 200, 6, True), "rms_px": _num(0.01, 10.0, 0.5),
                                       "coverage": _num(0.0, 1.0, 0.6)}},
            "exposure_s": {"anyOf": [_num(1e-6, 10.0, None), {"type": "null"}],
                           "description": "fixed exposure; null meters once"},
            "timeout_s": _num(5.0, 7200.0, 900.0),
            "idle_timeout_s": _num(2.0, 3600.0, 120.0),
        },
    }


@functools.cache
def _document(static_dir: str) -> str:
    doc = json.loads((Path(static_dir) / "openapi.json").read_text(encoding="utf-8"))
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    schemas["Config"] = config_schema(partial=False)
    schemas["ConfigPatch"] = config_schema(partial=True)
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            responses = op.setdefault("responses", {})
            extra = {"421"}
            if path != "/healthz":
                extra |= {"401", "403", "429"}  # reads need the token when the installer says so
            if op.get("parameters") or "requestBody" in op:
                extra.add("400")
            if "requestBody" in op:
                extra |= {"408", "413"}
            if path in _CAMERA_PATHS:
                extra.add("503")
            if (path, method) in _SAVES:
                extra.add("507")
            for code in sorted(extra):
                responses.setdefault(code, copy.deepcopy(_ERR))
            if path in _PRIVATE or method not in ("get", "head"):
                op.setdefault("security", [{"bearer": []}])
            op.setdefault("x-lightprobe-private", path in _PRIVATE)
    live = doc["paths"].get("/calibration/live", {}).get("post")
    if live is not None:
        live["requestBody"]["content"]["application/json"]["schema"] = _calibration_start_schema()
    cfg_ops = doc["paths"].get("/config", {})
    if "put" in cfg_ops:
        cfg_ops["put"]["requestBody"]["content"]["application/json"]["schema"] = {"$ref": "#/components/schemas/ConfigPatch"}
    return json.dumps(doc, indent=1)


def document(static_dir: Path) -> str:
    """The completed OpenAPI document (JSON text, built once)."""
    return _document(str(static_dir))
