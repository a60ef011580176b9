"""The frame loop: drives the pipeline, publishes the newest light set, survives camera faults.

- **Newest frame wins.** Each frame's light set is serialised once and stored in a
  :class:`FrameHub` slot that holds only the latest payload; WebSocket clients wait for a newer
  version than the one they sent, so a slow client skips frames and nothing queues without bound.
- **Faults.** A :class:`lightprobe.drivers.base.CameraError` from ``pipeline.step()`` marks the published
  lights ``stale: true`` (the last good set stays served), stops the pipeline (closing the
  camera) and reopens it with exponential backoff (``backoff_initial`` .. ``backoff_max``).
- **Pacing.** The loop targets ``pipeline.fps`` from the config; heavy work happens inside the
  pipeline off the event loop, JSON serialisation runs in a worker thread.
- **Progress**: ``last_progress`` (frames) drives ``/healthz``; ``last_activity`` (frames or
  reconnect attempts) drives the systemd watchdog, so a hung ``step()`` gets the service restarted.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Any, Protocol

import numpy as np

from lightprobe.core.lightset import LightSet

__all__ = ["FrameHub", "PipelineLike", "Runner"]

log = logging.getLogger(__name__)


class PipelineLike(Protocol):
    """The part of ``lightprobe.device.pipeline.Pipeline`` the service uses."""

    stats: dict[str, Any]

    async def start(self) -> None: ...

    async def step(self) -> Any: ...  # FrameResult

    async def stop(self) -> None: ...


class FrameHub:
    """A single-slot broadcast: ``publish`` replaces the payload, waiters get the newest one.

    The payload is the light set's JSON, encoded to UTF-8 bytes once per frame (in a worker
    thread); every WebSocket client sends those same bytes (no per-client JSON or encoding
    work). Waiting costs no task per client and frame: all clients wait on one shared future
    that ``publish`` resolves, then read the newest version.
    """

    def __init__(self) -> None:
        self.version = 0
        self.payload: bytes | None = None
        self.closed = False
        self._next: asyncio.Future[None] | None = None

    def changed(self, seen: int) -> asyncio.Future[None]:
        """A future that is done once a version newer than ``seen`` exists or the hub closed
        (shared between waiters: never cancel it; wrap it in :func:`asyncio.shield`)."""
        if self.version > seen or self.closed:
            done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            done.set_result(None)
            return done
        if self._next is None or self._next.done():
            self._next = asyncio.get_running_loop().create_future()
        return self._next

    def _wake(self) -> None:
        if self._next is not None and not self._next.done():
            self._next.set_result(None)
        self._next = None

    async def publish(self, payload: bytes | str) -> None:
        self.version += 1
        self.payload = payload.encode() if isinstance(payload, str) else payload
        self._wake()

    async def wait_newer(self, seen: int) -> tuple[int, bytes | None]:
        """Wait until a version newer than ``seen`` exists (or the hub closes); return it."""
        while self.version <= seen and not self.closed:
            await asyncio.shield(self.changed(seen))
        return self.version, self.payload

    async def close(self) -> None:
        self.closed = True
        self._wake()


def _lights_payload(lights: LightSet) -> str:
    return json.dumps(lights.to_json(), separators=(",", ":"))


def _sensor_period(pipeline: Any) -> float:
    """Seconds between the camera's frames (0 when unknown)."""
    try:
        return 1.0 / float(pipeline.camera.mode.max_fps)
    except (AttributeError, TypeError, ValueError, ZeroDivisionError):
        return 0.0


def _encode(lights: LightSet) -> tuple[str, bytes]:
    """The light set as JSON text (``GET /lights``) and its UTF-8 bytes (the WebSocket fan-out)."""
    text = _lights_payload(lights)
    return text, text.encode()


def _environment(estimator: Any, result: Any, lights: LightSet) -> Any:
    """A frame's SH + primary light (blocking; ``None`` if the result carries no map). A failure
    is logged and costs the hosts' formats that frame, never the light set."""
    equirect = getattr(result, "equirect", None)
    if equirect is None:
        return None
    try:
        return estimator.estimate(equirect, frame=int(lights.frame), timestamp=float(lights.timestamp),
                                  captured=lights.captured, unit=str(lights.unit), probe=str(lights.probe),
                                  pose=lights.pose)
    except Exception:
        log.exception("SH / primary light estimate failed for frame %s", lights.frame)
        return None


class Runner:
    """Owns the pipeline task. ``make_pipeline(cfg)`` builds a pipeline for the current config
    (called again after a config change that needs a rebuild, e.g. a new sampler)."""

    def __init__(self, make_pipeline: Callable[[Any], PipelineLike], config: Any, *,
                 backoff_initial: float = 0.5, backoff_max: float = 8.0,
                 reconfigure: Callable[[Any, Any], None] | None = None) -> None:
        self.make_pipeline = make_pipeline
        self.reconfigure = reconfigure
        self._started = False
        self.config = config
        self.backoff_initial, self.backoff_max = backoff_initial, backoff_max
        self.hub = FrameHub()
        # called with (lights, result) on every published set, in order (the OSC sender)
        self.listeners: list[Callable[[LightSet, Any], None]] = []
        self.pipeline: PipelineLike | None = None
        self.camera_state = "starting"
        # the camera the pipeline runs on once it started ({"model", "driver", "name"}), and who
        # wants to know when it changes (mDNS, MQTT): never a simulator unless one runs
        self.camera_info: dict[str, str] | None = None
        self.camera_listeners: list[Callable[[dict[str, str]], None]] = []
        self.last_error: str | None = None
        self.reconnects = 0
        self.frames = 0
        self.frames_skipped = 0
        self.result: Any = None  # the last FrameResult
        self.lights: LightSet | None = None
        self.lights_text: str | None = None  # self.lights as JSON (serialised once, off the loop)
        from lightprobe.device.formats.sh_primary import EnvironmentEstimator

        self.estimator = EnvironmentEstimator()  # SH + primary light, incremental, on demand
        self._env_cache: Any = None  # the Environment of the frame it was last asked for
        self._env_lock = asyncio.Lock()
        self.stale = True
        self.last_progress: float | None = None
        self.last_activity: float | None = None  # a frame or a reconnect attempt (watchdog)
        self.started_at = time.monotonic()
        self.fps = 0.0
        self._last_frame_t: float | None = None
        self._rebuild = False
        self._fresh = False
        self._task: asyncio.Task[None] | None = None
        self.cache: dict[str, tuple[int, bytes]] = {}  # per-frame encoded images (api.py)
        self.cache_locks: dict[str, asyncio.Lock] = {}  # one computation per key and frame

    # ---- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="lightprobe-pipeline")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self._stop_pipeline()
        self.camera_state = "stopped"
        await self.hub.close()

    @contextlib.asynccontextmanager
    async def camera_lease(self, camera: Any) -> AsyncIterator[Any]:
        """Pause the frame loop and lend ``camera``, opened, to someone else (live calibration).

        The lights turn ``stale: true`` and the camera state reads ``calibrating``; the holder
        should touch ``last_activity`` as it works (the systemd watchdog). On exit the camera is
        closed and the loop restarts with a freshly built pipeline, which reloads its calibration.
        """
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        await self._stop_pipeline()
        await self._mark_stale()
        self.camera_state, self.last_activity = "calibrating", time.monotonic()
        try:
            await camera.open()
            yield camera
        finally:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(camera.close(), 3.0)
            self.camera_state = "starting"
            if not self.hub.closed:
                self.start()

    def request_rebuild(self, config: Any) -> None:
        """Use ``config`` from the next frame on: ``reconfigure`` the pipeline in place when the
        factory can (keeps tables and sampler state), else rebuild it."""
        self.config = config
        self._rebuild = True

    def request_fresh_start(self) -> None:
        """Rebuild the pipeline before the next frame: a new estimate from a metering sweep, on
        the same tables (a recording starts so: its replay is then the run it recorded)."""
        self._fresh = True

    def set_config(self, config: Any) -> None:
        """Use ``config`` for pacing without touching the pipeline (fps-only changes)."""
        self.config = config

    async def _stop_pipeline(self, *, drop: bool = True) -> None:
        """Stop the pipeline (closing the camera). ``drop=False`` keeps the object, its tables
        and sampler state for a fast restart after a camera fault."""
        p = self.pipeline
        self._started = False
        if drop:
            self.pipeline = None
        if p is not None:
            try:
                await asyncio.wait_for(p.stop(), 3.0)
            except Exception as e:  # a failing stop must not stop the loop
                log.warning("pipeline stop failed: %s", e)

    async def _ensure_started(self) -> PipelineLike:
        if self._fresh:
            self._fresh = False
            await self._stop_pipeline()
        if self._rebuild:
            self._rebuild = False
            if self.pipeline is not None and self.reconfigure is not None:
                await asyncio.to_thread(self.reconfigure, self.pipeline, self.config)
            else:
                await self._stop_pipeline()
        if self.pipeline is None:
            self.camera_state = "starting"
            # construction may build lookup tables: off the loop
            self.pipeline = await asyncio.to_thread(self.make_pipeline, self.config)
        if not self._started:
            self.camera_state = "starting"
            await self.pipeline.start()
            self._started = True
            self._note_camera(self.pipeline)
        return self.pipeline

    def _note_camera(self, pipeline: Any) -> None:
        cam = getattr(pipeline, "camera", None)
        if cam is None:
            return
        try:
            model = str(cam.capabilities.model or "")
        except Exception:  # not open: its name is all there is
            model = ""
        info = {"model": model or str(cam.name), "driver": str(getattr(cam, "driver", "camera")), "name": str(cam.name)}
        if info == self.camera_info:
            return
        self.camera_info = info
        for listener in list(self.camera_listeners):
            try:
                listener(info)
            except Exception:  # a listener's fault is its own
                log.exception("camera listener failed")

    # ---- the loop ---------------------------------------------------------------------------
    async def _run(self) -> None:
        from lightprobe.core.errors import InputError
        from lightprobe.drivers.base import CameraError

        backoff = self.backoff_initial
        while True:
            try:
                pipeline = await self._ensure_started()
                t0 = time.monotonic()
                result = await pipeline.step()
                await self._publish(result)
                self.camera_state, self.last_error = "running", None
                backoff = self.backoff_initial
                period = 1.0 / float(self.config.get("pipeline", "fps"))
                if period > 1.05 * _sensor_period(pipeline):
                    # a rate below the camera's: wait (the camera paces itself otherwise, and a
                    # wait here would only hold a delivered frame back)
                    await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))
            except asyncio.CancelledError:
                raise
            except Exception as e:
                camera_fault = isinstance(e, CameraError)
                if camera_fault:
                    log.warning("camera error (%s): %s; reconnecting in %.2f s", type(e).__name__, e, backoff)
                elif isinstance(e, InputError):  # configuration: the message says it all
                    log.error("pipeline cannot start: %s; retrying in %.2f s", e, backoff)  # noqa: TRY400
                else:
                    log.exception("pipeline failed; rebuilding it in %.2f s", backoff)
                self.camera_state = "reconnecting"
                self.last_error = f"{type(e).__name__}: {e}"
                self.reconnects += 1
                self.last_activity = time.monotonic()
                await self._mark_stale()
                await self._stop_pipeline(drop=not camera_fault)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2.0, self.backoff_max)

    async def _publish(self, result: Any) -> None:
        lights: LightSet = result.lights
        if lights.stale:
            lights = dataclasses.replace(lights, stale=False)
        text, payload = await asyncio.to_thread(_encode, lights)
        now = time.monotonic()
        if self._last_frame_t is not None:
            dt = max(now - self._last_frame_t, 1e-6)
            self.fps = 1.0 / dt if self.fps == 0.0 else 0.8 * self.fps + 0.2 / dt
        self._last_frame_t = now
        self.result, self.lights, self.stale = result, lights, False
        self.lights_text = text
        self.frames += 1
        self.frames_skipped += int(bool(getattr(result, "skipped", False)))
        self.last_progress = self.last_activity = now
        self.cache.clear()
        await self.hub.publish(payload)
        self._tell(lights, result)
        # let the WebSocket senders the publish woke write it out before the next frame's
        # capture and processing take the loop (glass-to-host latency)
        await asyncio.sleep(0)

    def _tell(self, lights: LightSet, result: Any) -> None:
        for listener in list(self.listeners):
            try:
                listener(lights, result)
            except Exception:  # a listener's fault is its own
                log.exception("light-set listener failed")

    async def environment(self, result: Any = None, lights: LightSet | None = None) -> Any:
        """The latest frame's SH + primary light (``lightprobe.device.formats.sh_primary.Environment``), or
        ``None`` before the first frame; or of a given published ``result`` and its ``lights``
        (a listener's, which may be a frame behind). Computed when first asked for each frame (in a worker
        thread), so a probe nobody asks for SH spends nothing on it; the estimator compares each
        map with the last one it saw, so the update stays incremental whatever frames it skips."""
        if result is None or lights is None:
            result, lights = self.result, self.lights
        if result is None or lights is None:
            return None
        env = self._env_cache
        if env is not None and env.frame == int(lights.frame):
            return env
        async with self._env_lock:
            env = self._env_cache
            if env is not None and env.frame == int(lights.frame):
                return env
            env = await asyncio.to_thread(_environment, self.estimator, result, lights)
            if env is not None:
                self._env_cache = env
            return env

    async def _mark_stale(self) -> None:
        # encode first, then switch the flag, the set and its JSON together: a reader never sees
        # status "stale" next to a /lights body that still says fresh
        self._last_frame_t = None
        self.fps = 0.0
        if self.lights is not None and not self.lights.stale:
            lights = dataclasses.replace(self.lights, stale=True)
            text, payload = await asyncio.to_thread(_encode, lights)
            self.lights, self.lights_text, self.stale = lights, text, True
            await self.hub.publish(payload)
            self._tell(lights, self.result)
        else:
            self.stale = True

    # ---- views for the API ------------------------------------------------------------------
    def progressing(self, within: float) -> bool:
        """True when a frame was published in the last ``max(within, 3 x last burst time)`` s
        (a slow camera or a long exposure is not a stall)."""
        burst = float((getattr(self.result, "timings", None) or {}).get("total", 0.0)) if self.result else 0.0
        window = max(within, 3.0 * burst)
        return self.last_progress is not None and time.monotonic() - self.last_progress <= window

    def alive(self, within: float) -> bool:
        """True when the loop published a frame or attempted a reconnect in the last ``within``
        seconds: a pipeline stuck inside ``step()`` is not alive (the watchdog then restarts us)."""
        return self.last_activity is not None and time.monotonic() - self.last_activity <= within

    def status(self) -> dict[str, Any]:
        r = self.result
        stats = dict(getattr(self.pipeline, "stats", {}) or {}) if self.pipeline is not None else {}
        fps_target = float(self.config.get("pipeline", "fps"))
        healthy = not self.stale and self.progressing(max(3.0 / fps_target, 2.0))
        health = "ok" if healthy else ("starting" if self.frames == 0 and self.reconnects == 0 else "degraded")
        pipe_stats = {k: v for k, v in stats.items() if isinstance(v, int | float | str | bool)}
        return {
            "health": health,
            "camera": {"state": self.camera_state, "error": self.last_error, "reconnects": self.reconnects,
                       "model": (self.camera_info or {}).get("model"), "driver": (self.camera_info or {}).get("driver")},
            "stale": self.stale,
            "settling": bool(getattr(self.lights, "settling", False)),
            "frame": int(getattr(r, "frame", 0)) if r is not None else None,
            "frames": self.frames,
            "frames_skipped": self.frames_skipped,
            "fps": round(self.fps, 3),
            "fps_target": fps_target,
            "timings": {k: float(v) for k, v in (getattr(r, "timings", {}) or {}).items()} if r is not None else {},
            "exposures": [float(x) for x in getattr(r, "exposures", [])] if r is not None else [],
            "histogram": np.asarray(getattr(r, "histogram", []), np.float64).astype(int).tolist()
            if r is not None else [],
            "calibration_id": getattr(r, "calibration_id", None) if r is not None else None,
            "unit": getattr(r, "unit", None) if r is not None else None,
            "uptime_s": round(time.monotonic() - self.started_at, 3),
            "last_frame_age_s": None if self.last_progress is None
            else round(time.monotonic() - self.last_progress, 3),
            "pipeline": pipe_stats,
        }
