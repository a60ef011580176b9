"""``create_app``: one :class:`aiohttp.web.Application` wiring config, camera, pipeline, API,
dashboard and mDNS.

State lives on the app under typed :class:`aiohttp.web.AppKey` s. Each resource is a
``cleanup_ctx`` entry, started in order and torn down in reverse, only if it started:
camera -> pipeline task -> mDNS registration -> systemd notifier/watchdog; open WebSockets are
closed (1001) on shutdown, before the cleanups run.

Listen first. No start-up step holds the server: the camera is made and the pipeline built by
the frame loop's task in worker threads (importing the simulator or a driver, numba, OpenCV and
loading the projection tables take a while), and mDNS registration (~2 s of probing) runs as a
task; ``/healthz`` and ``/status`` (``"health": "starting"``) answer from the moment the socket
listens.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from device.service.auth import check_bearer
from device.service.config import ServiceConfig
from device.service.errors import ApiError, Handler, error_middleware
from device.service.notify import Notifier
from device.service.runner import PipelineLike, Runner
from device.service.state import HOST, PORT, STATE, ServiceState

__all__ = ["create_app"]

log = logging.getLogger(__name__)


CameraFactory = Callable[[], Any]
PipelineFactory = Callable[[Any, ServiceConfig], PipelineLike]


# ---- middlewares ----------------------------------------------------------------------------------
def _token_from(request: web.Request) -> str | None:
    header = request.headers.get("Authorization")
    if header:
        return header
    # Browsers cannot set headers on a WebSocket: accept ?access_token= for GET only.
    q = request.query.get("access_token")
    return f"Bearer {q}" if q and request.method == "GET" else None


@web.middleware
async def auth_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    st = request.app[STATE]
    path = request.path
    if path.startswith("/api/v1/") and path != "/api/v1/healthz" and request.method != "OPTIONS":
        write = request.method not in ("GET", "HEAD")
        if write or st.config.get("service", "require_token_for_reads"):
            header = _token_from(request)
            if header is None:
                raise ApiError(401, "missing bearer token (Authorization: Bearer <token>; "
                               "see `lightprobe token`)", param="Authorization",
                               headers={"WWW-Authenticate": 'Bearer realm="lightprobe"'})
            if not check_bearer(header, st.token):
                raise ApiError(403, "wrong bearer token", param="Authorization")
    return await handler(request)


@web.middleware
async def cors_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    """CORS is off unless ``service.cors_origins`` lists the requesting origin."""
    origins = request.app[STATE].config.get("service", "cors_origins")
    origin = request.headers.get("Origin")
    allowed = bool(origin) and (origin in origins or "*" in origins)
    if request.method == "OPTIONS" and allowed and request.headers.get("Access-Control-Request-Method"):
        resp: web.StreamResponse = web.Response(status=204)
    else:
        resp = await handler(request)
    if allowed and not resp.prepared:
        resp.headers["Access-Control-Allow-Origin"] = origin or ""
        resp.headers["Access-Control-Allow-Headers"] = "Authorization, Content-Type"
        resp.headers["Access-Control-Allow-Methods"] = "GET, PUT, OPTIONS"
        resp.headers["Vary"] = "Origin"
    return resp


@web.middleware
async def headers_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    resp = await handler(request)
    if not resp.prepared:
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("Cache-Control", "no-store")
    return resp


# ---- cleanup contexts -----------------------------------------------------------------------------
async def _camera_ctx(app: web.Application) -> AsyncIterator[None]:
    """The camera is made by the pipeline task (off the loop, after the API listens: importing
    the simulator or a driver takes a while); this entry closes it on shutdown if it exists."""
    st = app[STATE]
    try:
        yield
    finally:
        if st.camera is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(st.camera.close(), 2.0)


def _warm_imports() -> None:
    """Import the encoders once, in a thread, so no request pays (and no request stalls the loop
    on the import lock) for it later."""
    import cv2  # noqa: F401

    import device.core.imageio  # noqa: F401


async def _warm_after_first_frame(st: ServiceState) -> None:
    """The encoders are needed only once a frame exists: import them after the first lights,
    so they do not compete with the first frame for the interpreter."""
    await st.runner.hub.wait_newer(0)
    await asyncio.to_thread(_warm_imports)


async def _pipeline_ctx(app: web.Application) -> AsyncIterator[None]:
    """Start the frame loop as a task and return at once: the server listens (``/healthz``,
    ``/status`` say "starting") while imports, tables and the first burst happen behind it."""
    st = app[STATE]
    st.runner.start()
    warm = asyncio.create_task(_warm_after_first_frame(st), name="lightprobe-warm-imports")
    try:
        yield
    finally:
        warm.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await warm
        await st.runner.stop()


async def _close_websockets(app: web.Application) -> None:
    """on_shutdown: wake every stream handler and send close frames (1001 going away)."""
    st = app[STATE]
    await st.runner.hub.close()
    socks = list(st.websockets)
    if socks:
        await asyncio.wait([asyncio.create_task(_close_ws(ws)) for ws in socks], timeout=1.5)


async def _close_ws(ws: web.WebSocketResponse) -> None:
    with contextlib.suppress(Exception):
        await asyncio.wait_for(ws.close(code=1001, message=b"server shutdown"), 1.0)


def _mdns_interfaces(configured: list[str], host: str) -> list[str]:
    """The configured interfaces; else, when the API listens on one IPv4 address only (e.g.
    127.0.0.1 for ``make run``), that address, so we never advertise an unreachable service."""
    if configured:
        return configured
    import ipaddress

    try:
        addr = ipaddress.IPv4Address(host)
    except ValueError:
        return []
    return [] if addr.is_unspecified else [str(addr)]


async def _advertise(st: ServiceState, adv: Any) -> None:
    """Register (mDNS probing takes ~2 s) in the background; then catch up with a name or
    sampler change made while registering."""
    try:
        await adv.start()
    except Exception as e:  # no multicast route must not stop the API
        log.warning("mdns: cannot advertise: %s", e)
        with contextlib.suppress(Exception):
            await adv.close()
        return
    st.advertiser = adv
    name, sampler = st.config.get("probe", "name"), st.config.get("pipeline", "sampler")
    if (name, sampler) != (adv.info.name, adv.info.sampler):
        try:
            await adv.update(name=name, sampler=sampler)
        except Exception as e:
            log.warning("mdns: re-announce failed: %s", e)


async def _mdns_ctx(app: web.Application) -> AsyncIterator[None]:
    """Advertise without holding up the server: registration runs as a task (the API answers
    meanwhile); shutdown cancels it or sends the goodbyes."""
    st = app[STATE]
    cfg = st.config
    if not cfg.get("mdns", "enabled"):
        yield
        return
    from device.service.mdns import Advertiser, MdnsInfo

    info = MdnsInfo(probe_id=st.probe_id, name=cfg.get("probe", "name"), port=app[PORT],
                    version=st.version, model=cfg.get("probe", "model"),
                    sampler=cfg.get("pipeline", "sampler"),
                    interfaces=_mdns_interfaces(list(cfg.get("mdns", "interfaces")), app[HOST]))
    adv = Advertiser(info)
    task = st.mdns_task = asyncio.create_task(_advertise(st, adv), name="lightprobe-mdns-register")
    try:
        yield
    finally:
        if not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        st.advertiser = None
        with contextlib.suppress(Exception):
            await asyncio.wait_for(adv.close(), 2.0)


async def _notify_ctx(app: web.Application) -> AsyncIterator[None]:
    st = app[STATE]
    task = None
    interval = st.notifier.watchdog_interval
    if interval:
        task = asyncio.create_task(_watchdog(st, interval), name="sd-watchdog")
    try:
        yield
    finally:
        st.notifier.stopping()
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def _watchdog(st: ServiceState, interval: float) -> None:
    """WATCHDOG=1 every ``interval`` s while the loop makes progress: frames, or reconnect
    attempts while the camera is away. A ``step()`` that hangs stops the pings."""
    last_status = ""
    while True:
        fps = float(st.config.get("pipeline", "fps"))
        if st.runner.alive(within=max(2 * interval, 5.0 / fps) + st.runner.backoff_max):
            st.notifier.watchdog()
        status = f"{st.runner.camera_state}, {st.runner.frames} frames, {st.runner.fps:.1f} fps"
        if status.split(",")[0] != last_status:
            st.notifier.status(status)
            last_status = status.split(",")[0]
        await asyncio.sleep(interval)


# ---- the app --------------------------------------------------------------------------------------
def create_app(config: ServiceConfig, make_camera: CameraFactory, make_pipeline: PipelineFactory, *,
               token: str, probe_id: str, port: int | None = None, host: str | None = None,
               notifier: Notifier | None = None,
               backoff: tuple[float, float] = (0.5, 1.0)) -> web.Application:
    """Build the service. ``make_camera()`` returns an unopened camera; ``make_pipeline(camera,
    config)`` a pipeline over it; if the factory also has ``reconfigure(pipeline, config)`` a
    sampler or light-count change is applied in place, else the pipeline is rebuilt. ``port`` and
    ``host`` are where the API listens (defaults from ``[service]``), for mDNS."""
    from device.service.routes import calibration, probe, q2tree

    app = web.Application(
        client_max_size=int(config.get("service", "client_max_size")),
        middlewares=[headers_middleware, cors_middleware, error_middleware, auth_middleware],
    )
    app[PORT] = int(port if port is not None else config.get("service", "port"))
    app[HOST] = str(host if host is not None else config.get("service", "host"))
    state_holder: dict[str, ServiceState] = {}

    def build(cfg: ServiceConfig) -> PipelineLike:  # runs in a worker thread (Runner)
        return make_pipeline(state_holder["s"].camera_or_make(), cfg)

    reconf = getattr(make_pipeline, "reconfigure", None)  # optional: apply config in place
    runner = Runner(build, config, backoff_initial=backoff[0], backoff_max=backoff[1], reconfigure=reconf)
    st = ServiceState(config=config, token=token, probe_id=probe_id, runner=runner,
                      notifier=notifier or Notifier({}), make_camera=make_camera)
    state_holder["s"] = st
    app[STATE] = st
    static = Path(__file__).parent / "static"
    probe.add_routes(app, static)
    q2tree.add_routes(app)  # GET /api/v1/q2tree (binary tree for host-side merging)
    calibration.add_routes(app, getattr(make_pipeline, "state_dir", None), static)  # live calibration
    app.cleanup_ctx.extend([_camera_ctx, _pipeline_ctx, _mdns_ctx, _notify_ctx])
    app.on_shutdown.append(_close_websockets)
    return app
