"""``/api/v1/recordings``: record the camera's frames while the service runs, list, download, delete.

- ``POST /api/v1/recordings`` ``{"seconds": 10, "max_mb": 512}`` (token): starts one (202, its
  state, with the limits in effect: ``[recordings]``' cap larger requests); 409 while one is
  being made, 400 for a bad body, 507 when the recordings would exceed ``recordings.keep_mb`` or
  the disk is full;
- ``GET /api/v1/recordings``: every recording with its state (``starting``, ``recording``,
  ``finishing``, ``done``, ``failed``), size and, while it is made, frames and seconds;
- ``GET /api/v1/recordings/{id}``: the file (``application/octet-stream``; 409 while it is made);
- ``DELETE /api/v1/recordings/{id}``: removes it (stops it first if it is being made).

A recording is an image of the room: every route needs the token unless
``service.public_images`` opens camera images (:data:`lightprobe.device.service.app.PRIVATE_PREFIXES`).
The mechanics: :mod:`lightprobe.device.service.recordings`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from aiohttp import web

from lightprobe.device.service.errors import ApiError
from lightprobe.device.service.recordings import Recordings
from lightprobe.device.service.state import STATE

__all__ = ["add_routes"]

ROUTE = "/api/v1/recordings"


def _number(body: dict[str, Any], key: str, default: float | None) -> float | None:
    if key not in body:
        return default
    v = body[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ApiError(400, f"{key} must be a number", param=key)
    return float(v)


async def start(request: web.Request) -> web.Response:
    st = request.app[STATE]
    raw = await request.read()
    try:
        body = json.loads(raw) if raw.strip() else {}
    except ValueError as e:
        raise ApiError(400, f"the body is not JSON: {e}", param="body") from e
    if not isinstance(body, dict):
        raise ApiError(400, "the body must be a JSON object", param="body")
    unknown = set(body) - {"seconds", "max_mb"}
    if unknown:
        raise ApiError(400, f"unknown field {sorted(unknown)[0]!r} (seconds, max_mb)", param=sorted(unknown)[0])
    seconds = _number(body, "seconds", 10.0)
    max_mb = _number(body, "max_mb", None)
    assert seconds is not None
    if not 0 < seconds <= 3600:
        raise ApiError(400, f"seconds must be in (0, 3600], got {seconds:g}", param="seconds")
    if max_mb is not None and not 0 < max_mb <= 65536:
        raise ApiError(400, f"max_mb must be in (0, 65536], got {max_mb:g}", param="max_mb")
    camera = await st.ensure_camera()  # made off the loop if the pipeline has not made it yet
    out = st.recordings.start(st, camera, seconds, max_mb)
    return web.json_response(out, status=202)


async def listing(request: web.Request) -> web.Response:
    return web.json_response(request.app[STATE].recordings.listing())


async def download(request: web.Request) -> web.StreamResponse:
    rid = request.match_info["id"]
    path = request.app[STATE].recordings.path(rid)
    return web.FileResponse(path, headers={"Content-Type": "application/octet-stream",
                                           "Content-Disposition": f'attachment; filename="{rid}.lprec"'})


async def delete(request: web.Request) -> web.Response:
    await request.app[STATE].recordings.delete(request.match_info["id"])
    return web.Response(status=204)


async def _ctx(app: web.Application) -> Any:
    yield
    await app[STATE].recordings.close()


def add_routes(app: web.Application, state_dir: str | Path | None) -> None:
    """Register the routes; recordings live in ``state_dir/recordings`` (None: none can be made)."""
    app[STATE].recordings = Recordings(Path(state_dir) if state_dir is not None else None)
    r = app.router
    r.add_post(ROUTE, start)
    r.add_get(ROUTE, listing)
    r.add_get(ROUTE + "/{id}", download)
    r.add_delete(ROUTE + "/{id}", delete)
    app.cleanup_ctx.append(_ctx)
