"""``lightprobe serve``: run the probe service (wiring from :mod:`lightprobe.device.bootstrap`).

State directory: ``--state-dir``, else ``$STATE_DIRECTORY`` (systemd), else ``./state``. It holds
the API token (mode 0600), the writable config (``config.toml``) and an optional
``calibration.json``. When the state dir has no config yet, ``$CONFIGURATION_DIRECTORY/
lightprobe.toml`` (installer defaults, read-only under systemd) seeds it. SIGTERM/SIGINT shut
down gracefully within 3 s: WebSockets closed, mDNS goodbyes, camera closed, ``STOPPING=1``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["main"]

log = logging.getLogger("lightprobe.service")


class JsonFormatter(logging.Formatter):
    """One JSON object per line (journald keeps it as MESSAGE; log shippers parse it)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"ts": round(record.created, 3), "level": record.levelname.lower(),
                               "logger": record.name, "msg": record.getMessage()}
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def _setup_logging(fmt: str, level: str) -> None:
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json" or (fmt == "auto" and not sys.stderr.isatty()):
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)


def state_dir_from(arg: str | None, env: dict[str, str]) -> Path:
    if arg:
        return Path(arg)
    if env.get("STATE_DIRECTORY"):
        return Path(env["STATE_DIRECTORY"].split(":")[0])
    return Path("state")


def load_service_config(config_arg: str | None, state_dir: Path, env: dict[str, str]) -> Any:
    from lightprobe.device.service.config import ServiceConfig, load_config

    if config_arg:
        return load_config(config_arg)
    target = state_dir / "config.toml"
    if target.exists():
        return load_config(target)
    seed = Path(env.get("CONFIGURATION_DIRECTORY", "/nonexistent").split(":")[0]) / "lightprobe.toml"
    cfg = load_config(seed) if seed.exists() else ServiceConfig()
    return ServiceConfig(cfg.data, target)


def _bind(host: str, port: int) -> socket.socket:
    from lightprobe.core.errors import InputError

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise InputError(f"service.host {host!r} does not resolve: {e.strerror}", param="service.host") from e
    family, _, _, _, addr = infos[0]
    s = socket.socket(family, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        s.bind(addr)
    except OSError as e:
        s.close()
        raise InputError(f"cannot listen on {host}:{port}: {e.strerror}", param="--port") from e
    s.listen(128)
    s.setblocking(False)
    return s


def _exit_deadline(seconds: float) -> None:
    """Guarantee the 3 s stop budget: a worker thread still inside a whole-frame stage (which
    cannot be cancelled) would otherwise hold interpreter exit until it finishes."""
    import threading

    def hard_exit() -> None:
        log.warning("worker threads still busy %.1f s after SIGTERM: exiting now", seconds)
        logging.shutdown()
        os._exit(0)

    t = threading.Timer(seconds, hard_exit)
    t.daemon = True
    t.start()


def numba_cache_dir(env: dict[str, str], state_dir: Path, package_dir: Path | None = None) -> str | None:
    """Where numba should keep its compiled kernels, or None to leave numba's default.

    numba caches next to the sources (``__pycache__``); under systemd's ``ProtectSystem=strict``
    the package is read-only and numba's per-user fallback (``~/.cache``) is too, so every start
    would recompile every kernel (seconds each). Then the cache goes to ``STATE_DIR/cache/numba``.
    An explicit ``NUMBA_CACHE_DIR`` (the unit file sets one) always wins."""
    if env.get("NUMBA_CACHE_DIR"):
        return None
    pkg = package_dir or Path(__file__).resolve().parent.parent / "device"  # lightprobe.device
    probe = pkg / "__pycache__"
    writable = os.access(probe if probe.exists() else pkg, os.W_OK)
    return None if writable else str(state_dir / "cache" / "numba")


def single_blas_thread(environ: Any) -> None:
    """One OpenBLAS thread unless ``OPENBLAS_NUM_THREADS`` is set (call before numpy is imported).

    The service's BLAS calls are small (3-vector products per pixel); its parallelism is its own
    worker threads and the simulator's. An OpenBLAS pool (numpy's and scipy's each load one)
    busy-waits on the other core after loading and after every call: ~0.15 CPU s before the
    first lights on a 2-core probe, taken from the first burst's frames and the kernel loading."""
    environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _under_systemd(env: dict[str, str]) -> bool:
    """Started by systemd (its output goes to the journal)."""
    return bool(env.get("INVOCATION_ID") or env.get("JOURNAL_STREAM"))


def _token_or_error(state_dir: Path, load: Any) -> str:
    """The token, or an InputError naming the state dir and the cause (a full disk, a
    read-only directory), not a traceback."""
    from lightprobe.core.errors import InputError

    try:
        return str(load(state_dir))
    except OSError as e:
        raise InputError(f"state dir {state_dir}: cannot create the API token: {e.strerror or e}",
                         param="--state-dir") from e


async def serve(a: argparse.Namespace) -> int:
    from aiohttp import web

    from lightprobe.core.statelock import StateDirLock
    from lightprobe.device.bootstrap import camera_factory, pipeline_factory
    from lightprobe.device.service.app import create_app
    from lightprobe.device.service.auth import load_or_create_token
    from lightprobe.device.service.connection_limits import (
        ConnectionGuard,
        GuardedSite,
        install_log_limits,
        raise_fd_limit,
    )
    from lightprobe.device.service.mdns import camera_identity, stable_probe_id
    from lightprobe.device.service.notify import Notifier
    from lightprobe.device.service.state import STATE

    env = dict(os.environ)
    state_dir = state_dir_from(a.state_dir, env)
    lock = StateDirLock(state_dir)
    lock.acquire()  # one service per state dir: a second one exits 2 naming the owner
    cfg = load_service_config(a.config, state_dir, env)
    host = a.host or cfg.get("service", "host")
    port = a.port if a.port is not None else cfg.get("service", "port")
    from lightprobe.device.service.mqtt_settings import MqttSettings

    mqtt = MqttSettings.from_config(cfg, a.mqtt, env)  # a bad URL or password file: exit 2 now
    from lightprobe.device.service.osc import OscSettings

    osc = OscSettings.from_config(cfg, a.osc)  # a bad target: exit 2 now
    token = await asyncio.to_thread(_token_or_error, state_dir, load_or_create_token)
    probe_id = cfg.get("probe", "id") or await asyncio.to_thread(
        stable_probe_id, "/etc/machine-id", camera_identity(a.camera, state_dir))
    sock = _bind(host, port)
    port = sock.getsockname()[1]
    notifier = Notifier(env)
    make_camera = camera_factory(a.camera, a.scene, state_dir / "cache")
    app = create_app(cfg, make_camera, pipeline_factory(state_dir, probe_id),
                     token=token, probe_id=probe_id, port=port, host=host, notifier=notifier,
                     backoff=(a.backoff_initial, a.backoff_max), mqtt=mqtt, osc=osc,
                     view_mesh=a.view_mesh)
    guard = ConnectionGuard(max_connections=min(int(cfg.get("service", "max_connections")), raise_fd_limit()),
                            max_per_peer=int(cfg.get("service", "max_connections_per_peer")),
                            header_timeout=float(cfg.get("service", "header_timeout")),
                            body_timeout=float(cfg.get("service", "body_timeout")))
    app[STATE].guard = guard
    install_log_limits()
    runner = web.AppRunner(app, handle_signals=False, shutdown_timeout=0.5, access_log=None,
                           keepalive_timeout=float(cfg.get("service", "keepalive_timeout")))
    await runner.setup()
    await GuardedSite(runner, sock, guard).start()
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    url = f"http://{shown}:{port}/" if ":" not in shown else f"http://[{shown}]:{port}/"
    if _under_systemd(env):  # the journal is readable by more people than the token should be
        print(f"lightprobe: dashboard {url}  (API token: `lightprobe token`)", flush=True)
    else:
        print(f"lightprobe: dashboard {url}  (camera images need the token: {url}#token={token})", flush=True)
        print(f"lightprobe: API token {token}  (state dir {state_dir.resolve()})", flush=True)
    notifier.ready(f"serving on {url}")
    from lightprobe.core.errors import InputError
    from lightprobe.drivers.base import CameraError

    try:  # made off the loop while the API already answers; a bad --camera/--scene still exits 2
        await app[STATE].ensure_camera()
    except InputError:
        await asyncio.wait_for(runner.cleanup(), 2.7)
        raise
    except CameraError as e:  # absent hardware: stay up, retry, say why in /status (no lights)
        log.warning("camera %s: %s; the service keeps retrying", a.camera, e)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    t0 = time.monotonic()
    _exit_deadline(2.9)
    log.info("shutting down")
    notifier.stopping()
    try:
        await asyncio.wait_for(runner.cleanup(), 2.7)
    except TimeoutError:
        log.warning("shutdown took longer than 2.7 s; exiting anyway")
    log.info("stopped in %.2f s", time.monotonic() - t0)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lightprobe serve", description="Run the probe service "
                                "(HTTP/WebSocket API under /api/v1, dashboard at /, mDNS advertising).")
    p.add_argument("--camera", default="sim", help="auto | v4l2:/dev/videoN | libcamera | uvc[:VID:PID], a "
                   "recording: replay:FILE (paced at its rate), or the simulator: sim | v4l2-fake (default sim; "
                   "auto never picks the simulator)")
    p.add_argument("--scene", default=None, help="simulator scene NAME or map PATH (default flashlight)")
    p.add_argument("--host", default=None, help="listen address (default from config, 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="listen port (default from config, 8080; 0 = any)")
    p.add_argument("--config", default=None, help="TOML config file (default STATE_DIR/config.toml)")
    p.add_argument("--state-dir", default=None, help="state directory (default $STATE_DIRECTORY or ./state)")
    p.add_argument("--mqtt", default=None, metavar="mqtt://HOST[:PORT]",
                   help="also publish lights, SH, sensors and status to this MQTT broker, with Home "
                        "Assistant discovery (overrides [mqtt] url; password: [mqtt] password_file "
                        "or $LIGHTPROBE_MQTT_PASSWORD)")
    p.add_argument("--osc", action="append", default=None, metavar="udp://HOST:PORT",
                   help="also send each light set's primary light, SH, illuminance and times as OSC "
                        "messages to this host (repeatable; replaces [osc] targets; rate: [osc] rate)")
    p.add_argument("--view-mesh", default=None, metavar="MESH.obj",
                   help="an OBJ file /view shows beside its spheres (overrides [view] mesh)")
    p.add_argument("--log-format", choices=["auto", "json", "text"], default="auto",
                   help="log format on stderr (auto: text on a terminal, JSON lines otherwise)")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    p.add_argument("--backoff-initial", type=float, default=0.5, help="first reconnect delay, s")
    p.add_argument("--backoff-max", type=float, default=1.0,
                   help="longest reconnect delay, s (default 1: a returning camera is back in use within 1 s)")
    return p


def main(argv: list[str]) -> int:
    from lightprobe.core.command import run_command

    a = build_parser().parse_args(argv)
    _setup_logging(a.log_format, a.log_level)
    # Before anything imports numba (it reads its configuration once, at import)
    cache = numba_cache_dir(dict(os.environ), state_dir_from(a.state_dir, dict(os.environ)))
    if cache is not None:
        os.environ["NUMBA_CACHE_DIR"] = cache
    if os.environ.get("NUMBA_CACHE_DIR"):  # the install's compiled kernels, not a recompile
        from lightprobe.cli.warm_kernels import seed_cache

        seed_cache(os.environ["NUMBA_CACHE_DIR"])
    single_blas_thread(os.environ)  # before numpy loads OpenBLAS
    from lightprobe.device.allocator import skip_numba_blas_probe, tune_allocator

    tune_allocator()  # before any thread starts: a small board's memory
    skip_numba_blas_probe()  # scipy.linalg stays out of the service (16 MB)
    from lightprobe.device.threads import ThreadingLayerError, require_threadsafe, select

    select()
    try:
        layer = require_threadsafe()
    except ThreadingLayerError as e:
        print(f"lightprobe serve: error: {e}", file=sys.stderr)
        return 2
    log.info("numba threading layer: %s", layer)
    if a.port is not None and not 0 <= a.port <= 65535:
        print(f"lightprobe: error: --port must be in [0, 65535], got {a.port}", file=sys.stderr)
        return 2
    with contextlib.suppress(KeyboardInterrupt):
        return run_command(asyncio.run, serve(a))
    return 130
