"""What the handlers share: :class:`ServiceState` and the app's typed keys.

Route modules (``lightprobe.device.service.routes``) and ``create_app`` (``lightprobe.device.service.app``) both import
this module; it imports neither, so the service has no import circle.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

from lightprobe.device.service.config import ServiceConfig
from lightprobe.device.service.notify import Notifier
from lightprobe.device.service.runner import Runner
from lightprobe.device.service.viewmesh import ViewMesh

__all__ = ["HOST", "PORT", "STATE", "VERSION", "AuthFailures", "ServiceState"]

VERSION = "0.1.0"

log = logging.getLogger("lightprobe.service.auth")


@dataclass
class AuthFailures:
    """Failed authentications per peer: logged (the first, then once per window with a count),
    and after ``limit`` failures within ``window`` seconds the peer is answered 429 until the
    window ends. Monotonic clock."""

    limit: int = 10
    window: float = 60.0
    _peers: dict[str, tuple[float, int]] = field(default_factory=dict)
    _logged: dict[str, float] = field(default_factory=dict)

    def failed(self, peer: str, method: str, path: str) -> None:
        now = time.monotonic()
        start, n = self._peers.get(peer, (now, 0))
        if now - start > self.window:
            start, n = now, 0
        self._peers[peer] = (start, n + 1)
        if now - self._logged.get(peer, -1e18) >= self.window:
            self._logged[peer] = now
            log.warning("authentication failed from %s (%s %s; %d in the last %.0f s)", peer, method,
                        path[:80], n + 1, self.window)
        if len(self._peers) > 4096:  # a flood of addresses: forget the oldest
            for k in sorted(self._peers, key=lambda k: self._peers[k][0])[:2048]:
                self._peers.pop(k, None)
                self._logged.pop(k, None)

    def blocked(self, peer: str) -> int:
        """Seconds until ``peer`` may try again (0: now)."""
        hit = self._peers.get(peer)
        if hit is None or hit[1] < self.limit:
            return 0
        left = self.window - (time.monotonic() - hit[0])
        if left <= 0:
            self._peers.pop(peer, None)
            return 0
        return max(1, int(left + 0.999))


@dataclass
class ServiceState:
    """Everything the handlers share. ``config`` is replaced (never mutated) on PUT /config."""

    config: ServiceConfig
    token: str
    probe_id: str
    runner: Runner
    camera: Any = None
    advertiser: Any = None
    notifier: Notifier = field(default_factory=lambda: Notifier({}))
    websockets: weakref.WeakSet[web.WebSocketResponse] = field(default_factory=weakref.WeakSet)
    ws_dropped: int = 0
    ws_frames_skipped: int = 0
    config_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    version: str = VERSION
    started: float = field(default_factory=time.monotonic)  # monotonic: intervals only
    make_camera: Callable[[], Any] | None = None
    mdns_task: asyncio.Task[None] | None = None  # the mDNS registration while it runs
    auth_failures: AuthFailures = field(default_factory=AuthFailures)
    allowed_hosts: set[str] | None = None  # Host names answered (computed on first request)
    pending: dict[str, dict[str, Any]] = field(default_factory=dict)  # saved, applied at restart
    saved: ServiceConfig | None = None  # the config as saved (restart-only keys included), if it differs
    guard: Any = None  # lightprobe.device.service.connection_limits.ConnectionGuard of the listening socket, if any
    mqtt: Any = None  # lightprobe.device.service.mqtt.MqttPublisher while publishing to a broker
    osc: Any = None  # lightprobe.device.service.osc.OscSender while sending to OSC hosts
    recordings: Any = None  # lightprobe.device.service.recordings.Recordings
    recorder: Any = None  # the RecordingCamera the pipeline runs over since a recording started
    _camera_lock: threading.Lock = field(default_factory=threading.Lock)
    _camera_error: Exception | None = None

    def model(self, config: ServiceConfig | None = None) -> str:
        """The probe's model as /status, mDNS and MQTT say it: ``[probe] model`` when an
        installer set one, else the open camera's (its driver after a slash), else
        ``lightprobe`` (no camera open yet: never a simulator that is not running)."""
        set_ = str((config or self.config).get("probe", "model"))
        if set_:
            return set_
        info = self.runner.camera_info
        if info:
            return f"{info['model']} ({info['driver']})"[:63]
        return "lightprobe"

    def saved_config(self) -> ServiceConfig:
        """The config as saved on disk: the running one plus any pending restart-only values."""
        return self.saved if self.saved is not None else self.config

    def camera_or_make(self) -> Any:
        """The camera, made now if nobody made it yet (blocking: call from a worker thread).
        A bad camera spec (InputError) is remembered and raised again without retrying."""
        from lightprobe.core.errors import InputError

        with self._camera_lock:
            if self._camera_error is not None:
                raise self._camera_error
            if self.camera is None and self.make_camera is not None:
                try:
                    self.camera = self.make_camera()
                except InputError as e:
                    self._camera_error = e
                    raise
            return self.camera

    async def ensure_camera(self) -> Any:
        """The camera, made off the loop if the pipeline has not made it yet (start-up)."""
        if self.camera is not None:
            return self.camera
        return await asyncio.to_thread(self.camera_or_make)


STATE: web.AppKey[ServiceState] = web.AppKey("lightprobe_state", ServiceState)
PORT: web.AppKey[int] = web.AppKey("lightprobe_port", int)
HOST: web.AppKey[str] = web.AppKey("lightprobe_host", str)
MQTT: web.AppKey[Any] = web.AppKey("lightprobe_mqtt", object)  # MqttSettings or None
OSC: web.AppKey[Any] = web.AppKey("lightprobe_osc", object)  # OscSettings or None
VIEW_MESH: web.AppKey[ViewMesh | None] = web.AppKey("lightprobe_view_mesh")
