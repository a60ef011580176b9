"""What the handlers share: :class:`ServiceState` and the app's typed keys.

Route modules (``device.service.routes``) and ``create_app`` (``device.service.app``) both import
this module; it imports neither, so the service has no import circle.
"""

from __future__ import annotations

import asyncio
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

from device.service.config import ServiceConfig
from device.service.notify import Notifier
from device.service.runner import Runner

__all__ = ["HOST", "PORT", "STATE", "VERSION", "ServiceState"]

VERSION = "0.1.0"


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
    started: float = field(default_factory=time.time)
    make_camera: Callable[[], Any] | None = None
    mdns_task: asyncio.Task[None] | None = None  # the mDNS registration while it runs
    _camera_lock: threading.Lock = field(default_factory=threading.Lock)
    _camera_error: Exception | None = None

    def camera_or_make(self) -> Any:
        """The camera, made now if nobody made it yet (blocking: call from a worker thread).
        A bad camera spec (InputError) is remembered and raised again without retrying."""
        from device.core.errors import InputError

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
