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

from lightprobe.device.service.auth import check_bearer
from lightprobe.device.service.config import ServiceConfig
from lightprobe.device.service.errors import ApiError, Handler, error_middleware
from lightprobe.device.service.notify import Notifier
from lightprobe.device.service.runner import PipelineLike, Runner
from lightprobe.device.service.state import HOST, MQTT, OSC, PORT, STATE, VIEW_MESH, ServiceState
from lightprobe.device.service.viewmesh import load_view_mesh

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


# Camera images and maps of the room: private unless the installer opens them (service.public_images)
PRIVATE_PATHS = frozenset({"/api/v1/preview.jpg", "/api/v1/probe.exr", "/api/v1/probe.hdr",
                           "/api/v1/calibration/live/frame.jpg"})
# ... and everything made of the map's pixels for hosts: cubemaps, glTF images, USD dome textures
# (the SH and the primary light are lighting data, readable on the LAN)
PRIVATE_PREFIXES = ("/api/v1/cubemap", "/api/v1/environment", "/api/v1/recordings")


def needs_token(st: ServiceState, method: str, path: str) -> bool:
    """Writes always; camera images and maps unless opened in config; other reads (light sets,
    status, config) only when ``service.require_token_for_reads``."""
    if not path.startswith("/api/v1/") or path == "/api/v1/healthz" or method == "OPTIONS":
        return False
    if method not in ("GET", "HEAD"):
        return True
    if (path in PRIVATE_PATHS or path.startswith(PRIVATE_PREFIXES)) and not st.config.get("service", "public_images"):
        return True
    return bool(st.config.get("service", "require_token_for_reads"))


@web.middleware
async def auth_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    st = request.app[STATE]
    if request.match_info.http_exception is not None:
        return await handler(request)  # routing first: 404 / 405 for what does not exist
    if needs_token(st, request.method, request.path):
        header = _token_from(request)
        if header is None:
            raise ApiError(401, "missing bearer token (Authorization: Bearer <token>; "
                           "see `lightprobe token`)", param="Authorization",
                           headers={"WWW-Authenticate": 'Bearer realm="lightprobe"'})
        peer = request.remote or "?"
        retry = st.auth_failures.blocked(peer)  # a peer guessing tokens waits, right or wrong
        if retry:
            raise ApiError(429, "too many failed authentications from this address; try again later",
                           param="Authorization", headers={"Retry-After": str(retry)})
        if not check_bearer(header, st.token):
            st.auth_failures.failed(peer, request.method, request.path)
            raise ApiError(403, "wrong bearer token", param="Authorization")
    return await handler(request)


def _host_name(header: str) -> str:
    """The host part of a Host header, lower-cased, without port, brackets or a trailing dot."""
    h = header.strip().lower()
    if h.startswith("["):
        return h[1:h.find("]")] if "]" in h else h
    if h.count(":") == 1:
        h = h.split(":", 1)[0]
    return h.rstrip(".")


def _is_ip(name: str) -> bool:
    import ipaddress

    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def allowed_host_names(st: ServiceState, listen_host: str) -> set[str]:
    """Names a request may address the probe by: localhost, the machine's host name (plain and
    .local), the probe's mDNS host name, the listen address's name, and ``service.allowed_hosts``."""
    import socket

    names = {"localhost", "localhost.localdomain"}
    host = socket.gethostname().lower().rstrip(".")
    if host:
        names |= {host, host.split(".")[0], host.split(".")[0] + ".local"}
    names.add(f"lightprobe-{st.probe_id[:12]}.local")
    if listen_host and not _is_ip(listen_host):
        names.add(listen_host.lower().rstrip("."))
    names |= {str(a).lower().rstrip(".") for a in st.config.get("service", "allowed_hosts")}
    return names


@web.middleware
async def host_middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
    """421 for a Host the probe does not answer to: a page on another site that rebinds its name
    to the probe's address must not read the probe (DNS rebinding). Addresses are always
    fine (a browser that was given the address is on the probe's own origin)."""
    header = request.headers.get("Host")
    if header:
        name = _host_name(header)
        if not _is_ip(name):
            st = request.app[STATE]
            if st.allowed_hosts is None:
                st.allowed_hosts = allowed_host_names(st, request.app[HOST])
            if name not in st.allowed_hosts:
                raise ApiError(421, f"this probe does not answer to host {name[:64]!r}: use its address, "
                               "its .local name, or add the name to service.allowed_hosts", param="Host")
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

    import lightprobe.core.imageio  # noqa: F401


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
    name, sampler, model = st.config.get("probe", "name"), st.config.get("pipeline", "sampler"), st.model()
    if (name, sampler, model) != (adv.info.name, adv.info.sampler, adv.info.model):
        try:
            await adv.update(name=name, sampler=sampler, model=model)
        except Exception as e:
            log.warning("mdns: re-announce failed: %s", e)


async def _reannounce(adv: Any, model: str) -> None:
    try:
        await adv.update(model=model)
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
    from lightprobe.device.service.mdns import Advertiser, MdnsInfo

    info = MdnsInfo(probe_id=st.probe_id, name=cfg.get("probe", "name"), port=app[PORT],
                    version=st.version, model=st.model(),
                    sampler=cfg.get("pipeline", "sampler"),
                    interfaces=_mdns_interfaces(list(cfg.get("mdns", "interfaces")), app[HOST]))
    adv = Advertiser(info)
    task = st.mdns_task = asyncio.create_task(_advertise(st, adv), name="lightprobe-mdns-register")
    updates: set[asyncio.Task[None]] = set()

    def camera_changed(_info: dict[str, str]) -> None:  # the TXT record names the camera now open
        if st.advertiser is not None and st.model() != st.advertiser.info.model:
            t = asyncio.get_running_loop().create_task(_reannounce(st.advertiser, st.model()))
            updates.add(t)
            t.add_done_callback(updates.discard)

    st.runner.camera_listeners.append(camera_changed)
    try:
        yield
    finally:
        st.runner.camera_listeners.remove(camera_changed)
        for t in list(updates):
            t.cancel()
        if not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        st.advertiser = None
        with contextlib.suppress(Exception):
            await asyncio.wait_for(adv.close(), 2.0)


async def _mqtt_ctx(app: web.Application) -> AsyncIterator[None]:
    """Publish to the MQTT broker, if one is configured (a task: never holds up the server)."""
    st = app[STATE]
    settings = app[MQTT]
    if settings is None:
        yield
        return
    from lightprobe.device.service.mqtt import MqttPublisher, ServiceSource

    host = app[HOST]
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("::1" if host == "::" else host)
    url = f"http://[{shown}]:{app[PORT]}" if ":" in shown else f"http://{shown}:{app[PORT]}"
    pub = st.mqtt = MqttPublisher(ServiceSource(st, url), settings)
    pub.start()
    try:
        yield
    finally:
        await pub.stop(within=1.5)  # publishes "offline" itself
        st.mqtt = None


async def _osc_ctx(app: web.Application) -> AsyncIterator[None]:
    """Send each set over OSC, if targets are configured (a task: never holds up the server)."""
    st = app[STATE]
    settings = app[OSC]
    if settings is None:
        yield
        return
    from lightprobe.device.service.osc import OscSender

    sender = st.osc = OscSender(st, settings)
    sender.start()
    try:
        yield
    finally:
        await sender.stop()
        st.osc = None


async def _notify_ctx(app: web.Application) -> AsyncIterator[None]:
    st = app[STATE]
    task = None
    interval = st.notifier.watchdog_interval
    if interval:
        task = asyncio.create_task(_watchdog(st, interval, app[HOST], app[PORT]), name="sd-watchdog")
    try:
        yield
    finally:
        st.notifier.stopping()
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def serves_itself(host: str, port: int, wait_s: float = 2.0) -> bool:
    """True when the service answers its own ``/healthz`` over a real connection (any HTTP
    status: the loop accepts, parses and answers). A loop that is alive but cannot accept (file
    descriptors exhausted) or is too busy to answer fails it."""
    target = "127.0.0.1" if host in ("0.0.0.0", "") else ("::1" if host == "::" else host)
    writer = None
    try:
        async with asyncio.timeout(wait_s):
            reader, writer = await asyncio.open_connection(target, port)
            writer.write(b"GET /api/v1/healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            await writer.drain()
            line = await reader.readline()
    except (OSError, TimeoutError):
        return False
    finally:
        if writer is not None:
            writer.close()
    return line.startswith(b"HTTP/1.")


async def _watchdog(st: ServiceState, interval: float, host: str, port: int) -> None:
    """WATCHDOG=1 every ``interval`` s while the loop makes progress (frames, or reconnect
    attempts while the camera is away) and the service answers its own ``/healthz`` over the
    network. A ``step()`` that hangs, or a server that cannot accept, stops the pings, and
    systemd restarts the service."""
    last_status = ""
    misses = 0
    while True:
        fps = float(st.config.get("pipeline", "fps"))
        alive = st.runner.alive(within=max(2 * interval, 5.0 / fps) + st.runner.backoff_max)
        served = await serves_itself(host, port, wait_s=min(2.0, interval))
        misses = 0 if served else misses + 1
        if alive and misses < 2:
            st.notifier.watchdog()
        elif misses == 2:
            log.error("the service does not answer its own /healthz on port %d: stopping the watchdog pings", port)
        status = f"{st.runner.camera_state}, {st.runner.frames} frames, {st.runner.fps:.1f} fps"
        if status.split(",")[0] != last_status:
            st.notifier.status(status)
            last_status = status.split(",")[0]
        await asyncio.sleep(interval)


# ---- the app --------------------------------------------------------------------------------------
def create_app(config: ServiceConfig, make_camera: CameraFactory, make_pipeline: PipelineFactory, *,
               token: str, probe_id: str, port: int | None = None, host: str | None = None,
               notifier: Notifier | None = None,
               backoff: tuple[float, float] = (0.5, 1.0), mqtt: Any = None, osc: Any = None,
               view_mesh: str | None = None) -> web.Application:
    """Build the service. ``make_camera()`` returns an unopened camera; ``make_pipeline(camera,
    config)`` a pipeline over it; if the factory also has ``reconfigure(pipeline, config)`` a
    sampler or light-count change is applied in place, else the pipeline is rebuilt. ``port`` and
    ``host`` are where the API listens (defaults from ``[service]``), for mDNS. ``mqtt`` is a
    :class:`lightprobe.device.service.mqtt.MqttSettings` to publish to a broker (``None``: off); ``osc``
    a :class:`lightprobe.device.service.osc.OscSettings` to send to OSC hosts (``None``: off); ``view_mesh``
    an OBJ file for ``/view`` (``None``: ``[view] mesh``)."""
    from lightprobe.device.service.routes import calibration, environment, probe, q2tree, recordings

    app = web.Application(
        client_max_size=int(config.get("service", "client_max_size")),
        middlewares=[headers_middleware, cors_middleware, error_middleware, host_middleware, auth_middleware],
    )
    app[PORT] = int(port if port is not None else config.get("service", "port"))
    app[HOST] = str(host if host is not None else config.get("service", "host"))
    app[MQTT] = mqtt
    app[OSC] = osc
    mesh = str(config.get("view", "mesh")) if view_mesh is None else view_mesh
    # a bad file stops the start with an error naming it (exit 2), not a blank view later
    app[VIEW_MESH] = load_view_mesh(mesh, "view.mesh" if view_mesh is None else "--view-mesh") if mesh else None
    state_holder: dict[str, ServiceState] = {}

    def build(cfg: ServiceConfig) -> PipelineLike:  # runs in a worker thread (Runner)
        s = state_holder["s"]
        camera = s.camera_or_make()
        # since a recording started, over its wrapper (routes.recordings)
        return make_pipeline(s.recorder if s.recorder is not None else camera, cfg)

    reconf = getattr(make_pipeline, "reconfigure", None)  # optional: apply config in place
    runner = Runner(build, config, backoff_initial=backoff[0], backoff_max=backoff[1], reconfigure=reconf)
    st = ServiceState(config=config, token=token, probe_id=probe_id, runner=runner,
                      notifier=notifier or Notifier({}), make_camera=make_camera)
    state_holder["s"] = st
    app[STATE] = st
    static = Path(__file__).parent / "static"
    probe.add_routes(app, static)
    q2tree.add_routes(app)  # GET /api/v1/q2tree (binary tree for host-side merging)
    environment.add_routes(app, static)  # SH, cubemaps, glTF / USD, the live three.js view
    calibration.add_routes(app, getattr(make_pipeline, "state_dir", None), static)  # live calibration
    recordings.add_routes(app, getattr(make_pipeline, "state_dir", None))  # the camera's frames, to replay
    app.cleanup_ctx.extend([_camera_ctx, _pipeline_ctx, _mdns_ctx, _mqtt_ctx, _osc_ctx, _notify_ctx])
    app.on_shutdown.append(_close_websockets)
    return app
