"""HTTP routes under ``/api/v1`` and the dashboard's static files.

Every endpoint is documented in ``static/openapi.json`` (served at ``/api/v1/openapi.json``).
Image encoding (EXR, HDR, JPEG) runs in worker threads and is cached per frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import WSMsgType, web

from lightprobe.core.errors import InputError
from lightprobe.device.service.config import SAMPLERS, save_config
from lightprobe.device.service.encode import encode_hdr, encode_jpeg
from lightprobe.device.service.errors import ApiError
from lightprobe.device.service.payloads import sg_payload, sh_payload
from lightprobe.device.service.state import STATE, ServiceState
from lightprobe.device.threads import loaded_layer

__all__ = ["add_routes"]

log = logging.getLogger(__name__)

API = "/api/v1"
STATIC_FILES = {"index.html": "text/html", "app.js": "text/javascript", "style.css": "text/css",
                "view.html": "text/html", "view.js": "text/javascript",  # /view (routes.environment)
                "vendor/three.module.min.js": "text/javascript"}




# ---- helpers on the state -------------------------------------------------------------------------
def _current(st: ServiceState) -> Any:
    r = st.runner.result
    if r is None:
        raise ApiError(503, "no frame yet: the pipeline is starting or the camera is reconnecting",
                       param="camera", headers={"Retry-After": "1"})
    return r


async def _cached(st: ServiceState, key: str, fn: Any, *args: Any) -> bytes:
    """Encode once per frame: the runner clears the cache on every new frame."""
    frame = int(getattr(st.runner.result, "frame", 0))
    hit = st.runner.cache.get(key)
    if hit is not None and hit[0] == frame:
        return hit[1]
    data: bytes = await asyncio.to_thread(fn, *args)
    st.runner.cache[key] = (frame, data)
    return data


def _int_param(request: web.Request, name: str, lo: int, hi: int, default: int) -> int:
    raw = request.query.get(name)
    if raw is None:
        return default
    try:
        v = int(raw)
    except ValueError:
        raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {raw[:40]!r}", param=name) from None
    if not lo <= v <= hi:
        raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {v}", param=name)
    return v


def check_query(request: web.Request, allowed: set[str]) -> None:
    for k in request.query:
        if k not in allowed and k not in ("access_token", "t"):  # t: a client's cache buster
            raise InputError(f"unknown query parameter {k[:40]!r}", param=k[:40])


# ---- handlers -------------------------------------------------------------------------------------
async def healthz(request: web.Request) -> web.Response:
    st = request.app[STATE]
    fps = float(st.config.get("pipeline", "fps"))
    # healthy: frames flow, or a technician's calibration session holds the camera and works
    ok = st.runner.progressing(max(5.0 / fps, 5.0)) or (
        st.runner.camera_state == "calibrating" and st.runner.alive(30.0))
    body = {"ok": ok, "camera": st.runner.camera_state, "stale": st.runner.stale, "frames": st.runner.frames}
    return web.json_response(body, status=200 if ok else 503)


async def status(request: web.Request) -> web.Response:
    st = request.app[STATE]
    cfg = st.config
    body = st.runner.status()
    body.update({
        "probe": {"id": st.probe_id, "name": cfg.get("probe", "name"), "model": st.model(),
                  "version": st.version},
        "sampler": cfg.get("pipeline", "sampler"),
        "light_count": cfg.get("pipeline", "light_count"),
        "websocket": {"clients": len(st.websockets), "dropped": st.ws_dropped,
                      "frames_skipped": st.ws_frames_skipped},
        "mdns": {"advertised": st.advertiser.registered_names if st.advertiser is not None else []},
        "connections": st.guard.stats() if st.guard is not None else None,
        "mqtt": st.mqtt.stats() if st.mqtt is not None else None,
        "osc": st.osc.stats() if st.osc is not None else None,
        "pending_restart": sorted(f"{t}.{k}" for t, kv in st.pending.items() for k in kv),
        "threading_layer": loaded_layer(),  # numba's: omp or tbb (lightprobe.device.threads)
    })
    return web.json_response(body)


async def lights(request: web.Request) -> web.Response:
    st = request.app[STATE]
    check_query(request, {"method", "count"})
    method = request.query.get("method")
    if method is not None and method not in SAMPLERS:
        raise InputError(f"method must be one of {', '.join(SAMPLERS)}, got {method[:40]!r}", param="method")
    count = _int_param(request, "count", 1, 4096, int(st.config.get("pipeline", "light_count")))
    if method is None and "count" not in request.query:
        if st.runner.lights_text is None:
            _current(st)
        return web.Response(text=st.runner.lights_text, content_type="application/json")
    from lightprobe.device.pipeline import lights_on_demand

    # from the published frame, not the pipeline: a camera reconnecting, a calibration session
    # or a pipeline rebuilt after a change keeps the last good frame sampleable
    r = _current(st)
    ls = await asyncio.to_thread(lights_on_demand, r, method or st.config.get("pipeline", "sampler"), count)
    ls.stale = st.runner.stale
    return web.Response(text=await asyncio.to_thread(lambda: json.dumps(ls.to_json())),
                        content_type="application/json")


async def probe_exr(request: web.Request) -> web.Response:
    from lightprobe.core.imageio import exr_bytes

    st = request.app[STATE]
    r = _current(st)
    meta = {"unit": str(r.unit), "probe": st.probe_id, "timestamp": repr(float(r.timestamp)),
            **({} if getattr(r, "captured", None) is None else {"captured": repr(float(r.captured))}),
            "calibration_id": str(r.calibration_id), "frame": str(int(r.frame)),
            "frame_convention": "lightprobe probe frame, +y up, equirect row 0 at zenith"}
    image = r.equirect
    cov = getattr(r, "coverage", None)
    if cov is not None:  # a lens that is not a fisheye: A is the share of each pixel it sees
        image = np.concatenate([np.asarray(r.equirect, np.float32), np.asarray(cov, np.float32)[..., None]], axis=2)
        meta["alpha"] = "coverage: the share of each pixel the camera sees (0 = unseen, not black)"
    data = await _cached(st, "exr", exr_bytes, image, meta)
    return web.Response(body=data, content_type="image/x-exr",
                        headers={"Content-Disposition": 'inline; filename="probe.exr"'})


async def probe_hdr(request: web.Request) -> web.Response:
    st = request.app[STATE]
    r = _current(st)
    data = await _cached(st, "hdr", encode_hdr, r.equirect)
    return web.Response(body=data, content_type="image/vnd.radiance",
                        headers={"Content-Disposition": 'inline; filename="probe.hdr"'})


async def preview(request: web.Request) -> web.Response:
    st = request.app[STATE]
    check_query(request, {"view"})
    view = request.query.get("view", "fisheye")
    if view not in ("fisheye", "equirect"):
        raise InputError(f"view must be 'fisheye' or 'equirect', got {view[:40]!r}", param="view")
    r = _current(st)
    if view == "fisheye":
        # the preview is made on first use (a tone map of a whole frame): in the worker thread too
        data = await _cached(st, "jpg-fisheye", lambda res: encode_jpeg(np.asarray(res.preview, np.uint8)), r)
    else:
        from lightprobe.device.tonemap import tone_map  # the same operator as the fisheye preview

        data = await _cached(st, "jpg-equirect", lambda m: encode_jpeg(tone_map(m)), r.equirect)
    return web.Response(body=data, content_type="image/jpeg")


async def get_config(request: web.Request) -> web.Response:
    st = request.app[STATE]
    return web.json_response({"config": st.config.to_json(), "pending": st.pending,
                              "path": str(st.config.path) if st.config.path else None})


_STORAGE_ERRORS = {errno.ENOSPC: "ENOSPC: no space left on the device",
                   errno.EDQUOT: "EDQUOT: disk quota exceeded",
                   errno.EROFS: "EROFS: the state directory is read-only",
                   errno.EACCES: "EACCES: the state directory is not writable",
                   errno.EPERM: "EPERM: the state directory is not writable",
                   errno.EIO: "EIO: input/output error on the storage"}


async def _resolves(host: str) -> bool:
    import socket

    try:
        async with asyncio.timeout(3.0):
            await asyncio.get_running_loop().getaddrinfo(host, None, type=socket.SOCK_STREAM,
                                                         flags=socket.AI_PASSIVE)
    except (OSError, TimeoutError):
        return False
    return True


async def put_config(request: web.Request) -> web.Response:
    """Validate, save (atomically), apply what applies live. Restart-only keys are saved and
    reported pending; the running service keeps its values for them until it restarts."""
    st = request.app[STATE]
    if request.content_type != "application/json":
        raise InputError(f"Content-Type must be application/json, got {request.content_type!r}",
                         param="Content-Type")
    try:
        async with asyncio.timeout(float(st.config.get("service", "body_timeout"))):
            raw = await request.read()  # raises 413 past client_max_size
    except TimeoutError:
        raise ApiError(408, "request body not received in time", param="body") from None
    try:
        patch = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"body is not valid JSON: {e}", param="body") from None
    except RecursionError:
        raise InputError("body is nested too deeply", param="body") from None
    async with st.config_lock:
        saved = st.saved_config()
        new_saved = saved.with_patch(patch)  # validates everything before anything changes
        host = new_saved.get("service", "host")
        if host != saved.get("service", "host") and not await _resolves(host):
            raise InputError(f"service.host {host!r} does not resolve to an address of this machine",
                             param="service.host")
        mesh = new_saved.get("view", "mesh")
        if mesh and mesh != saved.get("view", "mesh"):  # a file the next start could not load: 400 now
            from lightprobe.device.service.viewmesh import load_view_mesh

            await asyncio.to_thread(load_view_mesh, mesh)
        transport = request.transport
        if transport is None or transport.is_closing():
            raise ApiError(400, "client went away before the change was applied", param="body")
        if new_saved.path is not None:
            try:
                await asyncio.to_thread(save_config, new_saved)
            except OSError as e:  # nothing changed: the old file is intact (atomic write)
                why = _STORAGE_ERRORS.get(e.errno or 0, f"{errno.errorcode.get(e.errno or 0, 'error')}: {e.strerror}")
                log.exception("cannot save config to %s: %s", new_saved.path, why)
                raise ApiError(507, f"cannot save the config to {new_saved.path}: {why}; nothing was changed",
                               param="config") from None
        old = st.config
        new = new_saved.running(old)
        st.config = new
        st.pending = new_saved.pending(new)
        st.saved = new_saved
        st.allowed_hosts = None  # service.allowed_hosts applies from the next request on
        await _apply_config(st, old, new)
    restart = sorted(f"{t}.{k}" for t, kv in st.pending.items() for k in kv)
    return web.json_response({"config": new.to_json(), "pending": st.pending, "restart_required": restart,
                              "saved": new_saved.path is not None})


async def _apply_config(st: ServiceState, old: Any, new: Any) -> None:
    """Apply what can change live: pacing, sampler and light count (pipeline rebuild), mDNS TXT."""
    rebuild = any(old.get("pipeline", k) != new.get("pipeline", k) for k in ("sampler", "light_count"))
    if rebuild:
        st.runner.request_rebuild(new)
    else:
        st.runner.set_config(new)
    name_changed = old.get("probe", "name") != new.get("probe", "name")
    if st.advertiser is None and st.mdns_task is not None and not st.mdns_task.done():
        with contextlib.suppress(TimeoutError, asyncio.CancelledError):  # still registering
            await asyncio.wait_for(asyncio.shield(st.mdns_task), 5.0)
    if st.advertiser is not None and (name_changed or old.get("pipeline", "sampler") != new.get("pipeline", "sampler")
                                      or old.get("probe", "model") != new.get("probe", "model")):
        try:
            await st.advertiser.update(name=new.get("probe", "name"), sampler=new.get("pipeline", "sampler"),
                                       model=st.model(new))
        except Exception as e:
            log.warning("mdns: re-announce failed: %s", e)


async def stream(request: web.Request) -> web.StreamResponse:
    """WS: one light-set JSON text message per frame, newest first; slow clients skip frames
    and are dropped when one send takes longer than ``service.ws_send_timeout``.

    A client that sends ``{"subscribe": ["sh"], "convention": "threejs"}`` (any convention of
    ``GET /api/v1/sh``) also gets, right after each light set, that frame's SH body (the same
    JSON as ``GET /api/v1/sh``, with ``"kind": "sh"``), so light sets and SH stay in step;
    ``"sg"`` in the list adds the frame's SG lobes (``GET /api/v1/sg``, ``"kind": "sg"``), fitted
    only while someone asks; ``{"subscribe": []}`` stops it. Other text is ignored."""
    st = request.app[STATE]
    check_query(request, set())
    ws = web.WebSocketResponse(heartbeat=15.0, max_msg_size=4096, compress=False)
    await ws.prepare(request)
    _bound_send_buffer(request)
    st.websockets.add(ws)
    subs: dict[str, Any] = {}
    reader = asyncio.create_task(_drain_incoming(ws, subs))
    hub = st.runner.hub
    seen = 0
    try:
        while not ws.closed and not hub.closed:
            changed = hub.changed(seen)  # one future shared by all clients: no task per frame
            if not changed.done():
                await asyncio.wait({changed, reader}, return_when=asyncio.FIRST_COMPLETED)
                if not changed.done():
                    break  # the client went away
            version, payload = hub.version, hub.payload
            if payload is None or hub.closed:
                break
            if seen and version > seen + 1:
                st.ws_frames_skipped += version - seen - 1
            seen = version
            extras: list[bytes] = []  # subscriptions, computed before the send clock starts
            if subs.get("sh"):
                extra = await sh_payload(st, subs["sh"])
                if extra is not None:
                    extras.append(extra)
            if subs.get("sg"):
                extra = await sg_payload(st)
                if extra is not None:
                    extras.append(extra)
            try:  # the frame's bytes, encoded once for every client, sent as a text message
                async with asyncio.timeout(float(st.config.get("service", "ws_send_timeout"))):
                    await ws.send_frame(payload, WSMsgType.TEXT)
                    for extra in extras:
                        await ws.send_frame(extra, WSMsgType.TEXT)
            except (TimeoutError, ConnectionResetError):
                st.ws_dropped += 1
                log.info("websocket client %s too slow: dropped", request.remote)
                if request.transport is not None:
                    request.transport.abort()
                break
    finally:
        reader.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await reader
        st.websockets.discard(ws)
        if not ws.closed:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), 1.0)
    return ws


WS_SNDBUF = 256 * 1024


def _bound_send_buffer(request: web.Request) -> None:
    """Cap the kernel send buffer of a stream socket (autotuning lets it grow to MBs per client),
    so a stalled client costs at most WS_SNDBUF + the transport's 64 KiB high-water mark."""
    import socket

    sock = request.transport.get_extra_info("socket") if request.transport is not None else None
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, WS_SNDBUF)


async def _drain_incoming(ws: web.WebSocketResponse, subs: dict[str, Any]) -> None:
    """Process control frames and subscription messages (see :func:`stream`); an invalid
    subscription gets one error message back and changes nothing."""
    from lightprobe.core.sh import CONVENTIONS

    async for msg in ws:
        if msg.type == WSMsgType.ERROR:
            break
        if msg.type != WSMsgType.TEXT:
            continue
        try:
            req = json.loads(msg.data)
        except ValueError:
            continue
        if not isinstance(req, dict) or "subscribe" not in req:
            continue
        topics, conv = req.get("subscribe"), req.get("convention", "canonical")
        if not isinstance(topics, list) or not set(map(str, topics)) <= {"sh", "sg"} or conv not in CONVENTIONS:
            with contextlib.suppress(Exception):
                await ws.send_str(json.dumps({"error": "subscribe takes a list of topics from ['sh', 'sg'] and a "
                                              f"convention from {list(CONVENTIONS)}", "param": "subscribe"}))
            continue
        if "sh" in topics:
            subs["sh"] = conv
        else:
            subs.pop("sh", None)
        if "sg" in topics:
            subs["sg"] = True
        else:
            subs.pop("sg", None)


def static_handler(static_dir: Path, name: str) -> Any:
    path = static_dir / name

    async def handler(request: web.Request) -> web.StreamResponse:
        if not path.is_file():
            raise web.HTTPNotFound()
        return web.FileResponse(path, headers={"Content-Type": STATIC_FILES.get(name, "application/json")})

    return handler


def _openapi_handler(static_dir: Path) -> Any:
    from lightprobe.device.service.openapi import document

    async def handler(request: web.Request) -> web.Response:
        return web.Response(text=document(static_dir), content_type="application/json")

    return handler


def add_routes(app: web.Application, static_dir: Path) -> None:
    """Register the API and the dashboard. Static files are a fixed list (no path traversal)."""
    r = app.router
    r.add_get(f"{API}/healthz", healthz)
    r.add_get(f"{API}/status", status)
    r.add_get(f"{API}/lights", lights)
    r.add_get(f"{API}/probe.exr", probe_exr)
    r.add_get(f"{API}/probe.hdr", probe_hdr)
    r.add_get(f"{API}/preview.jpg", preview)
    r.add_get(f"{API}/stream", stream)
    r.add_get(f"{API}/config", get_config)
    r.add_put(f"{API}/config", put_config)
    r.add_get(f"{API}/openapi.json", _openapi_handler(static_dir))
    r.add_get("/", static_handler(static_dir, "index.html"))
    for name in STATIC_FILES:
        r.add_get(f"/static/{name}", static_handler(static_dir, name))
